#!/usr/bin/env bash
# Side-by-side benchmark of `cloi optimize` against g2o (pip g2opy) and GTSAM (pip gtsam).
# Creates its own virtual environment (bench/.venv), builds cloi in release mode, pins every
# process to one CPU and prints a markdown table. Usage: bench/optimize.sh [--reps N] [--files ...]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
top=$(cd "$here/.." && pwd)
venv="$here/.venv"
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q --upgrade pip
  "$venv/bin/pip" install -q numpy gtsam
  # g2o's Python binding on PyPI is `g2opy` (module g2opy); the benchmark falls back to GTSAM
  # alone when it cannot be installed.
  "$venv/bin/pip" install -q g2opy || echo "g2opy did not install: GTSAM only" >&2
fi
(cd "$top" && cargo build --release -q -p cloi-host)
data="${CLOI_DATA_DIR:-$top/../shared/data}/g2o"
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
exec taskset -c 0 "$venv/bin/python" "$here/optimize.py" --cloi "$top/target/release/cloi" --data "$data" "$@"
