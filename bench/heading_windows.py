#!/usr/bin/env python3
"""Where a real-time heading goes wrong, and what the robot could see there.

    bench/heading_windows.py WORLD.toml TRAJ.tum GT.tum

prints the three 20 s windows (at least 40 s apart) in which the heading error of TRAJ against
ground truth changes most, aligned at the first pose, with the robot's distance to the nearest
glass wall and the nearest opaque wall of the world file there. Typical use on a
`bench/generalize.sh` run: `cloi sim --world gen:206:m:nogyro --dump-world w.toml --duration 1
--sensors L --out /tmp/w.mcap`, then `bench/heading_windows.py w.toml
OUT/gen_206_m_nogyro/map/gpe.tum OUT/gen_206_m_nogyro/sim.gt.tum`.
"""
import bisect
import math
import sys
import tomllib

WINDOW_S = 20.0
APART_S = 40.0


def load_tum(path):
    """(stamp, x, y, yaw) per line of a TUM file."""
    poses = []
    for line in open(path):
        if line.startswith("#") or not line.strip():
            continue
        v = list(map(float, line.split()))
        poses.append((v[0], v[1], v[2], 2 * math.atan2(v[6], v[7])))
    return poses


def wrap(a):
    return math.atan2(math.sin(a), math.cos(a))


def segment_distance(p, a, b):
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2))
    return math.hypot(p[0] - a[0] - t * dx, p[1] - a[1] - t * dy)


def nearest_wall(world, p, glass):
    best = math.inf
    for wall in world["wall"]:
        if (wall.get("material") == "glass") != glass:
            continue
        pts = wall["points"] + ([wall["points"][0]] if wall.get("closed") else [])
        for a, b in zip(pts, pts[1:]):
            best = min(best, segment_distance(p, a, b))
    return best


def main():
    world_path, est_path, gt_path = sys.argv[1:4]
    world = tomllib.load(open(world_path, "rb"))
    est, gt = load_tum(est_path), load_tum(gt_path)
    gt_stamps = [g[0] for g in gt]

    def truth(t):
        return gt[min(max(bisect.bisect_left(gt_stamps, t), 0), len(gt) - 1)]

    # Heading error aligned at the first pose, unwrapped so that windows can be differenced.
    offset = truth(est[0][0])[3] - est[0][3]
    stamps, errors, total, previous = [], [], 0.0, None
    for e in est:
        err = wrap(e[3] + offset - truth(e[0])[3])
        if previous is not None:
            total += wrap(err - previous)
        previous = err
        stamps.append(e[0])
        errors.append(total)
    windows = []
    for i, t in enumerate(stamps):
        j = bisect.bisect_left(stamps, t + WINDOW_S)
        if j < len(stamps):
            change = errors[j] - errors[i]
            windows.append((abs(change), t, change))
    windows.sort(reverse=True)
    shown = []
    for _, t, change in windows:
        if any(abs(t - u) < APART_S for u in shown):
            continue
        shown.append(t)
        g = truth(t + WINDOW_S / 2)
        p = (g[1], g[2])
        print(f"t = {t - stamps[0]:6.0f} s: heading error {math.degrees(change):+6.1f} deg in "
              f"{WINDOW_S:.0f} s at ({p[0]:.1f}, {p[1]:.1f}): nearest glass "
              f"{nearest_wall(world, p, True):.1f} m, nearest wall {nearest_wall(world, p, False):.1f} m")
        if len(shown) == 3:
            break


if __name__ == "__main__":
    main()
