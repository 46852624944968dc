"""Shared pytest fixtures for the stereo_vo_ros tests."""

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_data_candidates() -> list[Path]:
    """
    List the places searched for the shared stereo clips, in order.

    Returns
    -------
    list of pathlib.Path
        ``$STEREO_VO_DATA`` if set, then ``<repo>/../shared/data`` (the layout of a CI
        clone) and ``/work/shared/data``.

    """
    candidates = []
    if os.environ.get('STEREO_VO_DATA'):
        candidates.append(Path(os.environ['STEREO_VO_DATA']))
    candidates.append(REPO_ROOT.parent / 'shared' / 'data')
    candidates.append(Path('/work/shared/data'))
    return candidates


@pytest.fixture(scope='session')
def repo_root() -> Path:
    """
    Return the repository root (the directory holding ``setup.py``).

    Returns
    -------
    pathlib.Path
        Absolute path of the repository root.

    """
    return REPO_ROOT


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """
    Return the read-only folder of real stereo clips (KITTI-odometry layout).

    Skips the requesting test with a message naming the searched paths when the folder is
    absent. Tests must never write into it.

    Returns
    -------
    pathlib.Path
        Absolute path of the data folder, e.g. ``.../shared/data`` holding
        ``kitti01_f0000-0050/``.

    """
    candidates = shared_data_candidates()
    for candidate in candidates:
        if candidate.is_dir():
            return candidate.resolve()
    searched = ', '.join(str(c) for c in candidates)
    pytest.skip(f'shared stereo data not found (searched: {searched}); '
                'set STEREO_VO_DATA to its folder to run this test')


def pytest_configure(config: pytest.Config) -> None:
    """Register the markers of the ament linter tests (ament_lint is not installed)."""
    for marker in ('linter: a code style check', 'flake8: the ament_flake8 check',
                   'pep257: the ament_pep257 check'):
        config.addinivalue_line('markers', marker)
