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
import json, math, subprocess, sys

from truth import Truth

if len(sys.argv) != 3:
    sys.exit(__doc__)
d, binary = sys.argv[1], sys.argv[2]

truth = Truth(d)
verts, vt = truth.vertices, truth.vertex_stamp
edges = []
for line in open(d + '/map/graph.g2o'):
    f = line.split()
    if f and f[0] == 'EDGE_SE2':
        edges.append((int(f[1]), int(f[2]), tuple(map(float, f[3:6])), f[6:]))


kept, wrong, right_far = [], 0, 0
for i, j, z, info in edges:
    if abs(i - j) == 1:
        kept.append((i, j, z, info))
        continue
    if i not in vt or j not in vt:
        kept.append((i, j, z, info))
        continue
    if truth.claim_error(i, j, z) > 0.3:
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
                  'ate_final': round(truth.ate(verts), 3),
                  'ate_oracle': round(truth.ate(opt), 3) if opt else None}))

# Odometry edges against ground truth: Mahalanobis length of the true residual.
rows = []
for i, j, z, info in edges:
    if abs(i - j) != 1 or i not in vt or j not in vt:
        continue
    g = truth.relative(i, j)
    e = [z[0] - g[0], z[1] - g[1], math.atan2(math.sin(z[2] - g[2]), math.cos(z[2] - g[2]))]
    a = list(map(float, info))
    I = [[a[0], a[1], a[2]], [a[1], a[3], a[4]], [a[2], a[4], a[5]]]
    m = sum(e[p] * I[p][q] * e[q] for p in range(3) for q in range(3))
    rows.append((m, vt[i], i, e[2], 1 / math.sqrt(I[2][2]), math.hypot(e[0], e[1])))
ms = sorted(r[0] for r in rows)
print('odometry edges', len(rows), 'chi2 median', round(ms[len(ms) // 2], 2), 'p90', round(ms[int(0.9 * len(ms))], 1), 'p99', round(ms[int(0.99 * len(ms))], 1), 'share > 11.3 (99%):', round(sum(1 for m in ms if m > 11.34) / len(ms), 3))
for r in sorted(rows, reverse=True)[:12]:
    print(f'  chi2 {r[0]:9.1f} t {r[1]:7.1f} node {r[2]} heading err {math.degrees(r[3]):6.2f} deg (sigma {math.degrees(r[4]):.2f}) xy err {r[5]:.3f}')
