#!/usr/bin/env bash
# Creates (once) the Python virtual environment `.venv` at the repository root with the
# independent tools the interop tests compare against: rosbags and the mcap reader (ROS 2 bags),
# and evo (trajectory metrics). Safe to run again: it only installs what is missing.
#
#   bash scripts/venv.sh        # then: cargo test -p cloi-host --test 'interop_*'
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
python="${PYTHON:-python3}"

if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi

# Pinned so results do not drift; bump together with the tests.
packages=(
    "rosbags==0.11.9"
    "mcap==1.6.0"
    "mcap-ros2-support==0.6.0"
    "evo==1.38.1"
)
stamp="$venv/.cloi-packages"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "${packages[*]}" ]; then
    exit 0
fi
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check "${packages[@]}"
printf '%s' "${packages[*]}" > "$stamp"
echo "venv ready: $venv"
