"""
What to render: the sequence spec, its presets and the rendered frame record.

KITTI-like camera constants, ``SequenceSpec`` (image format, camera, scene, motion, rig error
and image degradations), the named presets and ``RenderedFrame``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math

import numpy as np

from ..errors import ConfigError
from ..estimation.camera import StereoCalibration
from ..records import StereoFrame


#: KITTI odometry (sequences 00-02) rectified intrinsics at 1241 x 376 pixels.
KITTI_WIDTH, KITTI_HEIGHT = 1241, 376
KITTI_FOCAL_PX = 718.856
KITTI_CX_PX, KITTI_CY_PX = 607.1928, 185.2157
KITTI_BASELINE_M = 0.537

SCENES = ('city', 'highway')

_WALL_W_M, _WALL_H_M = 12.8, 25.6  # size of every wall texture (m)
_FLOOR_M, _GROUND_FLOOR_M = 3.2, 4.0  # storey height, ground floor height (m)
_ROAD_HALF_M, _SIDEWALK_M, _LANE_OFFSET_M = 6.0, 3.5, 1.75  # city street cross-section
_HW_MEDIAN_M, _HW_LANE_M, _HW_LANES = 1.5, 3.75, 3  # highway cross-section
_VEHICLES = ((5.2, 2.3, 2.3), (9.0, 2.5, 3.4), (12.0, 2.5, 3.1))  # van, truck, bus: L, W, H
_MIN_T_M = 0.05  # nearest depth the ray caster accepts (m)


@dataclass(frozen=True)
class SequenceSpec:
    """
    What to render: image format, camera, scene, motion and image degradations.

    Attributes
    ----------
    name : str
        Label of the sequence (presets set it).
    width, height : int
        Image size (pixels). The intrinsics scale with ``width`` from KITTI's.
    frame_rate_hz : float
        Frame rate (Hz); stamps are ``start_time_s + i / frame_rate_hz`` (s).
    n_frames : int
        Number of stereo pairs.
    scene : str
        ``city`` (grid of streets and building blocks) or ``highway`` (straight, open).
    speed_mps : float
        Cruise speed of the camera (m/s); the city route slows down in turns.
    turns : bool
        City: take 90-degree turns at intersections; highway: change lanes.
    turn_probability : float
        Probability of turning at an intersection (city) when ``turns`` is set.
    moving_objects : int
        Number of independently moving vehicles.
    parked_vehicles : bool
        Park static vans along the city streets.
    exposure_change : float
        Amplitude of the automatic-exposure gain changes (natural log of the gain); 0: none.
    stereo_gain_mismatch : float
        Relative gain difference between the right and the left camera (varies in time).
    noise_std : float
        Standard deviation of the additive sensor noise (grey levels).
    blur_sigma_px : float
        Standard deviation of the Gaussian optical blur (pixels); 0: none.
    supersample : int
        Render at this factor and area-average (anti-aliased silhouettes; cost ~ factor^2).
    camera_height_m : float
        Height of the cameras above the road (m).
    bounce_m : float
        Amplitude of the vertical bounce of the cameras (m).
    baseline_m : float
        Stereo baseline (m).
    block_m : float
        City block pitch (m).
    start_time_s : float
        Stamp of the first frame (s).
    seed : int
        Seed of everything random: same spec, same images.
    rig_roll_deg, rig_pitch_deg, rig_yaw_deg : float
        Residual rotation (deg) of the rendered right camera against the calibration, about
        its optical-frame axes z (roll), x (pitch) and y (yaw): the true right camera is
        ``R = R_z(roll) R_x(pitch) R_y(yaw)`` (its axes as columns in the nominal right camera
        frame). Positive pitch tilts it up, so the right image rows move down by about
        ``f * pitch`` (0.02 deg at 718 px: +0.25 px, v_R - v_L); positive yaw turns it right,
        so right columns move left by ``f * yaw`` (0.008 deg: disparity +0.10 px); positive
        roll turns the camera's x axis down, so the image content turns the other way (rows
        move by ``-roll * (u - cx)``: up on the right half of the image).
    rig_focal_ratio : float
        Relative focal error of the right camera: its true focal is the left one times
        ``1 + rig_focal_ratio`` (3e-4 = +0.03 %), about the principal point.
    rig_disparity_offset_px : float
        Disparity offset (pixels): the true right principal point x is ``cx - offset``, so a
        point's measured disparity ``u_L - u_R`` is its true one plus the offset.
    rig_baseline_ratio, rig_focal_scale : float
        The true baseline and the true focal of both cameras are the nominal ones times
        ``1 + ratio``; the images are rendered with the true values, ``calibration()`` returns
        the nominal ones (metric scale error, unobservable from the images).
    gain_jitter : float
        Independent per-camera, per-frame gain: each camera's gain in each frame is multiplied
        by a factor drawn uniformly (not log-uniformly) in ``[1 - j, 1 + j]``; 0: none.
    gain_offset_jitter : float
        Independent per-camera, per-frame additive offset (grey levels), uniform in
        ``[-o, o]``; 0: none.
    vignetting : float
        Strength of a cos^4-like radial falloff: gain ``(1 + k r^2)^-2`` with ``r`` the
        distance from the image centre in units of the half diagonal and ``k`` chosen so that
        the gain at the corners is ``1 - vignetting``; 0: none.
    vignetting_mismatch : float
        Stereo difference of the vignetting: the right camera's strength is the left one times
        ``1 + m`` and its falloff centre is shifted by ``m`` times (10 % of the width, 5 % of
        the height) to the right and down.

    """

    name: str = 'custom'
    width: int = KITTI_WIDTH
    height: int = KITTI_HEIGHT
    frame_rate_hz: float = 10.0
    n_frames: int = 100
    scene: str = 'city'
    speed_mps: float = 10.0
    turns: bool = True
    turn_probability: float = 0.5
    moving_objects: int = 6
    parked_vehicles: bool = True
    exposure_change: float = 0.0
    stereo_gain_mismatch: float = 0.0
    noise_std: float = 1.0
    blur_sigma_px: float = 0.5
    supersample: int = 1
    camera_height_m: float = 1.65
    bounce_m: float = 0.01
    baseline_m: float = KITTI_BASELINE_M
    block_m: float = 80.0
    start_time_s: float = 0.0
    seed: int = 0
    rig_roll_deg: float = 0.0
    rig_pitch_deg: float = 0.0
    rig_yaw_deg: float = 0.0
    rig_focal_ratio: float = 0.0
    rig_disparity_offset_px: float = 0.0
    rig_baseline_ratio: float = 0.0
    rig_focal_scale: float = 0.0
    gain_jitter: float = 0.0
    gain_offset_jitter: float = 0.0
    vignetting: float = 0.0
    vignetting_mismatch: float = 0.0

    def __post_init__(self) -> None:
        checks = (
            (self.scene in SCENES, f'scene must be one of {SCENES}, got {self.scene!r}'),
            (32 <= self.width <= 8192 and 16 <= self.height <= 8192,
             f'width x height must be within 32x16..8192x8192, got {self.width}x{self.height}'),
            (self.n_frames >= 1, f'n_frames must be positive, got {self.n_frames}'),
            (0.1 <= self.frame_rate_hz <= 1000,
             f'frame_rate_hz must be within [0.1, 1000], got {self.frame_rate_hz}'),
            (0.5 <= self.speed_mps <= 50, f'speed_mps must be within [0.5, 50], got '
             f'{self.speed_mps}'),
            (0.0 <= self.turn_probability <= 1.0,
             f'turn_probability must be within [0, 1], got {self.turn_probability}'),
            (0 <= self.moving_objects <= 100,
             f'moving_objects must be within [0, 100], got {self.moving_objects}'),
            (self.noise_std >= 0 and self.blur_sigma_px >= 0 and self.exposure_change >= 0
             and self.stereo_gain_mismatch >= 0,
             'noise_std, blur_sigma_px, exposure_change and stereo_gain_mismatch must not be '
             f'negative, got {self.noise_std}, {self.blur_sigma_px}, {self.exposure_change}, '
             f'{self.stereo_gain_mismatch}'),
            (1 <= self.supersample <= 4, f'supersample must be 1..4, got {self.supersample}'),
            (1.0 <= self.camera_height_m <= 1.8,
             f'camera_height_m must be within [1.0, 1.8] (boxes are taller), got '
             f'{self.camera_height_m}'),
            (0 <= self.bounce_m <= 0.1, f'bounce_m must be within [0, 0.1], got {self.bounce_m}'),
            (0.05 <= self.baseline_m <= 2.0,
             f'baseline_m must be within [0.05, 2], got {self.baseline_m}'),
            (60.0 <= self.block_m <= 200.0,
             f'block_m must be within [60, 200], got {self.block_m}'),
            (max(abs(self.rig_roll_deg), abs(self.rig_pitch_deg), abs(self.rig_yaw_deg)) <= 5.0,
             'rig_roll_deg, rig_pitch_deg and rig_yaw_deg must be within [-5, 5], got '
             f'{self.rig_roll_deg}, {self.rig_pitch_deg}, {self.rig_yaw_deg}'),
            (max(abs(self.rig_focal_ratio), abs(self.rig_baseline_ratio),
                 abs(self.rig_focal_scale)) <= 0.1,
             'rig_focal_ratio, rig_baseline_ratio and rig_focal_scale must be within '
             f'[-0.1, 0.1], got {self.rig_focal_ratio}, {self.rig_baseline_ratio}, '
             f'{self.rig_focal_scale}'),
            (abs(self.rig_disparity_offset_px) <= 20.0,
             f'rig_disparity_offset_px must be within [-20, 20], got '
             f'{self.rig_disparity_offset_px}'),
            (0.0 <= self.gain_jitter < 1.0 and self.gain_offset_jitter >= 0.0,
             f'gain_jitter must be within [0, 1) and gain_offset_jitter not negative, got '
             f'{self.gain_jitter}, {self.gain_offset_jitter}'),
            (0.0 <= self.vignetting < 1.0 and 0.0 <= self.vignetting * (
                1.0 + self.vignetting_mismatch) < 1.0 and self.vignetting_mismatch > -1.0,
             f'vignetting (times 1 + vignetting_mismatch) must be within [0, 1), got '
             f'{self.vignetting}, {self.vignetting_mismatch}'),
        )
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)

    @classmethod
    def preset(cls, name: str, **overrides: object) -> 'SequenceSpec':
        """
        Return the named preset spec (a key of ``PRESETS``) with some fields overridden.

        Presets: urban, highway, exposure, demo; urban_rig and highway_rig (``RIG_ERROR``);
        urban_photometric and highway_photometric (``PHOTOMETRIC``); urban_rig_photometric.
        """
        if name not in PRESETS:
            raise ConfigError(f'unknown synthetic preset {name!r}; known: {sorted(PRESETS)}')
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(overrides) - fields)
        if unknown:
            raise ConfigError(f'unknown SequenceSpec field(s) {unknown}')
        return dataclasses.replace(PRESETS[name], **overrides)

    def replace(self, **overrides: object) -> 'SequenceSpec':
        """Return a copy with some fields changed (validated)."""
        return dataclasses.replace(self, **overrides)

    @property
    def focal_px(self) -> float:
        """Focal length fx = fy (pixels), KITTI's scaled with the width."""
        return KITTI_FOCAL_PX * self.width / KITTI_WIDTH

    @property
    def true_focal_px(self) -> float:
        """Focal length the images are rendered with (pixels): ``focal_px`` x (1 + scale)."""
        return self.focal_px * (1.0 + self.rig_focal_scale)

    @property
    def true_baseline_m(self) -> float:
        """Baseline the images are rendered with (m): ``baseline_m`` x (1 + ratio)."""
        return self.baseline_m * (1.0 + self.rig_baseline_ratio)

    @property
    def exact_rig(self) -> bool:
        """Tell whether the images are rendered with exactly the nominal calibration."""
        return not any((self.rig_roll_deg, self.rig_pitch_deg, self.rig_yaw_deg,
                        self.rig_focal_ratio, self.rig_disparity_offset_px,
                        self.rig_baseline_ratio, self.rig_focal_scale))

    def right_homography(self) -> np.ndarray:
        """
        Homography from the exact right image to the rendered (erroneous) right image.

        Returns
        -------
        np.ndarray
            (3, 3) float64 ``H = K_r R^T K^-1`` (pixels to pixels), with ``K`` the true
            intrinsics of both cameras (``true_focal_px``, nominal principal point), ``K_r``
            the right camera's (focal x (1 + rig_focal_ratio), principal point x shifted by
            ``-rig_disparity_offset_px``) and ``R`` the residual rotation (see the class).
            Identity for an exact rig.

        """
        f = self.true_focal_px
        cx, cy = self.principal_point_px
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        fr = f * (1.0 + self.rig_focal_ratio)
        K_r = np.array([[fr, 0.0, cx - self.rig_disparity_offset_px], [0.0, fr, cy],
                        [0.0, 0.0, 1.0]])
        r, p, y = (math.radians(a) for a in (self.rig_roll_deg, self.rig_pitch_deg,
                                             self.rig_yaw_deg))
        R_z = np.array([[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0],
                        [0.0, 0.0, 1.0]])
        R_x = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), -math.sin(p)],
                        [0.0, math.sin(p), math.cos(p)]])
        R_y = np.array([[math.cos(y), 0.0, math.sin(y)], [0.0, 1.0, 0.0],
                        [-math.sin(y), 0.0, math.cos(y)]])
        R = R_z @ R_x @ R_y
        return K_r @ R.T @ np.linalg.inv(K)

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """Principal point (cx, cy) in pixels, KITTI's scaled with the image size."""
        return (KITTI_CX_PX * self.width / KITTI_WIDTH,
                KITTI_CY_PX * self.height / KITTI_HEIGHT)

    @property
    def stamps(self) -> np.ndarray:
        """Frame stamps: (N,) float64, seconds."""
        return self.start_time_s + np.arange(self.n_frames) / self.frame_rate_hz

    def projections(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the rectified (3, 4) projection matrices P0 (left) and P1 (right), pixels."""
        f = self.focal_px
        cx, cy = self.principal_point_px
        P0 = np.array([[f, 0.0, cx, 0.0], [0.0, f, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
        P1 = P0.copy()
        P1[0, 3] = -f * self.baseline_m
        return P0, P1

    def calibration(self) -> StereoCalibration:
        """Return the rectified StereoCalibration of the rendered pairs."""
        P0, P1 = self.projections()
        return StereoCalibration.from_projections(P0, P1, self.width, self.height)


PRESETS: dict[str, SequenceSpec] = {
    'urban': SequenceSpec(name='urban', n_frames=300, scene='city', speed_mps=10.0,
                          turns=True, moving_objects=10),
    'highway': SequenceSpec(name='highway', n_frames=300, scene='highway', speed_mps=25.0,
                            turns=True, moving_objects=12, parked_vehicles=False),
    'exposure': SequenceSpec(name='exposure', n_frames=200, scene='city', speed_mps=10.0,
                             turns=True, moving_objects=6, exposure_change=0.35,
                             stereo_gain_mismatch=0.05),
    'demo': SequenceSpec(name='demo', width=620, height=188, n_frames=60, scene='city',
                         speed_mps=10.0, turns=True, turn_probability=1.0, moving_objects=4),
}
#: A good real rig's residual calibration error (the sizes of the user report): right image
#: rows off by +0.25 px (pitch) and up to +-0.11 px at the image edges (roll), disparity off
#: by +0.15 px at the centre (yaw 0.10 px + principal point 0.05 px), right focal +0.03 %
#: (+-0.18 px in u, +-0.06 px in v at the image edges), true baseline +0.3 % and true focal
#: -0.2 % against the calibration (metric scale about +0.1 %).
RIG_ERROR = {'rig_pitch_deg': 0.02, 'rig_roll_deg': 0.01, 'rig_yaw_deg': 0.008,
             'rig_focal_ratio': 3e-4, 'rig_disparity_offset_px': 0.05,
             'rig_baseline_ratio': 0.003, 'rig_focal_scale': -0.002}
#: Independent automatic exposure of both cameras: gain x U[0.7, 1.3] and offset U[-5, 5]
#: grey levels per camera and frame, vignetting to 70 % at the corners (the right camera's
#: 10 % stronger and off centre).
PHOTOMETRIC = {'gain_jitter': 0.3, 'gain_offset_jitter': 5.0, 'vignetting': 0.3,
               'vignetting_mismatch': 0.1}
PRESETS.update({
    'urban_rig': PRESETS['urban'].replace(name='urban_rig', **RIG_ERROR),
    'highway_rig': PRESETS['highway'].replace(name='highway_rig', **RIG_ERROR),
    'urban_photometric': PRESETS['urban'].replace(name='urban_photometric', **PHOTOMETRIC),
    'highway_photometric': PRESETS['highway'].replace(name='highway_photometric',
                                                      **PHOTOMETRIC),
    'urban_rig_photometric': PRESETS['urban'].replace(name='urban_rig_photometric',
                                                      **RIG_ERROR, **PHOTOMETRIC),
})


@dataclass(frozen=True)
class RenderedFrame:
    """
    One rendered stereo pair with its ground truth.

    Attributes
    ----------
    index : int
        Frame number.
    stamp_s : float
        Stamp (s).
    left, right : np.ndarray
        (H, W) uint8 rectified grey images.
    T_world_cam : np.ndarray
        (4, 4) float64 pose of the left camera in ``world`` (metres).
    depth_left, depth_right : np.ndarray or None
        (H, W) float32 depth z along the optical axis (m) of every pixel in its camera; inf on
        the sky. Only when requested.
    static_left, static_right : np.ndarray or None
        (H, W) bool, False where a moving vehicle is seen. Only when requested.

    """

    index: int
    stamp_s: float
    left: np.ndarray
    right: np.ndarray
    T_world_cam: np.ndarray
    depth_left: np.ndarray | None = None
    depth_right: np.ndarray | None = None
    static_left: np.ndarray | None = None
    static_right: np.ndarray | None = None

    def stereo_frame(self, calibration: StereoCalibration) -> StereoFrame:
        """Return the pair as a StereoFrame with the given calibration."""
        return StereoFrame(self.left, self.right, self.stamp_s, calibration)


# ---------------------------------------------------------------------------------------------
# Procedural textures (grey levels 0..255 as float32 while drawing, uint8 when stored)
# ---------------------------------------------------------------------------------------------
