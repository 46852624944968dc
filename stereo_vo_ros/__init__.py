"""
Stereo visual odometry for ROS 2: light adaptive KLT tracking + trifocal ISPKF egomotion.

The core modules (camera, trifocal, motion, filters, ransac, bucketing, estimator, tracker,
pipeline) import no ROS package; the ROS adapter lives in ``stereo_vo_ros.ros``.
"""

__version__ = '0.1.0'
