"""The vectorised estimator paths against plain reference implementations of the same maths."""

import numpy as np
import pytest

from stereo_vo_ros.config import Config
from stereo_vo_ros.estimation.camera import StereoCalibration
from stereo_vo_ros.estimation.filters import _upper_inverse, make_filter
from stereo_vo_ros.estimation.motion import rotation_from_rates, TransferModel
from stereo_vo_ros.estimation.ransac import (BatchedMeasurement, draw_samples,
                                             reprojection_errors)
from stereo_vo_ros.estimation.trifocal import perpendicular_lines, transfer_basis

FX, CX, CY, BASELINE = 718.856, 607.19, 185.22, 0.537


def kitti_model(rng, n=60, dt=0.1):
    P0 = np.array([[FX, 0, CX, 0], [0, FX, CY, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -FX * BASELINE
    calib = StereoCalibration.from_projections(P0, P1, 1241, 376)
    X = np.column_stack([rng.uniform(-15, 15, n), rng.uniform(-3, 2, n), rng.uniform(5, 60, n)])
    pl = X[:, :2] / X[:, 2:] * FX + [CX, CY]
    pr = (X[:, :2] - [BASELINE, 0]) / X[:, 2:] * FX + [CX, CY]
    return calib, TransferModel(calib, pl, pr, dt)


def reference_update(filt, mean, cov, h, z, noise_var, max_it):
    """Return the sigma-point update as first written (inverses, Cholesky, H explicitly)."""
    n = 6
    scale = np.sqrt(n + filt.lam)
    B = mean.shape[0]
    cov = np.broadcast_to(cov, (B, n, n))
    info = np.linalg.inv(cov)
    r_inv = np.broadcast_to(1.0 / noise_var, z.shape)
    L = np.linalg.cholesky(0.5 * (cov + np.swapaxes(cov, 1, 2))) * scale
    x, lam = mean.copy(), info.copy()
    iterations = np.zeros(B, int)
    active = np.arange(B)
    for _ in range(max_it if filt.iterated else 1):
        xa, La = x[active], L[active]
        offsets = np.swapaxes(La, 1, 2)
        pts = np.concatenate([xa[:, None] + offsets, xa[:, None] - offsets], axis=1)
        if filt.w0 != 0.0:
            pts = np.concatenate([xa[:, None], pts], axis=1)
        Z = h(pts, active)
        z0 = Z[:, 0] if filt.w0 != 0.0 else 0.0
        Z = Z[:, 1:] if filt.w0 != 0.0 else Z
        plus, minus = Z[:, :n], Z[:, n:]
        z_bar = (plus + minus).sum(axis=1) * ((1.0 - filt.w0) / (2 * n)) + filt.w0 * z0
        H = np.swapaxes(0.5 * (plus - minus), 1, 2) @ np.linalg.inv(La)
        valid = np.isfinite(z_bar) & np.isfinite(H).all(axis=2)
        resid = z[active] - z_bar - (H @ (mean[active] - xa)[..., None])[..., 0]
        resid = np.where(valid, resid, 0.0)
        H = np.where(valid[..., None], H, 0.0)
        Ht = np.swapaxes(H, 1, 2)
        lam_a = info[active] + Ht @ (r_inv[active][..., None] * H)
        x_new = mean[active] + np.linalg.solve(
            lam_a, (Ht @ (r_inv[active] * resid)[..., None]))[..., 0]
        lam[active] = lam_a
        iterations[active] += 1
        if filt.posterior_spread:
            L[active] = np.linalg.cholesky(np.linalg.inv(lam_a)) * scale
        done = np.all(np.abs(x_new - xa) < filt.threshold, axis=1)
        x[active] = x_new
        active = active[~done]
        if active.size == 0:
            break
    return x, np.linalg.inv(lam), iterations


@pytest.mark.parametrize('spread, alpha', [('posterior', 1.0), ('prior', 1.0),
                                           ('posterior', 0.9)])
def test_sigma_point_update_matches_the_reference(spread, alpha):
    # Many problems with their own points (RANSAC), one with many points (the final update),
    # a point without a prediction, and a centre point (alpha != 1 gives w0 != 0).
    rng = np.random.default_rng(3)
    _, model = kitti_model(rng)
    model.X[5] = 0.0  # no prediction (0 / 0)
    cfg = Config().replace(**{'filter.ispkf_spread': spread, 'filter.sigma_alpha': alpha,
                              'filter.threshold_velocity': 1e-5,
                              'filter.threshold_angular_deg': 1e-5}).filter
    filt = make_filter(cfg)
    y = np.array([0.3, -0.1, 10.0, 0.02, -0.05, 0.01])
    z_all = model.predict(y) + rng.normal(0, 0.5, (len(model.X), 4))
    var_all = rng.uniform(0.3, 2.0, z_all.shape)
    cov = np.diag([4.0] * 3 + [0.01] * 3)
    for index in (rng.permuted(np.tile(np.arange(60), (20, 1)), axis=1)[:, :3],
                  np.arange(60)[None], np.arange(4, 50)[None]):
        B = len(index)
        mean = np.broadcast_to(y + [0.5, 0, -1.0, 0, 0.01, 0], (B, 6))
        z = z_all[index].reshape(B, -1)
        var = var_all[index].reshape(B, -1)
        out = filt.update(mean, cov, BatchedMeasurement(model, index=index), z, var,
                          max_iterations=6)

        def h(pts, active, index=index):
            pred = model.predict(pts, model.X[index[active]])
            return pred.reshape(pred.shape[:2] + (-1,))
        x, P, iterations = reference_update(filt, np.array(mean), cov, h, z, var, 6)
        np.testing.assert_allclose(out.mean, x, rtol=1e-10, atol=1e-11)
        np.testing.assert_allclose(out.cov, P, rtol=1e-8, atol=1e-14)
        np.testing.assert_array_equal(out.iterations, iterations)
        # The same through a plain callable (no shared linearisation, measurement order).
        plain = filt.update(mean, cov, lambda pts, i=index: h(pts, np.arange(len(i))), z,
                            var, max_iterations=6)
        np.testing.assert_allclose(plain.mean, x, rtol=1e-10, atol=1e-11)


def test_an_update_can_start_from_the_linearisation_of_another():
    # The estimator's robust rounds: the same prior and measurements, other variances.
    rng = np.random.default_rng(5)
    _, model = kitti_model(rng)
    y = np.array([0.3, -0.1, 10.0, 0.02, -0.05, 0.01])
    z = (model.predict(y) + rng.normal(0, 0.5, (len(model.X), 4))).reshape(1, -1)
    var = np.full(z.shape, 0.5)
    reweighted = var / rng.uniform(0.2, 1.0, z.shape)
    mean = (y + [0.5, 0, -1.0, 0, 0.01, 0])[None]
    cov = np.diag([4.0] * 3 + [0.01] * 3)
    h = BatchedMeasurement(model, index=np.arange(len(model.X))[None])
    tight = {'filter.threshold_velocity': 1e-6, 'filter.threshold_angular_deg': 1e-6}
    filt = make_filter(Config().replace(**tight).filter)
    first = filt.update(mean, cov, h, z, var)
    cold = filt.update(mean, cov, h, z, reweighted)
    warm = filt.update(mean, cov, h, z, reweighted, start=first.linearization)
    assert warm.converged[0] and 2 <= warm.iterations[0] < cold.iterations[0]
    np.testing.assert_allclose(warm.mean, cold.mean, atol=1e-6)
    np.testing.assert_allclose(warm.cov, cold.cov, rtol=1e-6)
    assert np.abs(warm.mean - first.mean).max() > 1e-3  # the weights moved the estimate
    # One step at the start's linearisation: the information-form update with its H and z_bar.
    lin = first.linearization
    step = filt.update(mean, cov, h, z, reweighted, start=lin, max_iterations=1)
    r_inv = 1.0 / reweighted[0]
    lam = np.linalg.inv(cov) + (lin.Ht * r_inv) @ lin.Ht.T
    resid = z[0] - lin.z_bar - (mean[0] - lin.x) @ lin.Ht
    expected = mean[0] + np.linalg.solve(lam, (lin.Ht * r_inv) @ resid)
    np.testing.assert_allclose(step.mean[0], expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(step.cov[0], np.linalg.inv(lam), rtol=1e-9)
    assert step.iterations[0] == 1 and np.abs(step.mean - cold.mean).max() < 1e-3
    # A start taken on other measurements is not used: another count, or one now missing.
    sub = BatchedMeasurement(model, index=np.arange(10, len(model.X))[None])
    z_sub, var_sub = z[:, 40:], reweighted[:, 40:]
    np.testing.assert_array_equal(
        filt.update(mean, cov, sub, z_sub, var_sub, start=first.linearization).mean,
        filt.update(mean, cov, sub, z_sub, var_sub).mean)
    gap = z.copy()
    gap[0, 5] = np.nan
    np.testing.assert_array_equal(
        filt.update(mean, cov, h, gap, reweighted, start=first.linearization).mean,
        filt.update(mean, cov, h, gap, reweighted).mean)
    first_gap = filt.update(mean, cov, h, gap, var)
    assert first_gap.linearization.valid is not None
    np.testing.assert_allclose(
        filt.update(mean, cov, h, gap, reweighted, start=first_gap.linearization).mean,
        filt.update(mean, cov, h, gap, reweighted).mean, atol=1e-6)
    # A start from the same problem's own last linearisation still takes a fresh one.
    again = filt.update(mean, cov, h, z, var, start=first.linearization)
    assert again.iterations[0] == 2
    np.testing.assert_allclose(again.mean, first.mean, atol=1e-6)
    # The UKF linearises once, at the prior: a start is that same linearisation.
    ukf = make_filter(Config().replace(**{'filter.type': 'ukf'}).filter)
    start = ukf.update(mean, cov, h, z, var).linearization
    np.testing.assert_array_equal(ukf.update(mean, cov, h, z, reweighted, start=start).mean,
                                  ukf.update(mean, cov, h, z, reweighted).mean)
    # The EKF and IEKF start at the prior whatever they are given.
    for kind in ('ekf', 'iekf'):
        point = make_filter(Config().replace(**{'filter.type': kind}).filter)
        assert point.update(mean, cov, h, z, var).linearization is None
        np.testing.assert_array_equal(
            point.update(mean, cov, h, z, reweighted, start=first.linearization).mean,
            point.update(mean, cov, h, z, reweighted).mean)


def test_the_general_update_takes_over_where_the_compiled_one_cannot():
    # A prior whose information is not positive definite (one variance negative): the
    # compiled update gives up on the first such problem and the general code, with its
    # fallbacks, solves the update.
    rng = np.random.default_rng(8)
    _, model = kitti_model(rng)
    y = np.array([0.3, -0.1, 10.0, 0.02, -0.05, 0.01])
    z_all = model.predict(y) + rng.normal(0, 0.5, (len(model.X), 4))
    index = rng.permuted(np.tile(np.arange(60), (10, 1)), axis=1)[:, :3]
    z, var = z_all[index].reshape(10, -1), np.full((10, 12), 0.5)
    mean = np.broadcast_to(y, (10, 6))
    filt = make_filter(Config().filter)
    h = BatchedMeasurement(model, index=index)
    for cov, compiled in ((np.diag([4.0] * 3 + [0.01] * 3), True),
                          (np.diag([4.0] * 3 + [0.01] * 2 + [-1e-9]), False)):
        scale = np.sqrt(6 + filt.lam)
        terms = filt._prior_terms(cov, scale)
        out = filt._update_compiled(y, *terms, h.transfer_inputs(), z, 1.0 / var, 3, False,
                                    scale, None)
        assert (out is not None) == compiled
        general = filt.update(mean, cov, lambda pts: h(pts), z, var, max_iterations=3)
        update = filt.update(mean, cov, h, z, var, max_iterations=3)
        if compiled:
            np.testing.assert_allclose(update.mean, general.mean, rtol=1e-10, atol=1e-11)
        else:
            np.testing.assert_array_equal(update.mean, general.mean)
        np.testing.assert_array_equal(update.iterations, general.iterations)


def test_predictions_match_the_projection_matrices():
    rng = np.random.default_rng(4)
    calib, model = kitti_model(rng)
    for K in (1, 12, 100):
        y = rng.normal(size=(K, 6)) * [3, 1, 10, 0.3, 0.5, 0.3]
        R, t = rotation_from_rates(y[:, 3:], model.dt), y[:, :3] * model.dt
        Rt = np.swapaxes(R, 1, 2)
        M = np.concatenate([Rt, -(Rt @ t[..., None])], axis=2)
        P = np.concatenate([calib.K_left @ M, calib.K_right @ (
            calib.R_right_left @ M + np.append(np.zeros(3), 1.0)[None, None] *
            calib.t_right_left[:, None])], axis=1)
        h = P @ model.X.T  # (K, 6, N)
        ref = np.stack([h[:, 0] / h[:, 2], h[:, 1] / h[:, 2], h[:, 3] / h[:, 5],
                        h[:, 4] / h[:, 5]], axis=-1)
        np.testing.assert_allclose(model.predict(y), ref, rtol=1e-13, atol=1e-9)
    # Batched: problem b's states see its own points; states that do not pair are refused.
    X = np.stack([model.X[:5], model.X[5:10]])  # (2, 5, 4)
    y = rng.normal(size=(6, 2, 3)) * np.array([3, 1, 10, 0.3, 0.5, 0.3])[:, None, None]
    batched = model.predict_planes(y, X)  # (4, 2, 3, 5)
    for b in range(2):
        np.testing.assert_allclose(batched[:, b], model.predict_planes(y[:, b], X[b]),
                                   rtol=1e-13)
    with pytest.raises(ValueError):
        model.predict_planes(y.reshape(6, 6), X)


def test_reprojection_errors_and_noise_gain_match_their_definitions():
    rng = np.random.default_rng(5)
    calib, model = kitti_model(rng)
    states = rng.normal(size=(7, 6)) * [1, 0.2, 10, 0.02, 0.05, 0.02]
    z = model.predict(states[0]) + rng.normal(0, 1.0, (len(model.X), 4))
    scale = rng.uniform(1.0, 2.0, (len(model.X), 2))
    d = model.predict(states) - z
    ref = np.maximum(np.hypot(d[..., 0], d[..., 1]) / scale[:, 0],
                     np.hypot(d[..., 2], d[..., 3]) / scale[:, 1])
    np.testing.assert_allclose(reprojection_errors(model, states, z, scale), ref, rtol=1e-12)
    idx = np.array([3, 1, 7])
    np.testing.assert_allclose(reprojection_errors(model, states, z, scale, idx), ref[:, idx],
                               rtol=1e-12)
    # Finite differences of the transfer under each previous coordinate, one at a time.
    y = states[1]
    base = model.predict(y)
    gain = np.zeros_like(base)
    for side, col in ((0, 0), (0, 1), (1, 0), (1, 1)):
        pl, pr = model.prev_left.copy(), model.prev_right.copy()
        (pl if side == 0 else pr)[:, col] += 0.5
        X = transfer_basis(model.G, pl, perpendicular_lines(model.F, pl, pr))
        gain += ((model.predict(y, X) - base) / 0.5) ** 2
    np.testing.assert_allclose(model.previous_noise_gain(y), gain, rtol=1e-7, atol=1e-12)


def test_samples_and_triangular_inverses():
    u = np.random.default_rng(6).random((35, 190))
    expected = np.argpartition(u, 2, axis=1)[:, :3]
    np.testing.assert_array_equal(draw_samples(np.random.default_rng(6), 35, 190), expected)
    A = np.random.default_rng(7).normal(size=(40, 6, 6))
    U = np.triu(A) + 3 * np.eye(6)
    np.testing.assert_allclose(_upper_inverse(U), np.linalg.inv(U), rtol=1e-12, atol=1e-14)
