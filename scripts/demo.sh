#!/usr/bin/env bash
# Run the demo: sets up <repo>/.venv (see scripts/_venv.sh), then `stereo_vo demo "$@"`.
set -euo pipefail

# shellcheck source=scripts/_venv.sh
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
svo_setup_venv

exec "$VENV/bin/stereo_vo" demo "$@"
