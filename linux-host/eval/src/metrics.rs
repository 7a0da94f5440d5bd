//! Absolute and relative trajectory errors (ATE/APE and RPE), defined as `evo` defines them so
//! the numbers can be checked against it:
//! * ATE: after alignment, for each matched pose `E_i = Q_i^-1 P_i` (Q reference, P estimate);
//!   translation error `|t(E_i)|`, rotation error the angle of `R(E_i)`.
//! * RPE: for pose pairs `(i, j)` picked on the estimate every `delta` frames or metres of
//!   travelled path, `E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`; same two errors.

use anyhow::{bail, Result};
use serde::Serialize;

use crate::traj::{align, associate, Alignment, ErrorStats, Trajectory};

/// Unit of the RPE step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DeltaUnit {
    /// Poses.
    Frames,
    /// Metres of travelled path.
    Meters,
}

/// Result of the ATE.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AteResult {
    /// Matched poses.
    pub matched: usize,
    /// Alignment used.
    pub alignment: Alignment,
    /// Scale applied (1 without scale correction).
    pub scale: f64,
    /// Translation errors (m).
    pub translation_m: ErrorStats,
    /// Rotation errors (deg).
    pub rotation_deg: ErrorStats,
}

/// Result of the RPE.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RpeResult {
    /// Matched poses.
    pub matched: usize,
    /// Step.
    pub delta: f64,
    /// Its unit.
    pub delta_unit: DeltaUnit,
    /// Pose pairs compared.
    pub pairs: usize,
    /// Translation errors (m).
    pub translation_m: ErrorStats,
    /// Rotation errors (deg).
    pub rotation_deg: ErrorStats,
}

fn matched(
    est: &Trajectory,
    reference: &Trajectory,
    max_diff: f64,
) -> Result<(Trajectory, Trajectory)> {
    let pairs = associate(est, reference, max_diff);
    if pairs.len() < 2 {
        bail!(
            "only {} poses matched in time (max difference {max_diff} s)",
            pairs.len()
        );
    }
    let (ie, ir): (Vec<usize>, Vec<usize>) = pairs.into_iter().unzip();
    Ok((est.select(&ie), reference.select(&ir)))
}

/// Absolute trajectory error.
///
/// # Errors
/// Too few matched poses, or a degenerate alignment.
pub fn ate(
    est: &Trajectory,
    reference: &Trajectory,
    alignment: Alignment,
    max_diff: f64,
) -> Result<AteResult> {
    let (mut est, reference) = matched(est, reference, max_diff)?;
    let scale = align(&mut est, &reference, alignment)?;
    let mut trans = Vec::with_capacity(est.len());
    let mut rot = Vec::with_capacity(est.len());
    for (p, q) in est.poses.iter().zip(&reference.poses) {
        let e = q.inverse().compose(p);
        trans.push(e.t.norm());
        rot.push(e.rotation_angle().to_degrees());
    }
    Ok(AteResult {
        matched: est.len(),
        alignment,
        scale,
        translation_m: ErrorStats::of(&trans)?,
        rotation_deg: ErrorStats::of(&rot)?,
    })
}

/// Pose pairs of the RPE: every `delta` poses, or consecutive poses after at least `delta`
/// metres of travelled path, as `evo` picks them. Current evo starts the first pair at pose 0;
/// older evo versions (which made the stored `evo_results`) started it at the first pose
/// `delta` metres along: `first_at_delta` selects that.
pub fn rpe_pairs(
    traj: &Trajectory,
    delta: f64,
    unit: DeltaUnit,
    first_at_delta: bool,
) -> Vec<(usize, usize)> {
    match unit {
        DeltaUnit::Frames => {
            let step = (delta.round() as usize).max(1);
            (0..traj.len().saturating_sub(step))
                .step_by(step)
                .map(|i| (i, i + step))
                .collect()
        }
        DeltaUnit::Meters => {
            let positions = traj.positions();
            let mut ids = if first_at_delta { vec![] } else { vec![0] };
            let mut path = 0.0;
            for i in 1..positions.len() {
                path += (positions[i] - positions[i - 1]).norm();
                if path >= delta {
                    ids.push(i);
                    path = 0.0;
                }
            }
            ids.windows(2).map(|w| (w[0], w[1])).collect()
        }
    }
}

/// Relative pose error (alignment does not change it); see [`rpe_pairs`] for
/// `first_at_delta`.
///
/// # Errors
/// Too few matched poses or no pairs.
pub fn rpe(
    est: &Trajectory,
    reference: &Trajectory,
    delta: f64,
    unit: DeltaUnit,
    max_diff: f64,
    first_at_delta: bool,
) -> Result<RpeResult> {
    if !(delta.is_finite() && delta > 0.0) {
        bail!("the RPE step must be positive, got {delta}");
    }
    let (est, reference) = matched(est, reference, max_diff)?;
    let pairs = rpe_pairs(&est, delta, unit, first_at_delta);
    let mut trans = Vec::with_capacity(pairs.len());
    let mut rot = Vec::with_capacity(pairs.len());
    for &(i, j) in &pairs {
        let q_rel = reference.poses[i].inverse().compose(&reference.poses[j]);
        let p_rel = est.poses[i].inverse().compose(&est.poses[j]);
        let e = q_rel.inverse().compose(&p_rel);
        trans.push(e.t.norm());
        rot.push(e.rotation_angle().to_degrees());
    }
    Ok(RpeResult {
        matched: est.len(),
        delta,
        delta_unit: unit,
        pairs: pairs.len(),
        translation_m: ErrorStats::of(&trans)?,
        rotation_deg: ErrorStats::of(&rot)?,
    })
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector3};

    use super::*;
    use crate::traj::Pose3;

    fn circle(n: usize, noise: f64) -> Trajectory {
        Trajectory {
            stamps: (0..n).map(|i| i as f64 * 0.1).collect(),
            poses: (0..n)
                .map(|i| {
                    let a = i as f64 * 0.1;
                    let wobble = noise * (i as f64 * 1.7).sin();
                    Pose3::from_parts(
                        &UnitQuaternion::from_euler_angles(0.0, 0.0, a + 1.5 * wobble),
                        Vector3::new(5.0 * a.cos() + wobble, 5.0 * a.sin(), 0.0),
                    )
                })
                .collect(),
        }
    }

    #[test]
    fn ate_is_zero_for_a_moved_copy_after_alignment() {
        let reference = circle(50, 0.0);
        let mut est = reference.clone();
        est.transform(&Pose3::from_parts(
            &UnitQuaternion::from_euler_angles(0.0, 0.0, 0.8),
            Vector3::new(3.0, -1.0, 0.0),
        ));
        for how in [Alignment::Se3, Alignment::Se2, Alignment::Sim3] {
            let r = ate(&est, &reference, how, 0.01).unwrap();
            assert!(r.translation_m.max < 1e-9, "{how:?} {r:?}");
            assert!(r.rotation_deg.max < 1e-6);
        }
        let r = ate(&est, &reference, Alignment::None, 0.01).unwrap();
        assert!(r.translation_m.min > 0.1);
        assert_eq!(r.matched, 50);
    }

    #[test]
    fn rpe_ignores_a_global_motion_and_sees_noise() {
        let reference = circle(60, 0.0);
        let mut est = reference.clone();
        est.transform(&Pose3::translation(10.0, 0.0, 0.0));
        let r = rpe(&est, &reference, 1.0, DeltaUnit::Frames, 0.01, false).unwrap();
        assert_eq!(r.pairs, 59);
        assert!(r.translation_m.max < 1e-9);
        let noisy = circle(60, 0.05);
        let r = rpe(&noisy, &reference, 2.0, DeltaUnit::Meters, 0.01, false).unwrap();
        assert!(r.translation_m.mean > 1e-3);
        assert!(rpe(&noisy, &reference, 0.0, DeltaUnit::Frames, 0.01, false).is_err());
    }

    #[test]
    fn pairs_by_path_length() {
        let t = Trajectory {
            stamps: vec![0.0; 6],
            poses: [0.0, 0.6, 1.2, 1.5, 2.6, 2.7]
                .iter()
                .map(|&x| Pose3::translation(x, 0.0, 0.0))
                .collect(),
        };
        // Path since the last pick: 0.6, 1.2 -> pick 2; 0.3, 1.4 -> pick 4; 0.1.
        assert_eq!(
            rpe_pairs(&t, 1.0, DeltaUnit::Meters, false),
            vec![(0, 2), (2, 4)]
        );
        // Older evo: the first pick is 1 m along, at pose 2; then pose 4.
        assert_eq!(rpe_pairs(&t, 1.0, DeltaUnit::Meters, true), vec![(2, 4)]);
        assert_eq!(
            rpe_pairs(&t, 2.0, DeltaUnit::Frames, false),
            vec![(0, 2), (2, 4)]
        );
    }
}
