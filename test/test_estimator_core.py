"""Kitt et al. core: trifocal transfer, Euler convention, filters, RANSAC, calibration."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stereo_vo_ros.config import Config
from stereo_vo_ros.errors import CalibrationError
from stereo_vo_ros.estimation.camera import StereoCalibration
from stereo_vo_ros.estimation.estimator import (adaptive_gate, COAST_VARIANCE_CAP,
                                                epipolar_corrected, MotionEstimator)
from stereo_vo_ros.estimation.filters import make_filter
from stereo_vo_ros.estimation.motion import (rates_from_rotation, rotation_from_rates,
                                             TransferModel, transform_from_velocity,
                                             velocity_from_transform)
from stereo_vo_ros.estimation.ransac import BatchedMeasurement, num_samples
from stereo_vo_ros.estimation.trifocal import (fundamental_from_projections, perpendicular_lines,
                                               tensor_basis, transfer_basis, transfer_points,
                                               trifocal_tensor)
from stereo_vo_ros.records import Correspondences, TrackingStatus

FX, CX, CY, BASELINE = 718.856, 607.19, 185.22, 0.537


def kitti_calibration():
    P0 = np.array([[FX, 0, CX, 0], [0, FX, CY, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -FX * BASELINE
    return StereoCalibration.from_projections(P0, P1, 1241, 376)


def project(P, X):
    h = X @ P[:, :3].T + P[:, 3]
    return h[:, :2] / h[:, 2:]


def random_scene(rng, n):
    return np.column_stack([rng.uniform(-15, 15, n), rng.uniform(-3, 2, n),
                            rng.uniform(5, 60, n)])


def observe(calib, X_prev, T_prev_cur):
    """Pixels of points (previous left frame) in the previous and current stereo pairs."""
    Xc = (X_prev - T_prev_cur[:3, 3]) @ T_prev_cur[:3, :3]
    PL, PR = calib.projection_left(), calib.projection_right()
    return project(PL, X_prev), project(PR, X_prev), project(PL, Xc), project(PR, Xc)


def random_pose(rng):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    T[:3, 3] = rng.normal(0, 0.5, 3)
    return T


@pytest.mark.parametrize('seed', range(5))
def test_transfer_matches_triangulate_and_reproject(seed):
    rng = np.random.default_rng(seed)
    # Three general cameras (not a rectified pair) looking at a random scene.
    K = np.array([[700.0, 0, 320], [0, 710.0, 240], [0, 0, 1]])
    P_A = K @ np.eye(3, 4)
    T_B, T_C = random_pose(rng), random_pose(rng)
    T_B[:3, 3] += [-0.5, 0, 0]
    P_B = K @ np.linalg.inv(T_B)[:3]
    P_C = K @ np.linalg.inv(T_C)[:3]
    X = random_scene(rng, 50)
    x_A, x_B, x_C = project(P_A, X), project(P_B, X), project(P_C, X)
    T = trifocal_tensor(P_A, P_B, P_C)
    lines = perpendicular_lines(fundamental_from_projections(P_A, P_B), x_A, x_B)
    # Lines pass through x_B.
    assert np.abs(np.sum(lines[:, :2] * x_B, axis=1) + lines[:, 2]).max() < 1e-6 * np.abs(
        lines).max()
    np.testing.assert_allclose(transfer_points(T, x_A, lines), x_C, atol=1e-9)
    # The factored form used by the estimator is eq. 4 + eq. 5 exactly.
    G = tensor_basis(P_A, P_B)
    np.testing.assert_allclose(np.einsum('iqk,rk->iqr', G, P_C), T, rtol=1e-9,
                               atol=1e-9 * np.abs(T).max())
    Xh = transfer_basis(G, x_A, lines)
    np.testing.assert_allclose(project(P_C, Xh[:, :3] / Xh[:, 3:]), x_C, atol=1e-9)


def test_euler_convention_round_trip():
    rng = np.random.default_rng(1)
    omega = rng.uniform(-1.0, 1.0, (100, 3))
    dt = 0.1
    R = rotation_from_rates(omega, dt)
    # Eq. 6: R = R_Z(theta) R_X(phi) R_Y(psi): SciPy's intrinsic 'ZXY' sequence.
    a = omega * dt
    ref = Rotation.from_euler('ZXY', np.column_stack([a[:, 2], a[:, 0], a[:, 1]])).as_matrix()
    np.testing.assert_allclose(R, ref, atol=1e-12)
    for w, Ri in zip(omega, R):
        np.testing.assert_allclose(rates_from_rotation(Ri, dt), w, atol=1e-10)
    y = np.concatenate([rng.normal(0, 5, 3), omega[0]])
    np.testing.assert_allclose(velocity_from_transform(transform_from_velocity(y, dt), dt), y,
                               atol=1e-10)


def test_measurement_function_predicts_exact_pixels():
    rng = np.random.default_rng(2)
    calib = kitti_calibration()
    y = np.array([0.3, -0.1, 10.0, 0.02, 0.1, -0.03])
    pl, pr, cl, cr = observe(calib, random_scene(rng, 80), transform_from_velocity(y, 0.1))
    pred = TransferModel(calib, pl, pr, 0.1).predict(y)
    np.testing.assert_allclose(pred[:, :2], cl, atol=1e-8)
    np.testing.assert_allclose(pred[:, 2:], cr, atol=1e-8)


def _config(filter_type, **extra):
    values = {'filter.type': filter_type, 'ransac.enabled': False,
              'filter.threshold_velocity': 1e-6, 'filter.threshold_angular_deg': 1e-6,
              'filter.max_iterations': 200}
    values.update(extra)
    return Config().replace(**values)


@pytest.mark.parametrize('filter_type', ['ispkf', 'iekf'])
def test_iterated_filters_converge_on_noiseless_data(filter_type):
    rng = np.random.default_rng(3)
    calib = kitti_calibration()
    y = np.array([0.4, -0.2, 12.0, 0.05, 0.2, -0.04])
    corr = Correspondences(*observe(calib, random_scene(rng, 150),
                                    transform_from_velocity(y, 0.1)))
    # Default (vague) prior from zero velocity; noiseless data with a small assumed noise.
    est = MotionEstimator(_config(filter_type, **{'filter.pixel_noise_px': 0.01}))
    res = est.estimate(corr, calib, 0.1)
    assert res.status is TrackingStatus.OK
    np.testing.assert_allclose(res.velocity, y, atol=1e-6)
    assert res.iterations < 20
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


@pytest.mark.parametrize('filter_type', ['ukf', 'ekf'])
def test_single_step_filters_converge_over_frames(filter_type):
    rng = np.random.default_rng(4)
    calib = kitti_calibration()
    y = np.array([0.1, 0.0, 8.0, 0.01, 0.05, 0.0])
    # A constant motion: small process noise, so the filter can settle on it.
    est = MotionEstimator(_config(filter_type, **{'filter.velocity_process_noise': 0.05,
                                                  'filter.angular_process_noise_deg': 0.5}))
    for _ in range(15):
        corr = Correspondences(*observe(calib, random_scene(rng, 100),
                                        transform_from_velocity(y, 0.1)))
        res = est.estimate(corr, calib, 0.1)
    np.testing.assert_allclose(res.velocity, y, atol=1e-3)


@pytest.mark.parametrize('filter_type', ['ispkf', 'iekf'])
def test_ransac_recovers_motion_with_half_outliers(filter_type):
    # The filter makes the hypotheses too; the IEKF's hypotheses converge after different
    # numbers of iterations, so the batched update goes on with a subset of them.
    rng = np.random.default_rng(5)
    calib = kitti_calibration()
    y = np.array([-0.2, 0.1, 9.0, -0.01, 0.08, 0.02])
    pl, pr, cl, cr = observe(calib, random_scene(rng, 200), transform_from_velocity(y, 0.1))
    outlier = rng.random(200) < 0.5
    cl = cl.copy()
    n_out = int(outlier.sum())
    cl[outlier] += rng.uniform(5, 40, (n_out, 2)) * rng.choice([-1, 1], (n_out, 2))
    noise = 0.3
    corr = Correspondences(pl, pr, cl + rng.normal(0, noise, cl.shape),
                           cr + rng.normal(0, noise, cr.shape))
    cfg = _config(filter_type, **{'bucketing.enabled': False, 'ransac.enabled': True,
                                  'ransac.outlier_ratio': 0.5, 'ransac.startup_outlier_ratio': 0,
                                  'filter.threshold_velocity': 1e-3,
                                  'filter.threshold_angular_deg': 1e-3})
    res = MotionEstimator(cfg).estimate(corr, calib, 0.1)
    assert res.status is TrackingStatus.OK
    assert res.hypotheses == num_samples(0.99, 0.5, 3, cfg.ransac.max_hypotheses)
    np.testing.assert_allclose(res.velocity[:3], y[:3], atol=0.1)
    np.testing.assert_allclose(res.velocity[3:], y[3:], atol=2e-3)
    assert not np.any(res.inliers & outlier)
    assert np.count_nonzero(res.inliers & ~outlier) > 0.9 * np.count_nonzero(~outlier)
    # Without RANSAC the same data gives a visibly wrong motion in Kitt et al.'s plain update (the
    # robust reweighting alone resists these outliers too).
    bad = MotionEstimator(cfg.replace(**{'ransac.enabled': False, 'filter.robust_loss': 'none'})
                          ).estimate(corr, calib, 0.1)
    assert np.abs(bad.velocity - y).max() > 2 * np.abs(res.velocity - y).max()


def test_first_estimate_after_a_reset_draws_more_samples():
    rng = np.random.default_rng(6)
    calib = kitti_calibration()
    y = np.array([0.1, 0.0, 20.0, 0.0, 0.01, 0.0])
    pl, pr, cl, cr = observe(calib, random_scene(rng, 80), transform_from_velocity(y, 0.1))
    corr = Correspondences(pl, pr, cl, cr)
    cfg = Config().replace(**{'bucketing.enabled': False})
    est = MotionEstimator(cfg)
    startup = num_samples(0.99, cfg.ransac.startup_outlier_ratio, 3, cfg.ransac.max_hypotheses)
    usual = num_samples(0.99, cfg.ransac.outlier_ratio, 3, cfg.ransac.max_hypotheses)
    assert (startup, usual) == (300, 35)
    counts = [est.estimate(corr, calib, 0.1).hypotheses for _ in range(2)]
    est.coast()  # a coasting filter keeps its prediction: still the usual count
    counts.append(est.estimate(corr, calib, 0.1).hypotheses)
    est.reset()
    counts.append(est.estimate(corr, calib, 0.1).hypotheses)
    assert counts == [startup, usual, usual, startup]
    np.testing.assert_allclose(est.mean[:3], y[:3], atol=0.05)
    # A failed first estimate leaves the estimator fresh; a ratio below outlier_ratio is moot.
    est.reset()
    assert est.estimate(corr.subset(np.arange(3)), calib, 0.1).status is not TrackingStatus.OK
    assert est.estimate(corr, calib, 0.1).hypotheses == startup
    low = MotionEstimator(cfg.replace(**{'ransac.startup_outlier_ratio': 0.2}))
    assert low.estimate(corr, calib, 0.1).hypotheses == usual


def test_adaptive_gate_follows_the_residual_scale():
    cfg = Config().ransac  # 3 sigma between 0.5 and 2 px
    rng = np.random.default_rng(2)
    for sigma, expected in ((0.1, 0.5), (0.4, 1.2), (1.0, 2.0)):
        errors = np.linalg.norm(rng.normal(0, sigma, (20000, 2)), axis=1)
        assert adaptive_gate(errors, cfg) == pytest.approx(expected, rel=0.03)
    assert adaptive_gate(np.zeros(0), cfg) == cfg.inlier_threshold_px


def test_adaptive_threshold_rejects_near_misses():
    # Precise matches (0.1 px) and a quarter of the points off by 1.3-1.9 units of their error
    # scale (pixels over the spread of the previous pair's noise through the transfer, the
    # units of the RANSAC gate): a KLT window straddling an occlusion, an edge that slid.
    # Inside the fixed 2 px gate they count as inliers; the threshold tightened to the
    # residual scale (3 sigma, at least 0.5 px) leaves them out of the final update.
    rng = np.random.default_rng(8)
    calib = kitti_calibration()
    y = np.array([0.1, 0.0, 10.0, 0.01, 0.02, 0.0])
    pl, pr, cl, cr = observe(calib, random_scene(rng, 200), transform_from_velocity(y, 0.1))
    cl = cl + rng.normal(0, 0.1, cl.shape)
    cr = cr + rng.normal(0, 0.1, cr.shape)
    gain = TransferModel(calib, pl, pr, 0.1).previous_noise_gain(np.zeros(6))  # the prior
    scale = np.sqrt(1.0 + 0.5 * np.maximum(gain[:, 0] + gain[:, 1], gain[:, 2] + gain[:, 3]))
    off = rng.random(200) < 0.25
    angle = rng.uniform(0, 2 * np.pi, off.sum())
    shift = (rng.uniform(1.3, 1.9, off.sum()) * scale[off])[:, None] * np.column_stack(
        [np.cos(angle), np.sin(angle)])
    cl[off] += shift  # the same feature mislocated in both images (on its epipolar line)
    cr[off] += shift
    corr = Correspondences(pl, pr, cl, cr)
    base = {'bucketing.enabled': False, 'filter.robust_loss': 'none'}  # the gate alone
    fixed = MotionEstimator(Config().replace(**base, **{'ransac.adaptive_threshold': False}))
    res_fixed = fixed.estimate(corr, calib, 0.1)
    res = MotionEstimator(Config().replace(**base)).estimate(corr, calib, 0.1)
    assert res.status is TrackingStatus.OK and res_fixed.status is TrackingStatus.OK
    assert np.count_nonzero(res_fixed.inliers & off) > 0.75 * np.count_nonzero(off)
    assert np.count_nonzero(res.inliers & off) < 0.1 * np.count_nonzero(off)
    assert np.count_nonzero(res.inliers & ~off) > 0.95 * np.count_nonzero(~off)
    assert np.abs(res.velocity - y).max() <= np.abs(res_fixed.velocity - y).max()


@pytest.mark.parametrize('filter_type', ['ispkf', 'iekf'])
def test_batched_update_with_per_problem_noise_and_early_convergence(filter_type):
    # RANSAC's batched update: every problem has its own points and noise variances, and the
    # problems that converge early leave the others iterating on a subset of the batch.
    rng = np.random.default_rng(8)
    calib = kitti_calibration()
    y = np.array([0.3, -0.1, 10.0, 0.02, -0.05, 0.01])
    pl, pr, cl, cr = observe(calib, random_scene(rng, 12), transform_from_velocity(y, 0.1))
    model = TransferModel(calib, pl, pr, 0.1)
    samples = np.arange(12).reshape(4, 3)
    z = np.hstack([cl, cr])[samples].reshape(4, -1)
    var = rng.uniform(0.5, 2.0, z.shape)
    # Problems 0 and 2 start at the truth and barely trust their points (converged at once);
    # 1 and 3 start away from it.
    var[[0, 2]] = 1e8
    off = np.array([0.5, 0.2, -1.0, 0.01, 0.01, -0.01])
    prior = np.array([y, y + off, y, y + 2 * off])
    cov = np.diag([100.0] * 3 + [1.0] * 3)  # vague: the noiseless points decide
    cfg = Config().replace(**{'filter.type': filter_type}).filter
    out = make_filter(cfg).update(prior, cov, BatchedMeasurement(model, model.X[samples]),
                                  z, var, max_iterations=50)
    assert len(set(out.iterations.tolist())) > 1, out.iterations
    assert np.all(out.converged)
    np.testing.assert_allclose(out.mean, np.broadcast_to(y, (4, 6)), atol=0.05)


@pytest.mark.parametrize('correction', [True, False])
def test_camera_at_rest_with_a_vertical_stereo_offset(correction):
    # Identical pairs whose right points sit 0.1 px (+/- 0.4 px) off their epipolar lines, as
    # KLT matches on real rigs do: the transfer predicts the right point on the line, and the
    # offset must not be read as a rotation (the epipolar correction moves both pairs onto it).
    rng = np.random.default_rng(9)
    calib = kitti_calibration()
    pl, pr, _, _ = observe(calib, random_scene(rng, 150), np.eye(4))
    pr = pr + np.column_stack([np.zeros(150), -0.1 + rng.normal(0, 0.4, 150)])
    corr = Correspondences(pl, pr, pl.copy(), pr.copy())
    cfg = Config().replace(**{'filter.epipolar_correction': correction})
    est = MotionEstimator(cfg)
    for _ in range(10):
        res = est.estimate(corr, calib, 0.1)
    assert res.status is TrackingStatus.OK
    rot_deg_per_frame = np.rad2deg(np.linalg.norm(res.velocity[3:]) * 0.1)
    if correction:
        assert rot_deg_per_frame < 1e-6 and np.linalg.norm(res.velocity[:3]) < 1e-5
    else:  # the bias the correction removes
        assert rot_deg_per_frame > 1e-3


def test_epipolar_correction_moves_matches_onto_their_epipolar_lines():
    rng = np.random.default_rng(10)
    calib = kitti_calibration()
    pl, pr, cl, cr = observe(calib, random_scene(rng, 50), random_pose(rng))
    noisy = [a + rng.normal(0, 0.5, a.shape) for a in (pl, pr, cl, cr)]
    before = [a.copy() for a in noisy]
    out = epipolar_corrected(Correspondences(*noisy), calib, calib)
    for left, right in ((out.prev_left, out.prev_right), (out.cur_left, out.cur_right)):
        assert calib.epipolar_distance(left, right).max() < 1e-6
    # Rectified: rows become the mean of both, columns stay; the inputs are untouched.
    np.testing.assert_allclose(out.prev_left[:, 1], 0.5 * (noisy[0][:, 1] + noisy[1][:, 1]))
    np.testing.assert_allclose(out.prev_left[:, 0], noisy[0][:, 0])
    for a, b in zip(noisy, before):
        np.testing.assert_array_equal(a, b)


def raw_rig():
    """Return an unrectified, undistorted rig (EuRoC-like): raw calibration, K1, K2, R, t."""
    w, h = 752, 480
    K1 = np.array([[458.0, 0, 367.0], [0, 457.0, 248.0], [0, 0, 1]])
    K2 = np.array([[457.0, 0, 379.0], [0, 456.0, 255.0], [0, 0, 1]])
    R_rl = Rotation.from_rotvec([0.003, -0.01, 0.002]).as_matrix()
    t_rl = np.array([-0.11, 0.0004, -0.0008])
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K1, np.zeros(5), K2, np.zeros(5), (w, h), R_rl,
                                           t_rl.reshape(3, 1), alpha=0)
    raw = StereoCalibration.from_camera_info(_camera_info(K1, [0] * 5, R1, P1, w, h),
                                             _camera_info(K2, [0] * 5, R2, P2, w, h), 'raw')
    return raw, K1, K2, R_rl, t_rl


def test_epipolar_correction_of_raw_matches_uses_the_calibrated_geometry():
    # Unrectified cameras (cv2.correctMatches with the calibrated F): corrected pairs lie on
    # their epipolar lines and move by no more than the noise.
    rng = np.random.default_rng(12)
    raw, K1, K2, R_rl, t_rl = raw_rig()
    X = np.column_stack([rng.uniform(-3, 3, 40), rng.uniform(-2, 2, 40),
                         rng.uniform(2, 12, 40)])
    left, right = project(raw.projection_left(), X), project(raw.projection_right(), X)
    noisy_left = left + rng.normal(0, 0.5, left.shape)
    noisy_right = right + rng.normal(0, 0.5, right.shape)
    assert raw.epipolar_distance(noisy_left, noisy_right).mean() > 0.1
    out = epipolar_corrected(Correspondences(noisy_left, noisy_right, noisy_left, noisy_right),
                             raw, raw)
    assert raw.epipolar_distance(out.cur_left, out.cur_right).max() < 1e-6
    assert np.abs(out.cur_left - noisy_left).max() < 3.0


def test_coasting_keeps_the_velocity_covariance_positive_definite():
    # A posterior with strong correlations, then many frames without measurements: the
    # inflation is capped per standard deviation without breaking positive definiteness.
    rng = np.random.default_rng(11)
    calib = kitti_calibration()
    y = np.array([0.2, 0.0, 10.0, 0.01, 0.03, 0.0])
    est = MotionEstimator(Config())
    est.estimate(Correspondences(*observe(calib, random_scene(rng, 100),
                                          transform_from_velocity(y, 0.1))), calib, 0.1)
    for _ in range(30):
        est.coast()
        assert np.linalg.eigvalsh(est.cov).min() > 0
    cap = np.diag(est.initial_covariance()) * COAST_VARIANCE_CAP
    assert np.all(np.diag(est.cov) <= cap * (1 + 1e-12))
    # After many coasted frames the velocity is as uncertain as at the start, not more.
    np.testing.assert_allclose(np.diag(est.cov), cap, rtol=1e-6)
    np.testing.assert_allclose(est.mean, y, atol=0.05)  # coasting keeps the velocity


def test_acceleration_std_sets_the_velocity_process_noise_from_the_time_step():
    """vehicle.acceleration_std: the linear velocities may change by about a * dt per pair."""
    per_frame = MotionEstimator(Config())
    car = MotionEstimator(Config().replace(**{'vehicle.acceleration_std': 3.0}))
    angular = np.deg2rad(Config().filter.angular_process_noise_deg) ** 2
    np.testing.assert_allclose(np.diag(per_frame.process_noise(0.1)), [4.0] * 3 + [angular] * 3)
    np.testing.assert_allclose(np.diag(car.process_noise(0.1)), [0.09] * 3 + [angular] * 3)
    np.testing.assert_allclose(np.diag(car.process_noise(1 / 30)), [0.01] * 3 + [angular] * 3)
    # Without a time step (or a bad one) the per-frame value applies.
    for dt in (None, 0.0, -0.1):
        np.testing.assert_allclose(np.diag(car.process_noise(dt))[:3], [4.0] * 3)
    # A pair without an estimate inflates the rates' covariance but widens a car's velocity by
    # its acceleration only.
    for est, linear in ((per_frame, 2 * (1e-4 + 4.0)), (car, 1e-4 + 0.09)):
        est.cov = np.eye(6) * 1e-4
        est.coast(inflation=2.0, dt=0.1)
        np.testing.assert_allclose(np.diag(est.cov), [linear] * 3 + [2 * (1e-4 + angular)] * 3)
    # Features that say the car lost 12 m/s within 0.1 s (more than 12 g): with the per-frame
    # noise the estimate follows them, a car's acceleration takes them for outliers.
    rng = np.random.default_rng(5)
    calib = kitti_calibration()
    cruise = np.array([0.0, 0.0, 25.0, 0.0, 0.0, 0.0])
    braked = np.array([0.0, 0.0, 13.0, 0.0, 0.0, 0.0])
    corr = Correspondences(*observe(calib, random_scene(rng, 30),
                                    transform_from_velocity(braked, 0.1)))
    corr.cur_left += rng.normal(0, 0.5, corr.cur_left.shape)
    corr.cur_right += rng.normal(0, 0.5, corr.cur_right.shape)
    speeds = []
    for accel in (0.0, 3.0):
        est = MotionEstimator(Config().replace(**{'vehicle.acceleration_std': accel}))
        est.reset(cruise)
        est.cov = np.diag([0.05 ** 2] * 3 + [1e-6] * 3)
        out = est.estimate(corr, calib, 0.1)
        assert out.status is TrackingStatus.OK
        speeds.append(out.velocity[2])
    assert speeds[0] < 17.0
    assert speeds[1] > 24.0


def test_num_samples_eq14():
    assert num_samples(0.99, 0.5, 3) == 35
    assert num_samples(0.99, 0.2, 3) == 7
    assert num_samples(0.99, 0.0, 3) == 1
    assert num_samples(0.999, 0.5, 3, max_samples=10) == 10


def _camera_info(K, D, R, P, w, h):
    return {'k': K.ravel().tolist(), 'd': list(D), 'r': R.ravel().tolist(),
            'p': P.ravel().tolist(), 'width': w, 'height': h}


def test_raw_calibration_matches_rectified_equivalent():
    rng = np.random.default_rng(6)
    w, h = 752, 480
    K1 = np.array([[458.0, 0, 367.0], [0, 457.0, 248.0], [0, 0, 1]])
    K2 = np.array([[457.0, 0, 379.0], [0, 456.0, 255.0], [0, 0, 1]])
    D1 = np.array([-0.28, 0.07, 0.0002, 0.00002, 0.0])
    D2 = np.array([-0.28, 0.07, -0.0001, -0.00005, 0.0])
    R_rl = Rotation.from_rotvec([0.003, -0.01, 0.002]).as_matrix()
    t_rl = np.array([-0.11, 0.0004, -0.0008])
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K1, D1, K2, D2, (w, h), R_rl,
                                           t_rl.reshape(3, 1), alpha=0)
    raw = StereoCalibration.from_camera_info(_camera_info(K1, D1, R1, P1, w, h),
                                             _camera_info(K2, D2, R2, P2, w, h), 'raw')
    np.testing.assert_allclose(raw.R_right_left, R_rl, atol=1e-9)
    np.testing.assert_allclose(raw.t_right_left, t_rl, atol=1e-9)
    rect = StereoCalibration.from_camera_info(
        _camera_info(P1[:, :3], [0] * 5, np.eye(3), P1, w, h),
        _camera_info(P2[:, :3], [0] * 5, np.eye(3), P2, w, h))
    # Scene and motion in the raw left camera frame.
    X = np.column_stack([rng.uniform(-3, 3, 150), rng.uniform(-2, 2, 150),
                         rng.uniform(2, 12, 150)])
    y = np.array([0.3, 0.1, 1.5, 0.05, -0.1, 0.02])
    T = transform_from_velocity(y, 0.05)
    Xc = (X - T[:3, 3]) @ T[:3, :3]

    def raw_pixels(Xl, K, D, R, t):
        pts, _ = cv2.projectPoints(Xl @ R.T + t, np.zeros(3), np.zeros(3), K, D)
        return pts.reshape(-1, 2)
    I3, z3 = np.eye(3), np.zeros(3)
    raw_obs = [raw_pixels(X, K1, D1, I3, z3), raw_pixels(X, K2, D2, R_rl, t_rl),
               raw_pixels(Xc, K1, D1, I3, z3), raw_pixels(Xc, K2, D2, R_rl, t_rl)]
    # Keep what a tracker could see: points well inside all four images.
    inside = np.all([(o[:, 0] > 20) & (o[:, 0] < w - 20) & (o[:, 1] > 20) & (o[:, 1] < h - 20)
                     for o in raw_obs], axis=0)
    assert inside.sum() > 60
    X, Xc = X[inside], Xc[inside]
    raw_obs = [o[inside] for o in raw_obs]
    und = [raw.undistort_left(raw_obs[0]), raw.undistort_right(raw_obs[1]),
           raw.undistort_left(raw_obs[2]), raw.undistort_right(raw_obs[3])]
    # Distort/undistort round trip.
    np.testing.assert_allclose(raw.distort_left(und[0]), raw_obs[0], atol=1e-3)
    cfg = _config('ispkf', **{'filter.initial_velocity_std': 100.0})
    res_raw = MotionEstimator(cfg).estimate(Correspondences(*und), raw, 0.05)
    # Rectified equivalent: the same scene in the rectified left frame.
    Xr, Xcr = X @ R1.T, Xc @ R1.T
    rect_obs = [project(P1, Xr), project(P2, Xr), project(P1, Xcr), project(P2, Xcr)]
    res_rect = MotionEstimator(cfg).estimate(Correspondences(*rect_obs), rect, 0.05)
    assert res_raw.status is res_rect.status is TrackingStatus.OK
    T_raw_in_rect = np.eye(4)
    T_raw_in_rect[:3, :3] = R1
    expected = T_raw_in_rect @ res_raw.T_prev_cur @ np.linalg.inv(T_raw_in_rect)
    np.testing.assert_allclose(res_rect.T_prev_cur, expected, atol=2e-4)
    np.testing.assert_allclose(res_raw.T_prev_cur, T, atol=2e-4)
    # The epipolar distance of true raw correspondences is ~0 after undistortion.
    assert raw.epipolar_distance(und[0], und[1]).max() < 1e-3


def _pinhole(fx=500.0, tx=-50.0, w=640, h=480):
    P = [[fx, 0, 320, tx], [0, fx, 240, 0], [0, 0, 1, 0]]
    K = [[fx, 0, 320], [0, fx, 240], [0, 0, 1]]
    return {'k': np.ravel(K).tolist(), 'd': [0.0] * 5, 'r': np.eye(3).ravel().tolist(),
            'p': np.ravel(P).tolist(), 'width': w, 'height': h}


@pytest.mark.parametrize('right, match', [
    ({'fx': float('nan')}, 'non-finite'),
    ({'fx': 0.0}, 'focal length must be positive'),
    ({'fx': -10.0}, 'focal length must be positive'),
    ({'tx': 0.0}, 'baseline must be positive'),
    ({'tx': 50.0}, 'right camera must be to the right'),
    ({'w': 320}, 'sizes differ'),
    ({'w': 0}, 'size must be positive'),
])
def test_invalid_calibration_rejected(right, match):
    left = _pinhole(tx=0.0)
    with pytest.raises(CalibrationError, match=match):
        StereoCalibration.from_camera_info(left, _pinhole(**right))


def test_invalid_calibration_messages_name_values():
    left = _pinhole(tx=0.0)
    bad = _pinhole()
    bad['p'] = bad['p'][:10]
    with pytest.raises(CalibrationError, match="'p' must have 12 values, got 10"):
        StereoCalibration.from_camera_info(left, bad)
    raw = _pinhole()
    raw['r'] = [0.0] * 9
    with pytest.raises(CalibrationError, match='right R is not a rotation'):
        StereoCalibration.from_camera_info(_pinhole(tx=0.0), raw, 'raw')


@pytest.mark.parametrize('loss', ['none', 'cauchy'])
def test_robust_update_on_exact_data_is_exact(loss):
    rng = np.random.default_rng(5)
    calib = kitti_calibration()
    y = np.array([0.3, 0.1, 15.0, 0.02, -0.05, 0.01])
    corr = Correspondences(*observe(calib, random_scene(rng, 120),
                                    transform_from_velocity(y, 0.1)))
    cfg = Config().replace(**{'filter.robust_loss': loss, 'filter.pixel_noise_px': 0.01,
                              'filter.threshold_velocity': 1e-7,
                              'filter.threshold_angular_deg': 1e-7,
                              'filter.max_iterations': 200, 'bucketing.enabled': False})
    res = MotionEstimator(cfg).estimate(corr, calib, 0.1)
    assert res.status is TrackingStatus.OK
    np.testing.assert_allclose(res.velocity, y, atol=1e-5)


@pytest.mark.parametrize('seed', [11, 12, 13])
def test_robust_update_discounts_a_coherent_minority(seed):
    # Forward at 20 m/s with 0.1 px noise; 15 % of the features moved as if at 16 m/s (a
    # group that lags, as matches that land short on a fast road). With RANSAC off every
    # feature enters the final update: the plain Gaussian update follows the group, the
    # Cauchy reweighting leaves it out.
    rng = np.random.default_rng(seed)
    calib = kitti_calibration()
    y = np.array([0.0, 0.0, 20.0, 0.0, 0.0, 0.0])
    X = random_scene(rng, 200)
    pl, pr, cl, cr = observe(calib, X, transform_from_velocity(y, 0.1))
    _, _, slow_l, slow_r = observe(calib, X, transform_from_velocity(0.8 * y, 0.1))
    lag = rng.random(200) < 0.15
    cl = np.where(lag[:, None], slow_l, cl) + rng.normal(0, 0.1, cl.shape)
    cr = np.where(lag[:, None], slow_r, cr) + rng.normal(0, 0.1, cr.shape)
    corr = Correspondences(pl, pr, cl, cr)
    error = {}
    for loss in ('none', 'cauchy'):
        cfg = Config().replace(**{'filter.robust_loss': loss, 'bucketing.enabled': False,
                                  'ransac.enabled': False})
        res = MotionEstimator(cfg).estimate(corr, calib, 0.1)
        assert res.status is TrackingStatus.OK
        error[loss] = np.abs(res.velocity - y).max()
    assert error['none'] > 0.2  # m/s or rad/s
    assert error['cauchy'] < 0.05 and error['cauchy'] < 0.1 * error['none']
