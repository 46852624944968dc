"""
Trajectory files in the formats evo and the KITTI devkit read: KITTI and TUM.

Both formats hold camera poses ``T_world_cam`` (4x4, camera to world, metres): the pose of the
left camera optical frame (x right, y down, z forward) in ``world``, which for this package is
the optical frame of the first left camera of the run.

* KITTI odometry: one pose per line, 12 numbers, the upper 3x4 block of ``T_world_cam`` in
  row-major order; no stamps.
* TUM RGB-D: one pose per line, ``stamp x y z qx qy qz qw`` (seconds, metres, unit quaternion
  with the scalar last); lines starting with ``#`` are comments.

Files are written at full precision: every number is the shortest decimal string that reads
back to the same float64 (Python ``repr``), so positions and stamps round-trip exactly and a
KITTI pose round-trips bit for bit.
"""

from __future__ import annotations

import logging
import os
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import DatasetError

_LOG = logging.getLogger(__name__)

KITTI_COLUMNS = 12  #: numbers per line of a KITTI pose file
TUM_COLUMNS = 8  #: numbers per line of a TUM trajectory file
ROTATION_TOLERANCE = 1e-2  #: largest |R R^T - I| element or | |q| - 1 | accepted when reading
TUM_HEADER = '# timestamp tx ty tz qx qy qz qw'

PathLike = str | os.PathLike


class Trajectory(NamedTuple):
    """
    Poses read from a trajectory file.

    Attributes
    ----------
    poses : np.ndarray
        (N, 4, 4) float64 ``T_world_cam`` (camera to world, metres).
    stamps : np.ndarray or None
        (N,) float64 stamps (s) for TUM files, None for KITTI files.
    file_format : str
        ``'kitti'`` or ``'tum'``.

    """

    poses: np.ndarray
    stamps: np.ndarray | None
    file_format: str


def as_poses(poses: np.ndarray, name: str = 'poses') -> np.ndarray:
    """
    Return a validated float64 copy of a pose array as (N, 4, 4) homogeneous transforms.

    Parameters
    ----------
    poses : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres). The input is never modified.
    name : str
        Name used in error messages.

    Returns
    -------
    np.ndarray
        (N, 4, 4) float64 copy with the last row set to ``[0, 0, 0, 1]``.

    Raises
    ------
    ValueError
        On a wrong shape, non-finite values or a 4x4 input whose last row is not
        ``[0, 0, 0, 1]``.

    """
    arr = np.array(poses, dtype=np.float64, copy=True)
    if arr.ndim != 3 or arr.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f'{name} must have shape (N, 4, 4) or (N, 3, 4), got {arr.shape}')
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(arr.reshape(len(arr), -1)), axis=1))[0])
        raise ValueError(f'{name}[{bad}] has non-finite values')
    if arr.shape[1] == 4:
        bottom = arr[:, 3, :]
        wrong = np.any(bottom != np.array([0.0, 0.0, 0.0, 1.0]), axis=1)
        if np.any(wrong):
            bad = int(np.flatnonzero(wrong)[0])
            raise ValueError(f'{name}[{bad}] last row is {bottom[bad].tolist()}, '
                             'expected [0, 0, 0, 1]')
        return arr
    out = np.zeros((arr.shape[0], 4, 4))
    out[:, :3, :] = arr
    out[:, 3, 3] = 1.0
    return out


def _parse_rows(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """
    Read the numeric rows of a whitespace (or comma) separated file.

    Returns
    -------
    rows : (N, C) float64 values.
    line_numbers : (N,) int64 1-based line number of each row in the file.

    """
    try:
        with open(path, encoding='utf-8') as fh:
            text = fh.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f'cannot read trajectory file {os.fspath(path)!r}: {exc}') from exc
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    columns = None
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith('#'):
            continue
        tokens = stripped.replace(',', ' ').split()
        if columns is None:
            columns = len(tokens)
        if len(tokens) != columns:
            raise DatasetError(f'{os.fspath(path)}:{number}: {len(tokens)} numbers, expected '
                               f'{columns} like the first pose line')
        try:
            values = [float(tok) for tok in tokens]
        except ValueError as exc:
            raise DatasetError(f'{os.fspath(path)}:{number}: not a number ({exc})') from None
        rows.append(values)
        line_numbers.append(number)
    if not rows:
        raise DatasetError(f'trajectory file {os.fspath(path)!r} contains no pose')
    arr = np.array(rows, dtype=np.float64)
    lines = np.array(line_numbers, dtype=np.int64)
    finite = np.all(np.isfinite(arr), axis=1)
    if not np.all(finite):
        bad = int(np.flatnonzero(~finite)[0])
        raise DatasetError(f'{os.fspath(path)}:{lines[bad]}: non-finite value')
    return arr, lines


def _check_rotations(path: PathLike, rot: np.ndarray, lines: np.ndarray) -> None:
    """Raise DatasetError naming the first line whose (3, 3) matrix is not a rotation."""
    gram = np.einsum('nij,nkj->nik', rot, rot) - np.eye(3)
    err = np.max(np.abs(gram), axis=(1, 2))
    bad = (err > ROTATION_TOLERANCE) | (np.linalg.det(rot) <= 0.0)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise DatasetError(f'{os.fspath(path)}:{lines[i]}: the 3x3 block is not a rotation '
                           f'(max |R R^T - I| = {err[i]:.3g}, det = {np.linalg.det(rot[i]):.3g})')


def read_kitti(path: PathLike) -> np.ndarray:
    """
    Read a KITTI odometry pose file.

    Parameters
    ----------
    path : str or os.PathLike
        File with 12 numbers per line (row-major 3x4 ``T_world_cam``).

    Returns
    -------
    np.ndarray
        (N, 4, 4) float64 ``T_world_cam`` (metres).

    Raises
    ------
    DatasetError
        Unreadable file, no pose, a line with another number of values or a non-number, a
        non-finite value, or a 3x3 block that is not a rotation (tolerance
        ``ROTATION_TOLERANCE``). The message names the file and the line.

    """
    return _kitti_from_rows(path, *_parse_rows(path))


def _kitti_from_rows(path: PathLike, rows: np.ndarray, lines: np.ndarray) -> np.ndarray:
    if rows.shape[1] != KITTI_COLUMNS:
        raise DatasetError(f'{os.fspath(path)}:{lines[0]}: {rows.shape[1]} numbers per line, '
                           f'a KITTI pose file has {KITTI_COLUMNS}')
    poses = np.zeros((rows.shape[0], 4, 4))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    _check_rotations(path, poses[:, :3, :3], lines)
    return poses


def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """
    Read a TUM trajectory file (``stamp x y z qx qy qz qw`` per line).

    Parameters
    ----------
    path : str or os.PathLike
        TUM file; lines starting with ``#`` and blank lines are skipped.

    Returns
    -------
    stamps : np.ndarray
        (N,) float64 stamps (s), non-decreasing.
    poses : np.ndarray
        (N, 4, 4) float64 ``T_world_cam`` (metres); quaternions are normalised.

    Raises
    ------
    DatasetError
        Unreadable file, no pose, wrong number of values, a non-number or non-finite value, a
        quaternion whose norm is off 1 by more than ``ROTATION_TOLERANCE``, or a stamp smaller
        than the previous one. The message names the file and the line.

    """
    return _tum_from_rows(path, *_parse_rows(path))


def _tum_from_rows(path: PathLike, rows: np.ndarray,
                   lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if rows.shape[1] != TUM_COLUMNS:
        raise DatasetError(f'{os.fspath(path)}:{lines[0]}: {rows.shape[1]} numbers per line, '
                           f'a TUM trajectory file has {TUM_COLUMNS}')
    stamps = rows[:, 0].copy()
    back = np.flatnonzero(np.diff(stamps) < 0.0)
    if back.size:
        i = int(back[0]) + 1
        raise DatasetError(f'{os.fspath(path)}:{lines[i]}: stamp {float(stamps[i])!r} is '
                           f'before the previous stamp {float(stamps[i - 1])!r}')
    quat = rows[:, 4:8]
    norm = np.linalg.norm(quat, axis=1)
    bad = np.abs(norm - 1.0) > ROTATION_TOLERANCE
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise DatasetError(f'{os.fspath(path)}:{lines[i]}: quaternion norm {norm[i]:.6g} is '
                           'not 1 (expected qx qy qz qw, unit norm)')
    poses = np.zeros((rows.shape[0], 4, 4))
    poses[:, :3, :3] = Rotation.from_quat(quat / norm[:, None]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    poses[:, 3, 3] = 1.0
    return stamps, poses


def read_poses(path: PathLike, format: str | None = None) -> Trajectory:  # noqa: A002
    """
    Read a KITTI or TUM trajectory file, detecting the format when not given.

    Parameters
    ----------
    path : str or os.PathLike
        Trajectory file.
    format : {'kitti', 'tum'} or None
        None detects it from the first pose line: 12 numbers is KITTI, 8 is TUM.

    Returns
    -------
    Trajectory
        ``(poses, stamps, file_format)``: (N, 4, 4) float64 ``T_world_cam`` (metres), (N,) float64
        stamps (s) or None for KITTI, and the format read.

    Raises
    ------
    ValueError
        ``format`` is not one of the above.
    DatasetError
        The file cannot be read or is malformed (see ``read_kitti`` and ``read_tum``); the
        message names the file and the line.

    """
    if format not in (None, 'kitti', 'tum'):
        raise ValueError(f"format must be 'kitti', 'tum' or None, got {format!r}")
    rows, lines = _parse_rows(path)
    fmt = format
    if fmt is None:
        if rows.shape[1] == KITTI_COLUMNS:
            fmt = 'kitti'
        elif rows.shape[1] == TUM_COLUMNS:
            fmt = 'tum'
        else:
            raise DatasetError(
                f'{os.fspath(path)}:{lines[0]}: {rows.shape[1]} numbers per line; expected '
                f'{KITTI_COLUMNS} (KITTI) or {TUM_COLUMNS} (TUM)')
    if fmt == 'kitti':
        poses = _kitti_from_rows(path, rows, lines)
        _LOG.debug('read %d KITTI poses from %s', len(poses), os.fspath(path))
        return Trajectory(poses, None, 'kitti')
    stamps, poses = _tum_from_rows(path, rows, lines)
    _LOG.debug('read %d TUM poses from %s', len(poses), os.fspath(path))
    return Trajectory(poses, stamps, 'tum')


def _format_row(values: np.ndarray) -> str:
    """Join float64 values with spaces, each as its shortest round-trip decimal string."""
    return ' '.join(repr(v) for v in values.tolist())


def write_kitti(path: PathLike, poses: np.ndarray) -> None:
    """
    Write poses as a KITTI odometry file at full precision.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (overwritten).
    poses : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres). Not modified.

    Raises
    ------
    ValueError
        Wrong shape or non-finite values.

    """
    arr = as_poses(poses)
    rows = arr[:, :3, :].reshape(-1, KITTI_COLUMNS)
    with open(path, 'w', encoding='utf-8') as fh:
        for row in rows:
            fh.write(_format_row(row) + '\n')
    _LOG.debug('wrote %d KITTI poses to %s', len(arr), os.fspath(path))


def write_tum(path: PathLike, stamps: np.ndarray, poses: np.ndarray) -> None:
    """
    Write stamped poses as a TUM trajectory file at full precision.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (overwritten); the first line is a ``#`` comment naming the columns.
    stamps : array_like
        (N,) float stamps (s).
    poses : array_like
        (N, 4, 4) or (N, 3, 4) ``T_world_cam`` (metres). Not modified. Rotations are
        written as unit quaternions (qx qy qz qw) with qw >= 0.

    Raises
    ------
    ValueError
        Wrong shapes, mismatched lengths or non-finite values.

    """
    arr = as_poses(poses)
    t = np.array(stamps, dtype=np.float64, copy=True).reshape(-1)
    if t.shape[0] != arr.shape[0]:
        raise ValueError(f'{t.shape[0]} stamps for {arr.shape[0]} poses')
    if not np.all(np.isfinite(t)):
        raise ValueError(f'stamp {int(np.flatnonzero(~np.isfinite(t))[0])} is not finite')
    quat = Rotation.from_matrix(arr[:, :3, :3]).as_quat()
    quat[quat[:, 3] < 0.0] *= -1.0
    rows = np.column_stack([t, arr[:, :3, 3], quat])
    with open(path, 'w', encoding='utf-8') as fh:
        fh.write(TUM_HEADER + '\n')
        for row in rows:
            fh.write(_format_row(row) + '\n')
    _LOG.debug('wrote %d TUM poses to %s', len(arr), os.fspath(path))
