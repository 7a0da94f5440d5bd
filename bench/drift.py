#!/usr/bin/env python3
"""Where a trajectory's drift builds up: its error against ground truth after aligning only the
first pose (no least-squares fit, so the error grows where the estimate goes wrong).

    bench/drift.py TRAJ.tum GT.tum [STEP_S]

prints every STEP_S seconds (default 100) the ground-truth position, the position error and the
heading error. Typical use on a `bench/generalize.sh` run:
`bench/drift.py OUT/gen_401_xl/map/gpe.tum OUT/gen_401_xl/sim.gt.tum 100`.
"""
import bisect
import math
import sys


def load(path):
    out = []
    for line in open(path):
        if line.startswith("#") or not line.strip():
            continue
        v = [float(x) for x in line.split()]
        out.append((v[0], v[1], v[2], 2.0 * math.atan2(v[6], v[7])))
    return out


def main():
    traj, gt = load(sys.argv[1]), load(sys.argv[2])
    step = float(sys.argv[3]) if len(sys.argv) > 3 else 100.0
    stamps = [g[0] for g in gt]

    def at(t):
        i = min(max(bisect.bisect_left(stamps, t), 0), len(gt) - 1)
        return gt[i]

    t0, x0, y0, h0 = traj[0]
    g0 = at(t0)
    dh = g0[3] - h0
    c, s = math.cos(dh), math.sin(dh)
    last = -math.inf
    for t, x, y, h in traj:
        if t - last < step:
            continue
        last = t
        ex = c * (x - x0) - s * (y - y0) + g0[1]
        ey = s * (x - x0) + c * (y - y0) + g0[2]
        g = at(t)
        err = math.hypot(ex - g[1], ey - g[2])
        dth = math.degrees(math.remainder(h + dh - g[3], 2.0 * math.pi))
        print(f"{t - t0:8.0f} s  gt=({g[1]:7.1f},{g[2]:7.1f})  err={err:6.2f} m  dtheta={dth:6.2f} deg")


if __name__ == "__main__":
    main()
