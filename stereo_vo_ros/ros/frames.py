"""
The node's frames (REP-103, REP-105): camera mounting, /tf and path messages, ``~/set_pose``.

The node publishes the pose of the base frame (REP-103: x forward, y left, z up) in the odom
frame (REP-105: the base frame at the first pair; continuous, it drifts). The pipeline
estimates the left camera optical frame (x right, y down, z forward) in its world frame (that
camera at the first pair). The camera's mounting ``T_base_cam`` links the two;
``conversions`` holds the algebra. Transforms ``T_a_b`` are (4, 4) float64 and take points
from frame b to frame a, in metres.

* ``CameraMount``: ``T_base_cam``, the pose of the left camera optical frame in the base frame,
  looked up once in /tf_static and /tf (``tf_tree``), else built from the parameters
  ``ros.base_from_camera_xyz`` (m) and ``ros.base_from_camera_rpy_deg`` (deg); fixed for the
  run.
* ``path_msg`` and ``tf_msg``: the nav_msgs/Path of the recent poses in the odom frame, and the
  odom -> base transform (base -> odom with ``ros.invert_tf``) as tf2_ros's broadcaster sends
  it on /tf.
* ``base_pose_from_msg`` and ``camera_pose_from_base``: a ``~/set_pose`` request (pose of the
  base frame in the odom frame, covariance in ROS order x, y, z, rot_x, rot_y, rot_z) checked,
  then turned into the pose and covariance of the camera in the pipeline's world frame.
"""

from __future__ import annotations

from typing import Any, Iterable

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
import numpy as np

from . import conversions as conv
from .tf_tree import TransformListener
from ..config import RosConfig

try:  # a ROS install has it; a pip install gets it from scripts/build_tf2_msgs.sh
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the install
    TFMessage = None


class CameraMount:
    """
    The pose of the left camera optical frame in the base frame, found once per run.

    Parameters
    ----------
    listener : TransformListener or None
        The node's TF listener (None without tf2_msgs: the parameters are used).
    logger
        The node's logger: where the transform came from is logged once.

    """

    def __init__(self, listener: TransformListener | None, logger: Any) -> None:
        self._listener = listener
        self._logger = logger
        self._T_base_cam: np.ndarray | None = None

    def base_from_camera(self, camera_frame: str, cfg: RosConfig) -> np.ndarray:
        """Pose (4, 4) of the left camera optical frame in the base frame (fixed per run)."""
        if self._T_base_cam is not None:
            return self._T_base_cam
        reason = 'tf2_msgs is not importable (no TF listener)'
        if self._listener is not None and camera_frame:
            try:
                self._T_base_cam = self._listener.tree.lookup(cfg.base_frame, camera_frame)
                self._logger.info(f'{cfg.base_frame} <- {camera_frame} from TF: '
                                  f'{np.round(self._T_base_cam[:3], 6).tolist()}')
                return self._T_base_cam
            except LookupError as exc:
                reason = f'TF lookup {cfg.base_frame} <- {camera_frame!r} failed: {exc}'
        elif not camera_frame:
            reason = 'the camera frame is unknown (empty frame_id and ros.camera_frame)'
        self._T_base_cam = conv.transform_from_xyz_rpy(cfg.base_from_camera_xyz,
                                                       cfg.base_from_camera_rpy_deg)
        self._logger.warning(
            f'{reason}: using the base <- camera transform from the parameters '
            f'ros.base_from_camera_xyz={list(cfg.base_from_camera_xyz)} m and '
            f'ros.base_from_camera_rpy_deg={list(cfg.base_from_camera_rpy_deg)} deg')
        return self._T_base_cam


def path_msg(poses: Iterable[PoseStamped], stamp: Time, odom_frame: str) -> Path:
    """Build the nav_msgs/Path of the given poses (each in the odom frame)."""
    path = Path()
    path.header.stamp = stamp
    path.header.frame_id = odom_frame
    path.poses = list(poses)
    return path


def tf_msg(T_odom_base: np.ndarray, stamp: Time, cfg: RosConfig) -> Any:
    """Build the tf2_msgs/TFMessage of odom -> base (base -> odom if ``ros.invert_tf``)."""
    if cfg.invert_tf:
        tf = conv.transform_msg(np.linalg.inv(T_odom_base), stamp, cfg.base_frame,
                                cfg.odom_frame)
    else:
        tf = conv.transform_msg(T_odom_base, stamp, cfg.odom_frame, cfg.base_frame)
    return TFMessage(transforms=[tf])


def base_pose_from_msg(msg: PoseWithCovarianceStamped, odom_frame: str
                       ) -> tuple[np.ndarray, np.ndarray]:
    """
    Check a ``~/set_pose`` request and read the pose of the base frame in the odom frame.

    Returns
    -------
    T_odom_base : np.ndarray
        (4, 4) pose of the base frame in the odom frame.
    covariance : np.ndarray
        (6, 6) its covariance in ROS order.

    Raises
    ------
    ValueError
        Why the request is ignored: another frame than the odom frame (an empty frame_id is
        the odom frame), an invalid pose, a non-finite covariance.

    """
    if msg.header.frame_id not in ('', odom_frame):
        raise ValueError(f'frame {msg.header.frame_id!r} is not the odom frame '
                         f'{odom_frame!r}')
    T_odom_base = conv.transform_from_pose(msg.pose.pose.position, msg.pose.pose.orientation)
    cov = np.asarray(msg.pose.covariance, np.float64).reshape(6, 6)
    if not np.all(np.isfinite(cov)):
        raise ValueError('non-finite covariance')
    return T_odom_base, cov


def camera_pose_from_base(T_odom_base: np.ndarray, cov: np.ndarray, T_base_cam: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """
    Turn a pose of the base frame in the odom frame into the camera's, for the pipeline.

    Returns
    -------
    T_world_cam : np.ndarray
        (4, 4) pose of the left camera in the pipeline's world frame.
    covariance : np.ndarray
        (6, 6) its covariance in the pipeline's form (``conv.camera_pose_from_base_pose``).

    Raises
    ------
    ValueError
        The pose or its covariance overflows in the camera frame.

    """
    try:
        with np.errstate(all='ignore'):
            T_world_cam, cov_world = conv.camera_pose_from_base_pose(T_odom_base, cov,
                                                                     T_base_cam)
    except ValueError:  # LinAlgError included
        T_world_cam = cov_world = np.full((4, 4), np.nan)
    if not (np.all(np.isfinite(T_world_cam)) and np.all(np.isfinite(cov_world))):
        raise ValueError('the pose or its covariance overflows in the camera frame (position '
                         f'{T_odom_base[:3, 3]} m)')
    return T_world_cam, cov_world
