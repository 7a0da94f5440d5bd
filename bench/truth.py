"""Ground truth of one mapped generated world, shared by the bench scripts that judge a
final graph against it (`loop_oracle.py`, `loop_consistency.py`).

RUN_DIR is one world's directory of a `bench/generalize.sh` run: map/graph.g2o,
map/trajectory.tum and the simulator's sim.gt.tum. Graph vertices are matched to trajectory
scans by their printed pose (as `cloi eval loops` does), which gives each keyframe its stamp.
"""
import bisect
import math


def wrap(a):
    """The angle `a` in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


def load_tum(path):
    """The (t, x, y, heading) rows of a TUM trajectory file."""
    out = []
    for line in open(path):
        if line.startswith('#') or not line.strip():
            continue
        t, x, y, _, _, _, qz, qw = map(float, line.split()[:8])
        out.append((t, x, y, 2 * math.atan2(qz, qw)))
    return out


def between(a, b):
    """Pose b seen from pose a (planar)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    return (c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2]))


class Truth:
    """The run's ground truth and its graph's keyframe stamps."""

    def __init__(self, run_dir):
        self.gt = load_tum(run_dir + '/sim.gt.tum')
        self.stamps = [g[0] for g in self.gt]
        traj = load_tum(run_dir + '/map/trajectory.tum')
        key = {(round(x, 4), round(y, 4), round(th, 3)): t for t, x, y, th in traj}
        # Vertices of the final graph and their stamps (where the pose matched a scan).
        self.vertices = {}
        for line in open(run_dir + '/map/graph.g2o'):
            f = line.split()
            if f and f[0] == 'VERTEX_SE2':
                self.vertices[int(f[1])] = tuple(map(float, f[2:5]))
        self.vertex_stamp = {}
        for i, (x, y, th) in self.vertices.items():
            t = key.get((round(x, 4), round(y, 4), round(th, 3)))
            if t is not None:
                self.vertex_stamp[i] = t

    def at(self, t):
        """The true pose at time t, interpolated (clamped at the ends)."""
        gt = self.gt
        i = bisect.bisect_left(self.stamps, t)
        if i <= 0:
            return gt[0][1:]
        if i >= len(gt):
            return gt[-1][1:]
        a, b = gt[i - 1], gt[i]
        f = (t - a[0]) / (b[0] - a[0]) if b[0] > a[0] else 0
        return (a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]), a[3] + f * wrap(b[3] - a[3]))

    def relative(self, i, j):
        """The true pose of vertex j seen from vertex i, or None without both stamps."""
        if i not in self.vertex_stamp or j not in self.vertex_stamp:
            return None
        return between(self.at(self.vertex_stamp[i]), self.at(self.vertex_stamp[j]))

    def claim_error(self, i, j, z):
        """How far (m) an edge's claim z of vertex j seen from vertex i is from the truth, or
        None without both stamps."""
        g = self.relative(i, j)
        return None if g is None else math.hypot(g[0] - z[0], g[1] - z[1])

    def ate(self, poses):
        """Keyframe ATE RMSE (m) of poses {vertex: (x, y, ...)} after a rigid 2D fit to the
        truth (Umeyama without scale)."""
        ids = [i for i in poses if i in self.vertex_stamp]
        P = [poses[i][:2] for i in ids]
        G = [self.at(self.vertex_stamp[i])[:2] for i in ids]
        n = len(ids)
        mp = [sum(p[k] for p in P) / n for k in (0, 1)]
        mg = [sum(g[k] for g in G) / n for k in (0, 1)]
        sxx = sum((p[0] - mp[0]) * (g[0] - mg[0]) + (p[1] - mp[1]) * (g[1] - mg[1])
                  for p, g in zip(P, G))
        sxy = sum((p[0] - mp[0]) * (g[1] - mg[1]) - (p[1] - mp[1]) * (g[0] - mg[0])
                  for p, g in zip(P, G))
        a = math.atan2(sxy, sxx)
        c, s = math.cos(a), math.sin(a)
        err = 0
        for p, g in zip(P, G):
            x = c * (p[0] - mp[0]) - s * (p[1] - mp[1]) + mg[0]
            y = s * (p[0] - mp[0]) + c * (p[1] - mp[1]) + mg[1]
            err += (x - g[0]) ** 2 + (y - g[1]) ** 2
        return math.sqrt(err / n)
