//! Planar motion between two camera frames from their matched features (the visual odometry of
//! section III-B.1, before any 3D point exists): the heading change, which the wheels get
//! wrong first (slip in turns) and which spoils triangulation most, corrected from the images.
//!
//! For a right match, the ray of frame A, the ray of frame B and the segment between the two
//! camera centres lie in one plane (the epipolar constraint). The residual of a match is the
//! sine of the angle between that segment and the plane of its two rays, so it does not depend
//! on how far the point is. The robot moves on the floor along arcs: a heading error that built
//! up steadily along the way turns the chord between the two poses by half as much, so frame
//! B's pose is the odometry's with its heading changed by `delta` and its chord turned by
//! `delta / 2`, its length kept (two views alone do not fix the scale). Only `delta` is
//! estimated: the heading and the direction of travel cannot be told apart well by a narrow
//! view of a ceiling, and the wheels do know which way they rolled. A few Gauss-Newton steps
//! from the odometry, with Huber weights so that wrong matches pull little, and a step that
//! raises the cost is halved.

use nalgebra::{Vector2, Vector3};

use super::camera::{CameraExtrinsic, CameraModel};
use super::triangulate::CameraPose;
use crate::geom::Se2;

/// Refinement parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TwoViewConfig {
    /// Gauss-Newton steps at most.
    pub iterations: u32,
    /// Residual beyond which a match's weight falls (Huber), as an angle's sine: about two
    /// pixels at a quarter-VGA focal length.
    pub huber: f64,
    /// Shortest odometry distance that fixes a direction of travel, metres.
    pub min_distance: f64,
    /// Fewest usable matches.
    pub min_matches: usize,
}

impl Default for TwoViewConfig {
    fn default() -> Self {
        TwoViewConfig {
            iterations: 10,
            huber: 0.015,
            min_distance: 0.02,
            min_matches: 8,
        }
    }
}

/// Why no motion was estimated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TwoViewError {
    /// The odometry moved too little for a direction of travel.
    TooShort,
    /// Too few matches had a bearing in the camera model.
    TooFewMatches,
    /// The matches do not constrain the heading (all rays in one plane with the baseline).
    Degenerate,
}

/// The refined motion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanarMotion {
    /// Frame B's robot pose relative to frame A's.
    pub motion: Se2,
    /// Median absolute residual at the result (sine of an angle).
    pub median_residual: f64,
    /// Matches used.
    pub matches: usize,
}

/// The bearings of the matches in their own camera frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BearingPair {
    /// Unit bearing in camera A.
    pub a: Vector3<f64>,
    /// Unit bearing in camera B.
    pub b: Vector3<f64>,
}

impl BearingPair {
    /// The bearings of pixel `a` in frame A and `b` in frame B, or `None` outside the lens.
    pub fn of_pixels(model: &CameraModel, a: &Vector2<f64>, b: &Vector2<f64>) -> Option<Self> {
        Some(BearingPair {
            a: model.unproject(a)?,
            b: model.unproject(b)?,
        })
    }
}

/// Epipolar residual of one match with frame A's camera at `cam_a` and frame B's at `cam_b`.
fn residual(cam_a: &CameraPose, cam_b: &CameraPose, m: &BearingPair) -> f64 {
    let (da, db) = (cam_a.rotation * m.a, cam_b.rotation * m.b);
    let normal = da.cross(&db);
    let baseline = cam_b.centre - cam_a.centre;
    let scale = normal.norm() * baseline.norm();
    if scale > 0.0 {
        normal.dot(&baseline) / scale
    } else {
        0.0
    }
}

/// The robot's motion from frame A to frame B: `odometry` (B relative to A) with its heading
/// change and its direction of travel refined from the bearings of `matches`, its distance
/// kept. `scratch` holds one residual per match (at least `matches.len()`).
///
/// # Errors
/// [`TwoViewError`] when the pair cannot fix them.
pub fn refine_planar_motion(
    mount: &CameraExtrinsic,
    odometry: &Se2,
    matches: &[BearingPair],
    cfg: &TwoViewConfig,
    scratch: &mut [f64],
) -> Result<PlanarMotion, TwoViewError> {
    let distance = libm::hypot(odometry.x, odometry.y);
    if distance < cfg.min_distance {
        return Err(TwoViewError::TooShort);
    }
    let n = matches.len().min(scratch.len());
    if n < cfg.min_matches {
        return Err(TwoViewError::TooFewMatches);
    }
    let cam_a = CameraPose::of_robot(&Se2::IDENTITY, mount);
    let chord = libm::atan2(odometry.y, odometry.x);
    let motion_of = |theta: f64| {
        let direction = chord + 0.5 * (theta - odometry.theta);
        Se2::new(
            distance * libm::cos(direction),
            distance * libm::sin(direction),
            theta,
        )
    };
    let matches = matches.get(..n).unwrap_or_default();
    let huber = |r: f64| {
        let a = libm::fabs(r);
        if a <= cfg.huber {
            0.5 * r * r
        } else {
            cfg.huber * (a - 0.5 * cfg.huber)
        }
    };
    // Frame B's camera for a heading change `theta` (placed once per trial, not per match).
    let camera_b = |theta: f64| CameraPose::of_robot(&motion_of(theta), mount);
    let cost = |theta: f64| -> f64 {
        let cam_b = camera_b(theta);
        matches
            .iter()
            .map(|m| huber(residual(&cam_a, &cam_b, m)))
            .sum()
    };
    let mut theta = odometry.theta;
    let mut current = cost(theta);
    const STEP: f64 = 1e-6;
    for _ in 0..cfg.iterations {
        let (at, up, down) = (
            camera_b(theta),
            camera_b(theta + STEP),
            camera_b(theta - STEP),
        );
        let (mut h, mut g) = (0.0, 0.0);
        for m in matches {
            let r = residual(&cam_a, &at, m);
            let j = (residual(&cam_a, &up, m) - residual(&cam_a, &down, m)) / (2.0 * STEP);
            let w = if libm::fabs(r) <= cfg.huber {
                1.0
            } else {
                cfg.huber / libm::fabs(r)
            };
            h += w * j * j;
            g += w * j * r;
        }
        // Also refuses NaN: no usable derivative at all.
        let constrained = h > 0.0;
        if !constrained {
            return Err(TwoViewError::Degenerate);
        }
        let mut delta = -g / h;
        // Halve a step that raises the cost (the Huber weights change under it).
        let mut accepted = false;
        for _ in 0..8 {
            let trial = cost(theta + delta);
            if trial <= current {
                (theta, current, accepted) = (theta + delta, trial, true);
                break;
            }
            delta *= 0.5;
        }
        if !accepted || libm::fabs(delta) < 1e-9 {
            break;
        }
    }
    let (motion, cam_b) = (motion_of(theta), camera_b(theta));
    let residuals = scratch.get_mut(..n).unwrap_or_default();
    for (slot, m) in residuals.iter_mut().zip(matches) {
        *slot = libm::fabs(residual(&cam_a, &cam_b, m));
    }
    let mid = n / 2;
    crate::sort::select_nth_by(residuals, mid, |a, b| a.total_cmp(b));
    Ok(PlanarMotion {
        motion,
        median_residual: residuals.get(mid).copied().unwrap_or(f64::NAN),
        matches: n,
    })
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use crate::frontend::visual::synth::cleaner_camera;

    /// Bearings of ceiling points 2.4 m up seen from the origin and from `truth`.
    fn sightings(mount: &CameraExtrinsic, truth: &Se2) -> std::vec::Vec<BearingPair> {
        let (a, b) = (
            CameraPose::of_robot(&Se2::IDENTITY, mount),
            CameraPose::of_robot(truth, mount),
        );
        let mut out = std::vec::Vec::new();
        for i in 0..40 {
            let (u, v) = (f64::from(i % 8), f64::from(i / 8));
            let p = Vector3::new(1.2 + 0.35 * u, -1.0 + 0.5 * v, 2.4);
            let (ra, rb) = (a.world_to_camera(&p), b.world_to_camera(&p));
            if ra.z > 0.2 && rb.z > 0.2 {
                out.push(BearingPair {
                    a: ra.normalize(),
                    b: rb.normalize(),
                });
            }
        }
        out
    }

    #[test]
    fn the_heading_and_direction_come_back_from_a_wrong_odometry() {
        let (_, mount) = cleaner_camera();
        let truth = Se2::new(0.33, 0.05, 0.12);
        let mut matches = sightings(&mount, &truth);
        assert!(matches.len() >= 20);
        // Two wrong matches: bearings of other points.
        let (m0, m1) = (matches[0], matches[1]);
        matches.push(BearingPair { a: m0.a, b: m1.b });
        matches.push(BearingPair { a: m1.a, b: m0.b });
        // The odometry: 3 % long, its heading 0.08 rad off and its chord 0.04 rad off, as a
        // heading error built up along the way leaves it.
        let (d, dir) = (
            1.03 * libm::hypot(truth.x, truth.y),
            libm::atan2(truth.y, truth.x) + 0.04,
        );
        let odometry = Se2::new(d * libm::cos(dir), d * libm::sin(dir), truth.theta + 0.08);
        let mut scratch = [0.0; 64];
        let r = refine_planar_motion(
            &mount,
            &odometry,
            &matches,
            &TwoViewConfig::default(),
            &mut scratch,
        )
        .expect("a motion");
        let dir = |p: &Se2| libm::atan2(p.y, p.x);
        assert!(libm::fabs(r.motion.theta - truth.theta) < 1e-3, "{r:?}");
        assert!(libm::fabs(dir(&r.motion) - dir(&truth)) < 2e-3, "{r:?}");
        // The distance stays the odometry's.
        let d = |p: &Se2| libm::hypot(p.x, p.y);
        assert!(libm::fabs(d(&r.motion) - d(&odometry)) < 1e-12);
        // Not zero: the camera sits 0.1 m ahead of the turning centre, so the direction of
        // its baseline depends a little on the distance, here the odometry's 3 % long one.
        assert!(
            r.median_residual < 0.1 * TwoViewConfig::default().huber,
            "{r:?}"
        );
    }

    #[test]
    fn standing_still_or_too_few_matches_fix_nothing() {
        let (_, mount) = cleaner_camera();
        let matches = sightings(&mount, &Se2::new(0.3, 0.0, 0.0));
        let mut scratch = [0.0; 64];
        let cfg = TwoViewConfig::default();
        assert_eq!(
            refine_planar_motion(
                &mount,
                &Se2::new(0.005, 0.0, 0.2),
                &matches,
                &cfg,
                &mut scratch
            ),
            Err(TwoViewError::TooShort)
        );
        assert_eq!(
            refine_planar_motion(
                &mount,
                &Se2::new(0.3, 0.0, 0.0),
                &matches[..3],
                &cfg,
                &mut scratch
            ),
            Err(TwoViewError::TooFewMatches)
        );
    }
}
