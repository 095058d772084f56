"""ROS 2 adapter for jointfit_core: the node, its inputs and outputs, the offline fit, replay and the fake mocap."""
