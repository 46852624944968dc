"""
KITTI odometry folders: reader and writer.

Layout (one sequence)::

    image_0/000000.png ...   left grey images (rectified)
    image_1/000000.png ...   right grey images (rectified)
    calib.txt                lines ``P0: 12 numbers`` and ``P1: 12 numbers`` (3x4, row-major,
                             pixels; ``P1[0, 3] = -fx * baseline``)
    times.txt                optional, one stamp (s) per image
    poses.txt                optional, 12 numbers per image: the 3x4 row-major ``T_world_cam``
                             of the left camera, ``world`` = first left camera frame (metres)

The writer stores floats with ``repr`` so that a round trip is lossless.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np

from ..errors import CalibrationError, DatasetError
from ..estimation.camera import StereoCalibration
from ..records import StereoFrame

logger = logging.getLogger(__name__)

DEFAULT_FRAME_RATE_HZ = 10.0  #: stamps used when times.txt is absent


def _read_numbers(path: Path, per_line: int | None = None) -> list[list[float]]:
    """Read whitespace-separated floats per non-empty line; raise DatasetError if malformed."""
    rows = []
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f'cannot read {str(path)!r}: {exc.strerror}') from None
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            raise DatasetError(f'{str(path)!r} line {number} is not numeric: {line!r}') from None
        if per_line is not None and len(values) != per_line:
            raise DatasetError(f'{str(path)!r} line {number} has {len(values)} numbers, '
                               f'expected {per_line}')
        rows.append(values)
    return rows


def read_calib(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Return the (3, 4) projection matrices P0 and P1 of a KITTI ``calib.txt`` (pixels)."""
    path = Path(path)
    found: dict[str, np.ndarray] = {}
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f'cannot read {str(path)!r}: {exc.strerror}') from None
    for line in lines:
        key, sep, rest = line.partition(':')
        if not sep or key.strip() not in ('P0', 'P1'):
            continue
        try:
            values = np.array([float(v) for v in rest.split()], np.float64)
        except ValueError:
            raise DatasetError(f'{str(path)!r}: {key.strip()} is not numeric: {rest!r}') from None
        if values.size != 12:
            raise DatasetError(f'{str(path)!r}: {key.strip()} has {values.size} numbers, '
                               'expected 12')
        found[key.strip()] = values.reshape(3, 4)
    missing = [k for k in ('P0', 'P1') if k not in found]
    if missing:
        raise DatasetError(f'{str(path)!r} has no {" / ".join(missing)} line(s)')
    return found['P0'], found['P1']


def read_poses(path: str | Path) -> np.ndarray:
    """Return the (N, 4, 4) float64 poses of a KITTI ``poses.txt`` (3x4 row-major per line)."""
    rows = _read_numbers(Path(path), 12)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if rows:
        poses[:, :3, :] = np.asarray(rows, np.float64).reshape(-1, 3, 4)
    return poses


def read_image(path: Path) -> np.ndarray:
    """Read a grey image (uint8 or uint16); colour images are converted to grey."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f'cannot read image {str(path)!r}')
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    return img


class KittiSequence:
    """
    A KITTI-odometry folder as a sequence of StereoFrames with optional ground truth.

    Parameters
    ----------
    path : str or Path
        Folder holding ``image_0/``, ``image_1/`` and ``calib.txt``.

    Attributes
    ----------
    path : Path
        The folder.

    """

    format_name = 'kitti'

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f'KITTI sequence folder {str(self.path)!r} does not exist')
        for name in ('image_0', 'image_1', 'calib.txt'):
            if not (self.path / name).exists():
                raise DatasetError(f'{str(self.path)!r} is not a KITTI sequence: no {name}')
        self._left = sorted((self.path / 'image_0').glob('*.png'))
        names = [p.name for p in self._left]
        right_names = sorted(p.name for p in (self.path / 'image_1').glob('*.png'))
        if not names:
            raise DatasetError(f'{str(self.path / "image_0")!r} holds no PNG images')
        if names != right_names:
            only = sorted(set(names) ^ set(right_names))
            raise DatasetError(f'image_0 and image_1 of {str(self.path)!r} differ: '
                               f'{len(names)} vs {len(right_names)} images, unpaired '
                               f'{only[:5]}')
        first = read_image(self._left[0])
        P0, P1 = read_calib(self.path / 'calib.txt')
        try:
            self._calibration = StereoCalibration.from_projections(P0, P1, first.shape[1],
                                                                   first.shape[0])
        except CalibrationError as exc:
            raise DatasetError(f'{str(self.path / "calib.txt")!r}: {exc}') from None
        times = self.path / 'times.txt'
        if times.exists():
            rows = _read_numbers(times, 1)
            self._stamps = np.array([r[0] for r in rows], np.float64)
            if len(self._stamps) != len(names):
                raise DatasetError(f'{str(times)!r} has {len(self._stamps)} stamps for '
                                   f'{len(names)} images')
        else:
            logger.info('%s has no times.txt; assuming %.1f Hz', self.path, DEFAULT_FRAME_RATE_HZ)
            self._stamps = np.arange(len(names)) / DEFAULT_FRAME_RATE_HZ
        poses = self.path / 'poses.txt'
        self._poses = None
        if poses.exists():
            self._poses = read_poses(poses)
            if len(self._poses) != len(names):
                raise DatasetError(f'{str(poses)!r} has {len(self._poses)} poses for '
                                   f'{len(names)} images')

    @property
    def calibration(self) -> StereoCalibration:
        """Rectified stereo calibration from calib.txt and the image size."""
        return self._calibration

    @property
    def stamps(self) -> np.ndarray:
        """Stamps of the pairs: (N,) float64, seconds."""
        return self._stamps.copy()

    @property
    def ground_truth(self) -> np.ndarray | None:
        """(N, 4, 4) float64 ``T_world_cam`` of the left camera (metres), or None."""
        return None if self._poses is None else self._poses.copy()

    def __len__(self) -> int:
        return len(self._left)

    def __getitem__(self, index: int) -> StereoFrame:
        if not -len(self) <= index < len(self):
            raise IndexError(f'frame {index} outside a sequence of {len(self)}')
        left_path = self._left[index]
        left = read_image(left_path)
        right = read_image(self.path / 'image_1' / left_path.name)
        if left.shape != right.shape or left.shape[::-1] != self._calibration.size:
            raise DatasetError(f'image {left_path.name!r} of {str(self.path)!r} is '
                               f'{left.shape[1]}x{left.shape[0]} (right '
                               f'{right.shape[1]}x{right.shape[0]}), calibration says '
                               f'{self._calibration.size[0]}x{self._calibration.size[1]}')
        return StereoFrame(left, right, float(self._stamps[index]), self._calibration)

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self[i]


def _line(values: Iterable[float]) -> str:
    return ' '.join(repr(float(v)) for v in values)


def write_kitti(path: str | Path, frames: Iterable[StereoFrame],
                poses: np.ndarray | Iterable[np.ndarray] | None = None,
                overwrite: bool = False) -> int:
    """
    Write stereo frames (and optional poses) as a KITTI-odometry folder.

    Parameters
    ----------
    path : str or Path
        Target folder (created).
    frames : iterable of StereoFrame
        Rectified pairs (uint8 or uint16 grey); the first frame's calibration is written.
    poses : array_like, optional
        (N, 4, 4) ``T_world_cam`` of the left camera (metres), one per frame.
    overwrite : bool
        Allow writing into a folder that already holds ``image_0``.

    Returns
    -------
    int
        Number of frames written.

    """
    path = Path(path)
    if (path / 'image_0').exists() and not overwrite:
        raise DatasetError(f'{str(path)!r} already holds a KITTI sequence (overwrite=False)')
    for sub in ('image_0', 'image_1'):
        (path / sub).mkdir(parents=True, exist_ok=True)
    pose_iter = iter(poses) if poses is not None else None
    stamps, pose_rows, calibration, count = [], [], None, 0
    for count, frame in enumerate(frames, 1):
        if calibration is None:
            calibration = frame.calibration
            if calibration.kind != 'rectified':
                raise DatasetError('KITTI folders hold rectified pairs only; got a '
                                   f'{calibration.kind!r} calibration')
        name = f'{count - 1:06d}.png'
        for sub, img in (('image_0', frame.left), ('image_1', frame.right)):
            if not cv2.imwrite(str(path / sub / name), np.ascontiguousarray(img)):
                raise DatasetError(f'cannot write {str(path / sub / name)!r}')
        stamps.append(frame.stamp_s)
        if pose_iter is not None:
            try:
                T = np.asarray(next(pose_iter), np.float64)
            except StopIteration:
                raise DatasetError(f'fewer poses than frames ({count - 1})') from None
            pose_rows.append(_line(T[:3, :4].ravel()))
    if calibration is None:
        raise DatasetError(f'no frames to write to {str(path)!r}')
    P0, P1 = calibration.left.P, calibration.right.P
    (path / 'calib.txt').write_text(f'P0: {_line(P0.ravel())}\nP1: {_line(P1.ravel())}\n')
    (path / 'times.txt').write_text(''.join(f'{float(s)!r}\n' for s in stamps))
    if pose_iter is not None:
        (path / 'poses.txt').write_text(''.join(row + '\n' for row in pose_rows))
    logger.info('wrote %d stereo pairs to %s', count, path)
    return count
