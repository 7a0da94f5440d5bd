//! Robot paths: the route of a world expanded into straight drives and pure rotations with
//! trapezoidal speed profiles, repeated as a loop. A cleaning robot's zigzag coverage turns in
//! place at every lane end; a guide robot's tour returns to its points of interest, closing
//! loops. The trajectory is the exact ground truth: every sensor samples it.

use cloi_core::geom::{wrap_angle, Se2};

use crate::world::{LegSpec, RouteSpec, P2};

/// Speed limits of a robot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MotionLimits {
    /// Top forward speed, m/s.
    pub speed: f64,
    /// Forward acceleration, m/s^2.
    pub accel: f64,
    /// Top turn rate, rad/s.
    pub turn_rate: f64,
    /// Angular acceleration, rad/s^2.
    pub turn_accel: f64,
}

/// The state of the robot at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct State {
    /// Pose in the world.
    pub pose: Se2,
    /// Forward speed, m/s.
    pub v: f64,
    /// Turn rate, rad/s.
    pub w: f64,
    /// Forward acceleration, m/s^2.
    pub a: f64,
    /// Distance driven since the start, metres.
    pub distance: f64,
    /// Heading without wrapping, radians (its change is the integral of `w`).
    pub heading: f64,
}

#[derive(Clone, Copy, Debug)]
enum Kind {
    Drive(f64),
    Turn(f64),
}

#[derive(Clone, Copy, Debug)]
struct Motion {
    t0: f64,
    duration: f64,
    x: f64,
    y: f64,
    heading: f64,
    distance: f64,
    kind: Kind,
}

/// A time-parametrised ground-truth trajectory.
#[derive(Clone, Debug)]
pub struct Trajectory {
    motions: Vec<Motion>,
    end: State,
}

/// Duration of a trapezoidal profile over `len` (> 0).
fn trapezoid_duration(len: f64, vmax: f64, acc: f64) -> f64 {
    if len * acc >= vmax * vmax {
        len / vmax + vmax / acc
    } else {
        2.0 * (len / acc).sqrt()
    }
}

/// Position, speed and acceleration at time `t` into a trapezoidal profile over `len`.
fn trapezoid_at(len: f64, vmax: f64, acc: f64, t: f64) -> (f64, f64, f64) {
    let total = trapezoid_duration(len, vmax, acc);
    let t = t.clamp(0.0, total);
    let peak = vmax.min((len * acc).sqrt());
    let ramp = peak / acc;
    if t < ramp {
        (0.5 * acc * t * t, acc * t, acc)
    } else if t > total - ramp {
        let r = total - t;
        (len - 0.5 * acc * r * r, acc * r, -acc)
    } else {
        (0.5 * acc * ramp * ramp + peak * (t - ramp), peak, 0.0)
    }
}

/// Expands a route into the list of points visited in one lap, starting at `route.start`.
pub fn route_points(route: &RouteSpec) -> Vec<P2> {
    let mut pts = vec![route.start];
    for leg in &route.legs {
        match leg {
            LegSpec::Waypoints { points } => pts.extend_from_slice(points),
            LegSpec::Zigzag {
                min,
                max,
                spacing,
                vertical,
            } => {
                let (a, b) = if *vertical { (1, 0) } else { (0, 1) };
                let lanes = ((max[b] - min[b]) / spacing).floor() as usize + 1;
                for k in 0..lanes {
                    let across = min[b] + k as f64 * spacing;
                    let (from, to) = if k % 2 == 0 {
                        (min[a], max[a])
                    } else {
                        (max[a], min[a])
                    };
                    for along in [from, to] {
                        let mut p = [0.0; 2];
                        p[a] = along;
                        p[b] = across;
                        pts.push(p);
                    }
                }
            }
        }
    }
    pts.push(route.start);
    pts
}

/// Length (m) and duration (s) of one lap of the route with the given limits, turns included.
pub fn lap(route: &RouteSpec, limits: &MotionLimits) -> (f64, f64) {
    let pts = route_points(route);
    let mut heading = None;
    let (mut length, mut time) = (0.0, 0.0);
    for pair in pts.windows(2) {
        let (dx, dy) = (pair[1][0] - pair[0][0], pair[1][1] - pair[0][1]);
        let len = dx.hypot(dy);
        if len < 1e-6 {
            continue;
        }
        let dir = dy.atan2(dx);
        if let Some(h) = heading {
            let turn: f64 = wrap_angle(dir - h);
            if turn.abs() > 1e-9 {
                time += trapezoid_duration(turn.abs(), limits.turn_rate, limits.turn_accel);
            }
        }
        heading = Some(dir);
        time += trapezoid_duration(len, limits.speed, limits.accel);
        length += len;
    }
    (length, time)
}

impl Trajectory {
    /// Drives the route (as a loop) with the given limits until at least `duration` seconds
    /// are covered.
    pub fn new(route: &RouteSpec, limits: &MotionLimits, duration: f64) -> Trajectory {
        let lap = route_points(route);
        let mut motions = Vec::new();
        let (mut x, mut y) = (route.start[0], route.start[1]);
        let mut heading = lap
            .iter()
            .find(|p| (p[0] - x).hypot(p[1] - y) > 1e-6)
            .map_or(0.0, |p| (p[1] - y).atan2(p[0] - x));
        let mut t = 0.0;
        let mut distance = 0.0;
        let mut progress = true;
        while t < duration && progress {
            progress = false;
            for p in lap.iter().skip(1) {
                let (dx, dy) = (p[0] - x, p[1] - y);
                let len = dx.hypot(dy);
                if len < 1e-6 {
                    continue;
                }
                progress = true;
                let turn = wrap_angle(dy.atan2(dx) - heading);
                if turn.abs() > 1e-9 {
                    let dur = trapezoid_duration(turn.abs(), limits.turn_rate, limits.turn_accel);
                    motions.push(Motion {
                        t0: t,
                        duration: dur,
                        x,
                        y,
                        heading,
                        distance,
                        kind: Kind::Turn(turn),
                    });
                    t += dur;
                    heading += turn;
                }
                let dur = trapezoid_duration(len, limits.speed, limits.accel);
                motions.push(Motion {
                    t0: t,
                    duration: dur,
                    x,
                    y,
                    heading,
                    distance,
                    kind: Kind::Drive(len),
                });
                t += dur;
                x = p[0];
                y = p[1];
                distance += len;
                if t >= duration {
                    break;
                }
            }
        }
        let end = State {
            pose: Se2::new(x, y, heading),
            v: 0.0,
            w: 0.0,
            a: 0.0,
            distance,
            heading,
        };
        Trajectory { motions, end }
    }

    /// The robot state at time `t` (seconds); before 0 the start, after the end the end.
    pub fn at(&self, t: f64, limits: &MotionLimits) -> State {
        let idx = self.motions.partition_point(|m| m.t0 <= t);
        let Some(m) = idx.checked_sub(1).and_then(|i| self.motions.get(i)) else {
            return match self.motions.first() {
                Some(m) => State {
                    pose: Se2::new(m.x, m.y, m.heading),
                    v: 0.0,
                    w: 0.0,
                    a: 0.0,
                    distance: 0.0,
                    heading: m.heading,
                },
                None => self.end,
            };
        };
        if t > m.t0 + m.duration && idx == self.motions.len() {
            return self.end;
        }
        let tau = (t - m.t0).min(m.duration);
        match m.kind {
            Kind::Drive(len) => {
                let (s, v, a) = trapezoid_at(len, limits.speed, limits.accel, tau);
                let (c, sn) = (m.heading.cos(), m.heading.sin());
                State {
                    pose: Se2::new(m.x + s * c, m.y + s * sn, m.heading),
                    v,
                    w: 0.0,
                    a,
                    distance: m.distance + s,
                    heading: m.heading,
                }
            }
            Kind::Turn(turn) => {
                let (s, w, _) = trapezoid_at(turn.abs(), limits.turn_rate, limits.turn_accel, tau);
                let sign = turn.signum();
                State {
                    pose: Se2::new(m.x, m.y, m.heading + sign * s),
                    v: 0.0,
                    w: sign * w,
                    a: 0.0,
                    distance: m.distance,
                    heading: m.heading + sign * s,
                }
            }
        }
    }

    /// Total duration of the planned motion, seconds.
    pub fn duration(&self) -> f64 {
        self.motions.last().map_or(0.0, |m| m.t0 + m.duration)
    }

    /// The straight drives as (from, to) pairs (for route checks and previews).
    pub fn drives(&self) -> impl Iterator<Item = (P2, P2)> + '_ {
        self.motions.iter().filter_map(|m| match m.kind {
            Kind::Drive(len) => Some((
                [m.x, m.y],
                [m.x + len * m.heading.cos(), m.y + len * m.heading.sin()],
            )),
            Kind::Turn(_) => None,
        })
    }

    /// Number of pure rotations.
    pub fn turns(&self) -> usize {
        self.motions
            .iter()
            .filter(|m| matches!(m.kind, Kind::Turn(_)))
            .count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIM: MotionLimits = MotionLimits {
        speed: 0.3,
        accel: 0.5,
        turn_rate: 1.0,
        turn_accel: 2.0,
    };

    #[test]
    fn zigzag_turns_in_place_and_integrates_consistently() {
        let route = RouteSpec {
            start: [0.0, 0.0],
            legs: vec![LegSpec::Zigzag {
                min: [0.0, 0.0],
                max: [2.0, 1.0],
                spacing: 0.5,
                vertical: false,
            }],
        };
        let traj = Trajectory::new(&route, &LIM, 60.0);
        assert!(traj.turns() >= 5);
        // Numerically integrate v and w and compare with the poses.
        let dt = 1e-3;
        let mut s = traj.at(0.0, &LIM);
        let (mut x, mut y, mut th) = (s.pose.x, s.pose.y, s.heading);
        let mut t = 0.0;
        while t < 40.0 {
            let mid = traj.at(t + 0.5 * dt, &LIM);
            x += mid.v * dt * mid.heading.cos();
            y += mid.v * dt * mid.heading.sin();
            th += mid.w * dt;
            t += dt;
            s = traj.at(t, &LIM);
            // Never moves and turns at once (pure rotations).
            assert!(mid.v == 0.0 || mid.w == 0.0);
        }
        assert!((x - s.pose.x).abs() < 1e-3 && (y - s.pose.y).abs() < 1e-3);
        assert!((th - s.heading).abs() < 1e-3);
    }
}
