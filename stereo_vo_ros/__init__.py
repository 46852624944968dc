"""
Stereo visual odometry for ROS 2: light adaptive KLT tracking + trifocal ISPKF egomotion.

The public API of the core library::

    from stereo_vo_ros import StereoOdometry
    from stereo_vo_ros.config import load
    odometry = StereoOdometry(load('config/stereo_vo.yaml'))
    result = odometry.process(frame)  # one StereoFrame per stereo pair

The core subpackages (``tracking``, ``estimation``, ``road``, ``evaluation``, ``synthetic``,
``io``) and the pipeline import no ROS package; the ROS adapter lives in ``stereo_vo_ros.ros``.
"""

from .config import Config
from .pipeline import StereoOdometry
from .records import OdometryResult, StereoFrame, TrackingStatus

__all__ = ['Config', 'OdometryResult', 'StereoFrame', 'StereoOdometry', 'TrackingStatus']
__version__ = '0.1.0'
