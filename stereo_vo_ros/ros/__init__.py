"""
ROS 2 adapter of stereo_vo_ros: the node, message conversions, stereo sync and a bag player.

Only this subpackage imports rclpy and ROS messages; the core package stays ROS-free.
``sync`` is pure Python and can be used without rclpy.
"""
