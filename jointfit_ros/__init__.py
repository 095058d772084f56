"""ROS 2 adapter for jointfit_core; the node arrives with the node issue."""
