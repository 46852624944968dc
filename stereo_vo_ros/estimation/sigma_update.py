"""
The iterated sigma-point update of the trifocal transfer model, compiled.

:mod:`~.filters` states the update (information form, sigma points re-drawn around each
iterate, the posterior spread) for any measurement function, in NumPy. For the measurement
function of a frame (:class:`~.ransac.BatchedMeasurement`: problems that each see some of the
frame's correspondences) this module runs the same iterations as one compiled loop per problem:
the sigma points, their transfer to pixels (eqs. 6-8, as ``motion._project``), the moments,
the 6 x 6 information matrix and its reversed Cholesky factor. On a KITTI pair RANSAC's 35
hypotheses (3 correspondences each, 3 iterations) take about 0.15 ms this way and an update on
90 inliers about 0.06 ms, against 0.5 and 0.12 ms for the many small NumPy operations of the
general code.

A problem whose information matrix is not numerically positive definite is reported instead of
handled: the caller then runs the general code, which has the fallbacks (and raises where it
raises). Sums run in another order than NumPy's, so the results agree with the general code to
rounding, not to the bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .motion import STATE_DIM
from ..jit import cholesky, finite, kernel, readonly

_F8 = numba.types.float64
_SIGNATURE = numba.types.int64(
    readonly(_F8, 1), readonly(_F8, 2), readonly(_F8, 2), readonly(_F8, 2),  # x0, info, L, LiT
    readonly(_F8, 2), readonly(numba.types.int64, 2),  # XT (4, N), index (B, n)
    readonly(_F8, 2), readonly(_F8, 2),  # z, r_inv (B, 4n)
    _F8, readonly(_F8, 2), readonly(_F8, 1),  # dt, W, o
    _F8, _F8, readonly(_F8, 1), numba.types.int64, numba.types.boolean,  # w0, scale, thr, it, post
    readonly(_F8, 1), readonly(_F8, 1), readonly(_F8, 2), readonly(numba.types.boolean, 1),
    numba.types.boolean,  # start x, z_bar, Ht, valid; has start
    numba.types.Array(_F8, 2, 'C'), numba.types.Array(_F8, 3, 'C'),  # x, lam
    numba.types.Array(numba.types.int64, 1, 'C'), numba.types.Array(numba.types.boolean, 1, 'C'),
    numba.types.Array(_F8, 1, 'C'), numba.types.Array(_F8, 1, 'C'),  # last x, z_bar
    numba.types.Array(_F8, 2, 'C'), numba.types.Array(numba.types.boolean, 1, 'C'))


@kernel()
def _camera(c, s, t, W, o, P):
    """
    Write the stacked current cameras ``[W R^T | o - W R^T t]`` (6, 4) into ``P``.

    ``c`` and ``s`` hold the cosines and sines of the rotation angles about x, y and z over the
    time step (``R = R_Z R_X R_Y``, eq. 6, as ``motion._project``); ``t`` the translation (m).
    """
    cx, cy, cz = c[0], c[1], c[2]
    sx, sy, sz = s[0], s[1], s[2]
    szsx, czsx = sz * sx, cz * sx
    r00, r01, r02 = cz * cy - szsx * sy, -sz * cx, cz * sy + szsx * cy
    r10, r11, r12 = sz * cy + czsx * sy, cz * cx, sz * sy - czsx * cy
    r20, r21, r22 = -cx * sy, sx, cx * cy
    for r in range(6):
        w0, w1, w2 = W[r, 0], W[r, 1], W[r, 2]
        P[r, 0] = w0 * r00 + w1 * r01 + w2 * r02
        P[r, 1] = w0 * r10 + w1 * r11 + w2 * r12
        P[r, 2] = w0 * r20 + w1 * r21 + w2 * r22
        P[r, 3] = o[r] - (P[r, 0] * t[0] + P[r, 1] * t[1] + P[r, 2] * t[2])


@kernel()
def _sigma_cameras(x, L, centre, dt, W, o, Ps):
    """
    Write the cameras of the sigma points of ``x`` (6,) and offsets ``L`` (6, 6) into ``Ps``.

    Order as ``filters.sigma_points``: ``x`` when ``centre``, then ``x + L[:, j]`` and
    ``x - L[:, j]`` for j = 0..5. The angles of a pair are ``a +- d`` with the sines and
    cosines from those of ``a`` and ``d`` (angle addition): half the trigonometric calls.
    """
    ca, sa, cd, sd = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    cp, sp, cm, sm = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    tp, tm = np.empty(3), np.empty(3)
    for i in range(3):
        a = x[3 + i] * dt
        ca[i], sa[i] = math.cos(a), math.sin(a)
        tp[i] = x[i] * dt
    c0 = 1 if centre else 0
    if centre:
        _camera(ca, sa, tp, W, o, Ps[0])
    for j in range(STATE_DIM):
        for i in range(3):
            d = L[3 + i, j] * dt
            cd[i], sd[i] = math.cos(d), math.sin(d)
            cp[i] = ca[i] * cd[i] - sa[i] * sd[i]
            sp[i] = sa[i] * cd[i] + ca[i] * sd[i]
            cm[i] = ca[i] * cd[i] + sa[i] * sd[i]
            sm[i] = sa[i] * cd[i] - ca[i] * sd[i]
            tp[i] = (x[i] + L[i, j]) * dt
            tm[i] = (x[i] - L[i, j]) * dt
        _camera(cp, sp, tp, W, o, Ps[c0 + j])
        _camera(cm, sm, tm, W, o, Ps[c0 + STATE_DIM + j])


@kernel()
def _transfer(P, XT, idx, out):
    """Predicted pixels ``(u_L, v_L, u_R, v_R)`` of the points ``XT[:, idx]`` by cameras ``P``."""
    n = idx.shape[0]
    for k in range(n):
        p = idx[k]
        X0, X1, X2, X3 = XT[0, p], XT[1, p], XT[2, p], XT[3, p]
        h0 = P[0, 0] * X0 + P[0, 1] * X1 + P[0, 2] * X2 + P[0, 3] * X3
        h1 = P[1, 0] * X0 + P[1, 1] * X1 + P[1, 2] * X2 + P[1, 3] * X3
        h2 = P[2, 0] * X0 + P[2, 1] * X1 + P[2, 2] * X2 + P[2, 3] * X3
        h3 = P[3, 0] * X0 + P[3, 1] * X1 + P[3, 2] * X2 + P[3, 3] * X3
        h4 = P[4, 0] * X0 + P[4, 1] * X1 + P[4, 2] * X2 + P[4, 3] * X3
        h5 = P[5, 0] * X0 + P[5, 1] * X1 + P[5, 2] * X2 + P[5, 3] * X3
        out[4 * k] = h0 / h2
        out[4 * k + 1] = h1 / h2
        out[4 * k + 2] = h3 / h5
        out[4 * k + 3] = h4 / h5


@kernel()
def _upper_factor(lam, work, C, U, U_inv):
    """
    ``lam = U U^T`` with U upper triangular, and ``U^-1``; False when not positive definite.

    The lower Cholesky factor of the reversed matrix, reversed (see ``filters``).
    """
    n = STATE_DIM
    for a in range(n):
        for b in range(n):
            work[a, b] = lam[n - 1 - a, n - 1 - b]
    C[:] = 0.0
    cholesky(work, n, C)
    for a in range(n):
        if not C[a, a] > 0.0:
            return False
    for a in range(n):
        for b in range(n):
            U[a, b] = C[n - 1 - a, n - 1 - b]
    # Inverse of the upper triangular U, column by column (back substitution).
    U_inv[:] = 0.0
    for c in range(n):
        U_inv[c, c] = 1.0 / U[c, c]
        for a in range(c - 1, -1, -1):
            s = 0.0
            for k in range(a + 1, c + 1):
                s += U[a, k] * U_inv[k, c]
            U_inv[a, c] = -s / U[a, a]
    return True


@kernel(_SIGNATURE)
def sigma_update(x0, info_prior, L0, LiT0, XT, index, z, r_inv, dt, W, o, w0, scale,
                 threshold, max_it, posterior, start_x, start_zbar, start_Ht, start_valid,
                 has_start, x_out, lam_out, iterations, converged, last_x, last_zbar, last_Ht,
                 last_valid):
    """
    Run the iterated sigma-point update of B problems with one prior (``filters``).

    Parameters (arrays C-contiguous)
    --------------------------------
    x0, info_prior, L0, LiT0
        The prior state (6,) (m/s, rad/s), its information (6, 6), the sigma-point offsets
        ``L0`` (columns, scaled by ``scale``) and ``L0^-T``.
    XT, index
        The frame's transfer vectors (4, N); problem b sees the correspondences ``index[b]``
        (B, n), so it has ``M = 4 n`` measurements, point by point ``(u_L, v_L, u_R, v_R)``.
    z, r_inv
        (B, M) measured pixels (non-finite: not used) and inverse noise variances (px^-2).
    dt, W, o
        Time step (s) and the current cameras (``TransferModel``).
    w0, scale, threshold, max_it, posterior
        Centre weight, ``sqrt(n + lambda)``, the per-component termination threshold (6,),
        the iteration limit, and whether the next iterate's sigma points spread by the latest
        posterior (ISPKF) rather than the prior.
    start_x, start_zbar, start_Ht, start_valid, has_start
        With ``has_start`` (one problem), the linearisation the first step uses
        (``filters.Linearization``; ``start_valid`` all True when it used every measurement).
    x_out, lam_out, iterations, converged
        Written: each problem's posterior mean (B, 6), information (B, 6, 6), iterations and
        whether it met the threshold.
    last_x, last_zbar, last_Ht, last_valid
        Written: the last problem's last linearisation.

    Returns -1, or the first problem whose information matrix was not numerically positive
    definite (the outputs are then incomplete).
    """
    B, n = index.shape
    M = 4 * n
    c0 = 1 if w0 != 0.0 else 0
    wi = (1.0 - w0) / (2 * STATE_DIM)
    shared = np.empty((c0 + 2 * STATE_DIM, 6, 4))
    own = np.empty_like(shared)
    _sigma_cameras(x0, L0, c0 == 1, dt, W, o, shared)
    plus = np.empty(M)
    minus = np.empty(M)
    zbar = np.empty(M)
    D = np.empty((STATE_DIM, M))
    Ht = np.empty((STATE_DIM, M))
    valid = np.empty(M, np.bool_)
    resid = np.empty(M)
    L = np.empty((STATE_DIM, STATE_DIM))
    LiT = np.empty((STATE_DIM, STATE_DIM))
    lam = np.empty((STATE_DIM, STATE_DIM))
    rhs = np.empty(STATE_DIM)
    dx = np.empty(STATE_DIM)
    y = np.empty(STATE_DIM)
    x = np.empty(STATE_DIM)
    xl = np.empty(STATE_DIM)
    work = np.empty((STATE_DIM, STATE_DIM))
    C = np.empty((STATE_DIM, STATE_DIM))
    U = np.empty((STATE_DIM, STATE_DIM))
    U_inv = np.empty((STATE_DIM, STATE_DIM))
    for b in range(B):
        idx = index[b]
        zb, rb = z[b], r_inv[b]
        x[:] = x0
        L[:] = L0
        LiT[:] = LiT0
        from_start = has_start
        done = False
        it = 0
        for it in range(max_it):
            if from_start:
                xl[:] = start_x
                zbar[:] = start_zbar
                Ht[:] = start_Ht
                valid[:] = start_valid
            else:
                xl[:] = x
                # The first iterate's sigma points are the prior's, shared by all problems.
                Ps = shared
                if it > 0:
                    Ps = own
                    _sigma_cameras(x, L, c0 == 1, dt, W, o, own)
                if c0:
                    _transfer(Ps[0], XT, idx, plus)
                    for m in range(M):
                        zbar[m] = w0 * plus[m]
                else:
                    zbar[:] = 0.0
                for j in range(STATE_DIM):
                    _transfer(Ps[c0 + j], XT, idx, plus)
                    _transfer(Ps[c0 + STATE_DIM + j], XT, idx, minus)
                    for m in range(M):
                        zbar[m] += wi * (plus[m] + minus[m])
                        D[j, m] = 0.5 * (plus[m] - minus[m])
                for m in range(M):
                    ok = finite(zb[m]) and finite(zbar[m])
                    for j in range(STATE_DIM):
                        ok = ok and finite(D[j, m])
                    valid[m] = ok
                    for i in range(STATE_DIM):
                        s = 0.0
                        if ok:
                            for j in range(STATE_DIM):
                                s += LiT[i, j] * D[j, m]
                        Ht[i, m] = s
            # Linearised about x_i: z_bar_i + H_i (x_prior - x_i).
            shift = it > 0 or from_start
            for i in range(STATE_DIM):
                y[i] = x0[i] - xl[i]
            for m in range(M):
                r = 0.0
                if valid[m]:
                    r = zb[m] - zbar[m]
                    if shift:
                        for i in range(STATE_DIM):
                            r -= y[i] * Ht[i, m]
                resid[m] = r
            for i in range(STATE_DIM):
                s = 0.0
                for m in range(M):
                    s += Ht[i, m] * rb[m] * resid[m]
                rhs[i] = s
                for j in range(i + 1):
                    s = 0.0
                    for m in range(M):
                        s += Ht[i, m] * rb[m] * Ht[j, m]
                    lam[i, j] = info_prior[i, j] + s
                    lam[j, i] = info_prior[j, i] + s
            if not _upper_factor(lam, work, C, U, U_inv):
                return b
            # dx = lam^-1 rhs = U^-T U^-1 rhs
            for a in range(STATE_DIM):
                s = 0.0
                for k in range(a, STATE_DIM):
                    s += U_inv[a, k] * rhs[k]
                y[a] = s
            for a in range(STATE_DIM):
                s = 0.0
                for k in range(a + 1):
                    s += U_inv[k, a] * y[k]
                dx[a] = s
            if posterior and it + 1 < max_it:
                for a in range(STATE_DIM):
                    for k in range(STATE_DIM):
                        L[a, k] = U_inv[k, a] * scale
                        LiT[a, k] = U[a, k] / scale
            done = not from_start
            for i in range(STATE_DIM):
                step = x0[i] + dx[i]
                done = done and abs(step - x[i]) < threshold[i]
                x[i] = step
            from_start = False
            if done:
                break
        x_out[b] = x
        lam_out[b] = lam
        iterations[b] = it + 1
        converged[b] = done
        if b == B - 1:
            last_x[:] = xl
            last_zbar[:] = zbar
            last_Ht[:] = Ht
            last_valid[:] = valid
    return -1
