# noqa: A005 (the subpackage of data input/output; absolute imports keep the standard io)
"""
Stereo sequences on disk: one small class per format, chosen by ``open_sequence``.

Every sequence offers the same protocol (``Sequence``): ``calibration``, ``stamps`` (s),
``ground_truth`` ((N, 4, 4) ``T_world_cam`` of the left camera or None), ``len()`` and
iteration over ``StereoFrame`` records.

Formats (``FORMATS``):

* ``kitti``: a KITTI-odometry folder (``image_0/``, ``image_1/``, ``calib.txt``, optional
  ``times.txt`` and ``poses.txt``);
* ``rosbag``: a rosbag2 folder (``metadata.yaml``) or a single ``.db3`` / ``.mcap`` file;
* ``synthetic``: ``synthetic:<preset>`` renders a ``SequenceSpec`` preset on the fly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

import numpy as np

from .kitti import KittiSequence, write_kitti
from .rosbag import BagTopics, RosbagSequence, write_stereo_bag
from ..errors import DatasetError
from ..estimation.camera import StereoCalibration
from ..records import StereoFrame
from ..synthetic import SequenceSpec, StereoRenderer, SyntheticSequence

__all__ = ['BagTopics', 'FORMATS', 'KittiSequence', 'RosbagSequence', 'Sequence',
           'SyntheticSequence', 'detect_format', 'open_sequence', 'render_to_bag',
           'render_to_kitti', 'write_kitti', 'write_stereo_bag']

SYNTHETIC_PREFIX = 'synthetic:'


class Sequence(Protocol):
    """What every dataset class offers."""

    @property
    def calibration(self) -> StereoCalibration:
        """Stereo calibration of the first pair."""

    @property
    def stamps(self) -> np.ndarray:
        """Stamps of the pairs: (N,) float64, seconds."""

    @property
    def ground_truth(self) -> np.ndarray | None:
        """(N, 4, 4) float64 ``T_world_cam`` of the left camera (metres), or None."""

    def __len__(self) -> int:
        """Return the number of stereo pairs."""

    def __iter__(self) -> Iterator[StereoFrame]:
        """Yield the stereo pairs in order."""


def _open_kitti(path: Path, config: Any) -> Sequence:
    return KittiSequence(path)


def _open_rosbag(path: Path, config: Any) -> Sequence:
    topics = BagTopics.from_config(config.ros) if config is not None else BagTopics()
    kind = config.pipeline.input_kind if config is not None else 'rectified'
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        path = _single_storage_file(path)
    return RosbagSequence(path, topics, kind)


def _open_synthetic(path: Path | str, config: Any) -> Sequence:
    return SyntheticSequence(SequenceSpec.preset(str(path)[len(SYNTHETIC_PREFIX):]))


#: format name -> opener(path, config)
FORMATS: dict[str, Callable[[Any, Any], Sequence]] = {
    'kitti': _open_kitti,
    'rosbag': _open_rosbag,
    'synthetic': _open_synthetic,
}


def _single_storage_file(folder: Path) -> Path:
    files = sorted(p for p in folder.iterdir() if p.suffix in ('.db3', '.mcap'))
    if len(files) != 1:
        raise DatasetError(f'{str(folder)!r} has no metadata.yaml and {len(files)} .db3/.mcap '
                           'files (need exactly one)')
    return files[0]


def detect_format(path: str | Path) -> str:
    """
    Return the format name of a sequence path (see ``FORMATS``).

    Raises
    ------
    DatasetError
        The path does not exist or is of no known format.

    """
    if str(path).startswith(SYNTHETIC_PREFIX):
        return 'synthetic'
    path = Path(path)
    if not path.exists():
        raise DatasetError(f'sequence path {str(path)!r} does not exist')
    if path.is_file():
        if path.suffix in ('.db3', '.mcap'):
            return 'rosbag'
        raise DatasetError(f'{str(path)!r} is not a .db3 or .mcap bag file')
    if (path / 'image_0').is_dir():
        return 'kitti'
    if (path / 'metadata.yaml').exists() or any(
            p.suffix in ('.db3', '.mcap') for p in path.iterdir()):
        return 'rosbag'
    raise DatasetError(f'{str(path)!r} is neither a KITTI folder (image_0/) nor a rosbag2 '
                       '(metadata.yaml, .db3 or .mcap)')


def open_sequence(path: str | Path, config: Any = None, fmt: str | None = None) -> Sequence:
    """
    Open a stereo sequence, choosing the reader from the path (or ``fmt``).

    Parameters
    ----------
    path : str or Path
        KITTI folder, rosbag2 folder / file, or ``synthetic:<preset>``.
    config : Config, optional
        Bag topics come from ``config.ros.*_topic``, the calibration kind from
        ``config.pipeline.input_kind``.
    fmt : str, optional
        Force a format of ``FORMATS``.

    """
    fmt = fmt or detect_format(path)
    if fmt not in FORMATS:
        raise DatasetError(f'unknown sequence format {fmt!r}; known: {sorted(FORMATS)}')
    if fmt == 'synthetic':
        return FORMATS[fmt](path, config)
    return FORMATS[fmt](Path(path), config)


def render_to_kitti(spec: SequenceSpec, path: str | Path, overwrite: bool = False) -> Path:
    """Render a synthetic sequence into a KITTI folder (images, calib, times, poses)."""
    renderer = StereoRenderer(spec)
    write_kitti(path, renderer.frames(), renderer.poses, overwrite=overwrite)
    return Path(path)


def render_to_bag(spec: SequenceSpec, path: str | Path, storage: str = 'sqlite3',
                  encoding: str = 'mono8', topics: BagTopics = BagTopics()) -> Path:
    """Render a synthetic sequence into a rosbag2 (images, camera infos, ground truth)."""
    renderer = StereoRenderer(spec)
    write_stereo_bag(path, renderer.frames(), renderer.calibration, renderer.poses,
                     storage=storage, encoding=encoding, topics=topics)
    return Path(path)
