"""ros_control's controller_manager command-line tools (client side only)."""
