#!/usr/bin/env bash
# Maps the three benchmark logs with `cloi map --deterministic` (office profile) and prints, per
# log: the relation error of the final and of the real-time (GPE) trajectory against the
# GMapping reference (`cloi eval ref`, pairs within 1 m; the reference holds the laser's poses,
# so the robot's trajectory is moved by the laser mounting `cloi map` used, from report.json),
# loop closures, data seconds per wall second, the real-time part's median and p99 per scan,
# and the largest GPE jump, with the back-end run continuously and held back by --delay
# seconds of data.
#
#   bench/map.sh [--delay 30] [--out target/bench-map]
set -euo pipefail
cd "$(dirname "$0")/.."
delay=30
out=target/bench-map
while [ $# -gt 0 ]; do
  case "$1" in
    --delay) delay=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    *) echo "unknown option $1" >&2; exit 2 ;;
  esac
done
data=../shared/data/carmen
cargo build -q --release -p cloi-host --bin cloi
cloi=target/release/cloi
mkdir -p "$out"
printf '| log | final m | gpe m | loops | x realtime | median us/scan | p99 us/scan | jump m | jump m (delay %ss) |\n' "$delay"
printf '|---|---:|---:|---:|---:|---:|---:|---:|---:|\n'
for log in intel fr079 mit-csail; do
  "$cloi" map "$data/$log.clf" --deterministic --quiet --out "$out/$log" > /dev/null
  "$cloi" map "$data/$log.clf" --deterministic --quiet --backend-delay "$delay" \
    --out "$out/$log-delay" > /dev/null
  ref="$data/$log.gfs_reference_poses.txt"
  laser=$(python3 -c 'import json, sys; o = json.load(open(sys.argv[1]))["input"]["laser_offset"] or [0, 0, 0]; print(",".join(map(repr, o)))' \
    "$out/$log/report.json")
  fin=$("$cloi" eval ref --trajectory "$out/$log/trajectory.tum" --reference "$ref" \
    --sensor-offset "$laser")
  gpe=$("$cloi" eval ref --trajectory "$out/$log/gpe.tum" --reference "$ref" \
    --sensor-offset "$laser")
  python3 - "$log" "$out/$log/report.json" "$out/$log-delay/report.json" "$fin" "$gpe" <<'PY'
import json, sys
log, rep, rep_delay, fin, gpe = sys.argv[1:]
r = json.load(open(rep)); d = json.load(open(rep_delay))
f = json.loads(fin); g = json.loads(gpe)
rt = r["realtime_us_per_scan"]
print(f"| {log} | {f['trans_mean_m']:.4f} | {g['trans_mean_m']:.4f} | {r['loop_closures']} | "
      f"{r['speed_x_realtime']:.0f} | {rt['median']:.0f} | {rt['p99']:.0f} | "
      f"{r['gpe_max_jump_m']:.4f} | {d['gpe_max_jump_m']:.4f} |")
PY
done
