"""
Odometry error metrics: KITTI devkit relative error, ATE, RPE and end-point drift.

Every function takes a ground truth and an estimate as (N, 4, 4) (or (N, 3, 4)) float arrays of
``T_world_cam`` (pose of the left camera in ``world``, camera to world, metres), one pose per
frame, frame ``i`` of the estimate matching frame ``i`` of the ground truth. Both must have the
same length: like the KITTI devkit (which refuses a result file with another number of poses),
a length mismatch raises ``ValueError`` naming both lengths rather than evaluating a prefix.
The inputs are never modified.

The KITTI metric follows ``evaluate_odometry.cpp`` of the KITTI odometry devkit:

* path distances are accumulated over consecutive ground-truth positions, in single precision
  exactly as the devkit does (this decides which frames end a segment);
* segments start every ``step_size = 10`` frames and have lengths 100, 200, ..., 800 m; the
  last frame of a segment is the first frame whose distance is strictly greater than the
  distance of the first frame plus the length; a segment without such a frame is skipped;
* with ``dGT = inv(GT[first]) GT[last]`` and ``dEST = inv(EST[first]) EST[last]``, the segment
  error is ``E = inv(dEST) dGT``; ``t_err = |translation(E)| / length`` and
  ``r_err = acos(clip((trace(R_E) - 1) / 2, -1, 1)) / length``;
* the sequence result is the plain mean over all segments (all lengths pooled), reported here
  as ``t_rel_pct = 100 * mean(t_err)`` (%) and ``r_rel_deg_per_100m = mean(r_err) * 180 / pi
  * 100`` (deg per 100 m).

The devkit computes the per-segment errors and their mean in single precision;
``kitti_segment_errors(..., devkit_float32=True)`` reproduces that, the default computes them
in double precision (see that function for the difference).
"""

from __future__ import annotations

from dataclasses import dataclass
import logging

import numpy as np

from .trajectory import as_poses

_LOG = logging.getLogger(__name__)

KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)  #: devkit lengths
KITTI_STEP_FRAMES = 10  #: devkit ``step_size``: a segment starts every 10 frames (1 s at 10 Hz)

EVALUATE_KEYS = ('t_rel_pct', 'r_rel_deg_per_100m', 'ate_rmse_m', 'rpe_trans_rmse_m',
                 'rpe_rot_rmse_deg', 'segments', 'end_drift_pct', 'path_length_m', 'frames')


@dataclass(frozen=True)
class KittiSegmentErrors:
    """
    Per-segment errors of the KITTI devkit, in the devkit's order (by first frame, length).

    Attributes
    ----------
    first_frame, last_frame : np.ndarray
        (S,) int64 frame indices where each segment starts and ends.
    length_m : np.ndarray
        (S,) float64 nominal segment length (m).
    t_err : np.ndarray
        (S,) float64 translation error per metre travelled (m/m; x100 gives %).
    r_err : np.ndarray
        (S,) float64 rotation error per metre travelled (rad/m).

    """

    first_frame: np.ndarray
    last_frame: np.ndarray
    length_m: np.ndarray
    t_err: np.ndarray
    r_err: np.ndarray

    def __len__(self) -> int:
        return int(self.first_frame.shape[0])


def _pair(gt: np.ndarray, est: np.ndarray, min_frames: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Validate and copy a ground truth / estimate pair of pose arrays."""
    g = as_poses(gt, 'gt')
    e = as_poses(est, 'est')
    if g.shape[0] != e.shape[0]:
        raise ValueError(f'ground truth has {g.shape[0]} poses but the estimate has '
                         f'{e.shape[0]}; they must match frame for frame')
    if g.shape[0] < min_frames:
        raise ValueError(f'need at least {min_frames} poses, got {g.shape[0]}')
    return g, e


def _inv_se3(poses: np.ndarray) -> np.ndarray:
    """Invert (N, 4, 4) rigid transforms in closed form."""
    out = np.zeros_like(poses)
    rt = np.swapaxes(poses[:, :3, :3], 1, 2)
    out[:, :3, :3] = rt
    out[:, :3, 3] = -np.einsum('nij,nj->ni', rt, poses[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """
    Angle of rotation matrices, accurate near 0 and near pi.

    Parameters
    ----------
    rot : np.ndarray
        (..., 3, 3) float rotation matrices.

    Returns
    -------
    np.ndarray
        (...) float64 angle (rad) in [0, pi], from ``atan2(|axis part|, (trace - 1) / 2)``.

    """
    r = np.asarray(rot, dtype=np.float64)
    skew = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                     r[..., 1, 0] - r[..., 0, 1]], axis=-1)
    cos = 0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), cos)


def path_distances(poses: np.ndarray) -> np.ndarray:
    """
    Cumulative distance travelled along a trajectory (double precision).

    Parameters
    ----------
    poses : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres).

    Returns
    -------
    np.ndarray
        (N,) float64 distance (m) from frame 0 to each frame along consecutive positions;
        the first value is 0.

    """
    p = as_poses(poses)[:, :3, 3]
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def kitti_distances(poses: np.ndarray) -> np.ndarray:
    """
    Cumulative distances as the KITTI devkit's ``trajectoryDistances`` computes them.

    The devkit rounds each coordinate difference to single precision, sums the squares, takes
    the square root and accumulates the distance in single precision; this is reproduced
    operation for operation so that segment ends match the devkit.

    Parameters
    ----------
    poses : array_like
        (N, 4, 4) or (N, 3, 4) ground-truth ``T_world_cam`` (metres).

    Returns
    -------
    np.ndarray
        (N,) float32 cumulative distance (m), first value 0.

    """
    p = as_poses(poses)[:, :3, 3]
    d = (p[:-1] - p[1:]).astype(np.float32)
    sq = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
    steps = np.sqrt(sq)
    # np.cumsum accumulates sequentially, like the devkit's running float sum.
    return np.concatenate([np.zeros(1, np.float32), np.cumsum(steps, dtype=np.float32)])


def kitti_segment_errors(gt: np.ndarray, est: np.ndarray,
                         lengths_m: tuple[float, ...] = KITTI_LENGTHS_M,
                         step_frames: int = KITTI_STEP_FRAMES,
                         devkit_float32: bool = False) -> KittiSegmentErrors:
    """
    Per-segment relative errors of the KITTI odometry devkit.

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N. Not modified.
    lengths_m : tuple of float
        Segment lengths (m); the devkit uses 100, 200, ..., 800.
    step_frames : int
        A segment starts at every ``step_frames``-th frame (devkit: 10).
    devkit_float32 : bool
        False (default) computes the segment errors in double precision. True reproduces the
        devkit's single-precision arithmetic (``float`` diagonal, ``acos`` and divisions).
        The two differ by float32 rounding: about 1e-7 relative in ``t_err``, and in
        ``r_err`` the devkit's ``acos`` of a float32 near 1 quantises small angles (the
        smallest non-zero angle is about 3.5e-4 rad; smaller errors become 0 or 3.5e-4).
        Segment ends always use the devkit's float32 distances (``kitti_distances``).

    Returns
    -------
    KittiSegmentErrors
        One entry per segment, ordered by first frame then length, like the devkit.

    Raises
    ------
    ValueError
        Mismatched lengths, bad shapes or non-finite poses.

    """
    g, e = _pair(gt, est, min_frames=1)
    if step_frames < 1:
        raise ValueError(f'step_frames must be >= 1, got {step_frames}')
    dist = kitti_distances(g)
    firsts = np.arange(0, g.shape[0], step_frames, dtype=np.int64)
    lens32 = np.asarray(lengths_m, dtype=np.float32)
    # devkit: first i >= first with dist[i] > dist[first] + len, both sides float32; dist is
    # non-decreasing, so a right-sided search over the whole array finds the same index.
    thresholds = dist[firsts][:, None] + lens32[None, :]  # (F, L) float32 sums
    lasts = np.searchsorted(dist, thresholds.ravel(), side='right').reshape(thresholds.shape)
    valid = lasts < g.shape[0]
    first_idx = np.broadcast_to(firsts[:, None], lasts.shape)[valid]
    last_idx = lasts[valid].astype(np.int64)
    seg_len = np.broadcast_to(lens32[None, :], lasts.shape)[valid].astype(np.float64)
    if first_idx.size == 0:
        empty = np.zeros(0)
        return KittiSegmentErrors(first_idx.copy(), last_idx.copy(), empty, empty.copy(),
                                  empty.copy())
    # The devkit inverts with a generic 4x4 Gauss-Jordan inverse; np.linalg.inv is the same
    # operation (not assuming an exactly orthonormal rotation).
    delta_gt = np.linalg.inv(g[first_idx]) @ g[last_idx]
    delta_est = np.linalg.inv(e[first_idx]) @ e[last_idx]
    err = np.linalg.inv(delta_est) @ delta_gt
    if devkit_float32:
        a, b, c = (err[:, i, i].astype(np.float32) for i in range(3))
        d = (0.5 * ((a + b + c).astype(np.float64) - 1.0)).astype(np.float32)
        r = np.arccos(np.clip(d, np.float32(-1.0), np.float32(1.0)))
        tx, ty, tz = (err[:, i, 3].astype(np.float32) for i in range(3))
        t = np.sqrt(tx * tx + ty * ty + tz * tz)
        len32 = seg_len.astype(np.float32)
        t_err = (t / len32).astype(np.float64)
        r_err = (r / len32).astype(np.float64)
    else:
        cos = 0.5 * (np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0)
        r_err = np.arccos(np.clip(cos, -1.0, 1.0)) / seg_len
        t_err = np.linalg.norm(err[:, :3, 3], axis=1) / seg_len
    return KittiSegmentErrors(first_idx.copy(), last_idx, seg_len, t_err, r_err)


def kitti_odometry_error(gt: np.ndarray, est: np.ndarray,
                         devkit_float32: bool = False) -> tuple[float, float, int]:
    """
    KITTI odometry metric of one sequence (``evaluate_odometry.cpp``).

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N. Not modified.
    devkit_float32 : bool
        Reproduce the devkit's single-precision arithmetic, including its float32 running
        sum for the mean (see ``kitti_segment_errors``).

    Returns
    -------
    t_rel_pct : float
        Mean translation error over all segments (% of the distance travelled).
    r_rel_deg_per_100m : float
        Mean rotation error over all segments (deg per 100 m).
    segments : int
        Number of segments. When 0 (ground truth shorter than 100 m plus one frame),
        ``t_rel_pct`` and ``r_rel_deg_per_100m`` are NaN.

    """
    seg = kitti_segment_errors(gt, est, devkit_float32=devkit_float32)
    n = len(seg)
    if n == 0:
        return float('nan'), float('nan'), 0
    if devkit_float32:
        num = np.float32(n)
        t_mean = float(np.cumsum(seg.t_err.astype(np.float32), dtype=np.float32)[-1] / num)
        r_mean = float(np.cumsum(seg.r_err.astype(np.float32), dtype=np.float32)[-1] / num)
    else:
        t_mean = float(np.mean(seg.t_err))
        r_mean = float(np.mean(seg.r_err))
    return t_mean * 100.0, float(np.degrees(r_mean)) * 100.0, n


def align_se3(source_xyz: np.ndarray, target_xyz: np.ndarray) -> np.ndarray:
    """
    Rigid transform that best maps source points onto target points (Umeyama, no scale).

    Parameters
    ----------
    source_xyz, target_xyz : array_like
        (N, 3) float corresponding points (metres), e.g. estimated and ground-truth positions
        in ``world``. Not modified.

    Returns
    -------
    np.ndarray
        (4, 4) float64 ``T_target_source`` minimising ``sum |target - (R source + t)|^2``,
        with ``det(R) = +1``.

    """
    src = np.asarray(source_xyz, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(target_xyz, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape or src.shape[0] == 0:
        raise ValueError(f'need two non-empty (N, 3) point sets of equal size, got {src.shape} '
                         f'and {dst.shape}')
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s) / src.shape[0]
    u, _, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[2, 2] = -1.0
    rot = u @ s @ vt
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = mu_d - rot @ mu_s
    return out


def scale_from_steps(gt: np.ndarray, est: np.ndarray) -> float:
    """
    One scale factor of an estimated trajectory: least squares over its step lengths.

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N >= 2. Not modified.

    Returns
    -------
    float
        ``s = sum(|dp_gt| |dp_est|) / sum(|dp_est|^2)`` over consecutive positions (unitless,
        true metres per estimated metre); NaN when the estimate does not move.

    """
    g, e = _pair(gt, est)
    step_gt = np.linalg.norm(np.diff(g[:, :3, 3], axis=0), axis=1)
    step_est = np.linalg.norm(np.diff(e[:, :3, 3], axis=0), axis=1)
    den = float(np.dot(step_est, step_est))
    return float(np.dot(step_gt, step_est) / den) if den > 0.0 else float('nan')


def scaled_trajectory(poses: np.ndarray, scale: float) -> np.ndarray:
    """
    Return a trajectory with every position multiplied by a scale (rotations unchanged).

    Parameters
    ----------
    poses : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres). Not modified.
    scale : float
        Factor (unitless), e.g. from ``scale_from_steps``.

    Returns
    -------
    np.ndarray
        (N, 4, 4) float64 copy; every relative translation is scaled by the same factor.

    """
    out = as_poses(poses).copy()
    out[:, :3, 3] *= scale
    return out


def kitti_odometry_error_scale_aligned(gt: np.ndarray, est: np.ndarray
                                       ) -> tuple[float, float, int, float]:
    """
    KITTI metric after one scale factor fitted to the whole trajectory.

    A rig whose true baseline or focal differs from its calibration scales every estimated
    translation by one factor that the images cannot reveal; this removes it.

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N >= 2. Not modified.

    Returns
    -------
    t_rel_pct, r_rel_deg_per_100m, segments
        As ``kitti_odometry_error`` of ``scaled_trajectory(est, scale)``.
    scale : float
        The factor of ``scale_from_steps`` (true over estimated length).

    """
    scale = scale_from_steps(gt, est)
    if not np.isfinite(scale):
        return float('nan'), float('nan'), 0, scale
    t_rel, r_rel, n = kitti_odometry_error(gt, scaled_trajectory(est, scale))
    return t_rel, r_rel, n, scale


def ate_rmse(gt: np.ndarray, est: np.ndarray) -> float:
    """
    Absolute trajectory error: RMSE of positions after rigid alignment (no scale).

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N >= 2. Not modified.

    Returns
    -------
    float
        ``sqrt(mean |p_gt - (R p_est + t)|^2)`` (m), with (R, t) from ``align_se3`` of the
        estimated onto the ground-truth positions.

    """
    g, e = _pair(gt, est)
    pg = g[:, :3, 3]
    pe = e[:, :3, 3]
    t_gt_est = align_se3(pe, pg)
    res = pg - (pe @ t_gt_est[:3, :3].T + t_gt_est[:3, 3])
    return float(np.sqrt(np.mean(np.sum(res * res, axis=1))))


def rpe_frame_to_frame(gt: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    """
    Relative pose error between consecutive frames (evo's RPE with delta = 1 frame).

    For each i, ``E_i = inv(dGT_i) dEST_i`` with ``dX_i = inv(X_i) X_{i+1}``.

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N >= 2. Not modified.

    Returns
    -------
    trans_rmse_m : float
        RMSE of ``|translation(E_i)|`` (m per frame).
    rot_rmse_deg : float
        RMSE of the rotation angle of ``E_i`` (deg per frame).

    """
    g, e = _pair(gt, est)
    dg = _inv_se3(g[:-1]) @ g[1:]
    de = _inv_se3(e[:-1]) @ e[1:]
    err = _inv_se3(dg) @ de
    trans = np.linalg.norm(err[:, :3, 3], axis=1)
    rot = np.degrees(rotation_angle(err[:, :3, :3]))
    return float(np.sqrt(np.mean(trans ** 2))), float(np.sqrt(np.mean(rot ** 2)))


def end_point_drift(gt: np.ndarray, est: np.ndarray) -> float:
    """
    Distance between the last estimated and last true positions, per distance travelled.

    No alignment: both trajectories are taken in the same ``world`` frame.

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N >= 2. Not modified.

    Returns
    -------
    float
        ``100 * |p_est[-1] - p_gt[-1]| / L`` (%), with ``L`` the ground-truth path length
        (m); NaN when ``L`` is 0.

    """
    g, e = _pair(gt, est)
    length = float(path_distances(g)[-1])
    if length <= 0.0:
        return float('nan')
    return 100.0 * float(np.linalg.norm(e[-1, :3, 3] - g[-1, :3, 3])) / length


def evaluate(gt: np.ndarray, est: np.ndarray) -> dict:
    """
    All metrics of an estimated trajectory against ground truth.

    Parameters
    ----------
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), one pose per frame, same N >= 2.
        Not modified.

    Returns
    -------
    dict
        ``t_rel_pct`` (%), ``r_rel_deg_per_100m`` (deg/100 m) and ``segments`` (int) from
        ``kitti_odometry_error`` (NaN, NaN, 0 below 100 m); ``ate_rmse_m`` (m);
        ``rpe_trans_rmse_m`` (m/frame) and ``rpe_rot_rmse_deg`` (deg/frame);
        ``end_drift_pct`` (%); ``path_length_m`` (ground truth, m); ``frames`` (int, N).

    Raises
    ------
    ValueError
        ``gt`` and ``est`` differ in length (the message names both), fewer than 2 poses,
        bad shapes or non-finite values.

    """
    g, e = _pair(gt, est)
    t_rel, r_rel, segments = kitti_odometry_error(g, e)
    rpe_t, rpe_r = rpe_frame_to_frame(g, e)
    out = {
        't_rel_pct': t_rel,
        'r_rel_deg_per_100m': r_rel,
        'ate_rmse_m': ate_rmse(g, e),
        'rpe_trans_rmse_m': rpe_t,
        'rpe_rot_rmse_deg': rpe_r,
        'segments': int(segments),
        'end_drift_pct': end_point_drift(g, e),
        'path_length_m': float(path_distances(g)[-1]),
        'frames': int(g.shape[0]),
    }
    _LOG.debug('metrics: %s', out)
    return out
