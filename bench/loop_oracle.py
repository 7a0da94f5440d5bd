#!/usr/bin/env python3
"""Two questions about one mapped generated world, answered with its ground truth.

    bench/loop_oracle.py RUN_DIR CLOI_BIN

RUN_DIR is one world's directory of a `bench/generalize.sh` run (map/graph.g2o,
map/trajectory.tum, sim.gt.tum).

1. Would the map be right without its wrong loop closures? Writes RUN_DIR/oracle.g2o: the
   final graph without the loop edges whose claim is more than 0.3 m off ground truth
   (switched off or not), optimizes it with `CLOI_BIN optimize` (plain least squares from the
   final poses) and prints the keyframe ATE RMSE (2D rigid fit) of the final graph and of that
   oracle solution. Where the oracle is right the failure is the wrong loops'; where it is
   not, the front-end or the missed revisits are to blame.
2. Do the odometry edges' informations say how well the front-end knew its motion? The squared
   Mahalanobis length of each odometry edge's true residual (claim against ground truth) under
   the edge's information: median, p90, p99 (3 degrees of freedom: 2.37, 6.25 and 11.34 when
   the information is right), the share beyond the 99 % bound and the worst edges.

Vertices are matched to trajectory scans by their printed pose (as `cloi eval loops` does).
"""
import bisect, json, math, subprocess, sys

if len(sys.argv) != 3:
    sys.exit(__doc__)
d, binary = sys.argv[1], sys.argv[2]


def load_tum(p):
    out = []
    for line in open(p):
        if line.startswith('#') or not line.strip():
            continue
        t, x, y, _, _, _, qz, qw = map(float, line.split()[:8])
        out.append((t, x, y, 2 * math.atan2(qz, qw)))
    return out


traj = load_tum(d + '/map/trajectory.tum')
gt = load_tum(d + '/sim.gt.tum')
gts = [g[0] for g in gt]


def gt_at(t):
    i = bisect.bisect_left(gts, t)
    if i <= 0:
        return gt[0][1:]
    if i >= len(gt):
        return gt[-1][1:]
    a, b = gt[i - 1], gt[i]
    f = (t - a[0]) / (b[0] - a[0]) if b[0] > a[0] else 0
    th = a[3] + f * math.atan2(math.sin(b[3] - a[3]), math.cos(b[3] - a[3]))
    return (a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]), th)


key = {}
for t, x, y, th in traj:
    key[(round(x, 4), round(y, 4), round(th, 3))] = t

verts, edges = {}, []
for line in open(d + '/map/graph.g2o'):
    f = line.split()
    if f[0] == 'VERTEX_SE2':
        verts[int(f[1])] = tuple(map(float, f[2:5]))
    elif f[0] == 'EDGE_SE2':
        edges.append((int(f[1]), int(f[2]), tuple(map(float, f[3:6])), f[6:]))

vt = {}
for i, (x, y, th) in verts.items():
    t = key.get((round(x, 4), round(y, 4), round(th, 3)))
    if t is not None:
        vt[i] = t


def between(a, b):
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    return (c * dx + s * dy, -s * dx + c * dy, math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2])))


kept, wrong, right_far = [], 0, 0
for i, j, z, info in edges:
    if abs(i - j) == 1:
        kept.append((i, j, z, info))
        continue
    if i not in vt or j not in vt:
        kept.append((i, j, z, info))
        continue
    g = between(gt_at(vt[i]), gt_at(vt[j]))
    e = math.hypot(g[0] - z[0], g[1] - z[1])
    if e > 0.3:
        wrong += 1
        continue
    if abs(vt[j] - vt[i]) > 300:
        right_far += 1
    kept.append((i, j, z, info))

with open(d + '/oracle.g2o', 'w') as o:
    for i in sorted(verts):
        x, y, th = verts[i]
        o.write(f'VERTEX_SE2 {i} {x} {y} {th}\n')
    for i, j, z, info in kept:
        o.write(f'EDGE_SE2 {i} {j} {z[0]} {z[1]} {z[2]} ' + ' '.join(info) + '\n')


def ate(poses):
    # SE(2) fit (Umeyama without scale) of poses {id: (x,y)} to ground truth.
    ids = [i for i in poses if i in vt]
    P = [poses[i][:2] for i in ids]
    G = [gt_at(vt[i])[:2] for i in ids]
    n = len(ids)
    mp = [sum(p[k] for p in P) / n for k in (0, 1)]
    mg = [sum(g[k] for g in G) / n for k in (0, 1)]
    sxx = sum((p[0] - mp[0]) * (g[0] - mg[0]) + (p[1] - mp[1]) * (g[1] - mg[1]) for p, g in zip(P, G))
    sxy = sum((p[0] - mp[0]) * (g[1] - mg[1]) - (p[1] - mp[1]) * (g[0] - mg[0]) for p, g in zip(P, G))
    a = math.atan2(sxy, sxx)
    c, s = math.cos(a), math.sin(a)
    err = 0
    for p, g in zip(P, G):
        x = c * (p[0] - mp[0]) - s * (p[1] - mp[1]) + mg[0]
        y = s * (p[0] - mp[0]) + c * (p[1] - mp[1]) + mg[1]
        err += (x - g[0]) ** 2 + (y - g[1]) ** 2
    return math.sqrt(err / n)


r = subprocess.run([binary, 'optimize', d + '/oracle.g2o', '--robust', 'none', '--quiet',
                    '--out', d + '/oracle_opt.g2o', '--max-iters', '200'], capture_output=True, text=True)
opt = {}
try:
    for line in open(d + '/oracle_opt.g2o'):
        f = line.split()
        if f[0] == 'VERTEX_SE2':
            opt[int(f[1])] = tuple(map(float, f[2:5]))
except OSError:
    print(r.stderr[-500:])
loops = len(edges) - sum(1 for e in edges if abs(e[0] - e[1]) == 1)
print(json.dumps({'run': d.rstrip('/').split('/')[-1], 'keyframes': len(verts), 'matched': len(vt),
                  'loops': loops, 'wrong_dropped': wrong, 'right_revisit_loops': right_far,
                  'ate_final': round(ate(verts), 3), 'ate_oracle': round(ate(opt), 3) if opt else None}))

# Odometry edges against ground truth: Mahalanobis length of the true residual.
rows = []
for i, j, z, info in edges:
    if abs(i - j) != 1 or i not in vt or j not in vt:
        continue
    g = between(gt_at(vt[i]), gt_at(vt[j]))
    e = [z[0] - g[0], z[1] - g[1], math.atan2(math.sin(z[2] - g[2]), math.cos(z[2] - g[2]))]
    a = list(map(float, info))
    I = [[a[0], a[1], a[2]], [a[1], a[3], a[4]], [a[2], a[4], a[5]]]
    m = sum(e[p] * I[p][q] * e[q] for p in range(3) for q in range(3))
    rows.append((m, vt[i], i, e[2], 1 / math.sqrt(I[2][2]), math.hypot(e[0], e[1])))
ms = sorted(r[0] for r in rows)
print('odometry edges', len(rows), 'chi2 median', round(ms[len(ms) // 2], 2), 'p90', round(ms[int(0.9 * len(ms))], 1), 'p99', round(ms[int(0.99 * len(ms))], 1), 'share > 11.3 (99%):', round(sum(1 for m in ms if m > 11.34) / len(ms), 3))
for r in sorted(rows, reverse=True)[:12]:
    print(f'  chi2 {r[0]:9.1f} t {r[1]:7.1f} node {r[2]} heading err {math.degrees(r[3]):6.2f} deg (sigma {math.degrees(r[4]):.2f}) xy err {r[5]:.3f}')
