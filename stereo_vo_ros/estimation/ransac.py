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

from .filters import Filter
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

    Parameters
    ----------
    model : TransferModel
        Measurement model of the frame.
    X : np.ndarray or None
        (B, n, 4) transfer vectors of each problem, or None for all of the frame's (shared).

    """

    def __init__(self, model: TransferModel, X: np.ndarray | None = None) -> None:
        self.model = model
        self.X = X

    def __call__(self, states: np.ndarray) -> np.ndarray:
        """Map states (B, S, 6) to predicted pixels (B, S, 4n)."""
        pred = self.model.predict(states, self.X)
        return pred.reshape(pred.shape[:2] + (-1,))

    def subset(self, idx: np.ndarray) -> 'BatchedMeasurement':
        """Return the measurement function of problems ``idx``."""
        return BatchedMeasurement(self.model, None if self.X is None else self.X[idx])


def reprojection_errors(model: TransferModel, states: np.ndarray, z: np.ndarray,
                        scale: np.ndarray | None = None) -> np.ndarray:
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

    Returns
    -------
    (H, N) float64: the larger of the left and right image errors (pixels, scaled), inf when
    undefined.

    """
    pred = model.predict(states)  # (H, N, 4)
    d = pred - z[None]
    e_left, e_right = np.hypot(d[..., 0], d[..., 1]), np.hypot(d[..., 2], d[..., 3])
    if scale is not None:
        e_left, e_right = e_left / scale[:, 0], e_right / scale[:, 1]
    err = np.maximum(e_left, e_right)
    return np.where(np.isfinite(err), err, np.inf)


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
    samples = np.argpartition(rng.random((n_hyp, N)), SAMPLE_SIZE - 1, axis=1)[:, :SAMPLE_SIZE]
    X = model.X[samples]  # (H, 3, 4)
    zs = z[samples].reshape(n_hyp, -1)  # (H, 12)
    var = np.broadcast_to(noise_var, z.shape)[samples].reshape(n_hyp, -1)
    out = filt.update(np.broadcast_to(prior_mean, (n_hyp, 6)), prior_cov,
                      BatchedMeasurement(model, X), zs, var,
                      max_iterations=cfg.hypothesis_iterations)
    err = reprojection_errors(model, out.mean, z, scale)  # (H, N)
    inl = err < cfg.inlier_threshold_px
    count = inl.sum(axis=1) if weights is None else inl @ np.asarray(weights, np.float64)
    score = np.where(inl, err, 0.0).sum(axis=1)
    best = int(np.lexsort((score, -count))[0])
    return RansacResult(inliers=inl[best], state=out.mean[best], hypotheses=n_hyp,
                        errors=err[best])
