"""
Records passed between the stages: stereo frames in, motion and odometry out.

Frames and units used throughout the package:

* camera optical frame: x right, y down, z forward (metres);
* ``world``: the optical frame of the FIRST left camera of a run (KITTI convention);
* ``T_a_b``: 4x4 homogeneous transform taking points from frame ``b`` to frame ``a``;
* velocities (V_X, V_Y, V_Z, w_X, w_Y, w_Z) are in m/s and rad/s, expressed in the previous left
  camera frame (Kitt et al.'s state, with the previous LEFT camera as reference).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import enum
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from .estimation.camera import StereoCalibration


class TrackingStatus(enum.Enum):
    """Outcome of one stereo frame."""

    INITIALIZING = 'initializing'  #: first frame, or first frame after a reset/loss
    OK = 'ok'
    DEGENERATE = 'degenerate'  #: too few correspondences or an ill-conditioned solve
    TOO_FEW_INLIERS = 'too_few_inliers'  #: RANSAC kept fewer inliers than configured
    LOST = 'lost'  #: coasting ran out; velocity zeroed, covariance large


@dataclass(frozen=True)
class StereoFrame:
    """
    One synchronised stereo pair.

    Attributes
    ----------
    left, right : np.ndarray
        (H, W) uint8 or uint16 grey images (rectified or raw, as ``calibration`` says).
    stamp_s : float
        Capture time (s).
    calibration : StereoCalibration
        Calibration valid for this pair.

    """

    left: np.ndarray
    right: np.ndarray
    stamp_s: float
    calibration: 'StereoCalibration'


@dataclass
class Correspondences:
    """
    Stereo correspondences between the previous and the current pair.

    Every array has N rows, one per feature; pixel coordinates are (x right, y down), float64,
    in the undistorted (ideal pinhole) image of the camera named.
    """

    prev_left: np.ndarray  #: (N, 2) left image at t-1 (pixels)
    prev_right: np.ndarray  #: (N, 2) right image at t-1 (pixels)
    cur_left: np.ndarray  #: (N, 2) left image at t (pixels)
    cur_right: np.ndarray  #: (N, 2) right image at t (pixels)
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  #: (N,) int64
    ages: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  #: (N,) frames

    def __len__(self) -> int:
        return int(self.prev_left.shape[0])

    def subset(self, mask: np.ndarray) -> 'Correspondences':
        """Return the rows selected by a boolean mask or an index array (copies)."""
        ids = self.ids[mask] if self.ids.size else self.ids
        ages = self.ages[mask] if self.ages.size else self.ages
        return Correspondences(self.prev_left[mask], self.prev_right[mask],
                               self.cur_left[mask], self.cur_right[mask], ids, ages)


@dataclass
class MotionEstimate:
    """
    Frame-to-frame egomotion from the estimator (Kitt et al.).

    Attributes
    ----------
    velocity : np.ndarray
        (6,) float64 (V_X, V_Y, V_Z [m/s], w_X, w_Y, w_Z [rad/s]) in the previous left frame.
    covariance : np.ndarray
        (6, 6) float64 covariance of ``velocity`` (same units, squared).
    T_prev_cur : np.ndarray
        (4, 4) pose of the current left camera in the previous left camera frame.
    inliers : np.ndarray
        (N,) bool, True for the correspondences used in the final update.
    iterations : int
        Filter iterations of the final update.
    status : TrackingStatus
        OK, DEGENERATE or TOO_FEW_INLIERS.
    hypotheses : int
        RANSAC samples drawn (0 without RANSAC).
    message : str
        Why the status is not OK (empty when OK).

    """

    velocity: np.ndarray
    covariance: np.ndarray
    T_prev_cur: np.ndarray
    inliers: np.ndarray
    iterations: int
    status: TrackingStatus
    hypotheses: int = 0
    message: str = ''


@dataclass
class RigEstimate:
    """
    Online estimate of the stereo rig's error (:mod:`~stereo_vo_ros.estimation.rig_calibration`).

    Attributes
    ----------
    theta : np.ndarray
        (5,) float64 error of the right camera against the calibration in use: roll, pitch,
        yaw (rad, about its optical z, x, y axes; ``R = R_z R_x R_y``), focal ratio (true right
        focal over the calibrated one, minus 1) and disparity offset (pixels; the true right
        principal point x is ``cx - offset``).
    covariance : np.ndarray
        (5, 5) float64 covariance of ``theta`` (same units, squared).
    row_offset_px, row_offset_std_px : float
        Rows of the right image minus those of the left at the principal point (``v_R - v_L``,
        pixels) that the estimate implies, and its std; NaN without a calibration.
    disparity_offset_px, disparity_offset_std_px : float
        Measured minus true disparity at the principal point (pixels) and its std.
    updates, rejected : int
        Pairs fused, pairs gated out since the start.
    settled : bool
        Both offset stds have been below ``rig.settled_std_px``.
    enabled : bool
        ``rig.enabled``.
    last : str
        What the latest pair did: updated, rejected, frozen, skipped, off or none.
    applied : np.ndarray
        (5,) float64 the part of ``theta`` that corrects the measurements (zero until a part
        differs from zero significantly, ``rig.apply_probability``).

    """

    theta: np.ndarray
    covariance: np.ndarray
    row_offset_px: float
    row_offset_std_px: float
    disparity_offset_px: float
    disparity_offset_std_px: float
    updates: int = 0
    rejected: int = 0
    settled: bool = False
    enabled: bool = True
    last: str = 'none'
    applied: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def as_dict(self) -> dict:
        """Plain JSON-ready form (angles in degrees, focal ratio in percent)."""
        std = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        deg, dstd = np.rad2deg(self.theta[:3]), np.rad2deg(std[:3])
        return {
            'enabled': self.enabled, 'settled': self.settled, 'updates': self.updates,
            'applied': [float(v) for v in self.applied],
            'rejected': self.rejected, 'last': self.last,
            'row_offset_px': self.row_offset_px, 'row_offset_std_px': self.row_offset_std_px,
            'disparity_offset_px': self.disparity_offset_px,
            'disparity_offset_std_px': self.disparity_offset_std_px,
            'roll_deg': float(deg[0]), 'pitch_deg': float(deg[1]), 'yaw_deg': float(deg[2]),
            'roll_std_deg': float(dstd[0]), 'pitch_std_deg': float(dstd[1]),
            'yaw_std_deg': float(dstd[2]),
            'focal_ratio_pct': 100.0 * float(self.theta[3]),
            'focal_ratio_std_pct': 100.0 * float(std[3]),
            'right_cx_offset_px': -float(self.theta[4]),
            'right_cx_offset_std_px': float(std[4]),
            'theta': [float(v) for v in self.theta],
            'covariance': [[float(v) for v in row] for row in self.covariance]}


@dataclass
class OdometryResult:
    """
    What the pipeline returns for every stereo pair.

    Attributes
    ----------
    stamp_s : float
        Stamp of the pair (s).
    T_world_cam : np.ndarray
        (4, 4) pose of the current left camera in ``world`` (the first left camera frame).
    pose_covariance : np.ndarray
        (6, 6) covariance of the pose as (x, y, z, rot_x, rot_y, rot_z) in ``world``
        (m^2, rad^2), a left perturbation ``T = exp(d) T_world_cam``, ROS order.
    velocity : np.ndarray
        (6,) camera velocity (m/s, rad/s) in the CURRENT left camera frame.
    velocity_covariance : np.ndarray
        (6, 6) covariance of ``velocity``.
    status : TrackingStatus
        Status of this frame.
    n_tracked, n_inliers, iterations : int
        Stereo correspondences handed to the estimator, inliers kept, filter iterations.
    timings_ms : dict
        Milliseconds per stage (``track``, ``estimate``, ``rig``, ...); ``total`` is the time
        ``process`` took (with the previous pair's work after its pose when that ran there).
        A pair's work after its pose (the rig update, the wait for the tracker's new corners,
        the road plane: ``StereoOdometry.settle``) fills in ``after_pose`` (0.0 until then),
        ``track``, ``track.*``, ``rig`` and ``road`` once it ran; a road plane refined next to
        the next pair's tracking counts in that pair's ``road``.
    message : str
        Human-readable reason when the status is not OK.
    features : Correspondences or None
        The correspondences of this frame (for the debug image); None on the first frame.
    inliers : np.ndarray or None
        (N,) bool inlier mask matching ``features``.
    accepted : bool
        False when the frame was ignored (stamp not after the previous one); the pose is then
        the previous one and nothing should be published for it.
    road_fused : bool
        Whether the road alignment (``road`` section) was fused into this pair's motion.
    vehicle_fused : bool
        Whether the rolling-vehicle prior (``vehicle`` section) was fused into it.
    rig : RigEstimate or None
        The online estimate of the stereo rig's error after this pair (``rig`` section);
        None when the refinement is off. Until the pair's update ran (it follows the pose:
        ``StereoOdometry.settle``), the estimate its pose used.

    """

    stamp_s: float
    T_world_cam: np.ndarray
    pose_covariance: np.ndarray
    velocity: np.ndarray
    velocity_covariance: np.ndarray
    status: TrackingStatus
    n_tracked: int = 0
    n_inliers: int = 0
    iterations: int = 0
    timings_ms: dict = field(default_factory=dict)
    message: str = ''
    features: Correspondences | None = None
    inliers: np.ndarray | None = None
    accepted: bool = True
    road_fused: bool = False
    vehicle_fused: bool = False
    rig: RigEstimate | None = None
