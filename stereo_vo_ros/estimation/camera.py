"""
Stereo camera model and calibration, built from the fields of two ``CameraInfo`` messages.

Two input kinds are supported:

* ``rectified``: the images are already rectified; the 3x4 projection matrices P of both cameras
  describe them (``P_right[0, 3] = -fx * baseline``). Measurements are the pixel coordinates.
* ``raw``: the images carry lens distortion; K and D describe each camera, and the rectification
  rotations R of both cameras plus P of the right one give the extrinsics between the cameras.
  Tracked points are undistorted to the ideal pinhole image of the camera's own K; the images
  are never rectified (Kitt et al. needs no rectification, only calibration).

Frames: camera optical frames (x right, y down, z forward, metres). The extrinsics map points
from the left camera frame into the right one: ``X_right = R_right_left @ X_left + t_right_left``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
import pickle
from typing import Any, Mapping
import weakref

import cv2
import numpy as np

from ..errors import CalibrationError

INPUT_KINDS = ('rectified', 'raw')
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)


def _undistort_points(pts: np.ndarray, K_raw: np.ndarray, D: np.ndarray,
                      K_new: np.ndarray) -> np.ndarray:
    """
    ``cv2.undistortPoints`` with ``_UNDISTORT_CRITERIA``, on any OpenCV this package supports.

    OpenCV 4 exposes the iteration criteria only as ``undistortPointsIter`` (which needs an
    explicit R); OpenCV 5 folds them into ``undistortPoints``.
    """
    if hasattr(cv2, 'undistortPointsIter'):
        return cv2.undistortPointsIter(pts, K_raw, D, np.eye(3), K_new, _UNDISTORT_CRITERIA)
    return cv2.undistortPoints(pts, K_raw, D, R=None, P=K_new, criteria=_UNDISTORT_CRITERIA)


@dataclass(frozen=True)
class CameraModel:
    """
    One camera as a ``sensor_msgs/CameraInfo`` describes it.

    Attributes
    ----------
    K : (3, 3) float64 intrinsics of the raw image (pixels).
    D : (n,) float64 distortion coefficients (plumb_bob / rational_polynomial order).
    R : (3, 3) float64 rectification rotation, camera frame -> rectified frame.
    P : (3, 4) float64 projection matrix of the rectified image (pixels).
    width, height : image size (pixels).
    distortion_model : the CameraInfo distortion model name.

    """

    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    width: int
    height: int
    distortion_model: str = 'plumb_bob'

    @classmethod
    def from_fields(cls, info: Mapping[str, Any] | Any, name: str = 'camera') -> 'CameraModel':
        """
        Build from a CameraInfo message or a mapping with k, d, r, p, width, height.

        Accepts both the ROS 2 field names (``k``, ``d``, ``r``, ``p``) and upper-case ones.
        """
        def get(key: str, default: Any = None) -> Any:
            for k in (key, key.upper()):
                if isinstance(info, Mapping):
                    if k in info:
                        return info[k]
                elif hasattr(info, k):
                    return getattr(info, k)
            return default

        def arr(key: str, shape: tuple[int, ...]) -> np.ndarray:
            value = get(key)
            if value is None:
                raise CalibrationError(f'{name} calibration has no {key!r}')
            a = np.asarray(value, dtype=np.float64)
            if a.size != int(np.prod(shape)):
                raise CalibrationError(
                    f'{name} calibration {key!r} must have {int(np.prod(shape))} values, '
                    f'got {a.size}')
            return a.reshape(shape)

        d = get('d', [])
        return cls(K=arr('k', (3, 3)), D=np.asarray(d if d is not None else [], np.float64),
                   R=arr('r', (3, 3)), P=arr('p', (3, 4)), width=int(get('width', 0)),
                   height=int(get('height', 0)),
                   distortion_model=str(get('distortion_model', 'plumb_bob') or 'plumb_bob'))


def _check_intrinsics(K: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(K)):
        raise CalibrationError(f'{what} has non-finite values: {K.ravel().tolist()}')
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(
            f'{what} focal length must be positive, got fx={float(K[0, 0])!r}, '
            f'fy={float(K[1, 1])!r}')
    if abs(K[2, 2] - 1.0) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9:
        raise CalibrationError(f'{what} last row must be (0, 0, 1), got {K[2].tolist()}')


def _check_rotation(R: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(R)) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or \
            np.linalg.det(R) < 0:
        raise CalibrationError(f'{what} is not a rotation matrix: {R.ravel().tolist()}')


@dataclass(frozen=True)
class StereoCalibration:
    """
    Calibrated stereo pair in the form the estimator and the tracker use.

    Attributes
    ----------
    left, right : CameraModel
        The two cameras as given.
    kind : str
        ``rectified`` or ``raw`` (see the module docstring).
    K_left, K_right : (3, 3) float64
        Intrinsics of the ideal pinhole images in which measurements are expressed (pixels).
    R_right_left : (3, 3) float64
        Rotation from the left to the right camera frame.
    t_right_left : (3,) float64
        Translation from the left to the right camera frame (m).
    baseline_m : float
        Distance between the optical centres (m), positive.

    """

    left: CameraModel
    right: CameraModel
    kind: str
    K_left: np.ndarray = field(repr=False)
    K_right: np.ndarray = field(repr=False)
    R_right_left: np.ndarray = field(repr=False)
    t_right_left: np.ndarray = field(repr=False)
    baseline_m: float = 0.0

    # -- construction --------------------------------------------------------------------
    @classmethod
    def from_camera_info(cls, left: Any, right: Any, kind: str = 'rectified'
                         ) -> 'StereoCalibration':
        """
        Build and validate from two CameraInfo messages (or mappings of their fields).

        Raises
        ------
        CalibrationError
            Non-finite values, non-positive focal length, zero or negative baseline, left and
            right image sizes that differ, or a zero image size.

        """
        return cls.from_models(CameraModel.from_fields(left, 'left'),
                               CameraModel.from_fields(right, 'right'), kind)

    @classmethod
    def from_models(cls, left: CameraModel, right: CameraModel, kind: str = 'rectified'
                    ) -> 'StereoCalibration':
        """Build and validate from two CameraModel records (see ``from_camera_info``)."""
        try:
            return cls._from_models(left, right, kind)
        except np.linalg.LinAlgError as exc:  # e.g. tiny focal lengths with a skew term
            raise CalibrationError(f'calibration matrices are numerically singular ({exc}): '
                                   f'left P {left.P.ravel().tolist()}, right P '
                                   f'{right.P.ravel().tolist()}') from None

    @classmethod
    def _from_models(cls, left: CameraModel, right: CameraModel, kind: str
                     ) -> 'StereoCalibration':
        if kind not in INPUT_KINDS:
            raise CalibrationError(f'calibration kind must be one of {INPUT_KINDS}, got {kind!r}')
        for cam, name in ((left, 'left'), (right, 'right')):
            if cam.width <= 0 or cam.height <= 0:
                raise CalibrationError(
                    f'{name} image size must be positive, got {cam.width}x{cam.height}')
            if not np.all(np.isfinite(cam.P)):
                raise CalibrationError(f'{name} P has non-finite values: {cam.P.ravel().tolist()}')
            _check_intrinsics(cam.P[:, :3], f'{name} P')
        if (left.width, left.height) != (right.width, right.height):
            raise CalibrationError(
                f'left and right image sizes differ: {left.width}x{left.height} vs '
                f'{right.width}x{right.height}')
        K_rect_l, K_rect_r = left.P[:, :3], right.P[:, :3]
        t_rect = np.linalg.solve(K_rect_r, right.P[:, 3]) - np.linalg.solve(K_rect_l, left.P[:, 3])
        if kind == 'rectified':
            K_left, K_right = K_rect_l.copy(), K_rect_r.copy()
            R_rl, t_rl = np.eye(3), t_rect
        else:
            for cam, name in ((left, 'left'), (right, 'right')):
                _check_intrinsics(cam.K, f'{name} K')
                _check_rotation(cam.R, f'{name} R')
                if not np.all(np.isfinite(cam.D)):
                    raise CalibrationError(f'{name} D has non-finite values: {cam.D.tolist()}')
            K_left, K_right = left.K.copy(), right.K.copy()
            # x_rect = R x_cam for each camera; X_rect_right = X_rect_left + t_rect.
            R_rl = right.R.T @ left.R
            t_rl = right.R.T @ t_rect
        baseline = float(np.linalg.norm(t_rect))
        if not np.isfinite(baseline) or baseline < 1e-6:
            raise CalibrationError(
                f'stereo baseline must be positive, got {float(baseline)!r} m '
                f'(right P[0,3] = {float(right.P[0, 3])!r})')
        if t_rect[0] >= 0:
            raise CalibrationError(
                f'right camera must be to the right of the left one (P_right[0,3] = -fx * '
                f'baseline < 0), got a baseline of {float(-t_rect[0])!r} m')
        return cls(left=left, right=right, kind=kind, K_left=K_left, K_right=K_right,
                   R_right_left=R_rl, t_right_left=t_rl, baseline_m=baseline)

    @classmethod
    def from_projections(cls, P_left: np.ndarray, P_right: np.ndarray, width: int,
                         height: int) -> 'StereoCalibration':
        """Build a rectified calibration from two 3x4 projection matrices (KITTI calib.txt)."""
        def model(P: np.ndarray) -> CameraModel:
            P = np.asarray(P, np.float64).reshape(3, 4)
            return CameraModel(K=P[:, :3].copy(), D=np.zeros(5), R=np.eye(3), P=P.copy(),
                               width=int(width), height=int(height))
        return cls.from_models(model(P_left), model(P_right), 'rectified')

    # -- geometry ---------------------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        """Return the image size as (width, height) in pixels."""
        return self.left.width, self.left.height

    def projection_left(self) -> np.ndarray:
        """Return (3, 4) P of the left camera in its own frame: K_left [I | 0]."""
        return np.hstack([self.K_left, np.zeros((3, 1))])

    def projection_right(self) -> np.ndarray:
        """Return (3, 4) P of the right camera in the left camera frame."""
        return self.K_right @ np.hstack([self.R_right_left, self.t_right_left[:, None]])

    def fundamental(self) -> np.ndarray:
        """Return F (3, 3) with ``x_right^T F x_left = 0`` for ideal pixel coordinates."""
        t = self.t_right_left
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        return np.linalg.inv(self.K_right).T @ tx @ self.R_right_left @ np.linalg.inv(self.K_left)

    def epipolar_distance(self, x_left: np.ndarray, x_right: np.ndarray) -> np.ndarray:
        """
        Distance (pixels) of right points to the epipolar lines of left points.

        For rectified input this is ``|y_left - y_right|`` (eq. 6 of Huang et al.). Inputs are
        (N, 2) ideal pixel coordinates; returns (N,) float64.
        """
        x_left = np.asarray(x_left, np.float64)
        x_right = np.asarray(x_right, np.float64)
        if self.kind == 'rectified':
            return np.abs(x_left[:, 1] - x_right[:, 1])
        hl = np.hstack([x_left, np.ones((len(x_left), 1))])
        hr = np.hstack([x_right, np.ones((len(x_right), 1))])
        lines = hl @ self.fundamental().T
        return np.abs(np.sum(lines * hr, axis=1)) / np.maximum(
            np.hypot(lines[:, 0], lines[:, 1]), 1e-12)

    def disparity(self, x_left: np.ndarray, x_right: np.ndarray) -> np.ndarray:
        """Horizontal disparity x_left - x_right (pixels) in the rectified geometry, (N,)."""
        if self.kind == 'rectified':
            return np.asarray(x_left)[:, 0] - np.asarray(x_right)[:, 0]
        rl = self._to_rectified(x_left, self.K_left, self.left)
        rr = self._to_rectified(x_right, self.K_right, self.right)
        return rl[:, 0] - rr[:, 0]

    def _to_rectified(self, pts: np.ndarray, K: np.ndarray, cam: CameraModel) -> np.ndarray:
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        h = np.hstack([pts, np.ones((len(pts), 1))]) @ np.linalg.inv(K).T @ cam.R.T
        h = h @ cam.P[:, :3].T
        return h[:, :2] / h[:, 2:3]

    def undistort_left(self, pts: np.ndarray) -> np.ndarray:
        """Raw left pixels (N, 2) -> ideal pinhole pixels of K_left; identity if rectified."""
        return self._undistort(pts, self.left, self.K_left)

    def undistort_right(self, pts: np.ndarray) -> np.ndarray:
        """Raw right pixels (N, 2) -> ideal pinhole pixels of K_right; identity if rectified."""
        return self._undistort(pts, self.right, self.K_right)

    def _undistort(self, pts: np.ndarray, cam: CameraModel, K: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        if self.kind == 'rectified' or len(pts) == 0 or not np.any(cam.D):
            return pts.copy()
        # OpenCV's default 5 iterations leave ~0.1 px errors at strong distortion; iterate more.
        out = _undistort_points(pts.reshape(-1, 1, 2), cam.K, cam.D, K)
        return out.reshape(-1, 2).astype(np.float64)

    def distort_left(self, pts: np.ndarray) -> np.ndarray:
        """Ideal left pixels (N, 2) -> raw (distorted) pixels; identity if rectified."""
        return self._distort(pts, self.left, self.K_left)

    def distort_right(self, pts: np.ndarray) -> np.ndarray:
        """Ideal right pixels (N, 2) -> raw (distorted) pixels; identity if rectified."""
        return self._distort(pts, self.right, self.K_right)

    def _distort(self, pts: np.ndarray, cam: CameraModel, K: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        if self.kind == 'rectified' or len(pts) == 0 or not np.any(cam.D):
            return pts.copy()
        rays = np.hstack([pts, np.ones((len(pts), 1))]) @ np.linalg.inv(K).T
        out, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K,
                                   cam.D)
        return out.reshape(-1, 2).astype(np.float64)

    def __reduce__(self) -> tuple:
        """
        Pickle by value (``_restore_calibration``: one object per value in a worker).

        The fields are pickled into one ``bytes`` value, which a worker process looks its
        calibrations up by without unpickling them.
        """
        return (_restore_calibration, (pickle.dumps(tuple(getattr(self, f.name) for f in
                                                          fields(self)),
                                                    protocol=pickle.HIGHEST_PROTOCOL),))

    def same_as(self, other: 'StereoCalibration | None') -> bool:
        """Return True if ``other`` describes the same geometry (used to detect changes)."""
        if other is self:
            return True
        if other is None or other.kind != self.kind or other.size != self.size:
            return False
        return all(np.array_equal(a, b) for a, b in (
            (self.left.P, other.left.P), (self.right.P, other.right.P),
            (self.left.K, other.left.K), (self.right.K, other.right.K),
            (self.left.D, other.left.D) if self.left.D.shape == other.left.D.shape else (0, 1),
            (self.right.D, other.right.D) if self.right.D.shape == other.right.D.shape else (0, 1),
            (self.left.R, other.left.R), (self.right.R, other.right.R)))


#: Calibrations unpickled in this process, by their pickled values, once
#: ``share_unpickled_calibrations`` was called (a worker process): an equal one then comes back
#: as the same object, so the caches keyed by the calibration object (the transfer model's pair
#: geometry) hold across the jobs the process receives. None: every unpickling (and copy) makes
#: a new object.
_UNPICKLED: 'weakref.WeakValueDictionary[bytes, StereoCalibration] | None' = None


def share_unpickled_calibrations() -> None:
    """Make equal calibrations unpickle as one object in this process (worker processes)."""
    global _UNPICKLED
    if _UNPICKLED is None:
        _UNPICKLED = weakref.WeakValueDictionary()


def _restore_calibration(value: bytes) -> StereoCalibration:
    """Return the calibration of ``value`` (its fields in order, pickled); see ``_UNPICKLED``."""
    calib = None if _UNPICKLED is None else _UNPICKLED.get(value)
    if calib is None:
        calib = StereoCalibration(*pickle.loads(value))
        if _UNPICKLED is not None:
            _UNPICKLED[value] = calib
    return calib
