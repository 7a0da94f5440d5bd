#!/usr/bin/env python3
"""Lifelong mapping over many sessions in a changing simulated world (issue: saved maps,
localization, lifelong).

Session 0 maps the world as written (`cloi map --save`); session k >= 1 is the world with its
`[[changes]]` up to session k applied (`cloi sim --session k`: furniture moved, a door closed or
opened, clutter), driven from the same start (the dock, the map's origin) with another draw of
the sensor noise, and extends the previous session's map (`cloi map --load PREV --initial-pose
0,0,0 --save NEXT`). Per session: the map file's size and counts, the peak memory of the run,
the time to the first fix, and the error against the simulator's ground truth of the session's
final trajectory (`trajectory.tum`) and real-time poses (`gpe.tum`): after its own rigid fit
(how good the session's map is) and in the frame fitted to session 0 (whether the map stays
where it was). With `--fresh` each session's bag is also mapped alone, for comparison.

With `--cycle N` the world keeps changing for as many sessions as asked: session k >= 1 is the
world of session ((k - 1) mod N) + 1, so the N sets of changes come and go again (a door that
closes is opened, furniture moves back), as in a home over months.

The seeds (SEED0 + k) were fixed before any result was seen.

    bench/lifelong.py [--world home] [--sessions 10] [--laps 1 | --duration S] [--cycle N]
        [--fresh] [--out DIR] [--bin target/release/cloi] [--png FILE]
"""

import argparse
import bisect
import json
import math
import os
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from localize import apply, fit, quantile, run, tum  # noqa: E402

SEED0 = 100


def at(track, stamps, t):
    """The pose of `track` (stamps `stamps`) nearest to stamp t."""
    i = bisect.bisect_left(stamps, t)
    best = min((j for j in (i - 1, i) if 0 <= j < len(track)), key=lambda j: abs(stamps[j] - t))
    return track[best]


def errors(est, truth, T=None):
    """Position errors of `est` against `truth` after the rigid fit T (its own when None)."""
    stamps = [p[0] for p in truth]
    pairs = [((p[1], p[2]), at(truth, stamps, p[0])[1:3]) for p in est]
    T = T or fit(pairs)
    out = []
    for p, (_, g) in zip(est, pairs):
        q = apply(T, p)
        out.append(math.hypot(q[0] - g[0], q[1] - g[1]))
    return out, T


def rmse(v):
    return math.sqrt(sum(x * x for x in v) / len(v)) if v else float("nan")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--world", default="home")
    ap.add_argument("--sessions", type=int, default=10)
    ap.add_argument("--laps", type=int, default=1)
    ap.add_argument("--duration", type=float, help="seconds per session instead of --laps")
    ap.add_argument("--cycle", type=int, help="repeat the world's first N sets of changes")
    ap.add_argument("--fresh", action="store_true", help="also map each session's bag alone")
    ap.add_argument("--out", default="target/bench-lifelong")
    ap.add_argument("--bin", default="target/release/cloi")
    ap.add_argument("--png", help="write the curves (needs matplotlib)")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    length = ["--duration", str(a.duration)] if a.duration else ["--laps", str(a.laps)]
    rows, T0 = [], None
    for k in range(a.sessions):
        d = os.path.join(a.out, f"s{k}")
        bag = f"{d}.mcap"
        world = (k - 1) % a.cycle + 1 if a.cycle and k > 0 else k
        run([a.bin, "sim", "--world", a.world, "--session", str(world), "--seed", str(SEED0 + k),
             "--sensors", "L", "--quiet", "--out", bag] + length)
        cmap = f"{d}.cloimap"
        cmd = [a.bin, "map", bag, "--deterministic", "--quiet", "--save", cmap, "--out", d]
        if k == 0:
            cmd += ["--profile", a.world]
        else:
            cmd += ["--load", os.path.join(a.out, f"s{k - 1}.cloimap"), "--initial-pose", "0,0,0"]
        run(cmd)
        r = json.load(open(f"{d}/report.json"))
        truth = tum(bag.replace(".mcap", ".gt.tum"))
        final, T = errors(tum(f"{d}/trajectory.tum"), truth)
        if T0 is None:
            T0 = T
        in_map, _ = errors(tum(f"{d}/trajectory.tum"), truth, T0)
        rt, _ = errors(tum(f"{d}/gpe.tum"), truth)
        shown = json.loads(run([a.bin, "show-map", cmap]).stdout)
        row = {
            "session": k,
            "world": world,
            "fix_s": (r.get("localization") or {}).get("time_to_first_fix_s"),
            "joined": (r.get("session") or {}).get("joined", k == 0),
            "nodes": shown["nodes"],
            "edges": shown["edges"],
            "submaps": shown["submaps"],
            "file_bytes": os.path.getsize(cmap),
            "peak_rss_mb": r["peak_rss_bytes"] / 1e6,
            "keyframes": r["keyframes"],
            "dropped": r["mapper"]["keyframes_dropped"],
            "loops": r["loop_closures"],
            "prunes": r["mapper"]["prunes"],
            "ate_rmse": rmse(final),
            "ate_max": max(final),
            "ate_map_frame_rmse": rmse(in_map),
            "rt_rmse": rmse(rt),
            "rt_p95": quantile(rt, 0.95),
        }
        if a.fresh:
            f = f"{d}-fresh"
            run([a.bin, "map", bag, "--profile", a.world, "--deterministic", "--quiet", "--out", f])
            row["fresh_ate_rmse"] = rmse(errors(tum(f"{f}/trajectory.tum"), truth)[0])
        rows.append(row)
        print(json.dumps(row), flush=True)
        os.remove(bag)
    json.dump(rows, open(os.path.join(a.out, "lifelong.json"), "w"), indent=1)
    cols = ["session", "fix_s", "nodes", "edges", "submaps", "file_bytes", "peak_rss_mb",
            "keyframes", "dropped", "loops", "prunes", "ate_rmse", "ate_max",
            "ate_map_frame_rmse", "rt_rmse", "rt_p95"] + (["fresh_ate_rmse"] if a.fresh else [])
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for row in rows:
        cells = []
        for c in cols:
            v = row[c]
            cells.append(f"{v:.3f}" if isinstance(v, float) else str(v))
        print("| " + " | ".join(cells) + " |")
    if a.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        s = [r["session"] for r in rows]
        fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
        ax[0].plot(s, [r["file_bytes"] / 1e6 for r in rows], "o-", label="map file (MB)")
        ax[0].plot(s, [r["peak_rss_mb"] for r in rows], "s-", label="peak RSS (MB)")
        ax[0].set_ylim(bottom=0)
        ax[0].legend()
        ax[0].set_title("memory")
        ax[1].plot(s, [r["nodes"] for r in rows], "o-", label="graph nodes")
        ax[1].plot(s, [r["submaps"] * 10 for r in rows], "s-", label="submaps x10")
        ax[1].set_ylim(bottom=0)
        ax[1].legend()
        ax[1].set_title("map")
        ax[2].plot(s, [r["ate_rmse"] for r in rows], "o-", label="final ATE RMSE (m)")
        ax[2].plot(s, [r["ate_map_frame_rmse"] for r in rows], "^-", label="in session 0's frame")
        ax[2].plot(s, [r["rt_rmse"] for r in rows], "s-", label="real-time RMSE (m)")
        if a.fresh:
            ax[2].plot(s, [r["fresh_ate_rmse"] for r in rows], "x--", label="bag mapped alone")
        ax[2].set_yscale("log")
        ax[2].legend(fontsize=7)
        ax[2].set_title("error")
        for x in ax:
            x.set_xlabel("session")
        fig.tight_layout()
        fig.savefig(a.png, dpi=90)


if __name__ == "__main__":
    main()
