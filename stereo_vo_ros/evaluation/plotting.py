"""
Plots of trajectories, errors and timings (the only module that imports matplotlib).

Every ``plot_*`` function draws into an Axes it is given and returns it; ``save_report``
builds its own figure on the Agg canvas and writes a PNG. Nothing here touches pyplot's global
state or calls ``show``, so the module works headless and in threads.

Poses are (N, 4, 4) (or (N, 3, 4)) float ``T_world_cam`` in metres, ``world`` being the first
left camera's optical frame (x right, y down, z forward): the x-z plane is the top view.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import logging
import math
import os
from pathlib import Path

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
import numpy as np

from .metrics import evaluate, path_distances
from .trajectory import as_poses

_LOG = logging.getLogger(__name__)

GT_STYLE = {'color': 'tab:red', 'linewidth': 1.6}
EST_STYLE = {'color': 'tab:blue', 'linewidth': 1.2}


def plot_top_view(ax: Axes, gt: np.ndarray | None, est: np.ndarray | None,
                  gt_label: str = 'ground truth', est_label: str = 'estimate',
                  title: str = 'Top view (x-z plane of the first camera)') -> Axes:
    """
    Draw trajectories seen from above: x (right) horizontally, z (forward) vertically.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Axes to draw into.
    gt, est : array_like or None
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres); either may be None (not both).
        Not modified.
    gt_label, est_label : str
        Legend entries.
    title : str
        Axes title.

    Returns
    -------
    matplotlib.axes.Axes
        ``ax``, with equal aspect, axis labels in metres, a legend and a start marker.

    """
    if gt is None and est is None:
        raise ValueError('plot_top_view needs gt or est, both are None')
    start = None
    for poses, label, style in ((gt, gt_label, GT_STYLE), (est, est_label, EST_STYLE)):
        if poses is None:
            continue
        p = as_poses(poses)[:, :3, 3]
        ax.plot(p[:, 0], p[:, 2], label=label, **style)
        if start is None:
            start = p[0]
    ax.plot([start[0]], [start[2]], 'ks', markersize=6, markerfacecolor='none',
            markeredgewidth=1.5, label='start')
    ax.set_aspect('equal', adjustable='datalim')
    ax.set_xlabel('x (right) [m]')
    ax.set_ylabel('z (forward) [m]')
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc='best', fontsize='small')
    return ax


def plot_error_over_distance(ax: Axes, gt: np.ndarray, est: np.ndarray,
                             title: str = 'Position error (no alignment)') -> Axes:
    """
    Draw the translation error of each frame against the distance travelled.

    The error is ``|p_est[i] - p_gt[i]|`` in ``world`` without any alignment (both
    trajectories start in the first camera frame); the distance is the ground-truth path length
    up to frame ``i``.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Axes to draw into.
    gt, est : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres), same N. Not modified.
    title : str
        Axes title.

    Returns
    -------
    matplotlib.axes.Axes
        ``ax``.

    """
    g = as_poses(gt, 'gt')
    e = as_poses(est, 'est')
    if g.shape[0] != e.shape[0]:
        raise ValueError(f'ground truth has {g.shape[0]} poses but the estimate has '
                         f'{e.shape[0]}')
    dist = path_distances(g)
    err = np.linalg.norm(e[:, :3, 3] - g[:, :3, 3], axis=1)
    ax.plot(dist, err, color='tab:purple', linewidth=1.2, label='|p_est - p_gt|')
    if dist[-1] > 0.0:
        ax.plot(dist, 0.01 * dist, color='0.5', linestyle='--', linewidth=1.0,
                label='1 % of distance')
    ax.set_xlabel('distance travelled [m]')
    ax.set_ylabel('translation error [m]')
    ax.set_title(title)
    ax.set_xlim(left=0.0)
    # scale to the error, not to the reference line (which is clipped when errors are small)
    top = float(np.max(err)) if err.size else 0.0
    ax.set_ylim(0.0, 1.15 * top if top > 0.0 else max(0.01 * float(dist[-1]), 1.0))
    ax.grid(True, alpha=0.3)
    ax.legend(loc='upper left', fontsize='small')
    return ax


def _timing_table(stats: Sequence[Mapping[str, float]]) -> dict[str, np.ndarray]:
    """Turn per-frame dicts of milliseconds into one (N,) float64 array per key (NaN gaps)."""
    keys: list[str] = []
    for row in stats:
        for key, value in row.items():
            if key not in keys and isinstance(value, (int, float, np.number)) \
                    and not isinstance(value, bool):
                keys.append(key)
    table = {}
    for key in keys:
        table[key] = np.array([float(row.get(key, math.nan)) for row in stats])
    return table


def plot_timing(ax: Axes, stats: Sequence[Mapping[str, float]],
                title: str = 'Processing time per frame') -> Axes:
    """
    Draw the per-frame processing time, total and per stage.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Axes to draw into.
    stats : sequence of mapping
        One dict per frame of stage name -> milliseconds (e.g. ``OdometryResult.timings_ms``:
        ``track``, ``estimate``, ``total``). A key missing in a frame is a gap. Without a
        ``total`` key the total is the sum of the stages of that frame.
    title : str
        Axes title.

    Returns
    -------
    matplotlib.axes.Axes
        ``ax``; the legend gives the mean of each curve (ms).

    """
    if len(stats) == 0:
        raise ValueError('plot_timing needs at least one frame of timings, got none')
    table = _timing_table(stats)
    if not table:
        raise ValueError(f'no numeric timing in the first frame: {dict(stats[0])!r}')
    frames = np.arange(len(stats))
    total = table.pop('total', None)
    total_label = 'total'
    if total is None:
        total = np.nansum(np.vstack(list(table.values())), axis=0)
        total_label = 'total (sum of stages)'
    for key, values in table.items():
        ax.plot(frames, values, linewidth=0.9, alpha=0.85,
                label=f'{key} (mean {np.nanmean(values):.1f} ms)')
    ax.plot(frames, total, color='k', linewidth=1.6,
            label=f'{total_label} (mean {np.nanmean(total):.1f} ms)')
    ax.set_xlabel('frame')
    ax.set_ylabel('time [ms]')
    ax.set_title(title)
    ax.set_xlim(0, max(len(stats) - 1, 1))
    top = np.nanmax(total) if np.any(np.isfinite(total)) else 1.0
    ax.set_ylim(0.0, 1.35 * top if top > 0.0 else 1.0)  # headroom for the legend
    ax.grid(True, alpha=0.3)
    ax.legend(loc='upper right', fontsize='small', ncols=2)
    return ax


def _metrics_line(metrics: Mapping[str, float]) -> str:
    """One-line summary of ``metrics.evaluate`` output."""
    parts = []
    if metrics['segments'] > 0:
        parts.append(f"t_rel {metrics['t_rel_pct']:.2f} %")
        parts.append(f"r_rel {metrics['r_rel_deg_per_100m']:.3f} deg/100 m")
        parts.append(f"({metrics['segments']} KITTI segments)")
    else:
        parts.append('KITTI t_rel/r_rel: path < 100 m')
    parts.append(f"ATE {metrics['ate_rmse_m']:.3f} m")
    parts.append(f"end drift {metrics['end_drift_pct']:.3g} %")
    parts.append(f"path {metrics['path_length_m']:.1f} m, {metrics['frames']} frames")
    return ',  '.join(parts)


def save_report(path_png: str | os.PathLike, gt: np.ndarray | None, est: np.ndarray,
                timings: Sequence[Mapping[str, float]] | None = None,
                title: str = 'Stereo visual odometry') -> Path:
    """
    Write one PNG with the top view, the error over distance and the timings.

    Parameters
    ----------
    path_png : str or os.PathLike
        Output PNG (overwritten).
    gt : array_like or None
        (N, 4, 4) or (N, 3, 4) ground-truth ``T_world_cam`` (metres), or None: then only the
        estimate (and the timings) are drawn.
    est : array_like
        (N, 4, 4) or (N, 3, 4) estimated ``T_world_cam`` (metres), same N as ``gt``.
    timings : sequence of mapping or None
        Per-frame stage timings in ms (see ``plot_timing``); None or empty omits the panel.
    title : str
        Figure title; with ground truth a second line gives the metrics of
        ``metrics.evaluate``.

    Returns
    -------
    pathlib.Path
        The file written.

    """
    panels = 1 + (gt is not None) + bool(timings)
    fig = Figure(figsize=(6.0 * panels, 6.0), layout='constrained')
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, panels, squeeze=False)[0]
    plot_top_view(axes[0], gt, est)
    i = 1
    full_title = title
    if gt is not None:
        plot_error_over_distance(axes[i], gt, est)
        i += 1
        full_title += '\n' + _metrics_line(evaluate(gt, est))
    if timings:
        plot_timing(axes[i], timings)
    fig.suptitle(full_title)
    out = Path(path_png)
    fig.savefig(out, dpi=100)
    _LOG.debug('wrote report %s', out)
    return out
