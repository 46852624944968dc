"""
Stereo correspondence files (.npz) and the egomotion of a whole correspondence sequence.

This is the input of ``stereo_vo estimate CORR.npz --poses OUT.txt [--config FILE]``: stereo
correspondences from any front end (another tracker, a simulation), turned into a trajectory by
the egomotion estimator of Kitt et al. without any image.

File format
-----------
A NumPy ``.npz`` archive (``numpy.savez``; no pickled objects) with these keys:

``prev_left``, ``prev_right``, ``cur_left``, ``cur_right``
    float arrays of shape (M, N, 2): pixel coordinates (x right, y down) of N matched points
    for each of M consecutive frame pairs. Row ``n`` of frame pair ``k`` is one point seen in
    the left and right images of stereo frame ``k`` (``prev_*``) and of stereo frame ``k + 1``
    (``cur_*``). Coordinates are in the rectified (ideal pinhole) images that ``P0`` and ``P1``
    describe. A point missing in a frame pair is a row containing NaN (any of its 8 numbers);
    N is the largest number of points of any pair, shorter pairs are padded with NaN rows.
    Infinite values are rejected.
``P0``, ``P1``
    float (3, 4) rectified projection matrices of the left and right cameras (pixels), as in a
    KITTI ``calib.txt``: ``P1[0, 3] = -fx * baseline`` with the baseline in metres.
``rate``
    float scalar, frame rate in Hz: stereo frame ``k`` was taken at ``k / rate`` seconds.

Optional keys:

``width``, ``height``
    int scalars, image size in pixels (used by bucketing). Without them the size is twice the
    principal point, enlarged when needed so that every point lies inside the image.
``stamps``
    float (M + 1,) capture times of the stereo frames in seconds, strictly increasing; when
    present they give the time steps instead of ``rate``.
``gt_poses``
    float (M + 1, 4, 4) ground-truth poses ``T_world_cam`` of the left camera in the frame of
    the first left camera (e.g. written by the simulation).

Any other key is rejected, so a misspelt key is never silently ignored.

The estimated trajectory (:func:`estimate_trajectory`) has M + 1 poses ``T_world_cam``: the
left camera optical frame (x right, y down, z forward, metres) of every stereo frame in the
frame of the first left camera, which is the identity (KITTI convention; write it with
:func:`stereo_vo_ros.evaluation.trajectory.write_kitti`).
"""

from __future__ import annotations

from dataclasses import dataclass
import logging
import math
import os
import time
from typing import Any, Iterator
import zipfile

import numpy as np

from ..config import Config
from ..errors import CalibrationError, DatasetError
from ..estimation.camera import StereoCalibration
from ..estimation.estimator import MotionEstimator
from ..records import Correspondences, MotionEstimate, TrackingStatus

LOG = logging.getLogger(__name__)

POINT_KEYS = ('prev_left', 'prev_right', 'cur_left', 'cur_right')
REQUIRED_KEYS = POINT_KEYS + ('P0', 'P1', 'rate')
OPTIONAL_KEYS = ('width', 'height', 'stamps', 'gt_poses')

PathLike = str | os.PathLike


@dataclass
class CorrespondenceData:
    """
    A sequence of stereo correspondences with its calibration (see the module docstring).

    Attributes
    ----------
    prev_left, prev_right, cur_left, cur_right : np.ndarray
        (M, N, 2) float64 pixels in the rectified images; NaN rows mark missing points.
    P0, P1 : np.ndarray
        (3, 4) float64 rectified projection matrices of the left and right camera (pixels).
    rate : float
        Frame rate (Hz), > 0.
    width, height : int or None
        Image size (pixels); None: derived (see :meth:`image_size`).
    stamps : np.ndarray or None
        (M + 1,) float64 frame times (s), strictly increasing, or None (use ``rate``).
    gt_poses : np.ndarray or None
        (M + 1, 4, 4) float64 ground-truth ``T_world_cam`` of the left camera, or None.

    The constructor validates everything and raises :class:`DatasetError` naming the problem.

    """

    prev_left: np.ndarray
    prev_right: np.ndarray
    cur_left: np.ndarray
    cur_right: np.ndarray
    P0: np.ndarray
    P1: np.ndarray
    rate: float
    width: int | None = None
    height: int | None = None
    stamps: np.ndarray | None = None
    gt_poses: np.ndarray | None = None

    def __post_init__(self) -> None:
        _validate(self, 'correspondence data')

    def __len__(self) -> int:
        """Return the number M of frame pairs."""
        return int(self.prev_left.shape[0])

    @property
    def num_points(self) -> int:
        """Return the number N of point rows per frame pair (including NaN padding)."""
        return int(self.prev_left.shape[1])

    def image_size(self) -> tuple[int, int]:
        """Return (width, height) in pixels, derived from P0 and the points when not given."""
        if self.width is not None and self.height is not None:
            return self.width, self.height
        pts = np.concatenate([getattr(self, k).reshape(-1, 2) for k in POINT_KEYS])
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        far = pts.max(axis=0) if len(pts) else np.zeros(2)
        width = self.width if self.width is not None else \
            max(math.ceil(2.0 * self.P0[0, 2]), math.floor(far[0]) + 1, 1)
        height = self.height if self.height is not None else \
            max(math.ceil(2.0 * self.P0[1, 2]), math.floor(far[1]) + 1, 1)
        return int(width), int(height)

    def calibration(self) -> StereoCalibration:
        """Return the rectified StereoCalibration of ``P0``, ``P1`` and :meth:`image_size`."""
        width, height = self.image_size()
        return StereoCalibration.from_projections(self.P0, self.P1, width, height)

    def time_steps(self) -> np.ndarray:
        """Return (M,) float64 time between consecutive stereo frames (s)."""
        if self.stamps is not None:
            return np.diff(self.stamps)
        return np.full(len(self), 1.0 / self.rate)

    def frame(self, k: int) -> Correspondences:
        """
        Return the correspondences of frame pair ``k`` (all N rows, NaN rows included).

        ``ids`` are the row indices 0..N-1, so the estimator's inlier mask maps to the rows.
        """
        n = self.num_points
        return Correspondences(self.prev_left[k], self.prev_right[k], self.cur_left[k],
                               self.cur_right[k], ids=np.arange(n, dtype=np.int64))

    def arrays(self) -> dict[str, np.ndarray]:
        """Return the archive content: key -> array (optional keys only when set)."""
        out = {k: getattr(self, k) for k in POINT_KEYS}
        out.update(P0=self.P0, P1=self.P1, rate=np.float64(self.rate))
        for key in OPTIONAL_KEYS:
            value = getattr(self, key)
            if value is not None:
                out[key] = np.int64(value) if key in ('width', 'height') else value
        return out


def _validate(data: CorrespondenceData, source: str) -> None:
    """Normalise dtypes in place and check shapes and values; raise DatasetError."""
    shape = None
    for key in POINT_KEYS:
        a = _float_array(getattr(data, key), key, source)
        if a.ndim != 3 or a.shape[2] != 2:
            raise DatasetError(f'{source}: {key} must have shape (M, N, 2), got {a.shape}')
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise DatasetError(f'{source}: {key} has shape {a.shape} but prev_left has {shape}')
        if np.isinf(a).any():
            where = np.argwhere(np.isinf(a))[0]
            raise DatasetError(f'{source}: {key} has an infinite value at frame pair '
                               f'{where[0]}, point {where[1]} (use NaN for missing points)')
        setattr(data, key, a)
    if shape[0] < 1:
        raise DatasetError(f'{source}: no frame pairs (M = 0) in {POINT_KEYS[0]}')
    for key in ('P0', 'P1'):
        P = _float_array(getattr(data, key), key, source)
        if P.shape != (3, 4) or not np.all(np.isfinite(P)):
            raise DatasetError(f'{source}: {key} must be a finite 3x4 matrix, got shape '
                               f'{P.shape}: {P.ravel().tolist()}')
        setattr(data, key, P)
    data.rate = _positive_scalar(data.rate, 'rate', source, float)
    for key in ('width', 'height'):
        value = getattr(data, key)
        if value is not None:
            setattr(data, key, _positive_scalar(value, key, source, int))
    M = shape[0]
    if data.stamps is not None:
        stamps = _float_array(data.stamps, 'stamps', source)
        if stamps.shape != (M + 1,):
            raise DatasetError(f'{source}: stamps must have shape ({M + 1},) for {M} frame '
                               f'pairs, got {stamps.shape}')
        if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) <= 0):
            raise DatasetError(f'{source}: stamps must be finite and strictly increasing')
        data.stamps = stamps
    if data.gt_poses is not None:
        gt = _float_array(data.gt_poses, 'gt_poses', source)
        if gt.shape != (M + 1, 4, 4) or not np.all(np.isfinite(gt)):
            raise DatasetError(f'{source}: gt_poses must be finite with shape ({M + 1}, 4, 4), '
                               f'got {gt.shape}')
        data.gt_poses = gt
    try:
        data.calibration()
    except CalibrationError as exc:
        raise DatasetError(f'{source}: P0/P1 are not a valid rectified stereo pair: {exc}') \
            from None


def _float_array(value: Any, key: str, source: str) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in 'fiu' or a.dtype == np.bool_:
        raise DatasetError(f'{source}: {key} must be numeric, got dtype {a.dtype}')
    return a.astype(np.float64)


def _positive_scalar(value: Any, key: str, source: str, kind: type) -> Any:
    a = np.asarray(value)
    if a.shape not in ((), (1,)) or a.dtype.kind not in 'fiu':
        raise DatasetError(f'{source}: {key} must be a number, got {value!r}')
    x = float(a.reshape(()))
    if not math.isfinite(x) or x <= 0 or (kind is int and not x.is_integer()):
        raise DatasetError(f'{source}: {key} must be a positive {kind.__name__}, got {x!r}')
    return kind(x)


def load_npz(path: PathLike) -> CorrespondenceData:
    """
    Read and validate a correspondence file (format in the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
        The ``.npz`` file.

    Returns
    -------
    CorrespondenceData

    Raises
    ------
    DatasetError
        Unreadable file, missing or unknown key, wrong shape, dtype or value.

    """
    source = repr(os.fspath(path))
    try:
        with np.load(path, allow_pickle=False) as archive:
            content = {key: archive[key] for key in archive.files}
    except FileNotFoundError:
        raise DatasetError(f'correspondence file {source} does not exist') from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f'cannot read correspondence file {source}: {exc}') from None
    if not isinstance(content, dict):  # pragma: no cover - np.load of a .npy
        raise DatasetError(f'{source} is not an .npz archive')
    missing = [k for k in REQUIRED_KEYS if k not in content]
    if missing:
        raise DatasetError(f'{source}: missing key(s) {missing}; present: {sorted(content)}')
    unknown = sorted(set(content) - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
    if unknown:
        raise DatasetError(f'{source}: unknown key(s) {unknown}; allowed: '
                           f'{list(REQUIRED_KEYS + OPTIONAL_KEYS)}')
    data = CorrespondenceData.__new__(CorrespondenceData)
    for key in REQUIRED_KEYS + OPTIONAL_KEYS:
        setattr(data, key, content.get(key))
    _validate(data, source)
    return data


def save_npz(path: PathLike, data: CorrespondenceData) -> None:
    """
    Write ``data`` as an uncompressed ``.npz`` correspondence file (float64, no pickles).

    Parameters
    ----------
    path : str or os.PathLike
        Output file; NumPy appends ``.npz`` when the name has another suffix.
    data : CorrespondenceData
        Validated data (build it with the constructor).

    Raises
    ------
    DatasetError
        The file cannot be written.

    """
    try:
        np.savez(path, **data.arrays())
    except OSError as exc:
        raise DatasetError(f'cannot write correspondence file {os.fspath(path)!r}: '
                           f'{exc.strerror or exc}') from None


@dataclass
class FrameEstimate:
    """
    The estimator's output for one frame pair.

    Attributes
    ----------
    index : int
        Frame pair k (stereo frame k -> k + 1).
    estimate : MotionEstimate
        What :meth:`MotionEstimator.estimate` returned.
    T_world_cam : np.ndarray
        (4, 4) float64 pose of the left camera of stereo frame k + 1 in the first left frame.
    elapsed_ms : float
        Wall time of the ``estimate`` call (milliseconds).

    """

    index: int
    estimate: MotionEstimate
    T_world_cam: np.ndarray
    elapsed_ms: float


def iter_estimates(data: CorrespondenceData, config: Config | None = None,
                   estimator: MotionEstimator | None = None) -> Iterator[FrameEstimate]:
    """
    Run the egomotion estimator over every frame pair and integrate the poses.

    The pose is chained as ``T_world_cur = T_world_prev @ est.T_prev_cur``. As in the image
    pipeline, a time step longer than ``pipeline.max_gap_s`` re-initialises the velocity, and
    after ``pipeline.max_lost_time_s`` without an OK estimate the velocity is reset to zero (a
    failed frame otherwise coasts on the prediction, which the estimator handles).

    Parameters
    ----------
    data : CorrespondenceData
        The sequence (M frame pairs).
    config : Config, optional
        Defaults to ``Config()``; ignored when ``estimator`` is given.
    estimator : MotionEstimator, optional
        A ready estimator (its state is used as is).

    Yields
    ------
    FrameEstimate
        One per frame pair, in order.

    """
    config = config or Config()
    estimator = estimator or MotionEstimator(config)
    cfg = estimator.config.pipeline
    calib = data.calibration()
    size = calib.size
    dts = data.time_steps()
    T_world_cam = np.eye(4)
    lost_time = 0.0
    for k in range(len(data)):
        dt = float(dts[k])
        if dt > cfg.max_gap_s:
            LOG.warning('frame pair %d: gap of %.3f s, velocity re-initialised', k, dt)
            estimator.reset()
        corr = data.frame(k)
        t0 = time.perf_counter()
        est = estimator.estimate(corr, calib, dt, image_size=size)
        elapsed_ms = (time.perf_counter() - t0) * 1e3
        if est.status is TrackingStatus.OK:
            lost_time = 0.0
        else:
            lost_time += dt
            if lost_time > cfg.max_lost_time_s:
                LOG.warning('frame pair %d: no estimate for %.2f s, velocity reset', k,
                            lost_time)
                estimator.reset()
                lost_time = 0.0
        T_world_cam = T_world_cam @ est.T_prev_cur
        yield FrameEstimate(k, est, T_world_cam.copy(), elapsed_ms)


def estimate_trajectory(data: CorrespondenceData, config: Config | None = None) -> np.ndarray:
    """
    Return the estimated trajectory of a correspondence sequence.

    Parameters
    ----------
    data : CorrespondenceData
        M frame pairs.
    config : Config, optional
        Estimator configuration (``filter``, ``ransac``, ``bucketing``, ``pipeline``).

    Returns
    -------
    np.ndarray
        (M + 1, 4, 4) float64 poses ``T_world_cam`` of the left camera in the frame of the
        first left camera; the first is the identity (KITTI convention).

    """
    poses = np.empty((len(data) + 1, 4, 4))
    poses[0] = np.eye(4)
    for fe in iter_estimates(data, config):
        poses[fe.index + 1] = fe.T_world_cam
    return poses
