#!/usr/bin/env bash
# Run the test suite: sets up <repo>/.venv (see scripts/_venv.sh), then pytest.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh test/test_packaging.py -x`.
set -euo pipefail

# shellcheck source=scripts/_venv.sh
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
svo_setup_venv

cd "$REPO"
# The packaging tests fail instead of skipping when colcon or the installed
# distribution is missing: this script has just installed both.
export STEREO_VO_STRICT_PACKAGING=1
# testpaths = test (setup.cfg): no arguments runs test/, paths narrow it down. The tests run
# in STEREO_VO_TEST_WORKERS processes (pytest-xdist; default 2, the cores of the CI machine;
# 0 runs them in this process). Every ROS test picks its own ROS_DOMAIN_ID from its pid.
exec "$PY" -m pytest -q -n "${STEREO_VO_TEST_WORKERS:-2}" "$@"
