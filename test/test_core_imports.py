"""
The core library imports no ROS package, no plotting and no command-line tooling.

Core modules are every ``stereo_vo_ros/**/*.py`` except the ROS adapter (``ros/``), the CLI
(``cli.py``, ``__main__.py``) and ``plotting.py``; they are found by globbing so new modules
are covered without editing this file.

Two checks:

* at run time, importing all core modules in a fresh interpreter leaves no ROS package,
  matplotlib or tqdm in ``sys.modules`` (this catches indirect imports too);
* statically, no core source file imports any of those or argparse, not even lazily inside
  a function. ``argparse`` is not checked in ``sys.modules``: SciPy
  (``scipy.spatial.transform``) imports it itself, so its presence says nothing about our code.
"""

import ast
import json
from pathlib import Path
import subprocess
import sys

PACKAGE_DIR = Path(__file__).resolve().parent.parent / 'stereo_vo_ros'
NON_CORE_FILES = {'cli.py', '__main__.py', 'plotting.py'}
NON_CORE_DIRS = {'ros'}

ROS_MODULES = ('rclpy', 'sensor_msgs', 'nav_msgs', 'geometry_msgs', 'std_msgs',
               'diagnostic_msgs', 'std_srvs', 'rosgraph_msgs', 'tf2_ros', 'message_filters',
               'builtin_interfaces', 'launch', 'launch_ros')
RUNTIME_BANNED = ROS_MODULES + ('matplotlib', 'tqdm')
STATIC_BANNED = RUNTIME_BANNED + ('argparse',)


def core_files() -> list[Path]:
    """
    Find the core source files of the package.

    Returns
    -------
    list of pathlib.Path
        Sorted absolute paths of every core ``.py`` file.

    """
    files = []
    for path in sorted(PACKAGE_DIR.rglob('*.py')):
        rel = path.relative_to(PACKAGE_DIR)
        if rel.parts[0] in NON_CORE_DIRS or rel.name in NON_CORE_FILES:
            continue
        if '__pycache__' in rel.parts:
            continue
        files.append(path)
    return files


def module_name(path: Path) -> str:
    """
    Turn a source file of the package into its dotted module name.

    Parameters
    ----------
    path : pathlib.Path
        Absolute path of a ``.py`` file under ``stereo_vo_ros/``.

    Returns
    -------
    str
        For example ``stereo_vo_ros.estimation.camera`` or ``stereo_vo_ros.io`` for a
        package's ``__init__.py``.

    """
    parts = ('stereo_vo_ros',) + path.relative_to(PACKAGE_DIR).with_suffix('').parts
    if parts[-1] == '__init__':
        parts = parts[:-1]
    return '.'.join(parts)


def _is_type_checking_block(node: ast.AST) -> bool:
    """Tell whether ``node`` is an ``if TYPE_CHECKING:`` block (never run)."""
    if not isinstance(node, ast.If):
        return False
    test = node.test
    return ((isinstance(test, ast.Name) and test.id == 'TYPE_CHECKING')
            or (isinstance(test, ast.Attribute) and test.attr == 'TYPE_CHECKING'))


def banned_imports(path: Path) -> list[str]:
    """
    List the banned imports written in one source file.

    Parameters
    ----------
    path : pathlib.Path
        Python source file.

    Returns
    -------
    list of str
        ``'<file>:<line> imports <module>'`` for each import (at any nesting depth, except
        inside ``if TYPE_CHECKING:``) whose top-level module is in ``STATIC_BANNED``.

    """
    tree = ast.parse(path.read_text(encoding='utf-8'), filename=str(path))
    found = []
    stack = [tree]
    while stack:
        node = stack.pop()
        if _is_type_checking_block(node):
            stack.extend(node.orelse)
            continue
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        for name in names:
            if name.split('.')[0] in STATIC_BANNED:
                found.append(f'{path.name}:{node.lineno} imports {name}')
        stack.extend(ast.iter_child_nodes(node))
    return found


# Runs in a fresh interpreter: imports each module in turn and reports which banned
# top-level modules appeared in sys.modules after it.
_PROBE = """
import importlib
import json
import sys

banned = set(json.loads(sys.argv[1]))
report = {}
for name in json.loads(sys.argv[2]):
    before = {m.split('.')[0] for m in sys.modules}
    importlib.import_module(name)
    after = {m.split('.')[0] for m in sys.modules}
    report[name] = sorted((after - before) & banned)
print(json.dumps(report))
"""


def test_core_modules_are_found() -> None:
    """The glob finds the modules the package is known to have, and skips the non-core ones."""
    names = {module_name(p) for p in core_files()}
    assert {'stereo_vo_ros', 'stereo_vo_ros.config', 'stereo_vo_ros.estimation.camera',
            'stereo_vo_ros.records', 'stereo_vo_ros.errors'} <= names
    assert not any(n.startswith('stereo_vo_ros.ros') for n in names)
    assert 'stereo_vo_ros.evaluation.plotting' not in names
    assert 'stereo_vo_ros.cli' not in names


def test_core_imports_no_ros_matplotlib_tqdm_at_runtime() -> None:
    """Importing every core module pulls in no ROS package, matplotlib or tqdm."""
    modules = [module_name(p) for p in core_files()]
    proc = subprocess.run(
        [sys.executable, '-c', _PROBE, json.dumps(RUNTIME_BANNED), json.dumps(modules)],
        cwd=PACKAGE_DIR.parent, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, f'importing the core modules failed:\n{proc.stderr}'
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert sorted(report) == sorted(modules)
    offenders = {name: new for name, new in report.items() if new}
    assert not offenders, f'core modules pulled in banned modules: {offenders}'


def test_core_sources_import_no_banned_module() -> None:
    """No core source file imports ROS, matplotlib, tqdm or argparse, even lazily."""
    found = [hit for path in core_files() for hit in banned_imports(path)]
    assert not found, 'banned imports in core modules:\n' + '\n'.join(found)


def test_static_check_sees_lazy_imports(tmp_path: Path) -> None:
    """The static check finds nested imports and ignores ``if TYPE_CHECKING:`` blocks."""
    source = tmp_path / 'sample.py'
    source.write_text(
        'from typing import TYPE_CHECKING\n'
        'if TYPE_CHECKING:\n'
        '    import matplotlib\n'
        'def f():\n'
        '    import argparse\n'
        '    from rclpy.node import Node\n'
        '    return Node, argparse\n',
        encoding='utf-8')
    assert sorted(banned_imports(source)) == ['sample.py:5 imports argparse',
                                              'sample.py:6 imports rclpy.node']
