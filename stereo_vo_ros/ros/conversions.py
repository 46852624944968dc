"""
Conversions between ROS 2 messages and the package's numpy records.

Images: ``sensor_msgs/Image`` <-> numpy without cv_bridge (mono8, mono16, rgb8, bgr8, rgba8,
bgra8), honouring the row stride ``step`` and ``is_bigendian``. Calibration: two
``sensor_msgs/CameraInfo`` -> ``StereoCalibration``. Odometry: an ``OdometryResult`` (pose of
the left camera optical frame in the first left camera frame) -> REP-103/105 body odometry
(pose of ``base_link`` in ``odom``) and the ``nav_msgs/Odometry``, ``PoseStamped``,
``TransformStamped`` and ``DiagnosticStatus`` messages the node publishes.

Frames and conventions:

* ``T_a_b`` is a (4, 4) float64 homogeneous transform taking points from frame b to frame a.
* ``cam``: left camera optical frame (x right, y down, z forward); ``world``: ``cam`` at the
  first frame. ``base``: robot body frame (x forward, y left, z up, REP-103); ``odom``: ``base``
  at the first frame (REP-105). Hence ``T_odom_world = T_base_cam`` and
  ``T_odom_base = T_base_cam @ T_world_cam @ inv(T_base_cam)``.
* Pose covariance in ROS order (x, y, z, rot_x, rot_y, rot_z): the pipeline gives a left
  perturbation in ``world`` (``T = exp(d) T_world_cam``); the message carries the position error
  in ``odom`` and the orientation error about the fixed ``odom`` axes (``p' = p + dp``,
  ``R' = exp(dtheta) R``), the reading ROS tools use.
* Twist (v [m/s], w [rad/s]) in the child frame ``base``, covariance in the same order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

from builtin_interfaces.msg import Time
import cv2
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
import numpy as np
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image

from ..errors import ImageError
from ..estimation.camera import StereoCalibration
from ..records import Correspondences, OdometryResult, TrackingStatus

#: encoding -> (numpy dtype of one channel, channels). Everything else raises ImageError.
ENCODINGS: dict[str, tuple[type, int]] = {
    'mono8': (np.uint8, 1),
    'mono16': (np.uint16, 1),
    'rgb8': (np.uint8, 3),
    'bgr8': (np.uint8, 3),
    'rgba8': (np.uint8, 4),
    'bgra8': (np.uint8, 4),
}
_TO_GREY = {'rgb8': cv2.COLOR_RGB2GRAY, 'bgr8': cv2.COLOR_BGR2GRAY,
            'rgba8': cv2.COLOR_RGBA2GRAY, 'bgra8': cv2.COLOR_BGRA2GRAY}

#: Smallest variance (m^2, rad^2, (m/s)^2, (rad/s)^2) on the diagonal of every published
#: covariance: keeps it positive definite (the first pose is exact by definition of odom).
MIN_VARIANCE = 1e-9
#: Smallest variance put on the diagonal while tracking is LOST ("large but finite").
LOST_VARIANCE = 1e3


# -- images ------------------------------------------------------------------------------
def numpy_from_image(msg: Image) -> np.ndarray:
    """
    Return the pixels of an Image message as an array in native byte order.

    Parameters
    ----------
    msg : sensor_msgs.msg.Image
        Image with one of the encodings in ``ENCODINGS``; rows may be padded (``step`` larger
        than ``width * bytes per pixel``); mono16 may be big-endian.

    Returns
    -------
    np.ndarray
        (H, W) for mono encodings or (H, W, C) for colour ones, uint8 or uint16, channel
        order as the encoding names it. A copy, independent of ``msg``.

    Raises
    ------
    ImageError
        Unsupported encoding, zero size, a step shorter than a row, or a data length other
        than ``step * height``.

    """
    encoding = str(msg.encoding)
    if encoding not in ENCODINGS:
        raise ImageError(f'unsupported image encoding {encoding!r}; supported: '
                         f'{sorted(ENCODINGS)}')
    dtype, channels = ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise ImageError(f'image size must be positive, got {width}x{height} ({encoding})')
    row_bytes = width * channels * np.dtype(dtype).itemsize
    if step < row_bytes:
        raise ImageError(f'image step {step} is shorter than a row of {width} {encoding} '
                         f'pixels ({row_bytes} bytes)')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size != step * height:
        raise ImageError(f'image data has {buf.size} bytes, expected step*height = '
                         f'{step}*{height} = {step * height} ({encoding} {width}x{height})')
    rows = buf[:step * height].reshape(height, step)[:, :row_bytes]
    wire = np.dtype(dtype)
    if wire.itemsize > 1:
        wire = wire.newbyteorder('>' if msg.is_bigendian else '<')
    pixels = np.ascontiguousarray(rows).view(wire).astype(dtype)  # astype copies
    shape = (height, width) if channels == 1 else (height, width, channels)
    return pixels.reshape(shape)


def grey_from_image(msg: Image) -> np.ndarray:
    """
    Return an Image message as a grey array for the tracker.

    Returns
    -------
    np.ndarray
        (H, W) uint8 (8-bit encodings) or uint16 (mono16) grey image, C-contiguous copy.

    Raises
    ------
    ImageError
        See ``numpy_from_image``.

    """
    pixels = numpy_from_image(msg)
    if pixels.ndim == 2:
        return pixels
    return cv2.cvtColor(pixels, _TO_GREY[str(msg.encoding)])


def image_from_numpy(pixels: np.ndarray, encoding: str, stamp: Time | None = None,
                     frame_id: str = '') -> Image:
    """
    Build an Image message from an array (unpadded rows, little-endian).

    Parameters
    ----------
    pixels : np.ndarray
        (H, W) or (H, W, C) array whose dtype and channel count match ``encoding``.
    encoding : str
        One of ``ENCODINGS``.
    stamp : builtin_interfaces.msg.Time, optional
        Header stamp (zero if omitted).
    frame_id : str
        Header frame id.

    Raises
    ------
    ImageError
        Unknown encoding, or an array whose dtype or shape does not fit it.

    """
    if encoding not in ENCODINGS:
        raise ImageError(f'unsupported image encoding {encoding!r}; supported: '
                         f'{sorted(ENCODINGS)}')
    dtype, channels = ENCODINGS[encoding]
    pixels = np.asarray(pixels)
    expected = 2 if channels == 1 else 3
    if pixels.ndim != expected or (channels > 1 and pixels.shape[2] != channels) or \
            pixels.dtype != dtype or pixels.size == 0:
        raise ImageError(f'array of shape {pixels.shape} and dtype {pixels.dtype} cannot be '
                         f'encoded as {encoding}')
    msg = Image()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(pixels.shape[0]), int(pixels.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = int(pixels.shape[1] * channels * np.dtype(dtype).itemsize)
    msg.data = np.ascontiguousarray(pixels).astype(np.dtype(dtype).newbyteorder('<'),
                                                   copy=False).tobytes()
    return msg


# -- calibration -------------------------------------------------------------------------
def calibration_from_camera_info(left: CameraInfo, right: CameraInfo,
                                 kind: str = 'rectified') -> StereoCalibration:
    """
    Build the stereo calibration from the CameraInfo of both cameras.

    Raises
    ------
    CalibrationError
        See ``StereoCalibration.from_camera_info``; also for projection matrices that pass
        its checks but are numerically singular.

    """
    return StereoCalibration.from_camera_info(left, right, kind)


def camera_info_from_matrices(P: np.ndarray, width: int, height: int,
                              K: np.ndarray | None = None, D: Sequence[float] | None = None,
                              R: np.ndarray | None = None, stamp: Time | None = None,
                              frame_id: str = '') -> CameraInfo:
    """
    Build a CameraInfo message.

    Parameters
    ----------
    P : np.ndarray
        (3, 4) projection matrix of the rectified image (pixels).
    width, height : int
        Image size (pixels).
    K : np.ndarray, optional
        (3, 3) raw intrinsics; default ``P[:, :3]``.
    D : sequence of float, optional
        plumb_bob distortion; default five zeros.
    R : np.ndarray, optional
        (3, 3) rectification rotation; default identity.
    stamp, frame_id
        Header fields.

    """
    P = np.asarray(P, np.float64).reshape(3, 4)
    msg = CameraInfo()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(width), int(height)
    msg.distortion_model = 'plumb_bob'
    msg.d = [float(v) for v in (D if D is not None else [0.0] * 5)]
    msg.k = np.asarray(P[:, :3] if K is None else K, np.float64).ravel().tolist()
    msg.r = np.asarray(np.eye(3) if R is None else R, np.float64).ravel().tolist()
    msg.p = P.ravel().tolist()
    return msg


def camera_info_key(msg: CameraInfo) -> tuple:
    """Return a hashable summary of the geometry fields (to notice calibration changes)."""
    return (int(msg.width), int(msg.height), str(msg.distortion_model), tuple(msg.k),
            tuple(msg.d), tuple(msg.r), tuple(msg.p))


# -- time --------------------------------------------------------------------------------
def nanoseconds_from_time(stamp: Time) -> int:
    """Return a ``builtin_interfaces/Time`` as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def time_from_nanoseconds(ns: int) -> Time:
    """Return integer nanoseconds (>= 0) as a ``builtin_interfaces/Time``."""
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def seconds_from_time(stamp: Time) -> float:
    """Return a ``builtin_interfaces/Time`` in seconds."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


# -- geometry ----------------------------------------------------------------------------
def skew(v: np.ndarray) -> np.ndarray:
    """Return the (3, 3) cross-product matrix of a 3-vector ``v``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def adjoint(T_a_b: np.ndarray) -> np.ndarray:
    """
    Return the (6, 6) adjoint of ``T_a_b`` acting on twists ordered (v, w).

    Maps a twist (or a left perturbation) expressed in frame b to frame a.
    """
    R, t = T_a_b[:3, :3], T_a_b[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[:3, 3:] = skew(t) @ R
    return A


def transform_from_xyz_rpy(xyz: Sequence[float], rpy_deg: Sequence[float]) -> np.ndarray:
    """
    Return the (4, 4) transform with translation ``xyz`` (m) and fixed-axis roll, pitch, yaw.

    The rotation is ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (the URDF / tf2 convention); angles in
    degrees. With ``rpy_deg = (-90, 0, -90)`` it is the optical-to-body rotation
    (camera z forward -> body x forward, camera x right -> body -y, camera y down -> body -z).
    """
    xyz = np.asarray(xyz, np.float64).reshape(3)
    rpy = np.asarray(rpy_deg, np.float64).reshape(3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('xyz', rpy, degrees=True).as_matrix()
    T[:3, 3] = xyz
    return T


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """Return the unit quaternion (x, y, z, w) of a (3, 3) rotation matrix, w >= 0."""
    q = Rotation.from_matrix(np.asarray(R, np.float64)).as_quat()
    return -q if q[3] < 0 else q


def transform_from_pose(position: Any, orientation: Any) -> np.ndarray:
    """Return the (4, 4) transform of a ``geometry_msgs`` Point/Vector3 and Quaternion."""
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f'quaternion must be finite and non-zero, got {q.tolist()}')
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    T[:3, 3] = [position.x, position.y, position.z]
    return T


def spd(cov: np.ndarray, floor: float = MIN_VARIANCE) -> np.ndarray:
    """Return the symmetric matrix nearest to ``cov`` whose eigenvalues are at least ``floor``."""
    cov = 0.5 * (np.asarray(cov, np.float64) + np.asarray(cov, np.float64).T)
    w, V = np.linalg.eigh(cov)
    if w.min() >= floor:
        return cov
    return (V * np.maximum(w, floor)) @ V.T


def _decouple(T_odom_base: np.ndarray) -> np.ndarray:
    """Jacobian (6, 6) from a left perturbation in odom to (dp, dtheta) about odom axes."""
    J = np.eye(6)
    J[:3, 3:] = -skew(T_odom_base[:3, 3])
    return J


@dataclass
class BaseOdometry:
    """
    Odometry of the robot body in REP-103/105 frames.

    Attributes
    ----------
    T_odom_base : np.ndarray
        (4, 4) float64 pose of ``base`` in ``odom`` (m).
    pose_covariance : np.ndarray
        (6, 6) float64, ROS order (x, y, z, rot_x, rot_y, rot_z): position error in ``odom``
        (m^2) and orientation error about the fixed ``odom`` axes (rad^2).
    twist : np.ndarray
        (6,) float64 (v [m/s], w [rad/s]) of ``base`` expressed in ``base``.
    twist_covariance : np.ndarray
        (6, 6) float64 covariance of ``twist``.

    """

    T_odom_base: np.ndarray
    pose_covariance: np.ndarray
    twist: np.ndarray
    twist_covariance: np.ndarray

    def is_finite(self) -> bool:
        """Return True if every value is finite (nothing else may be published)."""
        return all(np.all(np.isfinite(a)) for a in (
            self.T_odom_base, self.pose_covariance, self.twist, self.twist_covariance))


def base_odometry_from_result(result: OdometryResult, T_base_cam: np.ndarray
                              ) -> BaseOdometry:
    """
    Convert the camera odometry of the pipeline to body odometry (REP-103/105).

    Parameters
    ----------
    result : OdometryResult
        ``T_world_cam`` (4, 4), ``pose_covariance`` (6, 6, left perturbation in ``world``),
        ``velocity`` (6,) and ``velocity_covariance`` (6, 6) in the current camera frame.
    T_base_cam : np.ndarray
        (4, 4) pose of the left camera optical frame in the body frame (m).

    Returns
    -------
    BaseOdometry
        Pose of ``base`` in ``odom`` (``odom`` = ``base`` at the first frame), covariances
        made symmetric positive definite (at least ``MIN_VARIANCE`` on the diagonal, at least
        ``LOST_VARIANCE`` while the status is LOST). Non-finite input, values that overflow
        and covariances too large to decompose give a non-finite result (check with
        ``is_finite``).

    """
    A = np.asarray(T_base_cam, np.float64)
    A_inv = np.linalg.inv(A)
    with np.errstate(all='ignore'):  # overflow shows as inf: see is_finite
        T_odom_base = A @ np.asarray(result.T_world_cam, np.float64) @ A_inv
        Ad = adjoint(A)
        J = _decouple(T_odom_base) @ Ad
        pose_cov = J @ np.asarray(result.pose_covariance, np.float64) @ J.T
        twist = Ad @ np.asarray(result.velocity, np.float64)
        twist_cov = Ad @ np.asarray(result.velocity_covariance, np.float64) @ Ad.T
    odom = BaseOdometry(T_odom_base, pose_cov, twist, twist_cov)
    if not odom.is_finite():
        return odom
    floor = LOST_VARIANCE if result.status is TrackingStatus.LOST else MIN_VARIANCE
    try:
        with np.errstate(all='ignore'):
            odom.pose_covariance = spd(pose_cov, floor)
            odom.twist_covariance = spd(twist_cov, floor)
    except np.linalg.LinAlgError:  # eigh fails on values near the float64 limits
        odom.pose_covariance = np.full((6, 6), np.nan)
    return odom


def camera_pose_from_base_pose(T_odom_base: np.ndarray, pose_covariance: np.ndarray | None,
                               T_base_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Inverse of the pose part of ``base_odometry_from_result``.

    Parameters
    ----------
    T_odom_base : np.ndarray
        (4, 4) pose of ``base`` in ``odom``.
    pose_covariance : np.ndarray or None
        (6, 6) ROS-order covariance as in ``BaseOdometry`` (None: zeros).
    T_base_cam : np.ndarray
        (4, 4) pose of the left camera in ``base``.

    Returns
    -------
    T_world_cam : np.ndarray
        (4, 4) pose of the left camera in ``world``.
    covariance : np.ndarray
        (6, 6) left perturbation covariance in ``world`` (the pipeline's form).

    """
    A = np.asarray(T_base_cam, np.float64)
    T_odom_base = np.asarray(T_odom_base, np.float64)
    T_world_cam = np.linalg.inv(A) @ T_odom_base @ A
    cov = np.zeros((6, 6)) if pose_covariance is None else \
        np.asarray(pose_covariance, np.float64).reshape(6, 6)
    J_inv = np.linalg.inv(_decouple(T_odom_base) @ adjoint(A))
    return T_world_cam, J_inv @ cov @ J_inv.T


# -- messages ----------------------------------------------------------------------------
def _fill_pose(pose: Any, T: np.ndarray) -> None:
    q = quaternion_from_rotation(T[:3, :3])
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (
        float(v) for v in q)


def odometry_msg(odom: BaseOdometry, stamp: Time, odom_frame: str, base_frame: str
                 ) -> Odometry:
    """Build ``nav_msgs/Odometry``: pose in ``odom_frame``, twist in ``base_frame``."""
    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = odom_frame
    msg.child_frame_id = base_frame
    _fill_pose(msg.pose.pose, odom.T_odom_base)
    msg.pose.covariance = np.asarray(odom.pose_covariance, np.float64).ravel().tolist()
    tw = np.asarray(odom.twist, np.float64)
    msg.twist.twist.linear.x, msg.twist.twist.linear.y, msg.twist.twist.linear.z = (
        float(v) for v in tw[:3])
    msg.twist.twist.angular.x, msg.twist.twist.angular.y, msg.twist.twist.angular.z = (
        float(v) for v in tw[3:])
    msg.twist.covariance = np.asarray(odom.twist_covariance, np.float64).ravel().tolist()
    return msg


def pose_stamped_msg(T: np.ndarray, stamp: Time, frame_id: str) -> PoseStamped:
    """Build ``geometry_msgs/PoseStamped`` from a (4, 4) pose in ``frame_id``."""
    msg = PoseStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    _fill_pose(msg.pose, np.asarray(T, np.float64))
    return msg


def transform_msg(T_parent_child: np.ndarray, stamp: Time, parent: str, child: str
                  ) -> TransformStamped:
    """Build ``geometry_msgs/TransformStamped`` (the pose of ``child`` in ``parent``)."""
    T = np.asarray(T_parent_child, np.float64)
    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = parent
    msg.child_frame_id = child
    q = quaternion_from_rotation(T[:3, :3])
    tr = msg.transform.translation
    tr.x, tr.y, tr.z = (float(v) for v in T[:3, 3])
    ro = msg.transform.rotation
    ro.x, ro.y, ro.z, ro.w = (float(v) for v in q)
    return msg


def diagnostic_status(level: bytes, name: str, message: str, values: Mapping[str, Any],
                      hardware_id: str = '') -> DiagnosticStatus:
    """Build ``diagnostic_msgs/DiagnosticStatus`` with one KeyValue per entry of ``values``."""
    status = DiagnosticStatus()
    status.level = level
    status.name = name
    status.message = message
    status.hardware_id = hardware_id
    status.values = [KeyValue(key=str(k), value=_format_value(v)) for k, v in values.items()]
    return status


def _format_value(value: Any) -> str:
    if isinstance(value, float):
        return f'{value:.6g}'
    return str(value)


# -- debug image -------------------------------------------------------------------------
def _to_bgr8(grey: np.ndarray) -> np.ndarray:
    if grey.dtype == np.uint16:
        top = max(int(grey.max()), 1)
        grey = cv2.convertScaleAbs(grey, alpha=255.0 / top)
    return cv2.cvtColor(np.ascontiguousarray(grey, np.uint8), cv2.COLOR_GRAY2BGR)


def _dots(img: np.ndarray, pts: np.ndarray, colour: tuple[int, int, int]) -> None:
    """Paint 3x3 squares at pixel positions (N, 2) in place (vectorised)."""
    if len(pts) == 0:
        return
    h, w = img.shape[:2]
    centre = np.round(pts).astype(np.int64)
    offsets = np.stack(np.meshgrid(np.arange(-1, 2), np.arange(-1, 2)), -1).reshape(-1, 2)
    xy = (centre[:, None, :] + offsets[None]).reshape(-1, 2)
    keep = (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
    img[xy[keep, 1], xy[keep, 0]] = colour


def debug_image(left: np.ndarray, features: Correspondences | None,
                inliers: np.ndarray | None) -> np.ndarray:
    """
    Draw the tracked features on the left image.

    Parameters
    ----------
    left : np.ndarray
        (H, W) uint8 or uint16 grey left image.
    features : Correspondences or None
        Correspondences of the frame; lines join the previous and current left positions
        (pixels; drawn as given, i.e. in the ideal pinhole image).
    inliers : np.ndarray or None
        (N,) bool mask; inliers are green, outliers red, features without a mask yellow.

    Returns
    -------
    np.ndarray
        (H, W, 3) uint8 BGR image.

    """
    img = _to_bgr8(left)
    if features is None or len(features) == 0:
        return img
    cur = np.asarray(features.cur_left, np.float64)
    prev = np.asarray(features.prev_left, np.float64)
    finite = np.all(np.isfinite(cur), axis=1) & np.all(np.isfinite(prev), axis=1)
    if inliers is None or len(inliers) != len(cur):
        groups = [(finite, (0, 255, 255))]
    else:
        mask = np.asarray(inliers, bool)
        groups = [(finite & mask, (0, 255, 0)), (finite & ~mask, (0, 0, 255))]
    for sel, colour in groups:
        lines = np.stack([prev[sel], cur[sel]], axis=1).round().astype(np.int32)
        if len(lines):
            cv2.polylines(img, list(lines), False, colour, 1, cv2.LINE_AA)
        _dots(img, cur[sel], colour)
    return img
