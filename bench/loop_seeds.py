#!/usr/bin/env python3
"""Windowed loop matches against ground truth: is the truth inside the search window?

For one generated world mapped with the debug log of `mapper::loops` on
(`RUST_LOG=cloi_core=debug cloi map --sim-world ... --out DIR/map 2> DIR/debug.log`, the
simulation's ground truth in DIR/sim.gt.tum, `cloi eval loops ... > DIR/loops.json`), prints
for the right and the wrong matches (match error against ground truth <= / > 0.3 m) the true
error of the search's seed (the graph's estimate of the keyframe in the submap's anchor
frame) against the window's half-width: a wrong match whose truth lay outside the window had
no chance; one whose truth lay inside it picked a look-alike over the truth.

    bench/loop_seeds.py DIR [--list]
"""
import bisect
import math
import re
import sys

d = sys.argv[1]


def yaw(qz, qw):
    return 2 * math.atan2(qz, qw)


traj = {}
for line in open(d + "/map/trajectory.tum"):
    if line.startswith("#"):
        continue
    t, x, y, _, _, _, qz, qw = map(float, line.split())
    traj[(round(x, 4), round(y, 4))] = t
gt_t, gt = [], []
for line in open(d + "/sim.gt.tum"):
    t, x, y, _, _, _, qz, qw = map(float, line.split())
    gt_t.append(t)
    gt.append((x, y, yaw(qz, qw)))
# Keyframe serial -> time: graph.g2o's vertices are trajectory.tum's poses (same solution).
vt = {}
for line in open(d + "/map/graph.g2o"):
    p = line.split()
    if p[0] == "VERTEX_SE2":
        key = (round(float(p[2]), 4), round(float(p[3]), 4))
        if key in traj:
            vt[int(p[1])] = traj[key]


def gt_at(t):
    i = min(max(bisect.bisect_left(gt_t, t - 1e-6), 0), len(gt) - 1)
    return gt[i]


def rel(a, b):
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    return (c * dx + s * dy, -s * dx + c * dy)


pat = re.compile(r"loop match: (\d+) -> (\d+) window (\S+) angle \S+ .*?seed (\S+) (\S+) \S+ z (\S+) (\S+) \S+")
rows = []
for line in open(d + "/debug.log"):
    r = pat.search(line)
    if not r:
        continue
    a, k = int(r[1]), int(r[2])
    w, sx, sy, zx, zy = map(float, r.groups()[2:])
    if a not in vt or k not in vt:
        continue  # a keyframe pruned since
    tx, ty = rel(gt_at(vt[a]), gt_at(vt[k]))
    rows.append((a, k, w, math.hypot(sx - tx, sy - ty), math.hypot(zx - tx, zy - ty)))


def q(v, p):
    v = sorted(v)
    return v[int(p * (len(v) - 1))] if v else float("nan")


print(f"{d}: {len(rows)} matches with both keyframes kept")
for name, sel in (("right", [r for r in rows if r[4] <= 0.3]), ("wrong", [r for r in rows if r[4] > 0.3])):
    inside = sum(r[3] <= r[2] for r in sel)
    print(f"  {name} {len(sel)}: seed error median {q([r[3] for r in sel], .5):.2f} m, p90 "
          f"{q([r[3] for r in sel], .9):.2f}; window median {q([r[2] for r in sel], .5):.2f} m; "
          f"truth inside the window {inside}/{len(sel)}")
    if "--list" in sys.argv and name == "wrong":
        for r in sel:
            print(f"    {r[0]} -> {r[1]}: window {r[2]:.2f} seed error {r[3]:.2f} match error {r[4]:.2f}")
