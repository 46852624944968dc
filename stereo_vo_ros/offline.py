"""
Offline runs: drive the pipeline over a sequence and summarise what happened.

Used by ``stereo_vo run`` and the benchmarks; no ROS, no argparse, no progress bar (the caller
passes a callback).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from .config import Config
from .estimation.camera import StereoCalibration
from .pipeline import StereoOdometry
from .records import OdometryResult, RigEstimate, StereoFrame, TrackingStatus


@dataclass
class RunOutput:
    """
    Trajectory and per-frame records of one run.

    Attributes
    ----------
    stamps : (N,) float64 stamps (s) of the accepted frames.
    poses : (N, 4, 4) float64 ``T_world_cam`` of the left camera in the first left camera frame.
    statuses : list of TrackingStatus, one per accepted frame.
    timings : list of dict of milliseconds per stage, one per accepted frame (image loading
        excluded).
    results : the OdometryResult records when ``keep_results`` was set, else empty.
    rig : the online rig estimate after the last frame (``RigEstimate``), None when off.
    calibration : the calibration of the last frame (``StereoCalibration``), None without
        frames.

    """

    stamps: np.ndarray
    poses: np.ndarray
    statuses: list
    timings: list
    results: list = field(default_factory=list)
    rig: RigEstimate | None = None
    calibration: StereoCalibration | None = None


def run_frames(frames: Iterable[StereoFrame], config: Config, max_frames: int | None = None,
               progress: Callable[[OdometryResult], None] | None = None,
               keep_results: bool = False) -> RunOutput:
    """Run the pipeline over frames; ignored frames (non-increasing stamps) are left out."""
    vo = StereoOdometry(config)
    stamps, poses, statuses, timings, results = [], [], [], [], []
    calibration = None
    for i, frame in enumerate(frames):
        if max_frames is not None and i >= max_frames:
            break
        res = vo.process(frame)
        calibration = frame.calibration
        if progress is not None:
            progress(res)
        if not res.accepted:
            continue
        stamps.append(res.stamp_s)
        poses.append(res.T_world_cam)
        statuses.append(res.status)
        timings.append(res.timings_ms)
        if keep_results:
            results.append(res)
    vo.close()  # the last pair's rig update
    rig = vo.rig_estimate()
    return RunOutput(np.asarray(stamps, np.float64),
                     np.asarray(poses, np.float64).reshape(-1, 4, 4), statuses, timings,
                     results, rig, calibration)


def summarize_ms(values: Iterable[float]) -> dict[str, float]:
    """Return mean, median and 95th percentile (ms) of a sequence of timings."""
    v = np.asarray(list(values), np.float64)
    if v.size == 0:
        return {'mean': float('nan'), 'median': float('nan'), 'p95': float('nan')}
    return {'mean': float(v.mean()), 'median': float(np.median(v)),
            'p95': float(np.percentile(v, 95))}


def run_stats(out: RunOutput, wall_s: float | None = None) -> dict:
    """
    Stats JSON of a run.

    ``{"frames": N, "lost_frames": N, "statuses": {...}, "ms": {"total": {"mean", "median",
    "p95"}, "<stage>": {...}}, "rig": {...}}``; the first frame (detection only) is left out of
    the timings; ``rig`` (``RigEstimate.as_dict``: offsets in pixels, angles in degrees, the
    focal ratio in percent, with their stds) only while the rig refinement is on.
    """
    stages: dict[str, list[float]] = {}
    for t in out.timings[1:]:
        for key, value in t.items():
            stages.setdefault(key, []).append(value)
    counts: dict[str, int] = {}
    for s in out.statuses:
        counts[s.value] = counts.get(s.value, 0) + 1
    good = (TrackingStatus.OK, TrackingStatus.INITIALIZING)
    lost = sum(1 for s in out.statuses if s not in good)
    stats = {'frames': len(out.statuses), 'lost_frames': lost, 'statuses': counts,
             'ms': {key: summarize_ms(v) for key, v in sorted(stages.items())}}
    if out.rig is not None:
        stats['rig'] = out.rig.as_dict()
    if wall_s is not None:
        stats['wall_s'] = wall_s
    return stats
