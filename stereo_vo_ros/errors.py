"""
Exception hierarchy of stereo_vo_ros.

Library code raises these; only the command line turns them into an exit code and only the ROS
node turns them into a log line, a diagnostics status and a lost tracking state. Messages name
the offending value.
"""


class StereoVOError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(StereoVOError, ValueError):
    """A configuration value is unknown, has the wrong type or is out of range."""


class CalibrationError(StereoVOError, ValueError):
    """Stereo calibration is missing, non-finite or geometrically invalid."""


class ImageError(StereoVOError, ValueError):
    """An image cannot be used (encoding, size, step or data length)."""


class DatasetError(StereoVOError):
    """A sequence (KITTI folder, rosbag2, correspondence file) cannot be read."""


class MissingDependencyError(StereoVOError):
    """A package that a feature needs is not installed (e.g. rclpy without the ROS extra)."""
