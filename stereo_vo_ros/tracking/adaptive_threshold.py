"""
Adaptive threshold of the light bi-circular check (Huang et al., eq. 8).

``delta_d = rho * loss / maxtrack + epsilon``: the threshold grows when many features are lost
in a frame (sharp turns, large displacements: keep more features with a loose check) and
shrinks towards ``epsilon`` when the oldest feature is old (stable tracking: keep only features
that satisfy a tight check).
"""

from __future__ import annotations

from .klt_checks import CheckSet
from ..config import TrackerConfig


def adaptive_threshold(loss: int, maxtrack: int, rho: float, epsilon_px: float) -> float:
    """
    Return delta_d of eq. 8 (pixels).

    Parameters
    ----------
    loss : int
        Features lost in the current frame before the bi-circular check (count, >= 0).
    maxtrack : int
        Age of the oldest tracked feature (frames); values below 1 count as 1.
    rho : float
        Gain on ``loss / maxtrack`` (pixels per lost feature; paper: 0.23).
    epsilon_px : float
        Floor of the threshold (pixels; paper: 5).

    Returns
    -------
    float
        delta_d (pixels).

    """
    return float(rho) * max(int(loss), 0) / max(int(maxtrack), 1) + float(epsilon_px)


def bicircular_threshold(cfg: TrackerConfig, loss: int, maxtrack: int) -> float:
    """
    Return the bi-circular threshold delta_d (pixels) of the configured variant.

    The ``full`` variant uses eq. 8 with ``cfg.adaptive_rho`` and ``cfg.adaptive_epsilon_px``;
    the others use the fixed ``cfg.bc_threshold_px``.
    """
    if CheckSet.for_variant(cfg.variant).adaptive:
        return adaptive_threshold(loss, maxtrack, cfg.adaptive_rho, cfg.adaptive_epsilon_px)
    return float(cfg.bc_threshold_px)
