"""
The sections of the configuration: one dataclass per component of the pipeline.

Every field is declared with ``_f``, which puts its documentation, unit, valid range, choices and
run-time mutability in the dataclass field metadata. That metadata is the schema: ``Config`` in
``config.py`` gathers these sections, validates values against it and writes the commented
``config/stereo_vo.yaml`` from it, and the ROS node builds its parameter descriptors from it.
Import the sections from ``stereo_vo_ros.config``, which re-exports them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .allocator import MAX_LIMIT_MB


def _f(default: Any, doc: str, lo: float | None = None, hi: float | None = None,
       choices: tuple[str, ...] | None = None, dynamic: bool = False) -> Any:
    """Declare a config field with its documentation, range and run-time mutability."""
    meta = {'doc': doc, 'lo': lo, 'hi': hi, 'choices': choices, 'dynamic': dynamic}
    if isinstance(default, (list, tuple)):
        value = list(default)
        return field(default_factory=lambda: list(value), metadata=meta)
    return field(default=default, metadata=meta)


TRACKER_VARIANTS = ('baseline', 'dc', 'bc', 'db', 'full')


@dataclass
class TrackerConfig:
    """KLT tracking with the checks of the light and adaptive feature tracking (Huang et al.)."""

    max_features: int = _f(
        200, 'Maximum number of tracked features (Huang et al. use 200).', 8, 5000)
    min_distance_px: float = _f(
        15.0, 'Minimum distance between detected corners (pixels).', 1.0, 200.0)
    quality_level: float = _f(
        0.01, 'Shi-Tomasi quality level relative to the best corner.', 1e-4, 1.0)
    block_size: int = _f(7, 'Shi-Tomasi block size (pixels).', 3, 31)
    win_size_px: int = _f(
        13, 'KLT window side (pixels, odd). Smaller than the usual 21: where the view deforms '
        'fast (the near road at speed) a small window follows it better.', 5, 61)
    pyramid_levels: int = _f(
        3, 'KLT pyramid levels above the base image when no prediction is available.', 0, 8)
    predicted_pyramid_levels: int = _f(
        1, 'KLT pyramid levels of the temporal pass when the motion prior gives an initial '
        "flow, and of the bi-circular check's pass.", 0, 8)
    stereo_pyramid_levels: int = _f(
        1, 'KLT pyramid levels of the stereo passes that start from a disparity: the tracked '
        "features' (the predicted or last disparity) and the new corners' near a tracked "
        'feature (its disparity).', 0, 8)
    use_motion_prior: bool = _f(
        True, 'Predict feature positions from the constant-velocity prior (initial flow).')
    max_iterations: int = _f(30, 'KLT iterations per pyramid level.', 1, 200)
    min_eigen_ratio: float = _f(
        0.03, 'Aperture check: drop a feature (at detection and before every temporal pass) '
        "whose KLT window's gradient matrix has a smaller/larger eigenvalue ratio below this: "
        'along a straight edge (the horizon, a lane line) KLT cannot measure the motion. '
        '0 disables.', 0.0, 1.0, dynamic=True)
    min_flow_edge_ratio: float = _f(
        0.1, 'Flow-aligned aperture check at detection (not in the paper): a corner whose KLT '
        'window has less gradient energy along the flow predicted by the motion prior than this '
        'fraction of that across it is not taken (the next corner of its bucket is): lane '
        'lines seen at speed slide along themselves. Needs the prior; 0 disables.',
        0.0, 10.0, dynamic=True)
    min_flow_edge_ratio_tracked: float = _f(
        0.05, 'The same check before every temporal pass of a tracked feature, along its '
        'predicted flow and over the affine refinement window (affine_win_size_px): a feature '
        'detected as a corner can become a piece of lane line as it nears. 0 disables.',
        0.0, 10.0, dynamic=True)
    affine_refinement: bool = _f(
        True, 'Refine every KLT match that passed its checks (temporal and stereo) with an '
        'affine window model (not in the paper): a translation-only window is biased where the '
        'view deforms (walls growing as the car approaches, the sheared road between left and '
        'right).', dynamic=True)
    affine_win_size_px: int = _f(
        21, 'Window side of the affine refinement of the temporal matches (pixels, odd).', 5, 61,
        dynamic=True)
    affine_stereo_win_size_px: int = _f(
        15, 'Window side of the affine refinement of the stereo matches (pixels, odd). Smaller '
        'than the temporal one, so that a nearer surface in the window (a barrier, a vehicle) '
        'biases the disparity less.', 5, 61, dynamic=True)
    affine_sigma_px: float = _f(
        5.0, 'The temporal refinement weights its samples by a Gaussian of their distance to the '
        "window's centre with this std (pixels; 0: all alike). A window across an object's "
        'border holds two surfaces that move differently, and the match follows both; weighted '
        'to its centre it follows the feature. Rendered, seeds 0-47 / 0-15, 150 frames, mean '
        't_rel all alike / 5 px: highway 0.375 / 0.306 % (28 of 45 scenes better), highway_rig '
        '0.703 / 0.666 %, urban_rig 0.154 / 0.140 %, urban 0.076 / 0.062 %, urban_photometric '
        '0.063 / 0.066 %; end drift over 12 RANSAC seeds kitti06 1.24 / 1.09 %, kitti01 1.45 / '
        '1.21 %.', 0.0, 100.0, dynamic=True)
    affine_stereo_sigma_px: float = _f(
        0.0, 'The same for the stereo refinement window (pixels; 0: all alike). At a nearer '
        "surface's border the stereo match is pulled towards its disparity (far points with a "
        'disparity that varies by 0.5-2 px over the window read +0.05 px on the rendered '
        'highway); 3 px cuts that to +0.01 px but leaves the matches noisier: highway (seeds '
        '0-23) 0.338 -> 0.396 %, highway_rig (0-15) 0.703 -> 0.891 % (the temporal weighting '
        'off).', 0.0, 100.0, dynamic=True)
    affine_step_px: int = _f(
        2, 'The affine refinement uses every n-th pixel of its window in both directions (1: '
        'all; 2 halves its cost).',
        1, 10, dynamic=True)
    affine_iterations: int = _f(
        3, 'Gauss-Newton steps of the affine refinement.', 1, 50, dynamic=True)
    replenish_after: str = _f(
        'temporal', 'When the replenishment (detection and stereo matching of new corners, not '
        'in the paper) starts. all: after every check, from the features that passed them. '
        'stereo: after the stereo checks (eq. 5, 6); temporal: after the forward-backward '
        'check (eq. 4). The earlier, the more of the tracking a worker (pipeline.threads >= 2) '
        'overlaps; new corners then keep away from, and count in their bucket, features a '
        'later check may still remove (as many corners as the later checks removed in the last '
        'pair are asked for on top, the surplus dropped). Results do not depend on the thread '
        'count; all gives the results of the pipeline before it had a worker.',
        choices=('all', 'stereo', 'temporal'), dynamic=True)
    photometric_compensation: bool = _f(
        True, 'Before every KLT pass, map the second image to the brightness of the first with '
        'one gain and offset (not in the paper; see photometric.py), fitted to the windows '
        'around the features (predicted positions) or, without them, to the grey-level '
        'histograms: KLT compares squared differences, so independent exposure changes of the '
        'cameras break it. A map that moves no grey level of 16-240 by 8 or more is not '
        'applied.', dynamic=True)
    variant: str = _f(
        'full', 'Which checks run: baseline (forward-backward + left-right, VINS-Fusion), '
        'dc (+disparity constraint), bc (+bi-circular check), db (dc+bc, fixed threshold), '
        'full (dc+bc with adaptive threshold).', choices=TRACKER_VARIANTS)
    bicircular_mode: str = _f(
        'closure', 'Reading of eq. 7 of Huang et al.: closure compares right(t2)->right(t1) '
        'with the stored right(t1) point (one KLT pass); roundtrip tracks '
        'right(t2)->right(t1)->right(t2) (two).',
        choices=('roundtrip', 'closure'))
    fb_threshold_px: float = _f(
        0.5, 'Forward-backward check threshold delta1 (pixels).', 0.01, 50.0, dynamic=True)
    lr_threshold_px: float = _f(
        0.5, 'Left-right check threshold delta2 (pixels).', 0.01, 50.0, dynamic=True)
    disparity_y_threshold_px: float = _f(
        2.0, 'Disparity constraint delta3: |y_left - y_right| (pixels); for raw input the '
        'distance to the epipolar line.', 0.01, 50.0, dynamic=True)
    min_disparity_px: float = _f(
        0.0, 'Smallest accepted disparity x_left - x_right (pixels).', -10.0, 1000.0,
        dynamic=True)
    max_disparity_px: float = _f(
        300.0, 'Largest accepted disparity (pixels).', 1.0, 5000.0, dynamic=True)
    bc_threshold_px: float = _f(
        5.0, 'Fixed bi-circular threshold delta_d for variants bc and db (pixels).',
        0.01, 100.0, dynamic=True)
    adaptive_rho: float = _f(
        0.23, 'rho of the adaptive threshold delta_d = rho*loss/maxtrack + epsilon.',
        0.0, 100.0, dynamic=True)
    adaptive_epsilon_px: float = _f(
        5.0, 'epsilon of the adaptive threshold (pixels).', 0.0, 100.0, dynamic=True)


@dataclass
class BucketingConfig:
    """Bucketing (Kitt et al., section III-C): region of interest and a grid of buckets."""

    enabled: bool = _f(True, 'Select features with the bucketing grid.', dynamic=True)
    roi_margin_px: int = _f(
        10, 'Border excluded from the region of interest on every side (pixels).', 0, 500)
    cols: int = _f(12, 'Bucket grid columns.', 1, 200)
    rows: int = _f(4, 'Bucket grid rows.', 1, 200)
    max_per_bucket: int = _f(6, 'Maximum features kept per bucket.', 1, 1000, dynamic=True)


@dataclass
class FilterConfig:
    """Kalman filter on the egomotion state (V_X, V_Y, V_Z, w_X, w_Y, w_Z) (Kitt et al., III-E)."""

    type: str = _f('ispkf', 'Filter: ispkf, iekf, ukf or ekf.',  # noqa: A003
                   choices=('ispkf', 'iekf', 'ukf', 'ekf'))
    pixel_noise_px: float = _f(
        1.0, 'Measurement noise standard deviation (pixels).', 1e-3, 100.0, dynamic=True)
    propagate_previous_noise: bool = _f(
        True, 'Add the pixel noise of the previous pair, propagated through the transfer, to '
        'each measurement variance (R stays diagonal) and widen the RANSAC gate accordingly.')
    epipolar_correction: bool = _f(
        True, 'Move each stereo match (previous and current pair) to the nearest pair on '
        'corresponding epipolar lines (Hartley-Sturm, cv2.correctMatches) before the update: '
        'the transfer assumes it, and a vertical stereo offset otherwise biases the rotation.')
    robust_loss: str = _f(
        'cauchy', 'Loss of the final update on the RANSAC inliers (on all correspondences '
        'with RANSAC off; not in Kitt et al.): cauchy reweights each by 1 / (1 + (e / c)^2), e '
        'its reprojection error (pixels) under the latest estimate, and updates again from the '
        'prior; none is the plain Gaussian update of the paper.',
        choices=('none', 'cauchy'), dynamic=True)
    robust_scale_sigmas: float = _f(
        1.0, 'Cauchy scale c in residual sigmas (sigma from the median inlier error, as the '
        'adaptive inlier threshold).', 0.1, 100.0, dynamic=True)
    robust_rounds: int = _f(
        2, 'Reweighted updates after the first (each an ISPKF update started from the last '
        'linearisation of the one before, about 0.2 ms at 200 features).', 1, 20,
        dynamic=True)
    velocity_process_noise: float = _f(
        2.0, 'Process noise std of linear velocity per frame (m/s); with '
        'vehicle.acceleration_std set, that acceleration times the time between the pairs '
        'instead.', 1e-6, 1e3, dynamic=True)
    angular_process_noise_deg: float = _f(
        10.0, 'Process noise std of angular velocity per frame (deg/s).', 1e-6, 1e4,
        dynamic=True)
    initial_velocity_std: float = _f(
        10.0, 'Prior std of linear velocity at start and after loss (m/s).', 1e-3, 1e4)
    initial_angular_std_deg: float = _f(
        30.0, 'Prior std of angular velocity at start and after loss (deg/s).', 1e-3, 1e5)
    max_iterations: int = _f(
        20, 'Maximum iterations of the iterated filters (ISPKF, IEKF).', 1, 100000)
    threshold_velocity: float = _f(
        1e-3, 'Termination: every linear velocity changes less than this (m/s).', 1e-12, 10.0)
    threshold_angular_deg: float = _f(
        1e-3, 'Termination: every angular velocity changes less than this (deg/s).',
        1e-12, 100.0)
    ispkf_spread: str = _f(
        'posterior', 'ISPKF sigma-point spread: posterior (covariance of the latest iterate) or '
        'prior (prior covariance at every iteration).', choices=('posterior', 'prior'))
    sigma_alpha: float = _f(1.0, 'Sigma-point spread alpha.', 1e-4, 10.0)
    sigma_beta: float = _f(2.0, 'Sigma-point beta (2 is optimal for Gaussians).', 0.0, 10.0)
    sigma_kappa: float = _f(0.0, 'Sigma-point kappa.', -5.0, 100.0)


@dataclass
class RansacConfig:
    """RANSAC outlier rejection (Kitt et al., section III-D, eq. 14)."""

    enabled: bool = _f(True, 'Reject outliers with RANSAC before the final update.', dynamic=True)
    probability: float = _f(
        0.99, 'p: probability that at least one sample is outlier-free.', 0.5, 0.999999)
    outlier_ratio: float = _f(
        0.5, 'epsilon: assumed outlier ratio used in eq. 14.', 0.0, 0.95)
    max_hypotheses: int = _f(300, 'Upper bound on the number of samples.', 1, 100000)
    startup_outlier_ratio: float = _f(
        0.8, 'epsilon of eq. 14 for the first estimate after a reset of the velocity (the '
        'first pair, a loss, a gap; not in the papers): 0.8 asks for 573 samples '
        '(max_hypotheses caps them) where 0.5 asks for 35, so that with no motion to start '
        'from a vehicle filling part of the view does not win. Only that pair pays for it.',
        0.0, 0.95, dynamic=True)
    inlier_threshold_px: float = _f(
        2.0, 'Inlier if the Euclidean reprojection error in both current images is below this '
        '(pixels).', 0.05, 100.0, dynamic=True)
    adaptive_threshold: bool = _f(
        True, 'Tighten the inlier threshold of the final update to the residual scale of the '
        'best hypothesis: adaptive_sigmas times sigma, sigma from the median inlier error '
        '(2-D Gaussian errors), between min_inlier_threshold_px and inlier_threshold_px.',
        dynamic=True)
    adaptive_sigmas: float = _f(
        3.0, 'Adaptive inlier threshold in sigmas of the residual (3: 98.9 % of 2-D Gaussian '
        'errors fall inside).', 1.0, 100.0, dynamic=True)
    min_inlier_threshold_px: float = _f(
        0.5, 'Lower bound of the adaptive inlier threshold (pixels).', 0.05, 100.0,
        dynamic=True)
    hypothesis_iterations: int = _f(
        3, 'Filter iterations per hypothesis on its minimal sample.', 1, 100)
    seed: int = _f(0, 'Seed of the random sampler (deterministic runs).', 0, 2**31 - 1)
    ground_weight: float = _f(
        4.0, 'Weight of an inlier on the ground plane in the RANSAC inlier count (1: a plain '
        'count, as in Kitt et al.). The road does not move; a vehicle ahead that keeps the '
        "camera's speed looks static and can otherwise outvote the true motion.", 1.0, 100.0,
        dynamic=True)
    ground_tolerance_m: float = _f(
        0.15, 'A point within this distance of the fitted ground plane is on the ground (m).',
        0.01, 2.0, dynamic=True)
    ground_max_tilt_deg: float = _f(
        15.0, "Largest angle between the ground plane's normal and the camera's y axis (down) "
        '(deg): the plane is searched for a forward-looking camera.', 0.0, 90.0, dynamic=True)
    ground_max_height_m: float = _f(
        4.0, 'Largest height of the camera above the ground plane (m).', 0.2, 100.0,
        dynamic=True)
    max_outlier_streak: int = _f(
        3, 'With RANSAC on, leave a feature out of RANSAC and the update once it has been a '
        'clear outlier '
        '(error above twice the inlier threshold) of the accepted motion in this many '
        'consecutive frames; it comes back when it fits again (0: never leave out). Keeps '
        'features on moving vehicles out.', 0, 1000, dynamic=True)


@dataclass
class PipelineConfig:
    """Images-to-odometry pipeline: gating, loss handling and covariance."""

    input_kind: str = _f(
        'rectified', 'Input images: rectified (CameraInfo P describes them) or raw (K, D and R '
        'describe them; tracked points are undistorted, images are not rectified).',
        choices=('rectified', 'raw'))
    min_features: int = _f(
        12, 'Fewer stereo correspondences than this: the frame is degenerate.', 3, 10000)
    min_inliers: int = _f(
        8, 'Fewer RANSAC inliers than this: too few inliers.', 3, 10000, dynamic=True)
    max_lost_time_s: float = _f(
        1.0, 'Coast on the constant-velocity prediction for at most this long when tracking is '
        'lost (s); then the velocity is zeroed and the state is LOST.', 0.0, 60.0)
    lost_covariance_inflation: float = _f(
        10.0, 'Factor on the velocity covariance for every coasted frame.', 1.0, 1e6)
    max_gap_s: float = _f(
        1.0, 'A larger time step than this re-initialises the velocity (s).', 0.0, 3600.0)
    max_speed: float = _f(
        60.0, 'A linear speed above this is rejected as implausible (m/s).', 0.1, 1000.0,
        dynamic=True)
    prior_max_velocity_std: float = _f(
        8.0, 'Track without the motion prior (from the previous positions, with '
        'tracker.pyramid_levels) while the std of the linear velocity exceeds this (m/s): at '
        'the start and after a long loss the prior predicts no motion, and fast features would '
        'be lost. One coasted frame (std about 6.5 m/s at the defaults) keeps the prior.',
        0.0, 1000.0, dynamic=True)
    road_speed_search: bool = _f(
        True, 'While the velocity is unknown, align the road of the previous and current left '
        'images over forward speeds from -10 m/s to max_speed in 1 m/s steps (ground plane of '
        'the previous features; rectified input) and track with the best speed as the motion '
        'prior when it is a clear minimum (not in the papers): without it the near road of a '
        'fast start is lost, and vehicles keeping pace can decide the first estimate.',
        dynamic=True)
    threads: int = _f(
        0, 'Cores per stereo pair, the calling thread included. With 2 or more the '
        'replenishment of features (detection and stereo matching of new corners) runs on '
        'the worker (see worker) while the motion is estimated, the aperture checks of the '
        'tracked features and the brightness maps of later passes run on a helper thread '
        'next to the temporal KLT passes, and OpenCV may spread '
        "its own calls over threads - 1 threads (OpenCV's thread count is per process). Results "
        'do not depend on the number. 0: the CPUs the process may use (its CPU affinity, '
        "e.g. taskset or a container's cpuset, capped by a control-group CPU limit such as "
        "a container's --cpus, rounded), 1 to 4.", 0, 64)
    worker: str = _f(
        'process', 'Where the replenishment runs with threads >= 2. process: a worker process '
        '(Linux; a thread elsewhere), which overlaps the motion estimate for real; thread: a '
        'background thread, which shares the interpreter lock with the estimate and overlaps '
        'little.', choices=('process', 'thread'))
    keep_freed_memory_mb: int = _f(
        32, 'glibc (Linux) only, process-wide: serve allocations below this size from the heap '
        'and keep up to this much freed memory in the process instead of returning it to the '
        'system (mallopt M_MMAP_THRESHOLD and M_TRIM_THRESHOLD, in the caller and the worker '
        "process). With glibc's defaults, depending on what the process freed before, the "
        'heap can grow by about 4 MB within a 1241x376 pair and be trimmed at its end, and the '
        'next pair faults those pages in again (kitti01: up to about 800 page faults, 1.3 ms of '
        'kernel time per pair). Every library and node in the process allocates under it, and '
        "each of glibc's per-thread arenas may keep this much free. Not applied where the "
        "environment sets glibc's malloc thresholds (MALLOC_*_, GLIBC_TUNABLES). 0: leave the "
        'allocator alone (a value set before stays for the life of the process).', 0,
        MAX_LIMIT_MB)


@dataclass
class RoadConfig:
    """Direct alignment of the road plane, fused with the feature estimate (not in the papers)."""

    enabled: bool = _f(
        False, 'Align the road pixels of the previous and the current left image over the '
        'motion (plane of the previous pair refined by aligning its left and right images) '
        'and fuse the result with the filter estimate (rectified input; skipped without an '
        'admissible road plane or when the two disagree beyond gate_chi2). Measures the '
        'forward speed on fast roads, where road features track worst; off by default for '
        'its cost, about 4 ms per 1241x376 pair (docs/tuning.md).',
        dynamic=True)
    motion: str = _f(
        'forward', 'What the road measures. forward: the forward speed (the alignment refines '
        "the forward and vertical translation and the pitch; the rest stays the features'); "
        'longitudinal: all three of those; full: all six.',
        choices=('forward', 'longitudinal', 'full'),
        dynamic=True)
    levels: int = _f(
        2, 'Image pyramid levels, coarse to fine (1: the input size only).', 1, 5, dynamic=True)
    first_level: int = _f(
        0, 'Finest pyramid level aligned (0: the input size; 1: half of it, about half the '
        'time and less accurate).', 0, 4, dynamic=True)
    pixel_step: int = _f(
        5, 'Every n-th pixel of the road in both directions is compared (pixels of each '
        'pyramid level).', 1, 64, dynamic=True)
    blur_px: float = _f(
        1.0, 'Gaussian blur of every pyramid level before the alignment (its pixels).', 0.0,
        10.0, dynamic=True)
    min_depth_m: float = _f(
        4.0, 'Road nearer than this is not compared (m).', 0.5, 100.0, dynamic=True)
    max_depth_m: float = _f(
        35.0, 'Road farther than this is not compared (m).', 1.0, 500.0, dynamic=True)
    max_lateral_m: float = _f(
        6.0, 'Road farther than this to either side of the optical axis is not compared (m): '
        'parked cars, kerbs and pavements stay out.', 0.5, 100.0, dynamic=True)
    min_pixels: int = _f(
        1500, 'Fewest road pixels an alignment needs at the input size (a quarter of it at the '
        'next pyramid level, and so on; scaled the same way from first_level).', 10, 10000000,
        dynamic=True)
    stereo_iterations: int = _f(
        1, 'Gauss-Newton iterations of the plane (left-right) on each pyramid level; the plane '
        'is refined again at every pair, starting from the last one.', 1, 100, dynamic=True)
    coarse_iterations: int = _f(
        5, 'Gauss-Newton iterations of the motion (previous-current) on each pyramid level '
        'above the finest.', 1, 100, dynamic=True)
    motion_iterations: int = _f(
        3, 'Gauss-Newton iterations of the motion (previous-current) on the finest level '
        '(first_level).', 1, 100, dynamic=True)
    covariance_inflation: float = _f(
        16.0, 'Factor on the covariance of the aligned motion (neighbouring pixels are not '
        'independent).', 1.0, 1e6, dynamic=True)
    gate_chi2: float = _f(
        10.8, 'Fuse only when the squared Mahalanobis distance between the road motion and the '
        'feature estimate, over the measured components, is below this (10.8: the 99.9 % point '
        'for one component, the forward speed; 16.3 for three, 22.5 for six).', 0.0, 1e9,
        dynamic=True)


@dataclass
class VehicleConfig:
    """Motion prior of a wheeled vehicle, fused after every estimate (not in the papers)."""

    nonholonomic: bool = _f(
        False, 'Fuse the motion of a vehicle that rolls along its heading: the camera looks '
        'forward along the vehicle, which does not slide sideways, so the lateral speed of '
        'the camera follows from its yaw rate (vehicle_motion.py). From a few pixels the '
        'features hardly tell a small yaw from a small lateral motion; this ties the two. '
        'Off by default: wrong for drones, hand-held and legged platforms, and for a camera '
        'that does not look along the direction of travel.', dynamic=True)
    lever_arm_m: float = _f(
        0.0, 'How far the left camera sits ahead of the point the vehicle turns about (for a '
        'car, the middle of the rear axle), along the vehicle (m).', -20.0, 20.0, dynamic=True)
    lateral_speed_std: float = _f(
        0.05, 'Standard deviation of the lateral speed that the prior allows: side slip, '
        'mounting errors (m/s).', 1e-4, 10.0, dynamic=True)
    gate_chi2: float = _f(
        10.8, 'Fuse only when the squared Mahalanobis distance of the estimate from the prior '
        'is below this (10.8: the 99.9 % point for one component); a vehicle that does slide '
        'keeps its estimate.', 0.0, 1e9, dynamic=True)
    acceleration_std: float = _f(
        0.0, "Standard deviation of a road vehicle's acceleration along each camera axis "
        '(m/s^2; 0: off). With it, the process noise std of the linear velocity from one pair '
        'to the next is this times the time between them, in place of '
        'filter.velocity_process_noise per frame: a car brakes at up to about 1 g (two '
        'standard deviations at 5 m/s^2), so a few features on vehicles that keep pace cannot '
        'take half its speed within a tenth of a second. Off by default: drones and hand-held '
        'cameras accelerate faster.', 0.0, 1e3, dynamic=True)


@dataclass
class RigConfig:
    """Online refinement of the stereo rig: the right camera's error (rig_calibration.py)."""

    enabled: bool = _f(
        True, "Estimate the right camera's residual rotation, focal ratio and disparity offset "
        'against the calibration while running (a slow Kalman filter fed by a small bundle '
        'adjustment of every pair) and correct the right measurements by it. The absolute '
        'baseline and the common focal length (metric scale) are not observable and not '
        'estimated.', dynamic=True)
    measure_every: int = _f(
        2, 'Measure the rig on every n-th pair with a motion estimate (the others only predict): '
        'a measurement (a small bundle adjustment) costs about 1 ms at 1241x376 with 200 '
        'features on a two-core machine, the correction of every pair (with the row slide of '
        'pinned matches) about 0.3 ms. Every third pair: rendered highway_rig seeds 0-7, 150 '
        'frames, mean t_rel 0.777 -> 0.908 %, urban_rig 0.152 -> 0.175 %.', 1, 1000,
        dynamic=True)
    min_points: int = _f(
        30, 'Fewest inliers of the motion estimate a pair needs to measure the rig.', 8, 10000,
        dynamic=True)
    min_translation_m: float = _f(
        0.03, 'The rig is not measured on pairs that moved less than this (m): standing still '
        'repeats the same stereo matches and tells nothing about the disparity offset (a '
        'robot at 0.3 m/s and 10 Hz still measures).', 0.0, 100.0, dynamic=True)
    iterations: int = _f(
        1, 'Gauss-Newton steps of the per-pair bundle adjustment (points and motion) before its '
        'information on the rig is taken (it starts from the motion estimate and the previous '
        "pair's triangulation; a second step changed nothing on synthetic pairs; 0 linearises "
        'at the start).', 0, 20, dynamic=True)
    update_iterations: int = _f(
        1, "Times a pair's measurement is taken: the first at the correction in use, each next "
        'one at the correction the estimate then applies, fused again from the same prior (an '
        'iterated update: the robust weights are taken at the estimate, not before it). 2 '
        'reaches a rig error of pixels in fewer pairs (KITTI 01 1.15 -> 1.08 %; rendered '
        'highways with its rig error, median t_rel 1.68 -> 1.35 %), but also a bias of the '
        'stereo matches sooner (nearly exact rendered highway rigs 0.48 -> 0.60 %), for about '
        '0.7 ms per pair after the pose.', 1, 5, dynamic=True)
    huber_sigmas: float = _f(
        2.0, 'Huber constant of the bundle adjustment in residual sigmas.', 0.5, 100.0,
        dynamic=True)
    outlier_sigmas: float = _f(
        5.0, 'A point with a residual above this many sigmas is left out of the pair.',
        2.0, 100.0, dynamic=True)
    min_sigma_px: float = _f(
        0.02, 'Floor of the residual scale of a pair (pixels).', 1e-4, 10.0, dynamic=True)
    measurement_inflation: float = _f(
        4.0, "Factor on each pair's measurement covariance: a stereo match is seen by two "
        'consecutive pairs and a feature keeps its tracking bias over its life, so the pairs '
        'are not independent.', 1.0, 1e6, dynamic=True)
    prior_angle_std_deg: float = _f(
        0.05, 'Prior std of the roll and the pitch of the right camera (deg).', 1e-6, 10.0)
    prior_yaw_std_deg: float = _f(
        0.1, 'Prior std of the yaw of the right camera (deg; 0.1 deg is 1.25 px of disparity at '
        '718 px). Besides its share f yaw of the disparity at the principal point '
        '(prior_disparity_offset_std_px), a yaw adds the border term f yaw ((u - cx) / f)^2, '
        'which the prior takes as independent of that share. Both KITTI clips, from two '
        'different calibrations, carry such a term of about -1.8 px ((u - cx) / f)^2 (-0.14 deg; '
        'measured against the ground-truth motion, the same with an independent matcher and at '
        'any flow, so not a tracking bias); with 0.01 deg most kitti01 pairs are gated out. '
        '0.2 deg helps a rig with that much border term and costs the well calibrated rendered '
        'rigs (docs/benchmarks.md).', 1e-6, 10.0)
    prior_focal_ratio_std: float = _f(
        1e-3, 'Prior std of the right focal length relative to the calibrated one.', 1e-9, 0.1)
    prior_disparity_offset_std_px: float = _f(
        0.5, 'Prior std of the disparity at the right principal point (pixels): the principal '
        'point offset and the share f yaw of the yaw together. The border term of the yaw (see '
        'prior_yaw_std_deg) is a priori independent of it, so the offset alone may be as large '
        'as f yaw (both KITTI calibrations: about 2.3 px with -0.2 deg of yaw).', 1e-6, 50.0)
    time_constant_s: float = _f(
        1e6, 'Time constant of the Gauss-Markov process of the rig error (s): the estimate '
        'forgets at this rate, its uncertainty grows back towards the prior. 1e6 s lets the '
        'disparity offset at the principal point drift by about 0.07 px per hour (a random '
        'walk) and remembers a few hundred pairs at 10 Hz.', 1.0, 1e12, dynamic=True)
    apply_probability: float = _f(
        0.99, 'The rows part (roll, pitch, focal ratio) and the disparity part (yaw, offset) of '
        'the estimate correct the measurements once they differ from zero with this '
        'probability (chi-square of the estimate over its covariance), and from then on: on an '
        'exact rig the estimate wanders by its uncertainty, 0.01-0.02 px of disparity after '
        '150 pairs, which cost 0.03 % of t_rel on the rendered city (0.081 -> 0.112 %, seeds '
        '0-7). 0 applies the estimate from the first pair.', 0.0, 0.999999, dynamic=True)
    apply_min_px: float = _f(
        0.1, 'A part of the estimate corrects the measurements only once it moves some pixel '
        'of the image (corners, edge middles, centre) by more than this as well (pixels): the '
        'tracking biases make the estimate drift significantly on exact renders. Rendered, '
        'seeds 0-7, 150 frames, mean t_rel with 0.05 / 0.1 px when this was chosen: clean '
        'highway 0.335 / 0.279 % (rig off 0.281 %), highway_rig 0.777 / 0.887 % (off 1.552 %), '
        'urban_rig 0.152 / 0.152 % (off 0.688 %). On the clean highway the stereo matches of '
        "far points at a nearer surface's border bias the estimate by about 0.05 px, which gets "
        'past both gates on 2 of 22 scenes (docs/benchmarks.md).', 0.0, 10.0, dynamic=True)
    settled_std_px: float = _f(
        0.01, 'The estimate counts as settled (logged once) when the std of the row and of the '
        'disparity offset at the principal point are below this (pixels).', 1e-4, 10.0,
        dynamic=True)


@dataclass
class RosConfig:
    """ROS 2 adapter: frames, topics, synchronisation and outputs."""

    odom_frame: str = _f('odom', 'Odometry frame (REP-105).')
    base_frame: str = _f('base_link', 'Robot body frame (REP-105) used as child frame.')
    camera_frame: str = _f(
        '', 'Left camera optical frame; empty: the header frame_id of the left image.')
    publish_tf: bool = _f(True, 'Broadcast odom -> base_frame on /tf (needs tf2_msgs).')
    invert_tf: bool = _f(False, 'Broadcast base_frame -> odom instead (for another parent).')
    base_from_camera_xyz: list = _f(
        [0.0, 0.0, 0.0], 'Fallback translation of the left camera in the base frame (m) '
        'when TF has no transform.')
    base_from_camera_rpy_deg: list = _f(
        [-90.0, 0.0, -90.0], 'Fallback rotation base <- camera as roll, pitch, yaw (deg); the '
        'default is the standard optical-to-body rotation (z forward -> x forward).')
    qos: str = _f(
        'auto', 'Reliability of the image subscriptions: auto (reliable when every publisher of '
        'the image topics offers reliable, best effort otherwise; re-checked every second), '
        'sensor_data (best effort) or reliable.', choices=('auto', 'sensor_data', 'reliable'))
    image_transport: str = _f(
        'raw', 'Image input: raw (sensor_msgs/Image) or compressed (sensor_msgs/CompressedImage '
        'on <image topic>/compressed, jpeg or png).', choices=('raw', 'compressed'))
    sync: str = _f('approximate', 'Stereo pairing: exact or approximate stamps.',
                   choices=('exact', 'approximate'))
    sync_slop_s: float = _f(0.005, 'Largest stamp difference of an approximate pair (s).',
                            0.0, 1.0)
    path_max_length: int = _f(5000, 'Poses kept in the published path.', 1, 1000000,
                              dynamic=True)
    publish_debug_image: bool = _f(True, 'Offer the debug image (drawn only when subscribed).')
    left_image_topic: str = _f('/left/image_rect', 'Left image topic read from bags.')
    right_image_topic: str = _f('/right/image_rect', 'Right image topic read from bags.')
    left_info_topic: str = _f('/left/camera_info', 'Left camera_info topic read from bags.')
    right_info_topic: str = _f('/right/camera_info', 'Right camera_info topic read from bags.')
