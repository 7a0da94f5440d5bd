#!/usr/bin/env python3
"""Would a consistency test over the whole graph have kept the wrong loop closures out?
A prototype of a back-end test, measured against ground truth.

    bench/loop_consistency.py RUN_DIR

RUN_DIR is one world's directory of a `bench/generalize.sh` run (map/graph.g2o,
map/trajectory.tum, sim.gt.tum). Needs numpy and scipy (`pip install numpy scipy`).

The loop edges of the final graph are grouped into clusters, one per revisit of one place: the
edges to one anchor whose keyframes follow each other by at most 10 keyframes. The test is a likelihood ratio, as in RRR
(Latif, Cadena and Neira, 2013): with the odometry and a set of clusters solved by least squares
(Gauss-Newton here, from the final poses), removing a right cluster lowers the optimal total
cost by about its own degrees of freedom (3 per edge), since its edges agree with the rest;
removing a wrong one lowers it by far more, since the rest had to bend to fit it. So, starting
from every cluster: the cluster whose removal lowers the cost the most, relative to the chi2
99.9 % quantile of its degrees of freedom, is dropped while that ratio exceeds 1, and the set is
solved again. The fall in cost is the leave-out formula of linear least squares at the current
optimum, `e^T (Lambda^-1 - J H^-1 J^T)^-1 e` over the cluster's residuals `e`, Jacobian `J` and
information `Lambda`, with one factorization of the information matrix `H` per round. A group
of agreeing wrong matches (which the max-mixture keeps, since they outvote the odometry locally)
still bends the graph, and the total cost sees it.

Prints the keyframe ATE RMSE (2D rigid fit) of the final graph, of the graph solved with every
loop edge by plain least squares, and with the kept clusters only; then, from the final poses,
with the mapper's max-mixture on the loop edges (the null hypothesis taking an edge whose chi2
exceeds the two components' crossing), over every loop edge and over the kept ones; the
clusters dropped (edges, wrong edges: claims more than 0.3 m off ground truth, as `cloi eval
loops` counts them), and the wrong edges kept and right edges dropped.
"""
import json, math, sys, time
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.stats import chi2 as chi2_dist

from truth import Truth, wrap

if len(sys.argv) != 2:
    sys.exit(__doc__)
d = sys.argv[1]

truth = Truth(d)
verts, vt = truth.vertices, truth.vertex_stamp
odo, loops = [], []
for line in open(d + '/map/graph.g2o'):
    f = line.split()
    if f and f[0] == 'EDGE_SE2':
        i, j = int(f[1]), int(f[2])
        I = list(map(float, f[6:12]))
        M = np.array([[I[0], I[1], I[2]], [I[1], I[3], I[4]], [I[2], I[4], I[5]]])
        e = (i, j, np.array(list(map(float, f[3:6]))), M)
        (odo if abs(i - j) == 1 else loops).append(e)


def is_wrong(e):
    i, j, z, _ = e
    err = truth.claim_error(i, j, z)
    return None if err is None else err > 0.3


ids = sorted(verts)
col = {v: k for k, v in enumerate(ids)}


def residual(xi, xj, z):
    c, s = math.cos(xi[2]), math.sin(xi[2])
    dx, dy = xj[0] - xi[0], xj[1] - xi[1]
    r = (c * dx + s * dy, -s * dx + c * dy)
    cz, sz = math.cos(z[2]), math.sin(z[2])
    ex, ey = r[0] - z[0], r[1] - z[1]
    e = np.array([cz * ex + sz * ey, -sz * ex + cz * ey, wrap(xj[2] - xi[2] - z[2])])
    Rz = np.array([[cz, sz, 0], [-sz, cz, 0], [0, 0, 1]])
    A = np.array([[-c, -s, -s * dx + c * dy], [s, -c, -c * dx - s * dy], [0, 0, -1]])
    B = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    return e, Rz @ A, Rz @ B


# The mapper's max-mixture on loop edges (`loops.null_weight`, `loops.null_scale`): the null
# component wins when chi2 exceeds this.
NULL_W, NULL_S = 1e-3, 1e-6
NULL_CHI2 = (-2 * math.log(NULL_W) - 3 * math.log(NULL_S)) / (1 - NULL_S)


def normal_equations(x, edges, mixture=False):
    """The information matrix H (the first vertex held fixed) and gradient b at x."""
    n = 3 * len(ids)
    rows, cols, vals = [], [], []
    b = np.zeros(n)
    for i, j, z, M in edges:
        e, A, B = residual(x[i], x[j], z)
        if mixture and abs(i - j) != 1 and float(e @ M @ e) > NULL_CHI2:
            M = M * NULL_S
        ci, cj = 3 * col[i], 3 * col[j]
        for (ca, Ja) in ((ci, A), (cj, B)):
            b[ca:ca + 3] += Ja.T @ M @ e
            for (cb, Jb) in ((ci, A), (cj, B)):
                H = Ja.T @ M @ Jb
                for r_ in range(3):
                    for c_ in range(3):
                        rows.append(ca + r_)
                        cols.append(cb + c_)
                        vals.append(H[r_, c_])
    for k in range(3):
        rows.append(k)
        cols.append(k)
        vals.append(1e12)
    return sp.csc_matrix((vals, (rows, cols)), shape=(n, n)), b


def solve(x0, edges, iters=15, mixture=False):
    x = {k: np.array(v) for k, v in x0.items()}
    for _ in range(iters):
        H, b = normal_equations(x, edges, mixture)
        dx = spla.spsolve(H, -b)
        for v in ids:
            c0 = 3 * col[v]
            x[v] = x[v] + dx[c0:c0 + 3]
            x[v][2] = wrap(x[v][2])
        if np.max(np.abs(dx)) < 1e-4:
            break
    return x


def chi2(x, e):
    i, j, z, M = e
    r, _, _ = residual(x[i], x[j], z)
    return float(r @ M @ r)


# Clusters: one revisit of one place, the loop edges to one anchor whose keyframes follow each
# other by at most 10 (the edges sorted by keyframe).
loops.sort(key=lambda e: (e[1], e[0]))
clusters = []
open_by_anchor = {}
for e in loops:
    k = open_by_anchor.get(e[0])
    if k is not None and e[1] - clusters[k][-1][1] <= 10:
        clusters[k].append(e)
    else:
        open_by_anchor[e[0]] = len(clusters)
        clusters.append([e])

x_final = verts
x_all = solve(x_final, odo + loops)


def score(x, c):
    return sum(chi2(x, e) for e in c) / len(c)


def cost(x, edges):
    return sum(chi2(x, e) for e in edges)


def removal_gain(x, lu, cluster):
    """How much the optimal cost falls when `cluster` is removed (linearized at the optimum x):
    e^T (Lambda^-1 - J H^-1 J^T)^-1 e over the cluster's stacked residuals e."""
    m = 3 * len(cluster)
    e = np.zeros(m)
    Li = np.zeros((m, m))
    J = np.zeros((m, 3 * len(ids)))
    for k, (i, j, z, M) in enumerate(cluster):
        r, A, B = residual(x[i], x[j], z)
        e[3 * k:3 * k + 3] = r
        Li[3 * k:3 * k + 3, 3 * k:3 * k + 3] = np.linalg.inv(M)
        J[3 * k:3 * k + 3, 3 * col[i]:3 * col[i] + 3] += A
        J[3 * k:3 * k + 3, 3 * col[j]:3 * col[j] + 3] += B
    W = lu.solve(J.T)
    S = Li - J @ W
    return float(e @ np.linalg.solve(S, e))


kept = list(range(len(clusters)))
dropped = []
x = x_all
t0 = time.time()
while True:
    lu = spla.splu(normal_equations(x, odo + [e for q in kept for e in clusters[q]])[0])
    best = None
    for k in kept:
        ratio = removal_gain(x, lu, clusters[k]) / chi2_dist.ppf(0.999, 3 * len(clusters[k]))
        if ratio > 1 and (best is None or ratio > best[0]):
            best = (ratio, k)
    if best is None:
        break
    ratio, k = best
    kept.remove(k)
    dropped.append(k)
    x = solve(x, odo + [e for q in kept for e in clusters[q]])
    c = clusters[k]
    print(f'dropped a cluster of {len(c)} edges ({sum(1 for e in c if is_wrong(e))} wrong): '
          f'cost ratio {ratio:.1f}', flush=True)

kept_edges = [e for q in kept for e in clusters[q]]
x_mm_all = solve(x_final, odo + loops, iters=30, mixture=True)
x_mm = solve(x_final, odo + kept_edges, iters=30, mixture=True)
dropped_edges = [e for q in dropped for e in clusters[q]]
print(json.dumps({
    'run': d.rstrip('/').split('/')[-1], 'loops': len(loops), 'clusters': len(clusters),
    'wrong': sum(1 for e in loops if is_wrong(e)), 'dropped_clusters': len(dropped),
    'wrong_kept': sum(1 for e in kept_edges if is_wrong(e)),
    'right_dropped': sum(1 for e in dropped_edges if is_wrong(e) is False),
    'ate_final': round(truth.ate(x_final), 3), 'ate_all_least_squares': round(truth.ate(x_all), 3),
    'ate_consistent': round(truth.ate(x), 3), 'ate_all_max_mixture': round(truth.ate(x_mm_all), 3),
    'ate_consistent_max_mixture': round(truth.ate(x_mm), 3), 'seconds': round(time.time() - t0)}))
