//! TUM and KITTI trajectories (`eval/traj.rs`, `eval/relations.rs`), then the ATE path on
//! the parsed trajectory against itself so that parsed numbers are also used.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    use cloi_host::eval::traj::{align, Alignment, Trajectory};
    let path = cloi_fuzz::scratch_file("traj", data);
    if let Ok(t) = Trajectory::load(&path) {
        let mut est = t.clone();
        let _ = align(&mut est, &t, Alignment::Se3);
        for p in &t.poses {
            let _ = p.rotation_angle();
        }
    }
    let _ = cloi_host::eval::relations::PlanarTrajectory::load_tum(&path);
    let _ = cloi_host::eval::relations::PlanarTrajectory::load_reference(&path);
});
