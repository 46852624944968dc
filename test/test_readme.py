"""
Every command in the README runs as written on a fresh clone.

The shell commands of the README's ``bash`` code blocks are read (continuation lines joined,
comments dropped). The offline tools that need no ROS install and no data run for real, in a
temporary folder, with the installed entry points next to ``sys.executable``. The others are
checked against what they name: ``ros2 run`` / ``ros2 launch`` / ``ros2 param`` lines against
``setup.py``'s console scripts, the launch file's arguments, the node's topics and the
configuration's parameters; ``stereo_vo`` lines on data that is not here against the
subcommand's ``--help``; scripts and parameter files against the repository.
"""

import ast
from pathlib import Path
import re
import shlex
import subprocess
import sys

import pytest

from stereo_vo_ros.config import Config

REPO = Path(__file__).resolve().parents[1]
README = REPO / 'README.md'
BIN = Path(sys.executable).parent
MAX_LINES = 250
#: Stands for ``$(ros2 pkg prefix stereo_vo_ros)``; its share/ files come from the repository.
INSTALL_PREFIX = '/opt/ros_ws/install/stereo_vo_ros'

#: Words only the builders understand.
FORBIDDEN = [
    (r'\bissues?\b', 'issue'),
    (r'\breleases?\b', 'release'),
    (r'\bpaper [12]\b', 'paper 1/2'),
    (r'\bthis VM\b', 'this VM'),
    (r'\bone-off\b', 'one-off'),
    (r'\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b', 'commit hash'),
]
#: Options of the stereo_vo subcommands that take no value.
FLAGS = {'-q', '--quiet', '--json', '-v', '--verbose', '-h', '--help', '--no-ransac', '--version'}
#: Topics of the node that ``-r`` may remap (relative names, as the node creates them).
NODE_TOPICS = {'left/image_rect', 'right/image_rect', 'left/camera_info', 'right/camera_info',
               'left/image_rect/compressed', 'right/image_rect/compressed', 'odom', 'path',
               '~/debug_image', '~/set_pose'}
#: Commands that only set up an environment; nothing of this package to check.
SETUP = {'cd', 'git', 'rosdep', 'colcon', 'source', '.', 'python3', 'sudo'}


def readme_commands() -> list[list[str]]:
    """Return the README's shell commands as argument lists, in order."""
    text = README.read_text()
    commands = []
    for block in re.findall(r'```bash\n(.*?)```', text, flags=re.S):
        joined = re.sub(r'\\\n\s*', ' ', block)
        for line in joined.splitlines():
            line = re.sub(r'\s#\s.*$', '', line).strip()
            line = line.replace('$(ros2 pkg prefix stereo_vo_ros)', INSTALL_PREFIX)
            if not line or line.startswith('#'):
                continue
            for part in line.split('&&'):
                commands.append(shlex.split(part.strip()))
    return commands


def config_parameters() -> set[str]:
    """Return every parameter name of the node."""
    return {name for name, _, _ in Config().items()} | {'use_sim_time'}


def launch_arguments() -> set[str]:
    """Return the argument names the launch file declares (``DeclareLaunchArgument``)."""
    tree = ast.parse((REPO / 'launch' / 'stereo_vo.launch.py').read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', '') == 'DeclareLaunchArgument':
            if isinstance(node.args[0], ast.Constant):
                names.add(node.args[0].value)
        if isinstance(node, ast.Assign) and getattr(node.targets[0], 'id', '') == 'remaps':
            names |= {elt.elts[0].value for elt in node.value.elts}
    return names


def console_scripts() -> set[str]:
    """Return the executables ``setup.py`` installs."""
    text = (REPO / 'setup.py').read_text()
    return set(re.findall(r"'(\w+) = stereo_vo_ros[\w.]*:\w+'", text))


def extras() -> set[str]:
    """Return the extras of ``setup.py``."""
    block = (REPO / 'setup.py').read_text().split('extras_require=')[1].split('},')[0]
    return set(re.findall(r"'(\w+)': \[", block))


def params_file(path: str) -> Path:
    """Map a README ``--params-file`` (repository or installed share path) to the repository."""
    marker = 'share/stereo_vo_ros/'
    return REPO / path.split(marker, 1)[1] if marker in path else REPO / path


def check_ros_args(args: list[str]) -> None:
    """Check ``--ros-args`` remappings, parameters and parameter files."""
    names = config_parameters()
    for flag, value in zip(args, args[1:]):
        if flag == '-r':
            assert value.split(':=')[0] in NODE_TOPICS, f'no such topic to remap: {value}'
        elif flag == '-p':
            assert value.split(':=')[0] in names, f'no such parameter: {value}'
        elif flag == '--params-file':
            assert params_file(value).is_file(), f'no such parameter file: {value}'


def check_ros2(cmd: list[str]) -> None:
    """Check a ``ros2`` command against the package."""
    verb = cmd[1]
    if verb == 'run':
        assert cmd[2] == 'stereo_vo_ros' and cmd[3] in console_scripts(), cmd
        check_ros_args(cmd[4:])
    elif verb == 'launch':
        assert cmd[2] == 'stereo_vo_ros' and (REPO / 'launch' / cmd[3]).is_file(), cmd
        declared = launch_arguments()
        for arg in cmd[4:]:
            assert arg.split(':=')[0] in declared, f'no such launch argument: {arg}'
    elif verb == 'param':
        assert cmd[3] == '/stereo_vo', f'the node is named stereo_vo: {cmd}'
        assert cmd[4] in config_parameters(), f'no such parameter: {cmd[4]}'
    else:
        pytest.fail(f'unchecked ros2 verb: {cmd}')


def positionals(args: list[str]) -> list[str]:
    """Return the positional arguments of a ``stereo_vo`` subcommand's argument list."""
    out, skip = [], False
    for arg in args:
        if skip:
            skip = False
        elif arg.startswith('-'):
            skip = arg not in FLAGS and '=' not in arg
        else:
            out.append(arg)
    return out


def runnable(cmd: list[str], cwd: Path) -> bool:
    """Whether a ``stereo_vo`` command needs nothing but what earlier commands made."""
    if len(cmd) < 2 or cmd[1] in ('demo', '--help'):
        return cmd[1:] == ['--help']
    return all(p.startswith('synthetic:') or (cwd / p).exists() for p in positionals(cmd[2:]))


def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """Run an installed entry point in ``cwd`` (the repository's config folder linked there)."""
    exe = BIN / cmd[0]
    if not exe.exists():
        pytest.skip(f'{exe} is not installed (pip install the package)')
    return subprocess.run([str(exe), *cmd[1:]], cwd=cwd, capture_output=True, text=True,
                          timeout=60)


def test_readme_is_short_and_speaks_to_users():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_LINES
    for pattern, what in FORBIDDEN:
        found = re.findall(pattern, text, flags=re.I if what != 'commit hash' else 0)
        assert not found, f'README names {what}: {found}'


def test_readme_links_and_images_exist():
    for target in re.findall(r'\]\(([^)#]+)(?:#[^)]*)?\)', README.read_text()):
        if not target.startswith('http'):
            assert (REPO / target).exists(), f'README links to a missing {target}'


def test_readme_names_the_two_commands():
    commands = readme_commands()
    for script in ('demo.sh', 'test.sh'):
        assert ['bash', f'scripts/{script}'] in commands
        assert (REPO / 'scripts' / script).stat().st_mode & 0o111


def test_readme_commands_run_or_name_what_exists(tmp_path):
    (tmp_path / 'config').symlink_to(REPO / 'config')
    help_texts: dict[str, str] = {}
    ran = []
    for cmd in readme_commands():
        tool = cmd[0]
        if tool in SETUP:
            continue
        if tool == 'bash':
            assert (REPO / cmd[1]).is_file(), cmd
        elif tool == 'pip':
            for extra in re.findall(r'\[([\w,]+)\]', ' '.join(cmd)):
                assert set(extra.split(',')) <= extras(), f'no such extra: {extra}'
        elif tool == 'ros2':
            check_ros2(cmd)
        elif tool == 'stereo_vo_node':
            assert tool in console_scripts()
            check_ros_args(cmd[1:])
        elif tool == 'python' and cmd[1].startswith('benchmarks/'):
            source = (REPO / cmd[1]).read_text()
            for opt in (a for a in cmd[2:] if a.startswith('--')):
                assert f"'{opt}'" in source, f'{cmd[1]} has no option {opt}'
        elif tool == 'stereo_vo':
            if runnable(cmd, tmp_path):
                result = run(cmd, tmp_path)
                assert result.returncode == 0, f'{shlex.join(cmd)}:\n{result.stderr}'
                ran.append(cmd[1])
            else:
                sub = cmd[1]
                if sub not in help_texts:
                    result = run([tool, sub, '--help'], tmp_path)
                    assert result.returncode == 0, f'no subcommand {sub}: {result.stderr}'
                    help_texts[sub] = result.stdout
                for opt in (a for a in cmd[2:] if a.startswith('-')):
                    assert opt.split('=')[0] in help_texts[sub], f'{sub} has no option {opt}'
        else:
            pytest.fail(f'README command not checked by this test: {shlex.join(cmd)}')
    assert {'run', 'eval', 'plot', 'config'} <= set(ran), ran
    assert (tmp_path / 'run.png').stat().st_size > 0


def test_readme_benchmark_commands_name_real_scripts_and_options():
    text = README.read_text()
    for line in re.findall(r'`python (benchmarks/[^`]+)`', text):
        cmd = shlex.split(line)
        source = (REPO / cmd[0]).read_text()
        for opt in (a for a in cmd[1:] if a.startswith('--')):
            assert f"'{opt}'" in source, f'{cmd[0]} has no option {opt}'
