"""
The package installs both ways: as a ROS 2 package with colcon and as a wheel with pip.

colcon: a build from the working tree into a temporary workspace puts the executables where
``ros2 run`` looks (``lib/stereo_vo_ros/``) and the manifest, parameter file, launch file and
ament index marker where ``ros2 launch`` and ament_index look (``share/``).

pip: the installed distribution (``pip install .[ros]``, as ``scripts/test.sh`` does) exposes
the console scripts, runs outside the source tree, and keeps ROS packages in the ``ros`` extra.

Checks that need colcon or the installed distribution skip when those are absent (e.g. a
plain ``pytest`` in an environment without them), except under ``scripts/test.sh``, which sets
``STEREO_VO_STRICT_PACKAGING=1`` after installing both and turns such a skip into a failure.
"""

import importlib.metadata
import importlib.util
import json
import os
from pathlib import Path
import re
import subprocess
import sys
import sysconfig

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
PACKAGE = 'stereo_vo_ros'
EXECUTABLES = ('stereo_vo', 'stereo_vo_node')
SHARE_FILES = ('package.xml', 'config/stereo_vo.yaml', 'config/road_vehicle.yaml',
               'config/fastdds_large_images.xml',
               'launch/stereo_vo.launch.py')
ROS_REQUIREMENT = re.compile(r'^(ros-|rclpy|rosidl|ament|[a-z0-9_-]*_msgs$|[a-z0-9_-]*-msgs$)')
SITE_PACKAGES = f'lib/python{sys.version_info.major}.{sys.version_info.minor}/site-packages'


def _skip_or_fail(reason: str) -> None:
    """Skip the test, or fail it when ``STEREO_VO_STRICT_PACKAGING`` is set."""
    if os.environ.get('STEREO_VO_STRICT_PACKAGING'):
        pytest.fail(f'{reason} (STEREO_VO_STRICT_PACKAGING is set)')
    pytest.skip(reason)


def _source_modules() -> list[str]:
    """List the package's ``.py`` files as POSIX paths relative to the repository root."""
    return sorted(p.relative_to(REPO_ROOT).as_posix()
                  for p in (REPO_ROOT / PACKAGE).rglob('*.py')
                  if '__pycache__' not in p.parts)


def _clean_env(**extra: str) -> dict[str, str]:
    """Return ``os.environ`` without Python/ROS path variables, plus ``extra``."""
    env = {k: v for k, v in os.environ.items()
           if k not in ('PYTHONPATH', 'AMENT_PREFIX_PATH', 'COLCON_PREFIX_PATH')}
    env.update(extra)
    return env


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """
    Build the working tree with colcon into a temporary workspace.

    Returns
    -------
    pathlib.Path
        The package's install prefix, ``<tmp>/install/stereo_vo_ros`` (isolated layout).

    """
    if importlib.util.find_spec('colcon_core') is None:
        _skip_or_fail('colcon is not importable: pip install colcon-core colcon-ros '
                      'colcon-python-setup-py (scripts/test.sh does)')
    if importlib.util.find_spec('colcon_ros') is None:
        _skip_or_fail('colcon-ros is not importable: pip install colcon-ros')
    work = tmp_path_factory.mktemp('colcon')
    cmd = [sys.executable, '-c', 'import sys; from colcon_core.command import main; '
           'sys.exit(main())',
           '--log-base', str(work / 'log'),
           'build', '--base-paths', str(REPO_ROOT), '--packages-select', PACKAGE,
           '--build-base', str(work / 'build'), '--install-base', str(work / 'install'),
           '--event-handlers', 'console_direct-']
    env = _clean_env(COLCON_HOME=str(work / 'colcon_home'))
    proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True,
                          timeout=300, check=False)
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    assert f'Finished <<< {PACKAGE}' in proc.stdout + proc.stderr, proc.stdout + proc.stderr
    return work / 'install' / PACKAGE


def test_colcon_installs_executables_where_ros2_run_looks(colcon_install: Path) -> None:
    """``ros2 run stereo_vo_ros <exe>`` finds executables in ``lib/stereo_vo_ros/``."""
    for name in EXECUTABLES:
        exe = colcon_install / 'lib' / PACKAGE / name
        assert exe.is_file(), f'{exe} missing'
        assert os.access(exe, os.X_OK), f'{exe} is not executable'


def test_colcon_installs_share_files_and_index_marker(colcon_install: Path) -> None:
    """Manifest, parameter file, launch file and ament index marker are installed."""
    share = colcon_install / 'share' / PACKAGE
    for rel in SHARE_FILES:
        installed = share / rel
        assert installed.is_file(), f'{installed} missing'
        assert installed.read_bytes() == (REPO_ROOT / rel).read_bytes()
    marker = colcon_install / 'share' / 'ament_index' / 'resource_index' / 'packages' / PACKAGE
    assert marker.is_file(), f'ament index marker {marker} missing'


def test_colcon_installs_every_module(colcon_install: Path) -> None:
    """Every ``.py`` of the package (subpackages too) reaches the install space."""
    site = colcon_install / SITE_PACKAGES
    missing = [rel for rel in _source_modules() if not (site / rel).is_file()]
    assert not missing, f'modules not installed by colcon (missing __init__.py?): {missing}'


def test_colcon_package_found_through_ament_index(colcon_install: Path, tmp_path: Path) -> None:
    """With the install prefix on AMENT_PREFIX_PATH, ament_index resolves the package."""
    if importlib.util.find_spec('ament_index_python') is None:
        _skip_or_fail('ament_index_python is not importable (it comes with the "ros" extra)')
    probe = ('import json\n'
             'from ament_index_python.packages import get_package_prefix, '
             'get_package_share_directory\n'
             f'print(json.dumps([get_package_prefix({PACKAGE!r}), '
             f'get_package_share_directory({PACKAGE!r})]))\n')
    proc = subprocess.run([sys.executable, '-c', probe], cwd=tmp_path,
                          env=_clean_env(AMENT_PREFIX_PATH=str(colcon_install)),
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    prefix, share = json.loads(proc.stdout)
    assert Path(prefix) == colcon_install
    assert Path(share) == colcon_install / 'share' / PACKAGE


def test_colcon_executable_runs(colcon_install: Path, tmp_path: Path) -> None:
    """The colcon-installed ``stereo_vo --help`` runs from the install space, not the source."""
    env = _clean_env(PYTHONPATH=str(colcon_install / SITE_PACKAGES),
                     AMENT_PREFIX_PATH=str(colcon_install))
    proc = subprocess.run([str(colcon_install / 'lib' / PACKAGE / 'stereo_vo'), '--help'],
                          cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert 'usage' in proc.stdout.lower()


@pytest.fixture(scope='module')
def installed() -> importlib.metadata.Distribution:
    """
    Return the pip-installed distribution of the package.

    Returns
    -------
    importlib.metadata.Distribution
        Metadata of ``stereo_vo_ros`` in the running interpreter's environment.

    """
    try:
        dist = importlib.metadata.distribution(PACKAGE)
    except importlib.metadata.PackageNotFoundError:
        _skip_or_fail(f'{PACKAGE} is not installed in {sys.prefix}: '
                      'run scripts/test.sh (pip install ".[ros,test]")')
    return dist


def test_pip_install_is_not_editable(installed: importlib.metadata.Distribution) -> None:
    """scripts/test.sh installs a real copy, so the tests below see what users get."""
    direct_url = installed.read_text('direct_url.json')
    if direct_url is not None:
        info = json.loads(direct_url)
        assert not info.get('dir_info', {}).get('editable', False), direct_url
    location = Path(installed.locate_file(f'{PACKAGE}/__init__.py')).resolve()
    assert location.is_file(), f'{location} missing'
    assert location.parent != (REPO_ROOT / PACKAGE).resolve(), \
        f'the installed distribution points at the source tree: {location}'


def test_pip_console_scripts(installed: importlib.metadata.Distribution) -> None:
    """The distribution declares the two console scripts with their entry functions."""
    scripts = {ep.name: ep.value for ep in installed.entry_points
               if ep.group == 'console_scripts'}
    assert scripts == {'stereo_vo': 'stereo_vo_ros.cli:main',
                       'stereo_vo_node': 'stereo_vo_ros.ros:node_main'}


def test_pip_installs_every_module_and_share_file(
        installed: importlib.metadata.Distribution) -> None:
    """Every package module and the ROS share files are in the installed distribution."""
    files = {f.as_posix() for f in installed.files or []}
    missing = [rel for rel in _source_modules() if rel not in files]
    assert not missing, (
        f'modules not in the installed distribution: {missing} (added since the last '
        'install? rerun scripts/test.sh; otherwise setup.py misses them)')
    suffixes = [f'share/{PACKAGE}/{rel}' for rel in SHARE_FILES]
    suffixes.append(f'share/ament_index/resource_index/packages/{PACKAGE}')
    for suffix in suffixes:
        assert any(f.endswith(suffix) for f in files), f'{suffix} not installed by pip'


def test_pip_console_script_runs(installed: importlib.metadata.Distribution,
                                 tmp_path: Path) -> None:
    """``stereo_vo --help`` from the environment's bin directory runs outside the source."""
    exe = Path(sysconfig.get_path('scripts')) / 'stereo_vo'
    assert exe.is_file(), f'{exe} missing'
    proc = subprocess.run([str(exe), '--help'], cwd=tmp_path, env=_clean_env(),
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert 'usage' in proc.stdout.lower()


def test_ros_packages_only_in_ros_extra(installed: importlib.metadata.Distribution) -> None:
    """install_requires holds no ROS package; rclpy and the messages are in the extra."""
    plain, ros_extra = [], []
    for requirement in installed.requires or []:
        spec, _, marker = requirement.partition(';')
        name = re.match(r'\s*([A-Za-z0-9._-]+)', spec).group(1).lower()
        if not marker.strip():
            plain.append(name)
        elif re.search(r'extra\s*==\s*["\']ros["\']', marker):
            ros_extra.append(name)
    ros_in_plain = [n for n in plain if ROS_REQUIREMENT.match(n)]
    assert not ros_in_plain, f'ROS packages in install_requires: {ros_in_plain}'
    assert 'numpy' in plain
    assert {'ros-jazzy-rclpy', 'ros-jazzy-sensor-msgs', 'ros-jazzy-nav-msgs',
            'ros-jazzy-geometry-msgs', 'ros-jazzy-std-msgs', 'ros-jazzy-std-srvs',
            'ros-jazzy-diagnostic-msgs'} <= set(ros_extra)
