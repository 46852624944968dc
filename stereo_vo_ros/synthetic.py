"""
Synthetic rectified stereo sequences of a textured street with exact ground truth.

The renderer ray-casts a procedural scene into a KITTI-like rectified stereo pair:

* a ground plane with an asphalt road, lane markings, crosswalks, kerbs, sidewalks and grass
  (one periodic texture tile: a city grid cell or a highway section);
* axis-aligned boxes standing on the ground: building blocks with windows, bricks and
  multi-scale grime, lamp posts, noise walls, warehouses, parked vans; and moving vehicles
  (vans, trucks, buses) that drive along the lanes at constant speed;
* a sky with faint clouds at infinity.

Frames and units: camera optical frame (x right, y down, z forward), metres, seconds, pixels.
``world`` is the optical frame of the first left camera (KITTI convention); the ground is the
plane ``y = camera height`` in it. Poses are ``T_world_cam`` (4x4, maps points from the left
camera frame to ``world``). Pixel centres are at integer coordinates (OpenCV convention).

Exactness: every pixel samples the scene along the ray through its centre, so a world point
seen at pixel (u, v) with depth d in the left image is seen at (u - fx * B / d, v) in the right
image and where the poses project it in any other frame (static surfaces only). Textures are
prefiltered (rip-maps chosen from the pixel footprint) so that distant surfaces do not alias;
silhouette edges are point sampled unless ``SequenceSpec.supersample`` is 2 or more. This holds
for an exact rig; ``SequenceSpec``'s ``rig_*`` fields render a rig that departs from the
calibration it hands out (true baseline and focal scaled; the right image warped by the
homography of a residual rotation and right-camera intrinsics error, ``right_homography``),
and its ``gain_*`` and ``vignetting*`` fields add independent per-camera exposure and
vignetting.

Restrictions that keep the renderer fast (a per-column ray cast): the cameras stay level
(yaw and height vary, pitch and roll are zero) and every box is taller than the camera.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import functools
import logging
import math
import time
from typing import Iterator

import cv2
import numpy as np

from .camera import StereoCalibration
from .errors import ConfigError
from .records import StereoFrame

logger = logging.getLogger(__name__)

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
def _pow2_divisor(n: int, target: float) -> int:
    """Largest power of two that divides ``n`` and is at most ``max(target, 1)``."""
    g = 1
    while n % (g * 2) == 0 and g * 2 <= max(target, 1.0):
        g *= 2
    return g


def _noise(rng: np.random.Generator, h: int, w: int, cell_y: float,
           cell_x: float | None = None) -> np.ndarray:
    """
    Return periodic smooth noise (h, w) float32 of unit standard deviation.

    Cubic interpolation of a random grid with about ``cell`` pixels per grid cell; the result
    tiles seamlessly (period h rows, w columns).
    """
    cell_x = cell_y if cell_x is None else cell_x
    gh, gw = _pow2_divisor(h, h / cell_y), _pow2_divisor(w, w / cell_x)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    if gh == h and gw == w:
        return grid
    sy, sx = h // gh, w // gw
    pad = 2
    padded = np.pad(grid, pad, mode='wrap')
    big = cv2.resize(padded, ((gw + 2 * pad) * sx, (gh + 2 * pad) * sy),
                     interpolation=cv2.INTER_CUBIC)
    out = big[pad * sy:pad * sy + h, pad * sx:pad * sx + w]
    return out / max(float(out[::4, ::4].std()), 1e-6)


def _fbm(rng: np.random.Generator, h: int, w: int, cells: tuple[float, ...],
         amps: tuple[float, ...]) -> np.ndarray:
    """Sum of periodic noise octaves (h, w) float32 with the given cell sizes and amplitudes."""
    out = np.zeros((h, w), np.float32)
    for cell, amp in zip(cells, amps):
        if cell >= 0.5:
            out += amp * _noise(rng, h, w, cell)
    return out


def _cover(signed_dist: np.ndarray, texel: float) -> np.ndarray:
    """Approximate area coverage (0..1) of a region with the given signed distance (m)."""
    return np.clip(signed_dist / texel + 0.5, 0.0, 1.0).astype(np.float32)


def _ground_city(rng: np.random.Generator, n: int, period_m: float) -> np.ndarray:
    """Texture (n, n) of one city grid cell: streets cross at the tile centre (rows: z)."""
    tex = period_m / n
    c = ((np.arange(n) + 0.5) * tex - period_m / 2).astype(np.float32)  # centred coordinate
    x, z = c[None, :], c[:, None]
    ax, az = np.abs(x), np.abs(z)
    px = 1.0 / tex  # pixels per metre
    cells = (1, 0.04 * px, 0.15 * px, 0.6 * px, 3.0 * px, 12.0 * px)
    octaves = [_noise(rng, n, n, cell) for cell in cells]

    def mix(weights: tuple[float, ...]) -> np.ndarray:
        out = np.zeros((n, n), np.float32)
        for w, octave in zip(weights, octaves):
            out += np.float32(w) * octave
        return out

    grain = mix((5.0, 5.0, 4.0, 5.0, 6.0, 6.0))
    half, walk = _ROAD_HALF_M, _ROAD_HALF_M + _SIDEWALK_M
    road_cov = np.maximum(_cover(half - ax, tex), _cover(half - az, tex))
    walk_cov = np.maximum(_cover(walk - ax, tex), _cover(walk - az, tex))
    out = 75.0 + mix((13.0, 11.0, -9.0, 11.0, -9.0, 8.0))  # grass
    # sidewalk: 0.5 m slabs with joints and a per-slab tone
    slab = 0.5
    slabs = rng.normal(0.0, 7.0, (int(round(period_m / slab)),) * 2).astype(np.float32)
    idx = (np.floor((c + period_m / 2) / slab).astype(np.int64) % slabs.shape[0])
    jx = _cover(np.abs(np.mod(x, slab) - slab / 2) - (slab / 2 - 0.012), tex)
    jz = _cover(np.abs(np.mod(z, slab) - slab / 2) - (slab / 2 - 0.012), tex)
    joints = np.maximum(jx, jz)
    sidewalk = 150.0 + slabs[idx[:, None], idx[None, :]] + 0.8 * grain - 45.0 * joints
    out += walk_cov * (sidewalk - out)
    del sidewalk
    kerb = np.maximum(_cover(half + 0.25 - ax, tex) * _cover(ax - half, tex),
                      _cover(half + 0.25 - az, tex) * _cover(az - half, tex)) * walk_cov
    stone_joint = np.maximum(_cover(0.015 - np.abs(np.mod(z, 1.0) - 0.5), tex),
                             _cover(0.015 - np.abs(np.mod(x, 1.0) - 0.5), tex))
    out += kerb * (175.0 + 0.5 * grain - 60.0 * stone_joint - out)
    out += road_cov * (92.0 + grain - out)

    def markings(a: np.ndarray, b: np.ndarray, hand: float) -> np.ndarray:
        """Return the marking coverage of a street with centre line a = 0 along b."""
        outside = _cover(np.abs(b) - (walk + 0.3), tex)
        dashes = _cover(1.5 - np.abs(np.mod(b, 6.0) - 3.0), tex)  # 3 m dash, 3 m gap
        centre = _cover(0.06 - np.abs(a), tex) * dashes * outside
        edge = _cover(0.06 - np.abs(np.abs(a) - 3.5), tex) * outside
        zebra_band = _cover(1.5 - np.abs(np.abs(b) - (half + 2.5)), tex)
        zebra = zebra_band * _cover(0.25 - np.abs(np.mod(a, 1.0) - 0.5), tex) * \
            _cover(half - 0.3 - np.abs(a), tex)
        stop = _cover(0.2 - np.abs(np.abs(b) - (half + 4.6)), tex) * \
            _cover(np.sign(-b) * a * hand, tex) * _cover(3.3 - np.abs(a), tex)
        return np.maximum.reduce([centre, edge, zebra, stop]) * _cover(half - np.abs(a), tex)

    strip = np.flatnonzero(np.abs(c) < half + tex)  # the street along z (columns) ...
    # worn paint: patches where the paint is gone or thin, ragged edges
    wear = np.clip(1.6 + 0.5 * octaves[1] + 0.9 * octaves[2] + 0.5 * octaves[3], 0.0, 1.0)
    white = 92.0 + grain + wear * (113.0 - 0.5 * grain)
    cols = (slice(None), strip)
    mark = markings(x[:, strip], z, 1.0)
    out[cols] += mark * (white[cols] - out[cols])
    rows = (strip, slice(None))  # ... and the street along x (rows)
    mark = markings(z[strip], x, -1.0)
    out[rows] += mark * (white[rows] - out[rows])
    _draw_blemishes(rng, out, tex, period_m, road_cov)
    return np.clip(out, 0, 255).astype(np.uint8)


def _draw_blemishes(rng: np.random.Generator, img: np.ndarray, tex: float, period_m: float,
                    road: np.ndarray) -> None:
    """Draw cracks, patches and manhole covers on the road part of a ground tile (in place)."""
    n_rows, n_cols = img.shape
    layer = np.zeros_like(img)
    area = period_m * period_m * float(road.mean())
    for _ in range(int(area / 60.0)):
        pts = [np.array([rng.uniform(0, n_cols), rng.uniform(0, n_rows)])]
        heading = rng.uniform(0, 2 * np.pi)
        for _ in range(rng.integers(3, 9)):
            heading += rng.normal(0, 0.6)
            pts.append(pts[-1] + rng.uniform(0.2, 0.8) / tex *
                       np.array([np.cos(heading), np.sin(heading)]))
        cv2.polylines(layer, [np.round(np.array(pts) * 16).astype(np.int32)], False,
                      -35.0, max(1, int(round(0.012 / tex))), cv2.LINE_AA, 4)
    for _ in range(int(area / 150.0)):
        centre = (int(rng.uniform(0, n_cols) * 16), int(rng.uniform(0, n_rows) * 16))
        if rng.random() < 0.3:
            radius = int(0.32 / tex * 16)
            cv2.circle(layer, centre, radius, -40.0, -1, cv2.LINE_AA, 4)
            cv2.circle(layer, centre, int(radius * 0.8), 10.0, max(1, int(0.03 / tex)),
                       cv2.LINE_AA, 4)
        else:
            size = (int(rng.uniform(0.5, 2.5) / tex * 16), int(rng.uniform(0.4, 1.5) / tex * 16))
            box = ((centre[0] / 16, centre[1] / 16), (size[0] / 16, size[1] / 16),
                   float(rng.uniform(0, 180)))
            cv2.fillPoly(layer, [np.round(cv2.boxPoints(box) * 16).astype(np.int32)],
                         float(rng.choice([-18.0, 12.0])), cv2.LINE_AA, 4)
    img += layer * road


def _ground_highway(rng: np.random.Generator, nx: int, nz: int, lx_m: float,
                    lz_m: float) -> np.ndarray:
    """Texture (nz, nx) of a highway section: median at the tile centre, along z (rows)."""
    tex = lx_m / nx
    x = ((np.arange(nx) + 0.5) * tex - lx_m / 2).astype(np.float32)[None, :]
    z = ((np.arange(nz) + 0.5) * tex).astype(np.float32)[:, None]
    ax = np.abs(x)
    px = 1.0 / tex
    grain = _fbm(rng, nz, nx, (1, 0.15 * px, 0.6 * px, 3 * px, 12 * px),
                 (5.0, 5.0, 5.0, 6.0, 6.0))
    asphalt = 88.0 + grain
    grass = 80.0 + 2.4 * _fbm(rng, nz, nx, (1, 0.05 * px, 0.3 * px, 2 * px, 8 * px, 24 * px),
                              (6.0, 5.0, 4.0, 5.0, 5.0, 5.0))
    inner, outer = _HW_MEDIAN_M, _HW_MEDIAN_M + _HW_LANES * _HW_LANE_M
    road = _cover(ax - inner, tex) * _cover(outer + 2.5 - ax, tex)
    gravel = _cover(outer + 4.0 - ax, tex) * _cover(ax - inner + 0.8, tex)
    out = grass + gravel * (125.0 + 1.5 * grain - grass)
    out += road * (asphalt - out)
    white = 210.0 + 0.5 * grain
    dash = _cover(1.5 - np.abs(np.mod(z, 12.0) - 1.5), tex)  # 3 m dash every 12 m
    lines = np.maximum(_cover(0.08 - np.abs(ax - inner - 0.3), tex),
                       _cover(0.12 - np.abs(ax - outer), tex))
    for k in range(1, _HW_LANES):
        lines = np.maximum(lines, dash * _cover(0.08 - np.abs(ax - inner - k * _HW_LANE_M), tex))
    out += lines * (white - out)
    _draw_blemishes(rng, out, tex, lz_m, road)
    return np.clip(out, 0, 255).astype(np.uint8)


def _wall_canvas(h: int, w: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Coordinates of a wall texture: along (1, w) and height (h, 1) in metres, texel (m)."""
    tex = _WALL_W_M / w
    along = ((np.arange(w) + 0.5) * tex).astype(np.float32)[None, :]
    height = (_WALL_H_M - (np.arange(h) + 0.5) * tex).astype(np.float32)[:, None]
    return along, height, tex


def _finish(img: np.ndarray) -> np.ndarray:
    """Clip to grey levels and store as uint8."""
    return np.clip(img, 0, 255).astype(np.uint8)


def _facade(rng: np.random.Generator, h: int, w: int, style: int) -> np.ndarray:
    """Draw a facade texture (h, w): storeys of windows, shop front, plaster or bricks."""
    x, y, tex = _wall_canvas(h, w)
    H, W = h, w
    px = 1.0 / tex
    base = float(rng.uniform(115, 195))
    img = base + _fbm(rng, H, W, (1, 0.04 * px, 0.2 * px, 1.0 * px, 4 * px),
                      (3.0, 3.0, 3.0, 5.0, 6.0))
    img *= 1.0 + 0.06 * _noise(rng, H, W, 3.0 * px, 0.15 * px)  # vertical grime streaks
    if style % 3 == 1:  # bricks
        course, brick = 0.075, 0.25
        row = np.floor(y / course)
        shift = np.mod(row, 2) * brick / 2
        col = np.floor((x + shift) / brick)
        tones = rng.normal(0, 9.0, 4096).astype(np.float32)
        bid = (row.astype(np.int64) * 97 + col.astype(np.int64) * 13) % 4096
        mortar = np.maximum(_cover(0.006 - np.mod(y, course), tex),
                            _cover(0.006 - np.mod(x + shift, brick), tex))
        img += tones[bid] - 0.25 * (base - 90.0)
        img += mortar * (base + 25.0 - img)
    n_cols = int(rng.choice([3, 4, 5]))
    pitch = _WALL_W_M / n_cols
    win_w = float(rng.uniform(0.9, min(1.7, 0.6 * pitch)))
    win_h = float(rng.uniform(1.3, 1.9))
    sill = float(rng.uniform(0.7, 1.0))
    frame_t = 0.07
    storey = np.floor((y - _GROUND_FLOOR_M) / _FLOOR_M)
    yin = y - _GROUND_FLOOR_M - storey * _FLOOR_M - sill
    colx = np.floor(x / pitch)
    xin = x - colx * pitch - (pitch - win_w) / 2
    inside = _cover(np.minimum(xin, win_w - xin), tex) * _cover(np.minimum(yin, win_h - yin),
                                                                tex)
    inside *= (storey >= 0)
    glass_tab = rng.uniform(25, 95, 4096).astype(np.float32)
    lit = rng.random(4096) < 0.2
    glass_tab[lit] = rng.uniform(110, 175, int(lit.sum()))
    wid = ((storey.astype(np.int64) + 8) * 31 + colx.astype(np.int64) * 7) % 4096
    glass = glass_tab[wid] + 25.0 * np.clip(yin / win_h, 0, 1)
    glass -= 10.0 * np.clip(xin / win_w, 0, 1)
    glass += 2.0 * _noise(rng, H, W, 0.05 * px)
    frame = 1.0 - _cover(np.minimum(np.minimum(xin, win_w - xin),
                                    np.minimum(yin, win_h - yin)) - frame_t, tex)
    mullion = _cover(0.03 - np.abs(xin - win_w / 2), tex) + _cover(
        0.03 - np.abs(yin - 0.62 * win_h), tex)
    frame = np.clip(frame + (style % 2) * mullion, 0, 1)
    frame_tone = 215.0 if base < 160 else 60.0
    pane = glass + frame * (frame_tone - glass)
    img += inside * (pane - img)
    sill_band = _cover(0.06 - np.abs(yin + 0.05), tex) * _cover(
        np.minimum(xin, win_w - xin) + 0.12, tex) * (storey >= 0)
    img += sill_band * (225.0 - img)
    if style % 2 == 0:  # cornice between storeys, with brackets every 0.4 m
        brackets = _cover(0.05 - np.abs(np.mod(x, 0.4) - 0.2), tex) * _cover(
            0.12 - np.abs(y - _GROUND_FLOOR_M - storey * _FLOOR_M + 0.1), tex)
        img += brackets * (base - 45.0 - img) * (storey >= 0)
        cornice = _cover(0.08 - np.abs(y - _GROUND_FLOOR_M - storey * _FLOOR_M), tex) * (
            storey >= 0)
        img += cornice * (base + 40.0 - img)
    # ground floor: shop windows and doors, with a sign band
    shop_w = pitch * float(rng.uniform(0.55, 0.8))
    sx = x - colx * pitch - (pitch - shop_w) / 2
    shop = _cover(np.minimum(sx, shop_w - sx), tex) * _cover(np.minimum(y - 0.3, 2.9 - y), tex)
    door = (np.mod(colx, 3) == 1)
    shop_glass = 45.0 + 30.0 * _noise(rng, H, W, 0.4 * px) * 0.5 + 35.0 * (y / 3.0)
    shop_glass = np.where(door & (y < 2.4), 70.0 + 10.0 * np.mod(np.floor(sx / 0.3), 2),
                          shop_glass)
    img += shop * (shop_glass - img)
    sign = _cover(np.minimum(y - 3.1, 3.6 - y), tex) * _cover(np.minimum(sx, shop_w - sx), tex)
    letters = 40.0 * (np.mod(np.floor(sx / 0.18) * 7 + np.floor(y / 0.13) * 3, 5) < 2)
    img += sign * (200.0 - letters * (np.mod(colx, 2) == 0) - img)
    pipe = _cover(0.05 - np.abs(x - 0.25), tex)
    img += pipe * (base - 50.0 - img)
    return _finish(img)


def _vehicle(rng: np.random.Generator, h: int, w: int, kind: int) -> np.ndarray:
    """
    Vehicle texture (h, w): side design on [0, L] and rear design on [W_tex - 3, W_tex - 0.5].

    ``kind`` indexes ``_VEHICLES`` (van, truck, bus).
    """
    x, y, tex = _wall_canvas(h, w)
    H, W = h, w
    px = 1.0 / tex
    length, width, height = _VEHICLES[kind]
    body = float(rng.choice([rng.uniform(50, 90), rng.uniform(150, 215)]))
    img = body + _fbm(rng, H, W, (1, 0.1 * px, 0.5 * px, 2 * px), (2.0, 2.0, 3.0, 4.0))
    img += 10.0 * np.clip(y / height, 0, 1)  # sky reflection on the upper body
    under = _cover(0.35 - y, tex)
    img += under * (30.0 - img)
    # side: panel lines, windows, wheels, logo
    panels = _cover(0.012 - np.abs(np.mod(x, length / 3) - 0.01), tex) * (x < length)
    img += panels * (body * 0.6 - img)
    if kind == 2:  # bus: a band of windows
        band = _cover(np.minimum(y - 1.25, 2.55 - y), tex) * _cover(
            np.minimum(x - 0.4, length - 0.3 - x), tex)
        bars = _cover(0.05 - np.abs(np.mod(x, 1.5) - 0.75), tex)
        img += band * (50.0 + 60.0 * bars + 15.0 * (y - 1.25) - img)
    else:  # cab window near the front
        cab = _cover(np.minimum(x - (length - 1.7), length - 0.35 - x), tex) * _cover(
            np.minimum(y - 1.25, height - 0.35 - y), tex)
        img += cab * (55.0 + 20.0 * (y - 1.2) - img)
        logo = _cover(np.minimum(x - 1.0, length - 2.6 - x), tex) * _cover(
            np.minimum(y - 1.0, height - 0.6 - y), tex)
        stripes = np.mod(np.floor(x / 0.35) * 3 + np.floor(y / 0.22) * 5, 7) < 3
        img += logo * stripes * ((230.0 if body < 128 else 40.0) - img) * 0.7
    for cx in (1.0, length - 1.3):
        r = np.sqrt((x - cx) ** 2 + (y - 0.45) ** 2)
        tyre = _cover(0.45 - r, tex) * (x < length)
        img += tyre * (28.0 - img)
        rim = _cover(0.22 - r, tex) * (x < length)
        img += rim * (150.0 - 40.0 * _cover(0.06 - r, tex) - img)
    # rear (also used for the front): doors, lights, plate
    rx = x - (_WALL_W_M - 3.0)
    rear = (rx > 0) & (rx < width)
    img = np.where(rear, body + 0.5 * _fbm(rng, H, W, (1, 0.2 * px), (2.0, 3.0)), img)
    img += rear * (under * (30.0 - img))
    seam = _cover(0.015 - np.abs(rx - width / 2), tex) * rear * (y > 0.4)
    img += seam * (body * 0.5 - img)
    window = _cover(np.minimum(rx - 0.25, width - 0.25 - rx), tex) * _cover(
        np.minimum(y - (height - 1.1), height - 0.25 - y), tex)
    img += window * (45.0 - img)
    for lx in (0.2, width - 0.2):
        light = _cover(0.12 - np.abs(rx - lx), tex) * _cover(0.2 - np.abs(y - 0.9), tex)
        img += light * (235.0 - img)
    plate = _cover(0.26 - np.abs(rx - width / 2), tex) * _cover(0.06 - np.abs(y - 0.55), tex)
    chars = np.mod(np.floor((rx - width / 2) / 0.045), 3) == 0
    img += plate * (225.0 - 170.0 * chars * _cover(0.035 - np.abs(y - 0.55), tex) - img)
    return _finish(img)


def _plain_wall(rng: np.random.Generator, h: int, w: int, kind: str) -> np.ndarray:
    """Pole, concrete noise wall or warehouse texture (h, w)."""
    x, y, tex = _wall_canvas(h, w)
    H, W = h, w
    px = 1.0 / tex
    if kind == 'pole':
        img = 135.0 + 12.0 * np.sin(x * 40.0)
        img = img + _fbm(rng, H, W, (1, 0.2 * px, 1.0 * px), (2.0, 4.0, 6.0))
        img += _cover(0.05 - np.abs(np.mod(y, 2.3) - 0.05), tex) * 40.0
        img += _cover(0.9 - y, tex) * (70.0 - img)
        img += _cover(0.25 - np.abs(y - 6.9), tex) * (240.0 - img)
        return _finish(img)
    if kind == 'concrete':
        img = 150.0 + _fbm(rng, H, W, (1, 0.02 * px, 0.08 * px, 0.5 * px, 2 * px),
                           (6.0, 6.0, 6.0, 7.0, 8.0))
        img *= 1.0 + 0.08 * _noise(rng, H, W, 2.0 * px, 0.1 * px)
        grooves = _cover(0.02 - np.abs(np.mod(x, 3.2) - 1.6), tex)
        img += grooves * (80.0 - img)
        post = _cover(0.1 - np.abs(np.mod(x, 3.2)), tex) + _cover(np.mod(x, 3.2) - 3.1, tex)
        img += np.clip(post, 0, 1) * (95.0 - img)
        img += _cover(0.03 - np.abs(np.mod(y, 1.0) - 0.5), tex) * 20.0
        return _finish(img)
    # warehouse: corrugated cladding, loading doors, high windows, a logo
    base = float(rng.uniform(120, 190))
    img = base + 18.0 * np.sin(x * 2 * np.pi / 0.2) + _fbm(
        rng, H, W, (1, 0.1 * px, 1.0 * px, 4 * px), (3.0, 3.0, 6.0, 8.0))
    dx = np.mod(x, 6.4) - 0.8
    door = _cover(np.minimum(dx, 3.5 - dx), tex) * _cover(4.0 - y, tex)
    img += door * (95.0 + 25.0 * (np.mod(y, 0.25) < 0.03) - img)
    band = _cover(np.minimum(y - 6.0, 7.0 - y), tex) * _cover(0.9 - np.abs(np.mod(x, 3.2)
                                                                           - 1.6), tex)
    img += band * (60.0 - img)
    logo = _cover(np.minimum(y - 8.0, 10.0 - y), tex) * _cover(4.0 - np.abs(x - 6.4), tex)
    img += logo * (np.mod(np.floor(x / 0.5) + np.floor(y / 0.4), 3) < 1) * (40.0 - img)
    return _finish(img)


def _sky(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Cloud brightness (h, w) float32 around 0 (grey levels): azimuth along x, elevation y."""
    coarse = _noise(rng, h, w, h / 4.0, w / 24.0)
    return 6.0 * coarse + 3.0 * _noise(rng, h, w, h / 16.0, w / 96.0)


class _RipMaps:
    """Rip-maps of one periodic texture: level (lx, ly) halves x lx times and y ly times."""

    def __init__(self, base: np.ndarray, texel_x: float, texel_y: float) -> None:
        self.texel_x, self.texel_y = texel_x, texel_y
        self.max_x = max(0, int(math.log2(base.shape[1])) - 2)
        self.max_y = max(0, int(math.log2(base.shape[0])) - 2)
        self._levels: dict[tuple[int, int], np.ndarray] = {(0, 0): base}
        for ly in range(self.max_y + 1):  # box filtered, still periodic
            if ly:
                src = self._levels[(0, ly - 1)]
                self._levels[(0, ly)] = cv2.resize(src, (src.shape[1], src.shape[0] // 2),
                                                   interpolation=cv2.INTER_AREA)
            for lx in range(1, self.max_x + 1):
                src = self._levels[(lx - 1, ly)]
                self._levels[(lx, ly)] = cv2.resize(src, (src.shape[1] // 2, src.shape[0]),
                                                    interpolation=cv2.INTER_AREA)

    def level(self, lx: int, ly: int) -> np.ndarray:
        """Return the (H >> ly, W >> lx) uint8 level."""
        return self._levels[(lx, ly)]


class _WallAtlas:
    """
    All wall textures with their rip-maps packed into one padded uint8 atlas.

    Texture ``i`` at level (lx, ly) starts at atlas column ``x0[i, lx]`` and row ``y0[ly]``;
    every level is padded by wrapping horizontally and by replication vertically so that
    bilinear lookups at the seams are correct.
    """

    PAD = 2

    def __init__(self, textures: list[np.ndarray]) -> None:
        h, w = textures[0].shape
        self.h, self.w = h, w
        self.texel = _WALL_W_M / w
        self.max_x = max(0, int(math.log2(w)) - 2)
        self.max_y = max(0, int(math.log2(h)) - 2)
        p = self.PAD
        widths = [(w >> lx) + 2 * p for lx in range(self.max_x + 1)]
        heights = [(h >> ly) + 2 * p for ly in range(self.max_y + 1)]
        block_w = sum(widths)
        self.x0 = np.zeros((len(textures), self.max_x + 1), np.float64)
        self.y0 = np.cumsum([0] + heights[:-1]).astype(np.float64) + p
        atlas = np.zeros((sum(heights), block_w * len(textures)), np.uint8)
        for i, tex in enumerate(textures):
            rip = _RipMaps(tex, 1.0, 1.0)
            xs = i * block_w + np.cumsum([0] + widths[:-1])
            self.x0[i] = xs + p
            for lx in range(self.max_x + 1):
                for ly in range(self.max_y + 1):
                    lev = rip.level(lx, ly)
                    lev = np.pad(np.pad(lev, ((0, 0), (p, p)), mode='wrap'), ((p, p), (0, 0)),
                                 mode='edge')
                    y = int(self.y0[ly]) - p
                    atlas[y:y + lev.shape[0], xs[lx]:xs[lx] + lev.shape[1]] = lev
        if atlas.shape[1] >= 32767 or atlas.shape[0] >= 32767:
            raise ConfigError(f'wall texture atlas too large ({atlas.shape}); lower the width')
        self.atlas = atlas


# ---------------------------------------------------------------------------------------------
# Trajectory
# ---------------------------------------------------------------------------------------------
def _smootherstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _smootherstep_slope(x: np.ndarray) -> np.ndarray:
    inside = (x > 0.0) & (x < 1.0)
    return np.where(inside, 30.0 * x * x * (1.0 - x) ** 2, 0.0)


_RAMP = 0.3  # fraction of a turn spent building up (and releasing) the yaw rate


def _turn_profile(x: np.ndarray) -> np.ndarray:
    """
    Fraction (0..1) of a turn's yaw done at fraction x of its length.

    The yaw rate ramps up along a smootherstep over the first ``_RAMP`` of the turn, stays
    constant, and ramps down symmetrically (a smooth clothoid-arc-clothoid); peak yaw rate is
    1 / (1 - _RAMP) times the mean.
    """
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    r = _RAMP

    def ramp_area(u: np.ndarray) -> np.ndarray:  # integral of smootherstep from 0 to u
        u = np.clip(u, 0.0, 1.0)
        return u ** 6 - 3.0 * u ** 5 + 2.5 * u ** 4

    area = 1.0 - r
    out = np.where(x < r, r * ramp_area(x / r), 0.5 * r + (x - r))
    out = np.where(x > 1.0 - r, area - r * ramp_area((1.0 - x) / r), out)
    return out / area


#: Displacement of a 90-degree turn along either axis, per metre of turn length.
_TURN_C = float(np.trapezoid(np.cos(0.5 * np.pi * _turn_profile(np.linspace(0, 1, 200001))),
                             dx=1.0 / 200000))


class Trajectory:
    """
    Smooth, vehicle-like planar path with a speed profile and a vertical bounce.

    The heading (yaw, rad, about the world y axis; 0 = +z, positive turns towards +x) is an
    analytic function of the arc length s (m): 90-degree turns follow ``_turn_profile`` (yaw
    rate continuous and smooth); lane changes add a smootherstep-derivative yaw bump.
    Positions are integrated on a 1 cm grid.
    """

    _DS = 0.01

    def __init__(self, length_m: float, turns: np.ndarray, lane_changes: np.ndarray,
                 speed_mps: float, turn_speed_mps: float, rng: np.random.Generator,
                 camera_height_m: float, bounce_m: float) -> None:
        self.turns = np.asarray(turns, np.float64).reshape(-1, 3)  # s0, length, dyaw
        self.lane_changes = np.asarray(lane_changes, np.float64).reshape(-1, 3)  # s0, L, dx
        s = np.arange(0.0, length_m + self._DS, self._DS)
        yaw = self.yaw(s)
        half = 0.5 * self._DS
        self._s = s
        self._x = np.concatenate([[0.0], np.cumsum((np.sin(yaw[1:]) + np.sin(yaw[:-1])) * half)])
        self._z = np.concatenate([[0.0], np.cumsum((np.cos(yaw[1:]) + np.cos(yaw[:-1])) * half)])
        ph = rng.uniform(0, 2 * np.pi, 4)
        v = speed_mps * (1.0 + 0.05 * np.sin(2 * np.pi * s / 170.0 + ph[0])
                         + 0.03 * np.sin(2 * np.pi * s / 61.0 + ph[1]))
        slow = np.zeros_like(s)
        ramp = 25.0
        for s0, length, _ in self.turns:
            w = np.minimum(_smootherstep((s - s0 + ramp) / ramp),
                           _smootherstep((s0 + length + ramp - s) / ramp))
            slow = np.maximum(slow, w)
        self._v = v * (1.0 - slow) + min(turn_speed_mps, speed_mps) * slow
        self._t = np.concatenate([[0.0], np.cumsum(self._DS * 0.5 * (1.0 / self._v[1:]
                                                                     + 1.0 / self._v[:-1]))])
        self.camera_height_m = camera_height_m
        self._bounce = (bounce_m, rng.uniform(1.0, 1.6), rng.uniform(1.8, 2.6), ph[2], ph[3])

    @property
    def duration_s(self) -> float:
        """Time to drive the whole path (s)."""
        return float(self._t[-1])

    def yaw(self, s: np.ndarray) -> np.ndarray:
        """Heading (rad) at arc length s (m), vectorized; turns and lane changes never overlap."""
        s = np.asarray(s, np.float64)
        yaw = np.zeros_like(s)
        if len(self.turns):
            s0, length, dyaw = self.turns.T
            done = np.searchsorted(s0 + length, s, side='right')  # completed turns
            yaw += np.concatenate([[0.0], np.cumsum(dyaw)])[done]
            k = np.minimum(done, len(s0) - 1)
            active = (done < len(s0)) & (s > s0[k])
            yaw[active] += dyaw[k[active]] * _turn_profile(
                (s[active] - s0[k[active]]) / length[k[active]])
        if len(self.lane_changes):
            s0, length, dx = self.lane_changes.T
            k = np.clip(np.searchsorted(s0, s, side='right') - 1, 0, len(s0) - 1)
            active = (s > s0[k]) & (s < s0[k] + length[k])
            kk = k[active]
            yaw[active] += dx[kk] / length[kk] * _smootherstep_slope(
                (s[active] - s0[kk]) / length[kk])
        return yaw

    def arc_length(self, t: np.ndarray) -> np.ndarray:
        """Arc length s (m) reached at time t (s) after the start."""
        return np.interp(t, self._t, self._s)

    def height(self, t: np.ndarray) -> np.ndarray:
        """Camera height above the road (m) at time t (s)."""
        a, f1, f2, p1, p2 = self._bounce
        t = np.asarray(t, np.float64)
        return self.camera_height_m + a * (0.6 * np.sin(2 * np.pi * f1 * t + p1)
                                           + 0.4 * np.sin(2 * np.pi * f2 * t + p2))

    def planar(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, z (m) and yaw (rad) of the left camera at times t (s)."""
        s = self.arc_length(t)
        return np.interp(s, self._s, self._x), np.interp(s, self._s, self._z), self.yaw(s)

    def poses(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) float64 ``T_world_cam`` of the left camera at times t (s)."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        x, z, yaw = self.planar(t)
        y = float(self.height(np.zeros(1))[0]) - self.height(t)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        c, s = np.cos(yaw), np.sin(yaw)
        T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, s, -s, c
        T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = x, y, z
        return T


# ---------------------------------------------------------------------------------------------
# Scene: boxes on a ground plane
# ---------------------------------------------------------------------------------------------
@dataclass
class _Boxes:
    """Axis-aligned boxes standing on the ground: x/z extents (m), height (m), looks."""

    xmin: np.ndarray
    xmax: np.ndarray
    zmin: np.ndarray
    zmax: np.ndarray
    height: np.ndarray
    tex: np.ndarray  # (N,) int atlas texture
    gain: np.ndarray  # (N,) brightness factor
    s_off: np.ndarray  # (N, 4) texture offset (m) of faces +x, -x, +z, -z

    @staticmethod
    def concat(items: list['_Boxes']) -> '_Boxes':
        return _Boxes(*[np.concatenate([getattr(b, f.name) for b in items])
                        for f in dataclasses.fields(_Boxes)])

    def __len__(self) -> int:
        return len(self.xmin)

    def faces(self) -> dict[str, np.ndarray]:
        """
        Return the four vertical faces of every box (4N entries, outward normals).

        ``q0`` (F, 2) start and ``e`` (F, 2) edge vector in world (x, z), oriented so that the
        texture runs left to right for a viewer outside; ``n`` outward unit normal.
        """
        n = len(self)
        q0 = np.empty((n, 4, 2))
        e = np.empty((n, 4, 2))
        nrm = np.zeros((n, 4, 2))
        q0[:, 0] = np.stack([self.xmax, self.zmin], 1)  # +x face, runs +z
        e[:, 0] = np.stack([np.zeros(n), self.zmax - self.zmin], 1)
        q0[:, 1] = np.stack([self.xmin, self.zmax], 1)  # -x face, runs -z
        e[:, 1] = np.stack([np.zeros(n), self.zmin - self.zmax], 1)
        q0[:, 2] = np.stack([self.xmax, self.zmax], 1)  # +z face, runs -x
        e[:, 2] = np.stack([self.xmin - self.xmax, np.zeros(n)], 1)
        q0[:, 3] = np.stack([self.xmin, self.zmin], 1)  # -z face, runs +x
        e[:, 3] = np.stack([self.xmax - self.xmin, np.zeros(n)], 1)
        nrm[:, 0, 0], nrm[:, 1, 0], nrm[:, 2, 1], nrm[:, 3, 1] = 1, -1, 1, -1
        rep = np.repeat
        return {'q0': q0.reshape(-1, 2), 'e': e.reshape(-1, 2), 'n': nrm.reshape(-1, 2),
                'height': rep(self.height, 4), 'tex': rep(self.tex, 4),
                'gain': rep(self.gain, 4) * np.tile([1.0, 0.82, 0.92, 0.72], n),
                's_off': self.s_off.reshape(-1)}

    def distance(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Return the horizontal distances (P, N), metres, of P points to the boxes; 0 inside."""
        dx = np.maximum(np.maximum(self.xmin[None] - x[:, None], x[:, None] - self.xmax[None]), 0)
        dz = np.maximum(np.maximum(self.zmin[None] - z[:, None], z[:, None] - self.zmax[None]), 0)
        return np.hypot(dx, dz)


@dataclass
class _Movers:
    """Vehicles moving at constant velocity along a lane (axis-aligned)."""

    x0: np.ndarray  # (M,) centre at t = 0 (m)
    z0: np.ndarray
    vx: np.ndarray  # (M,) velocity (m/s), along x or z
    vz: np.ndarray
    kind: np.ndarray  # (M,) index into _VEHICLES
    tex: np.ndarray
    gain: np.ndarray

    def boxes(self, t: float, wall_w_m: float = _WALL_W_M) -> _Boxes:
        """Boxes of the vehicles at time t (s) after the first frame."""
        dims = np.array(_VEHICLES)[self.kind] if len(self.kind) else np.zeros((0, 3))
        along_x = np.abs(self.vx) > np.abs(self.vz)
        half_x = np.where(along_x, dims[:, 0], dims[:, 1]) / 2
        half_z = np.where(along_x, dims[:, 1], dims[:, 0]) / 2
        cx, cz = self.x0 + self.vx * t, self.z0 + self.vz * t
        rear = wall_w_m - 3.0
        # faces +x, -x, +z, -z: side design (offset 0) on faces parallel to the motion
        s_off = np.where(along_x[:, None], [[rear, rear, 0.0, 0.0]], [[0.0, 0.0, rear, rear]])
        return _Boxes(cx - half_x, cx + half_x, cz - half_z, cz + half_z, dims[:, 2],
                      self.tex.copy(), self.gain.copy(), s_off)


class Scene:
    """
    The static boxes, the moving vehicles, the ground tile and the camera path of a spec.

    The geometry and the path depend on ``spec.seed`` and the motion fields only, not on the
    image size; textures are generated at a texel size matched to the focal length.

    Attributes
    ----------
    trajectory : Trajectory
        Path of the left camera.
    boxes : _Boxes
        Static axis-aligned boxes in ``world`` (x, z extents and height, metres).
    movers : _Movers
        Vehicles at constant velocity; ``movers.boxes(t)`` gives their boxes at time t (s).
    ground_y : float
        World y of the road plane (m); the camera height at the first frame.
    route_nodes : np.ndarray
        (K, 2) world (x, z) of the crossings the city route meets (m); empty on the highway.

    """

    def __init__(self, spec: SequenceSpec) -> None:
        t0 = time.perf_counter()
        self.spec = spec
        rng = np.random.default_rng([spec.seed, 7])  # geometry: independent of resolution
        self._tex_rng = np.random.default_rng([spec.seed, 8])  # textures
        f = spec.focal_px  # textures follow the output resolution, not the supersampling
        scale = KITTI_FOCAL_PX / f  # texel sizes grow when the images shrink
        wall_w = int(2 ** np.clip(round(math.log2(_WALL_W_M / (0.025 * scale))), 5, 10))
        self._wall_px = (2 * wall_w, wall_w)
        self.ground_y = spec.camera_height_m  # world y of the road; refined below
        self.duration_s = (spec.n_frames - 1) / spec.frame_rate_hz
        if spec.scene == 'city':
            self._build_city(rng, scale)
        else:
            self._build_highway(rng, scale)
        self.ground_y = float(self.trajectory.height(np.zeros(1))[0])
        self._check_clearance()
        logger.debug('scene %s built in %.2f s (%d boxes, %d movers)', spec.name,
                     time.perf_counter() - t0, len(self.boxes), len(self.movers.x0))

    # -- textures -------------------------------------------------------------------------
    def _wall_textures(self, rng: np.random.Generator, facades: int) -> None:
        h, w = self._wall_px
        tex = [_facade(rng, h, w, i) for i in range(facades)]
        self.tex_pole = len(tex)
        tex.append(_plain_wall(rng, h, w, 'pole'))
        self.tex_concrete = len(tex)
        tex.append(_plain_wall(rng, h, w, 'concrete'))
        self.tex_warehouse = len(tex)
        tex.append(_plain_wall(rng, h, w, 'warehouse'))
        self.tex_vehicle = len(tex)
        tex.extend(_vehicle(rng, h, w, k) for k in range(len(_VEHICLES)))
        self.n_facades = facades
        self.atlas = _WallAtlas(tex)
        self.sky = _sky(rng, 64, 1024)

    # -- city -----------------------------------------------------------------------------
    def _build_city(self, rng: np.random.Generator, scale: float) -> None:
        spec = self.spec
        P, a = spec.block_m, _LANE_OFFSET_M
        n = int(2 ** round(math.log2(P / (0.02 * scale))))
        n = int(np.clip(n, 256, 8192))
        self.ground = _RipMaps(_ground_city(self._tex_rng, n, P), P / n, P / n)
        # tile coordinate = world - origin; streets at tile P/2 -> world x = -a, z = P/2
        self.ground_origin = (-a - P / 2, 0.0)
        self.ground_period = (P, P)
        self._wall_textures(self._tex_rng, 6)
        self._plan_city_route(rng)
        self._city_blocks(rng)
        self._city_movers(rng)

    def _plan_city_route(self, rng: np.random.Generator) -> None:
        spec = self.spec
        P, a = spec.block_m, _LANE_OFFSET_M
        turn_len = 22.0
        e = _TURN_C * turn_len
        need = spec.speed_mps * 1.12 * self.duration_s + 60.0
        pos = np.array([0.0, 0.0])
        heading = 0  # multiples of 90 degrees
        node = np.array([-a, P / 2])
        s, turns, nodes = 0.0, [], []
        while True:
            f = np.array([math.sin(heading * np.pi / 2), math.cos(heading * np.pi / 2)])
            r = np.array([f[1], -f[0]])
            nodes.append(node.copy())
            turn = spec.turns and rng.random() < spec.turn_probability
            side = 1 if rng.random() < 0.5 else -1
            corner = node - a * f + a * r if side > 0 else node + a * f + a * r
            start = corner - e * f
            dist = float((start - pos) @ f)
            if turn and dist > 2.0 and s + dist < need:
                turns.append((s + dist, turn_len, side * np.pi / 2))
                s += dist + turn_len
                pos = corner + side * e * r
                heading = (heading + side) % 4
                f = np.array([math.sin(heading * np.pi / 2), math.cos(heading * np.pi / 2)])
            elif s + float((node - pos) @ f) > need:
                s += float((node - pos) @ f) + P / 2
                break
            node = node + P * f
        self.route_nodes = np.array(nodes)
        self.trajectory = Trajectory(s, np.array(turns), np.zeros((0, 3)), spec.speed_mps,
                                     7.5, rng, spec.camera_height_m, spec.bounce_m)

    def _path_samples(self, step_s: float | None = None) -> tuple[np.ndarray, ...]:
        """Sample the left camera path densely: times (s), x, z (m), yaw (rad)."""
        step = step_s or 0.25 / self.spec.frame_rate_hz
        t = np.arange(0.0, self.duration_s + step, step)
        x, z, yaw = self.trajectory.planar(t)
        return t, x, z, yaw

    def _city_blocks(self, rng: np.random.Generator) -> None:
        spec = self.spec
        P, a = spec.block_m, _LANE_OFFSET_M
        _, px, pz, _ = self._path_samples(0.5)
        reach = 170.0
        ix = np.floor((px + a) / P).astype(int)
        iz = np.floor((pz - P / 2) / P).astype(int)
        cells = set()
        k = int(math.ceil(reach / P))
        for i, j in set(zip(ix.tolist(), iz.tolist())):
            for di in range(-k, k + 1):
                for dj in range(-k, k + 1):
                    cells.add((i + di, j + dj))
        setback0 = _ROAD_HALF_M + _SIDEWALK_M
        boxes: list[tuple] = []
        for i, j in sorted(cells):
            x0, z0 = -a + i * P, P / 2 + j * P  # street centre lines bounding the block
            if np.min(np.hypot(px - (x0 + P / 2), pz - (z0 + P / 2))) > reach + P:
                continue
            lo, hi = setback0, P - setback0
            for side in range(4):
                u = lo
                while u < hi - 3.0:
                    width = min(float(rng.uniform(8.0, 22.0)), hi - u)
                    if hi - (u + width) < 6.0:
                        width = hi - u
                    depth = float(rng.uniform(10.0, 16.0))
                    back = setback0 + float(rng.choice([0.0, 0.0, rng.uniform(0.5, 4.0)]))
                    storeys = int(rng.integers(2, 7))
                    height = _GROUND_FLOOR_M + storeys * _FLOOR_M - 0.5
                    along = (u, u + width)
                    across = (back, back + depth)
                    if side == 0:  # facing -z street
                        bx, bz = along, across
                    elif side == 1:  # facing +z street
                        bx, bz = along, (P - across[1], P - across[0])
                    elif side == 2:  # facing -x street
                        bx, bz = across, along
                    else:
                        bx, bz = (P - across[1], P - across[0]), along
                    boxes.append((x0 + bx[0], x0 + bx[1], z0 + bz[0], z0 + bz[1], height,
                                  int(rng.integers(0, self.n_facades)),
                                  float(rng.uniform(0.8, 1.15))))
                    u += width + float(rng.choice([0.0, 0.0, 0.0, rng.uniform(1.5, 5.0)]))
            # lamp posts along the four kerbs, away from the crossings
            for side in range(4):
                for u in np.arange(setback0 + 8.0, P - setback0 - 8.0, 24.0):
                    off = _ROAD_HALF_M + 0.6
                    cx, cz = [(u, off), (u, P - off), (off, u), (P - off, u)][side]
                    boxes.append((x0 + cx - 0.1, x0 + cx + 0.1, z0 + cz - 0.1, z0 + cz + 0.1,
                                  7.2, self.tex_pole, 1.0))
        if spec.parked_vehicles:
            boxes.extend(self._parked(rng))
        arr = np.array(boxes, np.float64).reshape(-1, 7)
        keep = self._clear_of_path(arr, 1.0)
        if not np.all(keep[arr[:, 5] < self.n_facades]):
            raise ConfigError(f'synthetic city (seed {spec.seed}) puts a building on the path')
        arr = arr[keep]
        s_off = rng.uniform(0, _WALL_W_M, (len(arr), 4))
        vehicle = arr[:, 5] >= self.tex_vehicle
        along_x = (arr[:, 1] - arr[:, 0]) > (arr[:, 3] - arr[:, 2])
        rear = _WALL_W_M - 3.0
        s_off[vehicle] = np.where(along_x[vehicle, None], [[rear, rear, 0.0, 0.0]],
                                  [[0.0, 0.0, rear, rear]])
        self.boxes = _Boxes(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4],
                            arr[:, 5].astype(np.int64), arr[:, 6], s_off)

    def _clear_of_path(self, arr: np.ndarray, margin: float) -> np.ndarray:
        """
        Mask the boxes (rows xmin, xmax, zmin, zmax, ...) away from both cameras' paths.

        Path samples are processed in short stretches against the boxes near each stretch.
        """
        keep = np.ones(len(arr), bool)
        if len(arr) == 0:
            return keep
        _, x, z, yaw = self._path_samples()
        b = self.spec.baseline_m
        xmin, xmax, zmin, zmax = arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3]
        for px, pz in ((x, z), (x + b * np.cos(yaw), z - b * np.sin(yaw))):
            for i in range(0, len(px), 256):
                sx, sz = px[i:i + 256], pz[i:i + 256]
                near = np.flatnonzero((xmin < sx.max() + margin) & (xmax > sx.min() - margin)
                                      & (zmin < sz.max() + margin) & (zmax > sz.min() - margin))
                if near.size:
                    dx = np.maximum(np.maximum(xmin[near] - sx[:, None], sx[:, None] - xmax[near]),
                                    0)
                    dz = np.maximum(np.maximum(zmin[near] - sz[:, None], sz[:, None] - zmax[near]),
                                    0)
                    keep[near[np.hypot(dx, dz).min(0) <= margin]] = False
        return keep

    def _parked(self, rng: np.random.Generator) -> list[tuple]:
        """Vans parked on the kerb-side strips of the streets around the route's crossings."""
        P = self.spec.block_m
        length, width, height = _VEHICLES[0]
        out = []
        nodes = {tuple(np.round(n, 3)) for n in self.route_nodes.tolist()}
        for node in sorted(nodes):
            for axis in range(2):  # street along world x (0) or z (1)
                for arm in (-1.0, 1.0):
                    for kerb in (-1.0, 1.0):
                        for u in np.arange(_ROAD_HALF_M + _SIDEWALK_M + 6.0, P / 2 - 3.0, 7.0):
                            if rng.random() > 0.3:
                                continue
                            c = np.array(node, np.float64)
                            c[axis] += arm * (u + length / 2)
                            c[1 - axis] += kerb * 4.75
                            half = np.array([length, width])[[axis, 1 - axis]] / 2
                            out.append((c[0] - half[0], c[0] + half[0], c[1] - half[1],
                                        c[1] + half[1], height, self.tex_vehicle, 0.9))
        return out

    def _city_movers(self, rng: np.random.Generator) -> None:
        spec = self.spec
        a = _LANE_OFFSET_M
        t, x, z, yaw = self._path_samples()
        cands = []
        for _ in range(40 * max(spec.moving_objects, 1)):
            if len(cands) >= spec.moving_objects:
                break
            kind = int(rng.integers(0, len(_VEHICLES)))
            speed = float(rng.uniform(6.0, 12.0))
            if rng.random() < 0.6:  # oncoming, in view at time tm
                k = int(rng.integers(0, len(t)))
                h = yaw[k] / (np.pi / 2)
                if abs(h - round(h)) > 1e-6:
                    continue
                f = np.array([math.sin(yaw[k]), math.cos(yaw[k])])
                r = np.array([f[1], -f[0]])
                p = np.array([x[k], z[k]]) - 2 * a * r + f * rng.uniform(15.0, 70.0)
                v = -speed * f
                p0 = p - v * t[k]
            else:  # crossing the route at an intersection, before or after the camera
                node = self.route_nodes[int(rng.integers(0, len(self.route_nodes)))]
                k = int(np.argmin(np.hypot(x - node[0], z - node[1])))
                f = np.array([math.sin(yaw[k]), math.cos(yaw[k])])
                r = np.array([f[1], -f[0]])
                d = r * rng.choice([-1.0, 1.0])
                lane = node + a * np.array([d[1], -d[0]])
                v = speed * d
                tc = t[k] + rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 8.0)
                p0 = lane - v * tc
            cand = (p0[0], p0[1], v[0], v[1], kind, self.tex_vehicle + kind,
                    float(rng.uniform(0.85, 1.1)))
            if self._mover_ok(cand, cands, t, x, z, yaw):
                cands.append(cand)
        self.movers = self._movers(cands)

    @staticmethod
    def _movers(cands: list[tuple]) -> _Movers:
        arr = np.array(cands, np.float64).reshape(-1, 7)
        return _Movers(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4].astype(np.int64),
                       arr[:, 5].astype(np.int64), arr[:, 6])

    def _mover_ok(self, cand: tuple, others: list[tuple], t: np.ndarray, x: np.ndarray,
                  z: np.ndarray, yaw: np.ndarray) -> bool:
        """Reject a vehicle that comes near a camera, a static box or another vehicle."""
        def track(c: tuple) -> tuple[np.ndarray, ...]:
            length, width, _ = _VEHICLES[int(c[4])]
            along_x = abs(c[2]) > abs(c[3])
            hx, hz = (length / 2, width / 2) if along_x else (width / 2, length / 2)
            return c[0] + c[2] * t, c[1] + c[3] * t, hx, hz

        cx, cz, hx, hz = track(cand)
        b = self.spec.baseline_m
        for px, pz in ((x, z), (x + b * np.cos(yaw), z - b * np.sin(yaw))):
            d = np.hypot(np.maximum(np.abs(px - cx) - hx, 0), np.maximum(np.abs(pz - cz) - hz, 0))
            if d.min() < 2.0:
                return False
        for other in others:
            ox, oz, ohx, ohz = track(other)
            gap = np.maximum(np.abs(cx - ox) - hx - ohx, np.abs(cz - oz) - hz - ohz)
            if gap.min() < 0.5:
                return False
        bx = self.boxes
        near = np.flatnonzero((bx.xmin < cx.max() + hx + 1) & (bx.xmax > cx.min() - hx - 1)
                              & (bx.zmin < cz.max() + hz + 1) & (bx.zmax > cz.min() - hz - 1))
        step = max(1, int(0.5 / (max(abs(cand[2]), abs(cand[3])) * (t[1] - t[0]) + 1e-9)))
        for i in range(0, len(near), 64):  # boxes along the lane (a straight line) only
            n = near[i:i + 64]
            sx, sz = cx[::step, None], cz[::step, None]
            gap = np.maximum(np.maximum(bx.xmin[n] - sx - hx, sx - hx - bx.xmax[n]),
                             np.maximum(bx.zmin[n] - sz - hz, sz - hz - bx.zmax[n]))
            if gap.min() < 0.3:
                return False
        return True

    # -- highway --------------------------------------------------------------------------
    def _build_highway(self, rng: np.random.Generator, scale: float) -> None:
        spec = self.spec
        lx_m, lz_m = 96.0, 48.0
        nx = int(np.clip(2 ** round(math.log2(lx_m / (0.02 * scale))), 256, 8192))
        self.ground = _RipMaps(_ground_highway(self._tex_rng, nx, nx // 2, lx_m, lz_m), lx_m / nx,
                               lz_m / (nx // 2))
        ego_x = _HW_MEDIAN_M + 1.5 * _HW_LANE_M  # middle lane centre right of the median
        self.highway_centre_x = -ego_x
        self.ground_origin = (-ego_x - lx_m / 2, 0.0)
        self.ground_period = (lx_m, lz_m)
        self._wall_textures(self._tex_rng, 2)
        need = spec.speed_mps * 1.12 * self.duration_s + 60.0
        lane_changes, lane, s = [], 1, float(rng.uniform(40.0, 120.0))
        while spec.turns and s < need:
            length = 4.0 * spec.speed_mps
            step = int(rng.choice([-1, 1])) if lane == 1 else (1 - lane)
            lane_changes.append((s, length, step * _HW_LANE_M))
            lane += step
            s += length + float(rng.uniform(6.0, 14.0)) * spec.speed_mps
        self.route_nodes = np.zeros((0, 2))
        self.trajectory = Trajectory(need, np.zeros((0, 3)), np.array(lane_changes),
                                     spec.speed_mps, spec.speed_mps, rng, spec.camera_height_m,
                                     spec.bounce_m)
        boxes = []
        edge = _HW_MEDIAN_M + _HW_LANES * _HW_LANE_M + 4.0
        z = -60.0
        while z < need + 250.0:  # sign posts, noise walls and warehouses on both sides
            for sign in (-1.0, 1.0):
                xc = self.highway_centre_x + sign * (edge + 1.0)
                boxes.append((xc - 0.15, xc + 0.15, z - 0.15, z + 0.15, 6.5, self.tex_pole, 1.0))
                if rng.random() < 0.35:
                    wall_len = float(rng.uniform(40.0, 140.0))
                    xw = self.highway_centre_x + sign * (edge + 5.0)
                    boxes.append((xw - 0.2, xw + 0.2, z, z + wall_len,
                                  float(rng.uniform(3.0, 4.5)), self.tex_concrete, 1.0))
                if rng.random() < 0.4:
                    dist = float(rng.uniform(25.0, 90.0))
                    size_x, size_z = rng.uniform(15.0, 40.0, 2)
                    x_in = self.highway_centre_x + sign * (edge + dist)
                    x_out = x_in + sign * size_x
                    tex = int(rng.choice([self.tex_warehouse, 0, 1]))
                    boxes.append((min(x_in, x_out), max(x_in, x_out), z, z + size_z,
                                  float(rng.uniform(6.0, 16.0)), tex, float(rng.uniform(0.8,
                                                                                        1.1))))
            z += float(rng.uniform(40.0, 70.0))
        arr = np.array(boxes, np.float64).reshape(-1, 7)
        s_off = rng.uniform(0, _WALL_W_M, (len(arr), 4))
        self.boxes = _Boxes(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4],
                            arr[:, 5].astype(np.int64), arr[:, 6], s_off)
        t, x, zz, yaw = self._path_samples()
        cands: list[tuple] = []
        lanes_same = [-_HW_LANE_M, 0.0, _HW_LANE_M]
        c = self.highway_centre_x
        lanes_opp = [c - (_HW_MEDIAN_M + (k + 0.5) * _HW_LANE_M) for k in range(_HW_LANES)]
        for _ in range(40 * max(spec.moving_objects, 1)):
            if len(cands) >= spec.moving_objects:
                break
            kind = int(rng.integers(0, len(_VEHICLES)))
            tm = float(rng.uniform(0.0, max(self.duration_s, 1.0)))
            ego_z = float(np.interp(tm, t, zz))
            if rng.random() < 0.6:
                vz = spec.speed_mps + float(rng.uniform(-7.0, 5.0))
                lane_x = float(rng.choice(lanes_same))
                zm = ego_z + float(rng.choice([-1.0, 1.0])) * rng.uniform(15.0, 60.0)
            else:
                vz = -spec.speed_mps * float(rng.uniform(0.8, 1.2))
                lane_x = float(rng.choice(lanes_opp))
                zm = ego_z + float(rng.uniform(40.0, 150.0))
            cand = (lane_x, zm - vz * tm, 0.0, vz, kind, self.tex_vehicle + kind,
                    float(rng.uniform(0.85, 1.1)))
            if self._mover_ok(cand, cands, t, x, zz, yaw):
                cands.append(cand)
        self.movers = self._movers(cands)

    # -- checks and queries ---------------------------------------------------------------
    def _check_clearance(self) -> None:
        arr = np.stack([self.boxes.xmin, self.boxes.xmax, self.boxes.zmin, self.boxes.zmax,
                        self.boxes.height, self.boxes.gain, self.boxes.gain], 1)
        if not np.all(self._clear_of_path(arr, 1.0)):
            raise ConfigError(f'synthetic scene {self.spec.name!r} (seed {self.spec.seed}) puts '
                              'a box on the camera path')

    def boxes_at(self, t: float) -> _Boxes:
        """All boxes (static and moving) at time t (s after the first frame)."""
        return _Boxes.concat([self.boxes, self.movers.boxes(t)])

    def ray_depth(self, origin: np.ndarray, directions: np.ndarray, t: float) -> np.ndarray:
        """
        Distance parameter of the first hit of rays ``origin + lam * direction`` (brute force).

        Parameters
        ----------
        origin : np.ndarray
            (3,) ray origin in ``world`` (m).
        directions : np.ndarray
            (N, 3) ray directions in ``world`` (any length).
        t : float
            Time after the first frame (s), for the moving vehicles.

        Returns
        -------
        np.ndarray
            (N,) float64 ``lam`` of the nearest hit (ground or a box face), inf for the sky.

        """
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        o = np.asarray(origin, np.float64).reshape(3)
        lam = np.full(len(d), np.inf)
        down = d[:, 1] > 1e-12
        lam[down] = (self.ground_y - o[1]) / d[down, 1]
        faces = self.boxes_at(t).faces()
        q0, e = faces['q0'], faces['e']
        denom = d[:, 0, None] * e[None, :, 1] - d[:, 2, None] * e[None, :, 0]
        w = q0 - o[[0, 2]][None]
        with np.errstate(divide='ignore', invalid='ignore'):
            lf = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0])[None] / denom
            sf = (w[None, :, 0] * d[:, 2, None] - w[None, :, 1] * d[:, 0, None]) / denom
        y = o[1] + lf * d[:, 1, None]
        ok = (lf > 1e-9) & (sf >= 0) & (sf <= 1) & (y <= self.ground_y) & (
            y >= self.ground_y - faces['height'][None])
        lf = np.where(ok, lf, np.inf)
        return np.minimum(lam, lf.min(1) if lf.shape[1] else lam)


@functools.lru_cache(maxsize=2)
def _scene_for(spec: SequenceSpec) -> Scene:
    return Scene(spec)


def _cubic_weights(frac: np.ndarray) -> list[np.ndarray]:
    """Keys cubic convolution weights (a = -0.5) of the taps -1, 0, 1, 2 at ``frac``."""
    t = frac
    return [((-0.5 * t + 1.0) * t - 0.5) * t, (1.5 * t - 2.5) * t * t + 1.0,
            ((-1.5 * t + 2.0) * t + 0.5) * t, (0.5 * t - 0.5) * t * t]


# ---------------------------------------------------------------------------------------------
# Renderer
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Camera:
    """A level pinhole view: image size (pixels), focal length and principal point (pixels)."""

    width: int
    height: int
    f: float
    cx: float
    cy: float

    @functools.cached_property
    def xn(self) -> np.ndarray:
        """(W,) float64 normalised x of the column centres."""
        return (np.arange(self.width) - self.cx) / self.f


@dataclass
class _Layers:
    """Per-column visible wall layers (nearest first) of one view; arrays are (K, W)."""

    face: np.ndarray
    t: np.ndarray
    sigma: np.ndarray
    vtop: np.ndarray
    ok: np.ndarray


class StereoRenderer:
    """
    Render the stereo pairs of a SequenceSpec (deterministic, random access by index).

    Attributes
    ----------
    spec : SequenceSpec
        What is rendered.
    scene : Scene
        Boxes, vehicles, ground tile and camera path.
    calibration : StereoCalibration
        Rectified calibration of the pairs.
    stamps : np.ndarray
        (N,) float64 stamps (s).
    poses : np.ndarray
        (N, 4, 4) float64 ``T_world_cam`` of the left camera (metres).

    """

    MAX_LAYERS = 8
    MAX_RANGE_M = 5000.0

    def __init__(self, spec: SequenceSpec) -> None:
        self.spec = spec
        self.scene = _scene_for(spec)
        self.calibration = spec.calibration()
        self.stamps = spec.stamps
        self._times = np.arange(spec.n_frames) / spec.frame_rate_hz
        self.poses = self.scene.trajectory.poses(self._times)
        ss = spec.supersample
        cx, cy = spec.principal_point_px
        f = spec.true_focal_px
        self._cam = _Camera(spec.width, spec.height, f, cx, cy)
        self._cam_ss = _Camera(spec.width * ss, spec.height * ss, f * ss,
                               (cx + 0.5) * ss - 0.5, (cy + 0.5) * ss - 0.5)
        self._H_right = None if spec.exact_rig else spec.right_homography()
        self._vignette = [self._vignetting(cam) for cam in range(2)]
        faces = self.scene.boxes.faces()
        faces['moving'] = np.zeros(len(faces['q0']), bool)
        self._static_faces = faces
        self._gains = self._exposure_gains()

    def __len__(self) -> int:
        return self.spec.n_frames

    def __iter__(self) -> Iterator[RenderedFrame]:
        for i in range(len(self)):
            yield self.render(i)

    def _exposure_gains(self) -> np.ndarray:
        """(N, 2) gains of the left and right camera per frame."""
        spec = self.spec
        rng = np.random.default_rng([spec.seed, 11])
        t = self._times
        ph = rng.uniform(0, 2 * np.pi, 3)
        log_g = np.zeros_like(t)
        if spec.exposure_change > 0:
            amp = spec.exposure_change
            log_g += amp * (0.6 * np.sin(2 * np.pi * t / 9.0 + ph[0])
                            + 0.4 * np.sin(2 * np.pi * t / 3.7 + ph[1]))
            n_jumps = rng.poisson(max(t[-1], 1.0) / 4.0)
            for t_jump, size in zip(rng.uniform(0, t[-1] + 1e-9, n_jumps),
                                    rng.choice([-1, 1], n_jumps) * rng.uniform(0.5, 1.0, n_jumps)):
                late = t >= t_jump
                log_g[late] += amp * size * np.exp(-(t[late] - t_jump) / 0.8)
        left = np.exp(log_g)
        right = left * (1.0 + spec.stereo_gain_mismatch * np.sin(2 * np.pi * t / 5.0 + ph[2]))
        return np.stack([left, right], 1)

    def _vignetting(self, cam: int) -> np.ndarray | None:
        """(H, W) float32 vignetting gain of one camera (1 at its centre), None if none."""
        spec = self.spec
        if spec.vignetting <= 0:
            return None
        m = spec.vignetting_mismatch * cam
        strength = spec.vignetting * (1.0 + m)
        k = (1.0 - strength) ** -0.5 - 1.0
        H, W = spec.height, spec.width
        u0 = (W - 1) / 2.0 + m * 0.1 * W
        v0 = (H - 1) / 2.0 + m * 0.05 * H
        r2 = (((np.arange(W) - u0) ** 2)[None, :] + ((np.arange(H) - v0) ** 2)[:, None]) / (
            ((W - 1) / 2.0) ** 2 + ((H - 1) / 2.0) ** 2)
        return ((1.0 + k * r2) ** -2).astype(np.float32)

    def _warp_right(self, img: np.ndarray, nearest: bool = False) -> np.ndarray:
        """
        Apply the rig error homography to an exact right image (same size, border replicate).

        Bilinear interpolation in float32 with exact weights: OpenCV's ``warpPerspective`` and
        ``remap`` round the source coordinates to 1/32 pixel, too coarse for errors of a few
        hundredths of a pixel. ``nearest`` picks the nearest pixel (depth, masks).
        """
        H, W = img.shape
        Hinv = np.linalg.inv(self._H_right)
        u = np.arange(W, dtype=np.float64)[None, :]
        v = np.arange(H, dtype=np.float64)[:, None]
        w = Hinv[2, 0] * u + Hinv[2, 1] * v + Hinv[2, 2]
        x = np.clip((Hinv[0, 0] * u + Hinv[0, 1] * v + Hinv[0, 2]) / w, 0, W - 1)
        y = np.clip((Hinv[1, 0] * u + Hinv[1, 1] * v + Hinv[1, 2]) / w, 0, H - 1)
        if nearest:
            return img[np.rint(y).astype(np.intp), np.rint(x).astype(np.intp)]
        x0 = np.floor(x).astype(np.intp)
        y0 = np.floor(y).astype(np.intp)
        wx = _cubic_weights((x - x0).astype(np.float32))
        wy = _cubic_weights((y - y0).astype(np.float32))
        out = np.zeros((H, W), np.float32)
        for j in range(4):
            rows = np.clip(y0 + (j - 1), 0, H - 1)
            acc = np.zeros((H, W), np.float32)
            for i in range(4):
                acc += img[rows, np.clip(x0 + (i - 1), 0, W - 1)] * wx[i]
            out += acc * wy[j]
        return out

    # -- public ---------------------------------------------------------------------------
    def render(self, index: int, depth: bool = False) -> RenderedFrame:
        """Render stereo pair ``index`` (0-based); with ``depth`` also depth maps and masks."""
        if not 0 <= index < len(self):
            raise IndexError(f'frame index {index} outside [0, {len(self)})')
        spec = self.spec
        T = self.poses[index]
        t = float(self._times[index])
        hc = float(self.scene.trajectory.height(np.array([t]))[0])
        yaw = math.atan2(T[0, 2], T[2, 2])
        faces = self._faces_at(t)
        images, depths, statics = [], [], []
        for cam in range(2):
            cxz = np.array([T[0, 3], T[2, 3]]) + cam * spec.true_baseline_m * np.array(
                [math.cos(yaw), -math.sin(yaw)])
            img, dep, stat = self._view(self._cam_ss, cxz, yaw, hc, faces, shade=True,
                                        geometry=depth and spec.supersample == 1)
            if spec.supersample > 1:
                img = cv2.resize(img, (spec.width, spec.height), interpolation=cv2.INTER_AREA)
                if depth:
                    _, dep, stat = self._view(self._cam, cxz, yaw, hc, faces, shade=False,
                                              geometry=True)
            if cam == 1 and self._H_right is not None:
                img = self._warp_right(img)
                if dep is not None:
                    dep = self._warp_right(dep, nearest=True)
                    stat = self._warp_right(stat, nearest=True)
            images.append(self._sensor(img, index, cam))
            depths.append(dep)
            statics.append(stat)
        return RenderedFrame(index, float(self.stamps[index]), images[0], images[1], T.copy(),
                             depths[0], depths[1], statics[0], statics[1])

    def frames(self) -> Iterator[StereoFrame]:
        """Yield every pair as a StereoFrame."""
        for frame in self:
            yield frame.stereo_frame(self.calibration)

    # -- internals ------------------------------------------------------------------------
    def _faces_at(self, t: float) -> dict[str, np.ndarray]:
        moving = self.scene.movers.boxes(t).faces()
        moving['moving'] = np.ones(len(moving['q0']), bool)
        faces = {k: np.concatenate([v, moving[k]]) for k, v in self._static_faces.items()}
        faces['length'] = np.hypot(faces['e'][:, 0], faces['e'][:, 1])
        return faces

    def _sensor(self, img: np.ndarray, index: int, cam: int) -> np.ndarray:
        """
        Optical blur, vignetting, exposure gain and offset, sensor noise, 8-bit quantisation.

        The per-frame gain and offset jitter of each camera come from their own random stream
        (seed, index, camera), so a frame's images do not depend on the number of frames.
        """
        spec = self.spec
        if spec.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), spec.blur_sigma_px)
        gain = float(self._gains[index, cam])
        offset = 0.0
        if spec.gain_jitter > 0 or spec.gain_offset_jitter > 0:
            jitter = np.random.default_rng([spec.seed, index, cam, 17]).uniform(-1.0, 1.0, 2)
            gain *= 1.0 + spec.gain_jitter * jitter[0]
            offset = spec.gain_offset_jitter * jitter[1]
        if self._vignette[cam] is not None:
            img = img * self._vignette[cam]
        img = img * np.float32(gain)
        if offset:
            img += np.float32(offset)
        if spec.noise_std > 0:
            rng = np.random.default_rng([spec.seed, index, cam, 5])
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(spec.noise_std)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def _cull(self, faces: dict[str, np.ndarray], cxz: np.ndarray, fwd: np.ndarray,
              right: np.ndarray, cam: _Camera) -> np.ndarray:
        """Select the faces a camera at cxz can see (front-facing, in view); return indices."""
        q0 = faces['q0'] - cxz
        q1 = q0 + faces['e']
        facing = np.einsum('ij,ij->i', faces['n'], -q0) > 0
        xn_lo, xn_hi = cam.xn[0] - 1.0 / cam.f, cam.xn[-1] + 1.0 / cam.f
        x0, z0, x1, z1 = q0 @ right, q0 @ fwd, q1 @ right, q1 @ fwd
        out_r = (x0 - xn_hi * z0 > 0) & (x1 - xn_hi * z1 > 0)
        out_l = (x0 - xn_lo * z0 < 0) & (x1 - xn_lo * z1 < 0)
        behind = np.maximum(z0, z1) < _MIN_T_M
        # distance from the camera to the segment
        length2 = np.maximum(np.einsum('ij,ij->i', faces['e'], faces['e']), 1e-12)
        lam = np.clip(np.einsum('ij,ij->i', -q0, faces['e']) / length2, 0, 1)
        near = np.hypot(*(q0 + lam[:, None] * faces['e']).T) < self.MAX_RANGE_M
        return np.flatnonzero(facing & ~out_r & ~out_l & ~behind & near)

    def _layers(self, faces: dict[str, np.ndarray], sel: np.ndarray, cxz: np.ndarray,
                fwd: np.ndarray, right: np.ndarray, d: np.ndarray, hc: float,
                cam: _Camera) -> _Layers:
        """
        Visible wall layers per column, nearest first.

        Every face is intersected with the rays of the columns it projects to; per column the
        hits sorted by depth form a staircase: a farther wall is seen only if its top looks
        higher than the tops of all nearer walls (every wall stands on the road and is taller
        than the camera, so each layer covers the rows between its top and the next nearer
        layer's top).
        """
        W = cam.width
        q0 = faces['q0'][sel] - cxz
        e = faces['e'][sel]
        q1 = q0 + e
        x0, z0, x1, z1 = q0 @ right, q0 @ fwd, q1 @ right, q1 @ fwd
        with np.errstate(divide='ignore', invalid='ignore'):
            lam = (_MIN_T_M - z0) / (z1 - z0)  # clip the segment to the near plane
            x0c = np.where(z0 < _MIN_T_M, x0 + lam * (x1 - x0), x0)
            x1c = np.where(z1 < _MIN_T_M, x0 + lam * (x1 - x0), x1)
            u0 = cam.cx + cam.f * x0c / np.maximum(z0, _MIN_T_M)
            u1 = cam.cx + cam.f * x1c / np.maximum(z1, _MIN_T_M)
        lo = np.clip(np.floor(np.minimum(u0, u1)) - 1, 0, W).astype(np.int64)
        hi = np.clip(np.ceil(np.maximum(u0, u1)) + 1, -1, W - 1).astype(np.int64)
        count = np.maximum(hi - lo + 1, 0)
        total = int(count.sum())
        if total == 0:
            empty = np.zeros((0, W))
            return _Layers(empty.astype(np.int64), empty, empty, empty, empty.astype(bool))
        idx = np.repeat(np.arange(len(sel)), count)
        col = lo[idx] + np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        dc = d[col]
        ei, wi = e[idx], q0[idx]
        denom = dc[:, 0] * ei[:, 1] - dc[:, 1] * ei[:, 0]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (wi[:, 0] * ei[:, 1] - wi[:, 1] * ei[:, 0]) / denom
            sig = (wi[:, 0] * dc[:, 1] - wi[:, 1] * dc[:, 0]) / denom
        ok = (t > _MIN_T_M) & (sig >= 0.0) & (sig <= 1.0)
        idx, col, t, sig = idx[ok], col[ok], t[ok], sig[ok]
        vt = cam.cy - cam.f * (faces['height'][sel][idx] - hc) / t
        order = np.lexsort((t, col))
        idx, col, t, sig, vt = idx[order], col[order], t[order], sig[order], vt[order]
        # segmented running minimum of the tops along each column (columns in order)
        n = len(col)
        start = np.ones(n, bool)
        start[1:] = col[1:] != col[:-1]
        big = 4.0 * (1e6 + abs(cam.cy) + cam.height)
        key = np.maximum(vt, -1e6) - col * big
        prev = np.empty(n)
        prev[0] = np.inf
        prev[1:] = np.minimum.accumulate(key)[:-1]
        prev[start] = np.inf
        vis = key < prev
        first = np.maximum.accumulate(np.where(start, np.arange(n), 0))
        cs = np.cumsum(vis)
        rank = cs - 1 - (cs[first] - vis[first])
        keep = vis & (rank < self.MAX_LAYERS)
        K = int(rank[keep].max()) + 1 if keep.any() else 0
        lay = _Layers(np.zeros((K, W), np.int64), np.zeros((K, W)), np.zeros((K, W)),
                      np.full((K, W), -np.inf), np.zeros((K, W), bool))
        r, c = rank[keep], col[keep]
        lay.face[r, c] = sel[idx[keep]]
        lay.t[r, c] = t[keep]
        lay.sigma[r, c] = sig[keep]
        lay.vtop[r, c] = vt[keep]
        lay.ok[r, c] = True
        for k in range(1, K):  # nothing behind a wall whose top is above the image
            lay.ok[k] &= lay.ok[k - 1] & (lay.vtop[k - 1] > 0.0)
            lay.vtop[k][~lay.ok[k]] = -np.inf
        return lay

    def _view(self, cam: _Camera, cxz: np.ndarray, yaw: float, hc: float,
              faces: dict[str, np.ndarray], shade: bool, geometry: bool
              ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Render one level view: grey image (float32), depth (m) and static mask if asked."""
        H, W = cam.height, cam.width
        fwd = np.array([math.sin(yaw), math.cos(yaw)])
        right = np.array([math.cos(yaw), -math.sin(yaw)])
        d = fwd[None, :] + cam.xn[:, None] * right[None, :]  # (W, 2) rays with z_cam = 1
        sel = self._cull(faces, cxz, fwd, right, cam)
        lay = self._layers(faces, sel, cxz, fwd, right, d, hc, cam)
        v_h = min(H, max(0, int(math.floor(cam.cy)) + 1))  # first row below the horizon
        img = np.empty((H, W), np.float32) if shade else None
        if shade:
            self._sky(img[:v_h], cam, yaw)
            self._ground(img[v_h:], cam, v_h, cxz, d, yaw, hc)
        rows = np.arange(v_h, H)
        z_ground = (cam.f * hc / (rows - cam.cy)).astype(np.float32)
        depth = static = None
        if geometry:
            depth = np.full((H, W), np.inf, np.float32)
            depth[v_h:] = z_ground[:, None]
            static = np.ones((H, W), bool)
        n_lay = len(lay.t)
        if n_lay == 0:
            return img, depth, static
        vbot0 = np.where(lay.ok[0], cam.cy + cam.f * hc / np.where(lay.ok[0], lay.t[0], 1.0),
                         cam.cy)
        top = lay.vtop[lay.ok]
        r0 = max(0, int(math.floor(top.min())) if top.size else H)
        r1 = min(H, int(math.ceil(vbot0.max())) + 1)
        if r0 >= r1:
            return img, depth, static
        v = np.arange(r0, r1, dtype=np.float32)[:, None]
        level = np.zeros((r1 - r0, W), np.int8)
        for k in range(n_lay):
            level += v < lay.vtop[k][None, :].astype(np.float32)
        n_ok = lay.ok.sum(0).astype(np.int8)
        wall = (level < n_ok[None, :]) & ~(v > vbot0[None, :].astype(np.float32))
        flat = level.astype(np.int32) * W + np.arange(W, dtype=np.int32)[None, :]
        tabs = self._tables(lay, faces, cam, hc, d, shade)
        if shade:
            map_x = np.take(tabs['ax'], flat)
            map_y = np.take(tabs['ay0'], flat) + np.take(tabs['ay1'], flat) * v
            walls = cv2.remap(self.scene.atlas.atlas, map_x, map_y, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT).astype(np.float32)
            walls *= np.take(tabs['gain'], flat)
            np.copyto(img[r0:r1], walls, where=wall)
        if geometry:
            np.copyto(depth[r0:r1], np.take(tabs['t'], flat), where=wall)
            static[r0:r1] = ~(wall & np.take(tabs['moving'], flat))
        return img, depth, static

    def _tables(self, lay: _Layers, faces: dict[str, np.ndarray], cam: _Camera, hc: float,
                d: np.ndarray, shade: bool) -> dict[str, np.ndarray]:
        """Per-layer, per-column lookup tables (K + 1, W) flattened; the last row is unused."""
        K, W = lay.t.shape
        pad = np.zeros((1, W))
        tabs = {'t': np.concatenate([lay.t, pad]).astype(np.float32).ravel(),
                'moving': np.concatenate([faces['moving'][lay.face] & lay.ok,
                                          pad.astype(bool)]).ravel()}
        if not shade:
            return tabs
        atlas = self.scene.atlas
        face = lay.face
        t = np.where(lay.ok, lay.t, 1.0)
        n = faces['n'][face]  # (K, W, 2)
        cos_inc = np.abs(n[..., 0] * d[None, :, 0] + n[..., 1] * d[None, :, 1])
        foot_h = t / (cam.f * np.maximum(cos_inc, 1e-3))
        foot_v = t / cam.f
        tau = atlas.texel
        lx = np.clip(np.rint(np.log2(np.maximum(foot_h / tau, 1e-9))), 0, atlas.max_x).astype(int)
        ly = np.clip(np.rint(np.log2(np.maximum(foot_v / tau, 1e-9))), 0, atlas.max_y).astype(int)
        tex = faces['tex'][face]
        s_m = np.mod(faces['s_off'][face] + lay.sigma * faces['length'][face], _WALL_W_M)
        sx, sy = 0.5 ** lx, 0.5 ** ly
        ax = atlas.x0[tex, lx] + s_m / tau * sx - 0.5
        ay1 = t / (cam.f * tau) * sy
        ay0 = atlas.y0[ly] - 0.5 + (_WALL_H_M - hc) / tau * sy - ay1 * cam.cy
        gain = faces['gain'][face]
        for name, val in (('ax', ax), ('ay0', ay0), ('ay1', ay1), ('gain', gain)):
            tabs[name] = np.concatenate([np.where(lay.ok, val, 0.0), pad]).astype(
                np.float32).ravel()
        return tabs

    def _ground(self, out: np.ndarray, cam: _Camera, v_h: int, cxz: np.ndarray, d: np.ndarray,
                yaw: float, hc: float) -> None:
        """Fill rows v_h.. (below the horizon) with the rip-mapped road texture."""
        if out.shape[0] == 0:
            return
        scene = self.scene
        rip = scene.ground
        rows = np.arange(v_h, cam.height)
        z = cam.f * hc / (rows - cam.cy)
        lateral = z / cam.f
        along = z * z / (cam.f * hc)
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        foot_x = np.hypot(lateral * c, along * s)
        foot_z = np.hypot(lateral * s, along * c)
        lx = np.clip(np.rint(np.log2(foot_x / rip.texel_x)), 0, rip.max_x).astype(int)
        lz = np.clip(np.rint(np.log2(foot_z / rip.texel_y)), 0, rip.max_y).astype(int)
        key = lx * 64 + lz
        cuts = np.flatnonzero(np.diff(key)) + 1
        starts = np.concatenate([[0], cuts])
        ends = np.concatenate([cuts, [len(rows)]])
        px, pz = scene.ground_period
        ox = (cxz[0] - scene.ground_origin[0]) % px
        oz = (cxz[1] - scene.ground_origin[1]) % pz
        zf = z.astype(np.float32)[:, None]
        for a, b in zip(starts, ends):
            tex = rip.level(int(lx[a]), int(lz[a]))
            sx = rip.texel_x * 2 ** int(lx[a])
            sz = rip.texel_y * 2 ** int(lz[a])
            zz = zf[a:b]
            mx = np.mod(np.float32(ox / sx) + zz * (d[:, 0] / sx).astype(np.float32),
                        np.float32(tex.shape[1])) - np.float32(0.5)
            my = np.mod(np.float32(oz / sz) + zz * (d[:, 1] / sz).astype(np.float32),
                        np.float32(tex.shape[0])) - np.float32(0.5)
            out[a:b] = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def _sky(self, out: np.ndarray, cam: _Camera, yaw: float) -> None:
        """Fill rows 0..horizon with a bright gradient and faint clouds at infinity."""
        if out.shape[0] == 0:
            return
        rows = np.arange(out.shape[0], dtype=np.float64)
        norm = np.sqrt(1.0 + cam.xn ** 2)
        tan_el = ((cam.cy - rows) / cam.f)[:, None] / norm[None, :]
        tan_el = np.clip(tan_el, 0.0, 2.0).astype(np.float32)
        sky = self.scene.sky
        az = (yaw + np.arctan(cam.xn)) / (2 * np.pi) * sky.shape[1]
        map_x = np.broadcast_to(az.astype(np.float32)[None, :], out.shape)
        map_y = tan_el * np.float32(sky.shape[0] / 1.2)
        clouds = cv2.remap(sky, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        ramp = np.minimum(tan_el * 8.0, 1.0)
        np.copyto(out, 228.0 - 55.0 * np.minimum(tan_el / 0.8, 1.0) ** 0.8 + clouds * ramp)


def render_sequence(spec: SequenceSpec) -> Iterator[RenderedFrame]:
    """Yield the rendered pairs of a spec in order."""
    yield from StereoRenderer(spec)


class SyntheticSequence:
    """
    A rendered sequence seen as a dataset: StereoFrames, calibration and ground truth.

    Attributes
    ----------
    renderer : StereoRenderer
        The renderer behind it.

    """

    def __init__(self, spec: SequenceSpec) -> None:
        self.renderer = StereoRenderer(spec)

    @property
    def calibration(self) -> StereoCalibration:
        """Rectified calibration of every pair."""
        return self.renderer.calibration

    @property
    def stamps(self) -> np.ndarray:
        """Frame stamps: (N,) float64, seconds."""
        return self.renderer.stamps.copy()

    @property
    def ground_truth(self) -> np.ndarray:
        """(N, 4, 4) float64 ``T_world_cam`` of the left camera (metres)."""
        return self.renderer.poses.copy()

    def __len__(self) -> int:
        return len(self.renderer)

    def __iter__(self) -> Iterator[StereoFrame]:
        return self.renderer.frames()
