"""ROS 2 adapter for jointfit_core: the node, its inputs and outputs, the offline fit, replay and the fake mocap."""

import jointfit_core  # noqa: F401  (first: its BLAS thread setting must precede numpy, see there)
