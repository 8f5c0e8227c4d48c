"""MANI rover: ROS-free core (CAN protocol codec, configuration, kinematics,
odometry, simulated rover). The ROS nodes in nodes/ are thin adapters."""
