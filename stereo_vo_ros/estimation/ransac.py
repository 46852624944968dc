"""
RANSAC outlier rejection (Kitt et al., section III-D).

Minimal samples of ``s = 3`` correspondences; the number of samples follows eq. 14,
``n = log(1 - p) / log(1 - (1 - eps)^s)``. Every sample gives a motion hypothesis from the filter
update on its 3 correspondences (all hypotheses are solved in one batched update); inliers are
correspondences whose Euclidean reprojection error is below a threshold in BOTH current images;
the hypothesis with most inliers wins (ties: smaller summed inlier error), and the caller runs the
final update on all of its inliers.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from .filters import Filter, STATE_DIM
from .motion import TransferModel
from ..config import RansacConfig

SAMPLE_SIZE = 3


def num_samples(probability: float, outlier_ratio: float, sample_size: int = SAMPLE_SIZE,
                max_samples: int | None = None) -> int:
    """Eq. 14: samples needed so that one is outlier-free with the given probability."""
    if outlier_ratio <= 0.0:
        n = 1
    else:
        good = (1.0 - outlier_ratio) ** sample_size
        n = 1 if good >= 1.0 else math.ceil(math.log(1.0 - probability) / math.log(1.0 - good))
    n = max(n, 1)
    return min(n, max_samples) if max_samples else n


class BatchedMeasurement:
    """
    h for B problems that each use their own correspondences (a subset of the frame's).

    The sigma-point filters solve these problems compiled (:mod:`~.sigma_update`, through
    :meth:`transfer_inputs`); the other filters, and the sigma-point ones where the compiled
    update does not apply, call it as a measurement function.

    Parameters
    ----------
    model : TransferModel
        Measurement model of the frame.
    X : np.ndarray or None
        (B, n, 4) transfer vectors of each problem, or None for all of the frame's (shared).
    index : np.ndarray, optional
        (B, n) indices of each problem's correspondences in the frame (instead of ``X``).

    """

    def __init__(self, model: TransferModel, X: np.ndarray | None = None,
                 index: np.ndarray | None = None) -> None:
        self.model = model
        self.index = None if index is None else np.asarray(index, np.intp)
        self._X = X

    @property
    def X(self) -> np.ndarray | None:
        """(B, n, 4) transfer vectors of each problem, or None for all of the frame's."""
        if self._X is None and self.index is not None:
            # (B, n, 4) as a view of a contiguous (B, 4, n): the layout of the products.
            self._X = np.swapaxes(np.ascontiguousarray(
                np.swapaxes(self.model.X[self.index], 1, 2)), 1, 2)
        return self._X

    def __call__(self, states: np.ndarray) -> np.ndarray:
        """Map states (B, S, 6) to predicted pixels (B, S, 4n)."""
        pred = self.model.predict(states, self.X)
        return pred.reshape(pred.shape[:-2] + (-1,))

    def subset(self, idx: np.ndarray) -> 'BatchedMeasurement':
        """Return the measurement function of problems ``idx``."""
        if self.index is not None:
            return BatchedMeasurement(self.model, index=self.index[idx])
        return BatchedMeasurement(self.model, None if self.X is None else self.X[idx])

    def transfer_inputs(self) -> tuple | None:
        """
        Return what the compiled update (:mod:`~.sigma_update`) needs, or None (no ``index``).

        The frame's transfer vectors (4, N), each problem's correspondences (B, n), the time
        step (s) and the current cameras ``W`` (6, 3), ``o`` (6,) (see ``TransferModel``).
        """
        if self.index is None:
            return None
        m = self.model
        return np.ascontiguousarray(m.X.T), np.ascontiguousarray(self.index), m.dt, m.W, m.o


def reprojection_errors(model: TransferModel, states: np.ndarray, z: np.ndarray,
                        scale: np.ndarray | None = None, index: np.ndarray | None = None
                        ) -> np.ndarray:
    """
    Euclidean reprojection error in the current images.

    Parameters
    ----------
    model : TransferModel
        Measurement model of the frame.
    states : np.ndarray
        (H, 6) hypotheses (m/s, rad/s).
    z : np.ndarray
        (N, 4) measured (u_L, v_L, u_R, v_R) pixels.
    scale : np.ndarray, optional
        (N, 2) factors dividing the left and right image errors (the residual standard
        deviation relative to the nominal pixel noise, see ``previous_noise_gain``).
    index : np.ndarray, optional
        Only these correspondences (indices or a mask into the N): ``z`` and ``scale`` are
        still the full arrays.

    Returns
    -------
    (H, N) float64 (or (H, len(index))): the larger of the left and right image errors
    (pixels, scaled), inf when undefined.

    """
    X = None
    if index is not None:
        X, z = model.X[index], z[index]
        scale = None if scale is None else scale[index]
    d = model.predict_planes(np.asarray(states, np.float64).reshape(-1, STATE_DIM).T, X)
    d -= z.T[:, None, :]  # (4, H, N)
    d *= d
    e_left, e_right = d[0] + d[1], d[2] + d[3]  # squared errors (H, N)
    if scale is not None:
        w = 1.0 / (scale * scale)
        e_left *= w[:, 0]
        e_right *= w[:, 1]
    err = np.sqrt(np.maximum(e_left, e_right, out=e_left), out=e_left)
    if not np.isfinite(err.sum()):
        err[np.isnan(err)] = np.inf  # undefined (+inf stays)
    return err


def draw_samples(rng: np.random.Generator, n_hyp: int, N: int,
                 sample_size: int = SAMPLE_SIZE) -> np.ndarray:
    """
    Return (n_hyp, sample_size) indices: each row the positions of the smallest of N uniforms.

    The same indices in the same order as ``np.argpartition(u, sample_size - 1, axis=1)[:, :s]``
    (which sorts the first few by selection for a small ``s``), in a fraction of its time.
    """
    u = rng.random((n_hyp, N))
    rows = np.arange(n_hyp)
    out = np.empty((n_hyp, sample_size), np.intp)
    for k in range(sample_size):
        out[:, k] = i = u.argmin(axis=1)
        u[rows, i] = np.inf
    return out


@dataclass
class RansacResult:
    """
    Best hypothesis of a RANSAC run.

    Attributes
    ----------
    inliers : (N,) bool inliers of the best hypothesis.
    state : (6,) best hypothesis (m/s, rad/s).
    hypotheses : int samples drawn.
    errors : (N,) scaled reprojection error of every point under the best hypothesis (pixels).

    """

    inliers: np.ndarray
    state: np.ndarray
    hypotheses: int
    errors: np.ndarray


def ransac(model: TransferModel, z: np.ndarray, prior_mean: np.ndarray, prior_cov: np.ndarray,
           filt: Filter, noise_var: np.ndarray, cfg: RansacConfig, rng: np.random.Generator,
           scale: np.ndarray | None = None, weights: np.ndarray | None = None) -> RansacResult:
    """
    Select the inliers of the best 3-point hypothesis.

    Parameters
    ----------
    model : TransferModel
        Measurement model of the frame (N correspondences).
    z : np.ndarray
        (N, 4) measured current pixels.
    prior_mean : np.ndarray
        (6,) predicted state.
    prior_cov : np.ndarray
        (6, 6) predicted covariance.
    filt : Filter
        The filter that turns a sample into a hypothesis.
    noise_var : np.ndarray
        (N, 4) variance of each measurement (pixels^2).
    cfg : RansacConfig
        RANSAC configuration.
    rng : np.random.Generator
        Random generator (seeded by the caller for repeatable runs).
    scale : np.ndarray, optional
        (N, 2) error scale per point and image (see :func:`reprojection_errors`).
    weights : np.ndarray, optional
        (N,) weight of each point in the inlier count (default 1: the plain count of paper
        1; the estimator weights points on the ground plane).

    Returns
    -------
    RansacResult

    """
    N = len(z)
    n_hyp = num_samples(cfg.probability, cfg.outlier_ratio, SAMPLE_SIZE, cfg.max_hypotheses)
    samples = draw_samples(rng, n_hyp, N)  # (H, 3)
    zs = z[samples].reshape(n_hyp, -1)  # (H, 12)
    var = np.broadcast_to(noise_var, z.shape)[samples].reshape(n_hyp, -1)
    out = filt.update(np.broadcast_to(prior_mean, (n_hyp, 6)), prior_cov,
                      BatchedMeasurement(model, index=samples), zs, var,
                      max_iterations=cfg.hypothesis_iterations, need_cov=False)
    err = reprojection_errors(model, out.mean, z, scale)  # (H, N)
    inl = err < cfg.inlier_threshold_px
    count = np.count_nonzero(inl, axis=1) if weights is None else \
        inl @ np.asarray(weights, np.float64)
    score = np.where(inl, err, 0.0).sum(axis=1)
    best = int(np.lexsort((score, -count))[0])
    return RansacResult(inliers=inl[best], state=out.mean[best], hypotheses=n_hyp,
                        errors=err[best])
