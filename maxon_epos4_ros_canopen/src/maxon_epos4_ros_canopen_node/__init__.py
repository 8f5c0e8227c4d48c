"""The ROS side of canopen_motor_node: adapters that import rospy and
actionlib, used only by the node. The ROS-free core is the package
maxon_epos4_ros_canopen."""
