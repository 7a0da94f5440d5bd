#!/usr/bin/env python3
"""Localization in saved maps on simulated worlds (issue: saved maps, localization, lifelong).

For each world: one lap is simulated (seed MAP_SEED) and mapped with `cloi map --save`; two laps
of the same route with another draw of the sensor noise (seed LOC_SEED) are then localized in
that map with `cloi localize`:

* **tracking**: from the known start pose (the map's origin is the first pose of the mapping
  run, and both runs start there); real-time pose error of every scan (gpe.tum) against the
  simulator's ground truth, after one rigid 2D fit of the map frame to the ground truth's frame
  over the whole run (the map is a map: its own error is in the figures), as median, p95, p99
  and max, over the scans tracked and over all scans; the largest step of the pose beyond the
  odometry's while tracked (a jump);
* **global localization**: the same bag started at STARTS fixed times spread over the run
  (`--skip`), without an initial pose, each for WINDOW seconds of data: whether and when the
  first fix came (data seconds after the start), and whether it was right (within 0.3 m and
  5 deg of the ground truth, in the frame of the tracking run's fit).

The seeds and start times were fixed before any result was seen.

    bench/localize.py [--worlds home,office] [--starts 40] [--window 60] [--jobs 2] [--out DIR]
        [--bin target/release/cloi]
"""

import argparse
import bisect
import json
import math
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

MAP_SEED = 11
LOC_SEED = 12


def run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{r.stderr}")
    return r


def tum(path):
    """Stamp -> (x, y, yaw) of a TUM file."""
    out = []
    with open(path) as f:
        for line in f:
            if not line.strip() or line.startswith("#"):
                continue
            v = [float(x) for x in line.split()]
            qz, qw = v[6], v[7]
            out.append((v[0], v[1], v[2], 2.0 * math.atan2(qz, qw)))
    out.sort()
    return out


def at(track, t):
    """The pose of `track` nearest to stamp t (the simulator's truth is at 50 Hz)."""
    stamps = [p[0] for p in track]
    i = bisect.bisect_left(stamps, t)
    best = min((j for j in (i - 1, i) if 0 <= j < len(track)), key=lambda j: abs(stamps[j] - t))
    return track[best]


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def fit(pairs):
    """Rigid 2D transform (c, s, tx, ty) taking the first points onto the second (least squares)."""
    n = len(pairs)
    ax = sum(p[0][0] for p in pairs) / n
    ay = sum(p[0][1] for p in pairs) / n
    bx = sum(p[1][0] for p in pairs) / n
    by = sum(p[1][1] for p in pairs) / n
    sxx = sum((p[0][0] - ax) * (p[1][0] - bx) + (p[0][1] - ay) * (p[1][1] - by) for p in pairs)
    sxy = sum((p[0][0] - ax) * (p[1][1] - by) - (p[0][1] - ay) * (p[1][0] - bx) for p in pairs)
    th = math.atan2(sxy, sxx)
    c, s = math.cos(th), math.sin(th)
    return (c, s, bx - (c * ax - s * ay), by - (s * ax + c * ay), th)


def apply(T, p):
    c, s, tx, ty, th = T
    return (c * p[1] - s * p[2] + tx, s * p[1] + c * p[2] + ty, wrap(p[3] + th))


def quantile(v, q):
    v = sorted(v)
    return v[min(len(v) - 1, int(q * len(v)))] if v else float("nan")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--worlds", default="home,office")
    ap.add_argument("--starts", type=int, default=40)
    ap.add_argument("--window", type=float, default=60.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default="target/bench-localize")
    ap.add_argument("--bin", default="target/release/cloi")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    rows = []
    for world in a.worlds.split(","):
        d = os.path.join(a.out, world)
        os.makedirs(d, exist_ok=True)
        bag_map, bag_loc = f"{d}/map.mcap", f"{d}/loc.mcap"
        run([a.bin, "sim", "--world", world, "--laps", "1", "--seed", str(MAP_SEED),
             "--sensors", "L", "--quiet", "--out", bag_map])
        run([a.bin, "sim", "--world", world, "--laps", "2", "--seed", str(LOC_SEED),
             "--sensors", "L", "--quiet", "--out", bag_loc])
        cmap = f"{d}/{world}.cloimap"
        run([a.bin, "map", bag_map, "--profile", world, "--deterministic", "--quiet",
             "--save", cmap, "--out", f"{d}/map"])
        run([a.bin, "localize", cmap, bag_loc, "--deterministic", "--quiet", "--initial-pose",
             "0,0,0", "--out", f"{d}/track"])
        truth = tum(bag_loc.replace(".mcap", ".gt.tum"))
        gpe = tum(f"{d}/track/gpe.tum")
        report = json.load(open(f"{d}/track/report.json"))
        loc = report["localization"]
        pairs = [((p[1], p[2]), at(truth, p[0])[1:3]) for p in gpe]
        T = fit(pairs)
        # A stretch localized at a wrong place must not bend the fit: refit without the poses
        # more than 1 m off (they still count in the errors).
        for _ in range(2):
            good = [pr for pr, p in zip(pairs, gpe)
                    if math.hypot(apply(T, p)[0] - pr[1][0], apply(T, p)[1] - pr[1][1]) < 1.0]
            T = fit(good)
        err = []
        for p in gpe:
            q, g = apply(T, p), at(truth, p[0])
            err.append(math.hypot(q[0] - g[1], q[1] - g[2]))
        # The error of each localized stretch: where it is wrong, and for how long.
        wrong = sum(1 for e in err if e > 1.0)
        t0, t1 = gpe[0][0], gpe[-1][0]
        span = t1 - t0 - a.window
        starts = [5.0 + k * span / a.starts for k in range(a.starts)]

        def one(k):
            out = f"{d}/global{k:02}"
            run([a.bin, "localize", cmap, bag_loc, "--deterministic", "--quiet", "--skip",
                 f"{starts[k]:.3f}", "--max-scans", str(int(a.window * 5)), "--out", out])
            r = json.load(open(f"{out}/report.json"))["localization"]
            fix = r["time_to_first_fix_s"]
            if fix is None:
                return (k, None, False)
            poses = tum(f"{out}/gpe.tum")
            first = poses[0][0] + fix
            p = min(poses, key=lambda p: abs(p[0] - first))
            q, g = apply(T, p), at(truth, p[0])
            right = math.hypot(q[0] - g[1], q[1] - g[2]) <= 0.3 and \
                abs(wrap(q[2] - g[3])) <= math.radians(5)
            return (k, fix, right)

        with ThreadPoolExecutor(a.jobs) as ex:
            results = list(ex.map(one, range(a.starts)))
        fixed = [r for r in results if r[1] is not None]
        right = [r for r in fixed if r[2]]
        times = sorted(r[1] for r in right)
        rows.append({
            "world": world,
            "scans": len(gpe),
            "localized_fraction": loc["localized_fraction"],
            "lost": loc["lost"],
            "fixes": loc["fixes"],
            "err_median": quantile(err, 0.5),
            "err_p95": quantile(err, 0.95),
            "err_p99": quantile(err, 0.99),
            "err_max": max(err),
            "scans_off_by_1m": wrong,
            "gpe_max_jump_m": report["gpe_max_jump_m"],
            "global_starts": a.starts,
            "global_fixed": len(fixed),
            "global_right": len(right),
            "global_wrong": [r[0] for r in fixed if not r[2]],
            "fix_median_s": quantile(times, 0.5),
            "fix_max_s": max(times) if times else None,
        })
        print(json.dumps(rows[-1]), flush=True)
    print("| world | scans | localized | lost | error median / p95 / p99 / max (m) | scans > 1 m | "
          "global: fixed, right of starts | time to fix median / max (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['world']} | {r['scans']} | {100 * r['localized_fraction']:.1f} % | "
              f"{r['lost']} | {r['err_median']:.3f} / {r['err_p95']:.3f} / {r['err_p99']:.3f} / "
              f"{r['err_max']:.3f} | {r['scans_off_by_1m']} | {r['global_fixed']}, {r['global_right']} of "
              f"{r['global_starts']} | {r['fix_median_s']:.1f} / {r['fix_max_s']} |")


if __name__ == "__main__":
    main()
