#!/usr/bin/env bash
# A soak of the host: `cloi map` over hours of the simulated office (the simulator streams into
# the mapper, no bag on disk), its resident memory sampled every 2 s. Prints the RSS at each
# tenth of the run and the growth from its middle to 95 %, which must be ~0 (issue 19: host memory
# flat however long the robot maps; only the area mapped may grow it, and the office's area is
# explored in the first minutes).
#
#   bench/soak.sh [--hours H] [--world office] [--out target/soak]    (default 24 h)
#
# The run itself takes about 13 s of one core per simulated hour on the 2-core box.
set -euo pipefail
hours=24 world=office out=target/soak
while [ $# -gt 0 ]; do
  case "$1" in
    --hours) hours=$2; shift 2 ;;
    --world) world=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
cargo build -q --release -p cloi-host --bin cloi
cloi=${CLOI_BIN:-$PWD/target/release/cloi}
mkdir -p "$out"
secs=$(python3 -c "print(int($hours * 3600))")
"$cloi" map --sim-world "$world" --sim-duration "$secs" --deterministic --quiet --out "$out/map" \
  > "$out/map.txt" 2>&1 &
pid=$!
: > "$out/rss.txt"
while kill -0 "$pid" 2>/dev/null; do
  echo "$(date +%s.%N) $(awk '/VmRSS/{print $2}' /proc/$pid/status 2>/dev/null)" >> "$out/rss.txt"
  sleep 2
done
wait "$pid"
python3 - "$out" <<'PY'
import json, sys
out = sys.argv[1]
rows = [l.split() for l in open(f"{out}/rss.txt") if len(l.split()) == 2]
t = [float(a) for a, _ in rows]; kb = [int(b) for _, b in rows]
r = json.load(open(f"{out}/map/report.json"))
print(f"{r['data_seconds'] / 3600:.1f} h of data, {r['scans']} scans, {r['wall_seconds']:.0f} s wall, "
      f"peak RSS {r['peak_rss_bytes'] / 2**20:.1f} MiB, nodes pruned {r['mapper']['nodes_pruned']}")
n = len(kb)
print("RSS (MiB) at each tenth of the run:", " ".join(f"{kb[min(n - 1, n * k // 10)] / 1024:.1f}" for k in range(1, 11)))
# The last samples hold the outputs being written (the map composed from every submap).
half, end = n // 2, max(n // 2, n * 95 // 100)
print(f"growth from 50 % to 95 % of the run: {(kb[end] - kb[half]) / 1024:+.2f} MiB in {t[end] - t[half]:.0f} s")
PY
