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

from importlib import import_module
from typing import Any

__all__ = ['Config', 'OdometryResult', 'StereoFrame', 'StereoOdometry', 'TrackingStatus']
__version__ = '0.1.0'

#: Public names and their modules, imported on first use (``python -m stereo_vo_ros.config``
#: and the light modules do not load the pipeline).
_PUBLIC = {'Config': 'config', 'StereoOdometry': 'pipeline', 'OdometryResult': 'records',
           'StereoFrame': 'records', 'TrackingStatus': 'records'}


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(import_module(f'.{_PUBLIC[name]}', __name__), name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
