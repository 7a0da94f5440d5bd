#!/usr/bin/env python3
"""Side-by-side pose-graph benchmark: `cloi optimize` against g2o (pip `g2opy`) and GTSAM.

Every solver gets the same file and the same initial guess (the odometry chain, written once
by `cloi optimize --init odometry --max-iters 0 --no-linear-init`), runs single threaded
(the whole script is pinned to one CPU by bench/optimize.sh), and the runs alternate between
solvers. Final chi2 is computed for every solver by this script's own numpy implementation of
the g2o convention (sum of e^T Omega e, e = z^-1 (+) (x_i^-1 (+) x_j), angle wrapped), so the
column is comparable across solvers. Time is the solve alone (graph construction and file
reading excluded) and the table shows the median over the repetitions.

Not a test: timings depend on the machine and its load. Run it through bench/optimize.sh.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

FILES = ["M3500", "manhattan", "intel", "CSAIL", "FR079", "MITb", "city10000", "ring"]


def read_g2o(path):
    ids, poses, edges = [], {}, []
    with open(path) as f:
        for line in f:
            t = line.split()
            if not t:
                continue
            if t[0] == "VERTEX_SE2":
                poses[int(t[1])] = [float(v) for v in t[2:5]]
            elif t[0] == "EDGE_SE2":
                v = [float(x) for x in t[3:12]]
                i11, i12, i13, i22, i23, i33 = v[3:9]
                info = np.array([[i11, i12, i13], [i12, i22, i23], [i13, i23, i33]])
                edges.append((int(t[1]), int(t[2]), v[0:3], info))
    ids = sorted(poses)
    return ids, poses, edges


def wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def chi2_g2o(poses, edges):
    """poses: dict id -> (x, y, theta)."""
    i = np.array([e[0] for e in edges])
    j = np.array([e[1] for e in edges])
    z = np.array([e[2] for e in edges])
    om = np.array([e[3] for e in edges])
    p = np.array([poses[k] for k in range(len(poses))])
    xi, xj = p[i], p[j]
    c, s = np.cos(xi[:, 2]), np.sin(xi[:, 2])
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    tx, ty = c * dx + s * dy, -s * dx + c * dy
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    ux, uy = tx - z[:, 0], ty - z[:, 1]
    e = np.stack([cz * ux + sz * uy, -sz * ux + cz * uy, wrap(xj[:, 2] - xi[:, 2] - z[:, 2])], 1)
    return float(np.einsum("ni,nij,nj->", e, om, e))


def run_cloi(cloi, path, solver, report):
    subprocess.run(
        [cloi, "optimize", path, "--solver", solver, "--report", report, "--out", report + ".g2o"],
        check=False,
        stdout=subprocess.DEVNULL,
    )
    with open(report) as f:
        r = json.load(f)
    _, poses, _ = read_g2o(report + ".g2o")
    return r["time_ms"], poses


def run_g2o(path, lm):
    import g2opy as g2o

    opt = g2o.SparseOptimizer()
    block = g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())
    algo = g2o.OptimizationAlgorithmLevenberg(block) if lm else g2o.OptimizationAlgorithmGaussNewton(block)
    opt.set_algorithm(algo)
    if not opt.load(path):
        raise RuntimeError("g2o could not load " + path)
    opt.vertex(0).set_fixed(True)
    term = g2o.SparseOptimizerTerminateAction()
    term.set_gain_threshold(1e-8)
    term.set_max_iterations(100)
    opt.add_post_iteration_action(term)
    t0 = time.perf_counter()
    opt.initialize_optimization()
    opt.optimize(100)
    ms = (time.perf_counter() - t0) * 1e3
    poses = {}
    for vid, v in opt.vertices().items():
        est = v.estimate()
        poses[vid] = [est.translation()[0], est.translation()[1], est.rotation().angle()]
    return ms, poses


def run_gtsam(path, lm):
    import gtsam

    graph, initial = gtsam.readG2o(path, False)
    graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    if lm:
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        params.setRelativeErrorTol(1e-8)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    else:
        params = gtsam.GaussNewtonParams()
        params.setMaxIterations(100)
        params.setRelativeErrorTol(1e-8)
        opt = gtsam.GaussNewtonOptimizer(graph, initial, params)
    t0 = time.perf_counter()
    try:
        result = opt.optimize()
    except RuntimeError:
        return float("nan"), None
    ms = (time.perf_counter() - t0) * 1e3
    poses = {}
    for k in range(initial.size()):
        p = result.atPose2(k)
        poses[k] = [p.x(), p.y(), p.theta()]
    return ms, poses


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cloi", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--files", nargs="*", default=FILES)
    args = ap.parse_args()

    peers = {}
    try:
        import g2opy  # noqa: F401

        peers["g2o GN"] = lambda p: run_g2o(p, False)
        peers["g2o LM"] = lambda p: run_g2o(p, True)
    except ImportError:
        print("g2opy is not installed: comparing with GTSAM only", file=sys.stderr)
    peers["GTSAM GN"] = lambda p: run_gtsam(p, False)
    peers["GTSAM LM"] = lambda p: run_gtsam(p, True)

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.files:
            src = os.path.join(args.data, name + ".g2o")
            init = os.path.join(tmp, name + ".init.g2o")
            subprocess.run(
                [args.cloi, "optimize", src, "--init", "odometry", "--max-iters", "0",
                 "--no-linear-init", "--out", init],
                check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
            _, _, edges = read_g2o(init)
            solvers = {"cloi": lambda p: run_cloi(args.cloi, p, "auto", os.path.join(tmp, "r.json"))}
            solvers.update(peers)
            times = {k: [] for k in solvers}
            chi2 = {}
            for _ in range(args.reps):
                for label, fn in solvers.items():
                    ms, poses = fn(init)
                    times[label].append(ms)
                    chi2[label] = chi2_g2o(poses, edges) if poses else float("nan")
            med = {k: statistics.median(v) for k, v in times.items()}
            peer_times = [med[k] for k in peers if not np.isnan(med[k])
                          and np.isfinite(chi2[k]) and chi2[k] <= 1.001 * chi2["cloi"] + 0.01]
            fastest_peer = min(peer_times) if peer_times else float("nan")
            for label in solvers:
                rows.append((name, label, chi2[label], med[label], med[label] / fastest_peer))
            print(f"done {name}", file=sys.stderr)

    print("| file | solver | final chi2 | median time (ms) | time / fastest peer that reaches cloi's chi2 |")
    print("|---|---|---:|---:|---:|")
    for name, label, c, ms, ratio in rows:
        print(f"| {name} | {label} | {c:.2f} | {ms:.2f} | {ratio:.2f} |")


if __name__ == "__main__":
    main()
