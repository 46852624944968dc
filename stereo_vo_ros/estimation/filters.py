"""
Kalman filter updates for the 6-D egomotion state (Kitt et al., section III-E).

Four filters behind one interface (:class:`Filter`), all batched over B independent problems
(RANSAC hypotheses are solved side by side):

* ``ispkf`` -- Iterated Sigma Point Kalman Filter (Sibley, Sukhatme & Matthies 2006): sigma
  points are re-drawn around every iterate ``x_i``; their propagated mean and cross-covariance
  give a statistically linearised measurement model, and the update is iterated until every
  state component changes less than a threshold (m/s and deg/s) or a maximum number of
  iterations is reached. No analytic derivatives are needed. The spread of the sigma points is
  the covariance of the latest iterate (``filter.ispkf_spread = posterior``, the default; the
  first iteration uses the prior) or always the prior (``prior``). With the prior spread the
  fixed point is biased by the curvature of h across the prior uncertainty (measured: -1.4 m/s
  on noiseless data from a 10 m/s prior std), which the posterior spread removes.
* ``ukf`` -- the same with a single iteration around the prior mean (Julier & Uhlmann).
* ``ekf`` -- one update linearised at the prior mean with the Jacobian of h.
* ``iekf`` -- the update iterated with the Jacobian re-evaluated at each iterate (Gauss-Newton).

The Jacobian of h for the EKF/IEKF is evaluated by central differences with a tiny step, which
matches the analytic derivative to ~1e-9 relative.

All filters work in information form: with a diagonal measurement noise ``R = sigma^2 I`` the
update needs ``H^T R^-1 H`` (6x6) and ``H^T R^-1 r`` (6) only, so no 4N x 4N matrix is ever
formed or inverted. Iterated update (the IEKF form, with ``z_bar_i`` and ``H_i`` from the chosen
linearisation at ``x_i``)::

    Lambda_i = P^-1 + H_i^T R^-1 H_i
    x_{i+1}  = x_prior + Lambda_i^-1 H_i^T R^-1 (z - z_bar_i - H_i (x_prior - x_i))
    P_post   = Lambda_i^-1

For the sigma-point filters this is the statistical-linear-regression form of the UKF update;
it neglects the regression-residual term of the innovation covariance, which is what keeps the
update in 6x6 information form.

Implementation of the sigma-point filters (ISPKF, UKF): the regression Jacobian is
``H_i = D_i^T L_i^-1`` with ``D_i`` (6 x M) the half differences of h across the sigma pairs
(mean and differences of all sigma points in one matrix product), so no inverse of ``L_i`` is
needed once ``L_i^-T`` is known. The next iterate's factor ``L_{i+1} = chol(Lambda_i^-1)
sqrt(n + lambda)`` comes from one Cholesky factorisation of ``Lambda_i`` with rows and columns
reversed (``J Lambda J = C C^T`` gives ``Lambda = U U^T`` with the upper triangular
``U = J C J``, and ``chol(Lambda^-1) = U^-T``): ``L_{i+1}^-T = U / sqrt(n + lambda)`` as it is,
and ``L_{i+1}`` and the step ``Lambda_i^-1 b = U^-T U^-1 b`` from the triangular inverse of U.
The prior's information and factors are kept for the next update with the same prior (RANSAC,
the final update and its robust rounds share it), one problem runs on 2-D arrays with LAPACK
called directly, and a batch of problems keeps the converged ones in the batch (not updated
any more) instead of regrouping it. One problem's update can take its first step from the last
linearisation of another update of the same prior and measurements (``start``, a
:class:`Linearization`), as the estimator's robust reweighting rounds do.

The problems of the trifocal transfer model with one prior (RANSAC's hypotheses, the final
update: a measurement function with ``transfer_inputs``, see
:class:`~.ransac.BatchedMeasurement`) run the same iterations compiled, one loop per problem
(:mod:`~.sigma_update`); the code here is the reference for them and runs everything else.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np
from scipy.linalg import lapack

from .sigma_update import sigma_update
from ..config import FilterConfig
from ..errors import ConfigError

#: states (B, S, 6) -> predicted measurements (B, S, M)
MeasurementFn = Callable[[np.ndarray], np.ndarray]

STATE_DIM = 6
_EPS_JACOBIAN = 1e-6


@dataclass
class FilterOutput:
    """
    Posterior of a batched update.

    Attributes
    ----------
    mean : (B, 6) posterior state (m/s, rad/s).
    cov : (B, 6, 6) posterior covariance (None when the update was asked not to compute it).
    iterations : (B,) int iterations used.
    converged : (B,) bool True where the termination threshold was met.
    linearization : the last linearisation of a one-problem sigma-point update (else None),
        for another update to ``start`` from.

    """

    mean: np.ndarray
    cov: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    linearization: 'Linearization | None' = None


@dataclass
class Linearization:
    """
    The last linearisation of a one-problem sigma-point update (see ``_BaseFilter.update``).

    Another update of the same prior and the same measurements, with other noise variances
    (the robust reweighting rounds), starts from it instead of from the prior.

    Attributes
    ----------
    x : (6,) state it was taken at (m/s, rad/s).
    z_bar : (M,) sigma-point mean of h at ``x`` (pixels), in the measurement function's order.
    Ht : (6, M) transposed regression Jacobian (pixels per m/s and per rad/s); zero columns
        where h or z was not finite.
    valid : (M,) bool where the measurement was used, or None for all.

    """

    x: np.ndarray
    z_bar: np.ndarray
    Ht: np.ndarray
    valid: np.ndarray | None


class Filter(Protocol):
    """A measurement update of the egomotion state."""

    name: str

    def update(self, mean: np.ndarray, cov: np.ndarray, h: MeasurementFn, z: np.ndarray,
               noise_var: float | np.ndarray, max_iterations: int | None = None,
               need_cov: bool = True, start: Linearization | None = None) -> FilterOutput:
        """Update B priors ``(mean (B,6), cov (B,6,6))`` with measurements ``z (B,M)``."""


def sigma_points(x: np.ndarray, L: np.ndarray, w0: float) -> np.ndarray:
    """
    Return the sigma points (..., S, 6) of states x (..., 6) and offsets L (..., 6, 6).

    ``x + L[:, j]`` for j = 0..5, then ``x - L[:, j]``, after ``x`` itself when ``w0 != 0``
    (S = 12 or 13). x and L broadcast against each other.
    """
    offsets = np.swapaxes(L, -1, -2)  # row j = column j of L
    x = x[..., None, :]
    parts = [x + offsets, x - offsets]
    if w0 != 0.0:
        parts.insert(0, np.broadcast_to(x, parts[0].shape[:-2] + (1, STATE_DIM)))
    return np.concatenate(parts, axis=-2)


def sigma_points_t(x: np.ndarray, L: np.ndarray, w0: float) -> np.ndarray:
    """
    :func:`sigma_points` transposed: (6, B, S) for x (B, 6) and L (B, 6, 6) or (6, 6).

    Component i of sigma point s of problem b is ``[i, b, s]`` (the layout of
    ``TransferModel.predict_stacked``). With x (6,) and L (6, 6): (6, S).
    """
    xt = x.T[..., None]  # (6, B, 1) or (6, 1)
    if L.ndim == 3:
        Lt = L.transpose(1, 0, 2)  # [i, b, j] = L[b, i, j]
    elif x.ndim == 2:  # one L for all problems
        Lt = L[:, None, :]
    else:
        Lt = L
    c = 1 if w0 != 0.0 else 0
    pts = np.empty((STATE_DIM,) + x.shape[:-1] + (2 * STATE_DIM + c,))
    if c:
        pts[..., 0] = xt[..., 0]
    np.add(xt, Lt, out=pts[..., c:c + STATE_DIM])
    np.subtract(xt, Lt, out=pts[..., c + STATE_DIM:])
    return pts


_MOMENTS: dict = {}


def _moment_matrix(S: int, w0: float) -> np.ndarray:
    """(7, S): rows 0-5 the half differences of the sigma pairs, row 6 the weighted mean."""
    key = (S, w0)
    if key not in _MOMENTS:
        c = S - 2 * STATE_DIM  # 1 with the centre point first
        m = np.zeros((STATE_DIM + 1, S))
        idx = np.arange(STATE_DIM)
        m[idx, c + idx] = 0.5
        m[idx, c + STATE_DIM + idx] = -0.5
        m[STATE_DIM, c:] = (1.0 - w0) / (2 * STATE_DIM)
        if c:
            m[STATE_DIM, 0] = w0
        _MOMENTS[key] = m
    return _MOMENTS[key]


def sigma_moments(Z: np.ndarray, w0: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Mean and half differences of the propagated sigma points.

    ``Z`` (..., S, M) holds h at :func:`sigma_points` (same order). Returns ``z_bar``
    (..., M), the weighted mean (the centre has weight ``w0``, the other 2n points share
    ``1 - w0`` equally), and ``D`` (..., 6, M), row j the half difference
    ``(h(x + L_j) - h(x - L_j)) / 2``: the regression Jacobian is ``D^T L^-1``. Both come from
    one matrix product over the sigma points.
    """
    r = _moment_matrix(Z.shape[-2], w0) @ Z  # (..., 7, M)
    return r[..., STATE_DIM, :], r[..., :STATE_DIM, :]


def _linearize_point(x: np.ndarray, h: MeasurementFn) -> tuple[np.ndarray, np.ndarray]:
    """Return (h(x) (B,M), Jacobian (B,M,6)) by central differences at x."""
    B = x.shape[0]
    step = _EPS_JACOBIAN * np.maximum(1.0, np.abs(x))  # (B, 6)
    offsets = np.zeros((B, STATE_DIM, STATE_DIM))
    idx = np.arange(STATE_DIM)
    offsets[:, idx, idx] = step
    pts = np.concatenate([x[:, None, :], x[:, None, :] + offsets, x[:, None, :] - offsets],
                         axis=1)
    Z = h(pts)
    z0, plus, minus = Z[:, 0], Z[:, 1:1 + STATE_DIM], Z[:, 1 + STATE_DIM:]
    J = (plus - minus) / (2 * step[:, :, None])  # (B, 6, M)
    return z0, np.swapaxes(J, 1, 2)


def safe_cholesky(C: np.ndarray) -> np.ndarray:
    """
    Lower Cholesky factors of symmetric (B, n, n) covariances, robust to round-off.

    Falls back to an eigen-decomposition with eigenvalues clipped to a tiny positive floor for
    the matrices that are not numerically positive definite.
    """
    C = 0.5 * (C + np.swapaxes(C, -1, -2))
    try:
        return np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(C)
        floor = np.maximum(np.abs(w).max(axis=-1, keepdims=True) * 1e-12, 1e-300)
        w = np.maximum(w, floor)
        # A symmetric square root; any factor with L L^T = C works for sigma points.
        return V * np.sqrt(w)[..., None, :]


def _information_step(x_prior: np.ndarray, info_prior: np.ndarray, x_i: np.ndarray,
                      z_bar: np.ndarray, H: np.ndarray, z: np.ndarray, r_inv: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """One information-form update; non-finite predictions are left out. Returns (x, Lambda)."""
    valid = np.isfinite(z_bar) & np.isfinite(z) & np.isfinite(H).all(axis=2)
    resid = z - z_bar - (H @ (x_prior - x_i)[..., None])[..., 0]
    resid = np.where(valid, resid, 0.0)
    Hm = np.where(valid[..., None], H, 0.0)
    Ht = np.swapaxes(Hm, 1, 2)
    lam = info_prior + Ht @ (r_inv[..., None] * Hm)
    rhs = (Ht @ (r_inv * resid)[..., None])[..., 0]
    dx = np.linalg.solve(lam, rhs[..., None])[..., 0]
    return x_prior + dx, lam


def _reversed_cholesky(lam: np.ndarray) -> np.ndarray:
    """
    Upper triangular ``U`` (..., 6, 6) with ``lam = U U^T`` (lam symmetric positive definite).

    The lower Cholesky factor of the reversed matrix, reversed: ``chol(lam^-1) = U^-T``.
    Raises LinAlgError when a matrix is not numerically positive definite.
    """
    return np.linalg.cholesky(lam[..., ::-1, ::-1])[..., ::-1, ::-1]


def _upper_inverse(U: np.ndarray) -> np.ndarray:
    """
    Inverses of upper triangular matrices (B, 6, 6).

    In 3 x 3 blocks, ``[[A, C], [0, E]]^-1 = [[A^-1, -A^-1 C E^-1], [0, E^-1]]``, with the
    triangular 3 x 3 inverses in closed form, vectorised over the batch: for many small
    matrices a fraction of ``np.linalg.inv`` (an LU factorisation per matrix); a few go to
    LAPACK.
    """
    if U.shape[0] <= 8 or U.shape[-1] != 6:
        return np.linalg.inv(U)
    B = U.shape[0]
    T = np.stack([U[:, :3, :3], U[:, 3:, 3:]])  # (2, B, 3, 3): A and E
    a, b, c = T[..., 0, 0], T[..., 0, 1], T[..., 0, 2]
    d, e, f = T[..., 1, 1], T[..., 1, 2], T[..., 2, 2]
    ia, id_, if_ = 1.0 / a, 1.0 / d, 1.0 / f
    Ti = np.zeros(T.shape)
    Ti[..., 0, 0], Ti[..., 1, 1], Ti[..., 2, 2] = ia, id_, if_
    Ti[..., 0, 1] = -b * ia * id_
    Ti[..., 1, 2] = -e * id_ * if_
    Ti[..., 0, 2] = (b * e - c * d) * ia * id_ * if_
    V = np.zeros((B, 6, 6))
    V[:, :3, :3], V[:, 3:, 3:] = Ti
    V[:, :3, 3:] = -(Ti[0] @ U[:, :3, 3:] @ Ti[1])
    return V


_LOWER = np.tril(np.ones((STATE_DIM, STATE_DIM)))


def _posterior_factors_one(lam: np.ndarray, rhs: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the step and the next sigma factors of ONE problem (lam (6, 6), rhs (6,)).

    Returns ``(dx (6,), U_inv, U)`` with ``lam = U U^T`` (U upper triangular), by LAPACK
    directly (a few microseconds instead of NumPy's batched wrappers). Raises LinAlgError when
    lam is not numerically positive definite.
    """
    C, info = lapack.dpotrf(lam[::-1, ::-1], lower=1)  # J lam J = C C^T
    if info != 0:
        raise np.linalg.LinAlgError('not positive definite')
    C *= _LOWER  # dpotrf leaves the input in the other triangle
    C_inv, info = lapack.dtrtri(C, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError('singular factor')
    C_inv *= _LOWER
    U, U_inv = C[::-1, ::-1], C_inv[::-1, ::-1]  # U = J C J, U^-1 = J C^-1 J
    return U_inv.T @ (U_inv @ rhs), U_inv, U


class _BaseFilter:
    name = 'base'
    iterated = False
    sigma = False
    posterior_spread = False

    def __init__(self, cfg: FilterConfig) -> None:
        self.cfg = cfg
        self.posterior_spread = self.iterated and cfg.ispkf_spread == 'posterior'
        n = STATE_DIM
        alpha, kappa = cfg.sigma_alpha, cfg.sigma_kappa
        self.lam = alpha ** 2 * (n + kappa) - n
        if n + self.lam <= 0:
            raise ConfigError(f'sigma-point parameters give n + lambda = {n + self.lam} <= 0')
        self.w0 = self.lam / (n + self.lam)
        self.threshold = np.array([cfg.threshold_velocity] * 3 +
                                  [np.deg2rad(cfg.threshold_angular_deg)] * 3)
        self._prior_cache = None

    def update(self, mean: np.ndarray, cov: np.ndarray, h: MeasurementFn, z: np.ndarray,
               noise_var: float | np.ndarray, max_iterations: int | None = None,
               need_cov: bool = True, start: Linearization | None = None) -> FilterOutput:
        """
        Update B priors with measurements; see the module docstring for the equations.

        Parameters
        ----------
        mean : np.ndarray
            (B, 6) prior states.
        cov : np.ndarray
            (B, 6, 6) or (6, 6) prior covariance.
        h : MeasurementFn
            Measurement function, states (B, S, 6) -> (B, S, M) pixels. The sigma-point
            filters solve the problems of one with ``transfer_inputs`` compiled when they
            share the prior (see :class:`~.ransac.BatchedMeasurement`).
        z : np.ndarray
            (B, M) measured pixels (non-finite entries are ignored).
        noise_var : float or np.ndarray
            Measurement noise variance (pixels^2): a scalar, or (B, M) per measurement (R is
            diagonal either way).
        max_iterations : int, optional
            Overrides the configured maximum for iterated filters.
        need_cov : bool
            False: the posterior covariance is not computed (``cov`` is None), e.g. for RANSAC
            hypotheses.
        start : Linearization, optional
            ``linearization`` of an earlier update of this prior with these measurements and
            other noise variances. The sigma-point filters solving one problem take their first
            step with it instead of linearising at the prior; an iterated filter then goes on
            linearising until it converges, and does not stop on that first step. Where it
            does not apply (several problems, the EKF and IEKF, another number of measurements
            or one it used that is now not finite) the update starts at the prior.

        Returns
        -------
        FilterOutput; for one problem of a sigma-point filter its ``linearization`` is the last
        one taken.

        """
        mean = np.asarray(mean, np.float64)
        cov = np.asarray(cov, np.float64)
        z = np.asarray(z, np.float64)
        r_inv = 1.0 / np.asarray(noise_var, np.float64)
        if r_inv.shape != z.shape:
            r_inv = np.broadcast_to(r_inv, z.shape)
        max_it = (max_iterations or self.cfg.max_iterations) if self.iterated else 1
        if self.sigma:
            return self._update_sigma(mean, cov, h, z, r_inv, max_it, need_cov, start)
        return self._update_point(mean, cov, h, z, r_inv, max_it)

    def _update_point(self, mean: np.ndarray, cov: np.ndarray, h: MeasurementFn, z: np.ndarray,
                      r_inv: np.ndarray, max_it: int) -> FilterOutput:
        """EKF / IEKF: linearised at each iterate by central differences."""
        B = mean.shape[0]
        cov = np.broadcast_to(cov, (B, STATE_DIM, STATE_DIM))
        info_prior = np.broadcast_to(np.linalg.inv(cov[0]), cov.shape) if _all_same(cov) \
            else np.linalg.inv(cov)
        x = mean.copy()
        lam = info_prior
        iterations = np.zeros(B, np.int64)
        converged = np.zeros(B, bool)
        active = np.arange(B)
        for _ in range(max_it):
            xa = x[active]
            z_bar, H = _linearize_point(xa, _sub(h, active, B))
            x_new, lam_a = _information_step(mean[active], info_prior[active], xa, z_bar, H,
                                             z[active], r_inv[active])
            if lam is info_prior:
                lam = info_prior.copy()
            lam[active] = lam_a
            iterations[active] += 1
            done = np.all(np.abs(x_new - xa) < self.threshold, axis=1)
            x[active] = x_new
            converged[active[done]] = True
            active = active[~done]
            if active.size == 0:
                break
        return FilterOutput(x, _symmetric_inverse(lam), iterations,
                            converged | (not self.iterated))

    def _prior_terms(self, cov: np.ndarray, scale: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Prior information, sigma factor L and L^-T (contiguous) of a prior covariance.

        One (6, 6) covariance is shared by all problems of a frame (RANSAC, the final update
        and its robust rounds): its terms are kept for the next call with the same matrix.
        """
        key = cov.tobytes() if cov.ndim == 2 else None
        hit = self._prior_cache
        if key is not None and hit is not None and hit[0] == key and hit[1] == scale:
            return hit[2]
        info_prior = np.linalg.inv(cov)  # (6, 6) or (B, 6, 6)
        L = safe_cholesky(cov) * scale
        # L^-T, kept contiguous: stacked matrix products are fast on contiguous operands only.
        L_invT = np.ascontiguousarray(np.swapaxes(np.linalg.inv(L), -1, -2))
        if key is not None:
            self._prior_cache = (key, scale, (info_prior, L, L_invT))
        return info_prior, L, L_invT

    def _update_sigma(self, mean: np.ndarray, cov: np.ndarray, h: MeasurementFn, z: np.ndarray,
                      r_inv: np.ndarray, max_it: int, need_cov: bool,
                      start: Linearization | None = None) -> FilterOutput:
        """
        ISPKF / UKF (see the module docstring).

        All B problems are computed in every iteration (the ones that converged are not
        updated any more): for small problems that is cheaper than regrouping the batch.
        """
        B = mean.shape[0]
        scale = np.sqrt(STATE_DIM + self.lam)
        info_prior, L, L_invT = self._prior_terms(cov, scale)
        if start is not None and not (B == 1 and start.z_bar.shape == z.shape[1:] and np.all(
                np.isfinite(z[0]) if start.valid is None else np.isfinite(z[0]) | ~start.valid)):
            start = None  # one problem only, on these measurements: else start at the prior
        # The transfer model's problems with one prior (RANSAC, the final update) run compiled.
        shared = cov.ndim == 2 and (B == 1 or mean.strides[0] == 0 or
                                    not np.any(mean != mean[0]))
        transfer = getattr(h, 'transfer_inputs', None)
        transfer = transfer() if transfer is not None and shared else None
        if transfer is not None:
            out = self._update_compiled(mean[0], info_prior, L, L_invT, transfer, z, r_inv,
                                        max_it, need_cov, scale, start)
            if out is not None:
                return out
        if B == 1 and cov.ndim == 2:
            return self._update_sigma_one(mean, h, z, r_inv, max_it, need_cov, scale,
                                          info_prior, L, L_invT, start)
        z_ok = np.isfinite(z)
        all_z_ok = bool(z_ok.all())
        # Every sigma point has a non-zero weight in z_bar: a non-finite D shows in z_bar too.
        mean_sees_all = self.w0 != 1.0
        r_inv = r_inv[:, None, :]  # (B, 1, M)
        x = mean
        lam_post = None
        iterations = np.zeros(B, np.int64)
        converged = np.zeros(B, bool)
        active = np.ones(B, bool)
        everyone = True  # all problems active
        for it in range(max_it):
            z_bar, D = sigma_moments(h(sigma_points(x, L, self.w0)), self.w0)
            resid = z - z_bar  # (B, M)
            total = resid.sum() if mean_sees_all else resid.sum() + D.sum()
            if not (all_z_ok and np.isfinite(total)):
                # Non-finite predictions are left out (rows of H with a non-finite entry).
                valid = z_ok & np.isfinite(z_bar) & np.isfinite(D).all(axis=1)
                resid = np.where(valid, resid, 0.0)
                D = np.where(valid[:, None, :], D, 0.0)
            Ht = L_invT @ D  # (B, 6, M): the transposed regression Jacobian H^T = L^-T D
            if it > 0:  # linearised about x_i: z_bar_i + H_i (x_prior - x_i)
                resid -= ((mean - x)[:, None, :] @ Ht)[:, 0]
            HtR = Ht * r_inv
            lam = info_prior + HtR @ np.ascontiguousarray(Ht.swapaxes(1, 2))
            rhs = HtR @ resid[..., None]  # (B, 6, 1)
            L_new = None
            if self.posterior_spread and it + 1 < max_it:
                try:
                    # Lambda = U U^T with U upper triangular, and chol(Lambda^-1) = U^-T.
                    U = np.ascontiguousarray(_reversed_cholesky(lam))
                    U_inv = _upper_inverse(U)
                    dx = ((U_inv @ rhs).swapaxes(1, 2) @ U_inv)[:, 0]  # U^-T U^-1 rhs
                    L_new = U_inv.swapaxes(1, 2) * scale
                    L_invT_new = U / scale
                except np.linalg.LinAlgError:  # not numerically positive definite
                    L_new = safe_cholesky(np.linalg.inv(lam)) * scale
                    L_invT_new = np.ascontiguousarray(np.swapaxes(np.linalg.inv(L_new), 1, 2))
                    dx = np.linalg.solve(lam, rhs)[..., 0]
            else:
                dx = np.linalg.solve(lam, rhs)[..., 0]
            x_new = mean + dx
            done = (np.abs(x_new - x) < self.threshold).all(axis=1)
            iterations += active
            if everyone:
                x, lam_post = x_new, lam
                if L_new is not None:
                    L, L_invT = L_new, L_invT_new
                converged = done
                active = ~done
            else:
                x[active] = x_new[active]
                lam_post[active] = lam[active]
                if L_new is not None:
                    L[active] = L_new[active]
                    L_invT[active] = L_invT_new[active]
                converged |= active & done
                active &= ~done
            if not active.any():
                break
            everyone = bool(active.all())
        cov_post = _symmetric_inverse(lam_post) if need_cov else None
        return FilterOutput(x, cov_post, iterations, converged | (not self.iterated))

    def _update_compiled(self, x0: np.ndarray, info_prior: np.ndarray, L: np.ndarray,
                         L_invT: np.ndarray, transfer: tuple, z: np.ndarray, r_inv: np.ndarray,
                         max_it: int, need_cov: bool, scale: float,
                         start: Linearization | None) -> FilterOutput | None:
        """
        :meth:`_update_sigma` of the transfer model's problems with one prior, compiled.

        ``transfer`` is the measurement function's ``transfer_inputs()``: the frame's transfer
        vectors (4, N), each problem's correspondences (B, n), dt, and the current cameras (see
        :mod:`~.sigma_update`). Returns None where the compiled update met an information
        matrix that is not numerically positive definite: the general code then runs.
        """
        XT, index, dt, W, o = transfer
        B, M = z.shape
        x = np.empty((B, STATE_DIM))
        lam = np.empty((B, STATE_DIM, STATE_DIM))
        iterations = np.empty(B, np.int64)
        converged = np.empty(B, bool)
        last_x, last_zbar = np.empty(STATE_DIM), np.empty(M)
        last_Ht, last_valid = np.empty((STATE_DIM, M)), np.empty(M, bool)
        if start is None:
            begin = (x0, last_zbar, last_Ht, last_valid)
        else:
            begin = (start.x, start.z_bar, np.ascontiguousarray(start.Ht),
                     np.ones(M, bool) if start.valid is None else start.valid)
        failed = sigma_update(
            np.ascontiguousarray(x0), info_prior, L, L_invT, XT, index,
            np.ascontiguousarray(z), np.ascontiguousarray(r_inv), dt, W, o, self.w0, scale,
            self.threshold, max_it, self.posterior_spread, *begin, start is not None,
            x, lam, iterations, converged, last_x, last_zbar, last_Ht, last_valid)
        if failed >= 0:
            return None
        cov_post = _symmetric_inverse(lam) if need_cov else None
        last = None
        if B == 1:
            last = Linearization(last_x, last_zbar, last_Ht,
                                 None if last_valid.all() else last_valid)
        return FilterOutput(x, cov_post, iterations, converged | (not self.iterated), last)

    def _update_sigma_one(self, mean: np.ndarray, h: MeasurementFn, z: np.ndarray,
                          r_inv: np.ndarray, max_it: int, need_cov: bool, scale: float,
                          info_prior: np.ndarray, L: np.ndarray, L_invT: np.ndarray,
                          start: Linearization | None
                          ) -> FilterOutput:
        """:meth:`_update_sigma` for one problem (B = 1, one prior), on 2-D arrays."""
        x0 = mean[0]
        z, r_inv = z[0], r_inv[0]
        z_ok = np.isfinite(z)
        all_z_ok = bool(z_ok.all())
        mean_sees_all = self.w0 != 1.0  # see _update_sigma
        x = x0
        converged = False
        it = 0
        lam = info_prior
        lin = start
        for it in range(max_it):
            if lin is None:
                z_bar, D = sigma_moments(h(sigma_points(x[None], L, self.w0)), self.w0)
                z_bar, D = z_bar[0], D[0]  # (M,), (6, M)
                valid = None
                if not (all_z_ok and np.isfinite(z_bar.sum() if mean_sees_all else
                                                 z_bar.sum() + D.sum())):
                    valid = z_ok & np.isfinite(z_bar) & np.isfinite(D).all(axis=0)
                    D = np.where(valid, D, 0.0)
                lin = Linearization(x.copy(), z_bar, L_invT @ D, valid)  # Ht (6, M)
            resid = z - lin.z_bar
            if lin.valid is not None:
                resid = np.where(lin.valid, resid, 0.0)
            Ht = lin.Ht
            if it > 0 or lin is start:  # linearised about x_i: z_bar_i + H_i (x_prior - x_i)
                resid -= (x0 - lin.x) @ Ht
            HtR = Ht * r_inv
            lam = info_prior + HtR @ Ht.T
            rhs = HtR @ resid
            if self.posterior_spread and it + 1 < max_it:
                try:
                    dx, U_inv, U = _posterior_factors_one(lam, rhs)
                    L = U_inv.T * scale
                    L_invT = np.ascontiguousarray(U) / scale
                except np.linalg.LinAlgError:  # not numerically positive definite
                    L = safe_cholesky(np.linalg.inv(lam)) * scale
                    L_invT = np.ascontiguousarray(np.linalg.inv(L).T)
                    dx = np.linalg.solve(lam, rhs)
            else:
                _, _, dx, info = lapack.dgesv(lam, rhs)
                if info > 0:
                    raise np.linalg.LinAlgError('Singular matrix')
            x_new = x0 + dx
            # A step from another update's linearisation does not end an iterated one.
            converged = lin is not start and bool((np.abs(x_new - x) < self.threshold).all())
            last, lin, x = lin, None, x_new
            if converged:
                break
        cov_post = _symmetric_inverse(lam)[None] if need_cov else None
        return FilterOutput(x[None], cov_post, np.array([it + 1]),
                            np.array([converged or not self.iterated]), last)


def _symmetric_inverse(lam: np.ndarray) -> np.ndarray:
    """Return the inverses of information matrices (..., 6, 6), symmetrised: covariances."""
    cov = np.linalg.inv(lam)
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def _all_same(a: np.ndarray) -> bool:
    """Whether all entries along the first axis are equal (a broadcast prior)."""
    return a.shape[0] <= 1 or a.strides[0] == 0 or not np.any(a != a[0])


def _sub(h: MeasurementFn, active: np.ndarray, B: int) -> MeasurementFn:
    """Restrict a batched measurement function to the active problems."""
    if active.size == B:
        return h
    sub = getattr(h, 'subset', None)
    if sub is None:
        raise TypeError('measurement function of a batched update needs a subset() method')
    return sub(active)


class ISPKF(_BaseFilter):
    """Iterated Sigma Point Kalman Filter (the default, Kitt et al.)."""

    name = 'ispkf'
    iterated = True
    sigma = True


class UKF(_BaseFilter):
    """Unscented Kalman Filter: one sigma-point update around the prior."""

    name = 'ukf'
    sigma = True


class EKF(_BaseFilter):
    """Extended Kalman Filter: one update linearised at the prior."""

    name = 'ekf'


class IEKF(_BaseFilter):
    """Iterated Extended Kalman Filter (Gauss-Newton iterations)."""

    name = 'iekf'
    iterated = True


FILTERS = {cls.name: cls for cls in (ISPKF, UKF, EKF, IEKF)}


def make_filter(cfg: FilterConfig) -> Filter:
    """Return the filter named by ``cfg.type`` (ispkf, iekf, ukf or ekf)."""
    try:
        return FILTERS[cfg.type](cfg)
    except KeyError:
        raise ConfigError(f'unknown filter type {cfg.type!r}; known: {sorted(FILTERS)}') \
            from None
