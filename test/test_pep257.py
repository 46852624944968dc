"""Docstring check with ament_pep257 (the ROS 2 Jazzy "ament" convention)."""

import logging
from pathlib import Path

from ament_pep257.main import main
import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Every Python file of the repository passes ament_pep257."""
    monkeypatch.chdir(REPO_ROOT)
    # ament_pep257 turns on pydocstyle's per-file INFO lines; keep the report readable.
    logging.getLogger('pydocstyle.utils').setLevel(logging.WARNING)
    rc = main(argv=['.'])
    errors = [line for line in capsys.readouterr().err.splitlines()
              if line.startswith('./')]
    assert rc == 0, \
        'Found %d docstring errors:\n' % len(errors) + '\n'.join(errors)
