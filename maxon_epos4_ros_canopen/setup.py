# Used by catkin_python_setup() only; do not run directly.
from setuptools import setup
from catkin_pkg.python_setup import generate_distutils_setup

setup(**generate_distutils_setup(
    packages=["maxon_epos4_ros_canopen", "maxon_epos4_ros_canopen.sim", "maxon_epos4_ros_canopen.driver",
              "maxon_epos4_ros_canopen.settings",
              "maxon_epos4_ros_canopen_node"],
    package_dir={"": "src"},
))
