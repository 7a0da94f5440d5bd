//! Tests of grid-cell pruning: one node per cell, the optimum and the uncertainty kept.

use super::*;
use crate::geom::spd_inverse;
use crate::graph::{EdgeKind, GraphStorage};
use crate::solver::{solve, SolverOptions, SolverWorkspace};
use crate::storage::NodeId;
use nalgebra::Vector3;

#[test]
fn reversed_information_matches_numeric_propagation() {
    let z = Se2::new(1.2, -0.7, 0.9);
    let cov = Matrix3::new(0.02, 0.003, 0.001, 0.003, 0.05, -0.002, 0.001, -0.002, 0.01);
    let info = spd_inverse(&cov).unwrap();
    // e' as a function of e: z^-1 seen reversed is (z (+) e)^-1, measured against z^-1.
    let f = |e: Vector3<f64>| {
        let zi = z.inverse();
        zi.inverse()
            .compose(&z.compose(&Se2::from_vector(&e)).inverse())
            .to_vector()
    };
    let h = 1e-7;
    let mut a = Matrix3::zeros();
    for k in 0..3 {
        let mut d = Vector3::zeros();
        d[k] = h;
        a.set_column(k, &((f(d) - f(-d)) / (2.0 * h)));
    }
    let expected = spd_inverse(&(a * cov * a.transpose())).unwrap();
    let got = reversed_information(&z, &info);
    assert!(
        (got - expected).amax() < 1e-5 * expected.amax(),
        "{got} vs {expected}"
    );
}

/// A square loop of side 4 m walked in 0.25 m steps with a loop closure, noise-free.
fn square_loop(g: &mut PoseGraph<'_>) {
    let info = Matrix3::from_diagonal(&Vector3::new(100.0, 100.0, 400.0));
    let mut pose = Se2::IDENTITY;
    let mut n = 0u32;
    g.add_node(pose).unwrap();
    for side in 0..4 {
        for step in 0..16 {
            let turn = if step == 15 && side < 3 {
                core::f64::consts::FRAC_PI_2
            } else {
                0.0
            };
            let z = Se2::new(0.25, 0.0, turn);
            pose = pose.compose(&z);
            g.add_node(pose).unwrap();
            g.add_edge(PoseEdge::new(
                NodeId(n),
                NodeId(n + 1),
                z,
                info,
                EdgeKind::Odometry,
            ))
            .unwrap();
            n += 1;
        }
    }
    let first = g.node(NodeId(0)).unwrap().pose;
    let z = pose.between(&first);
    g.add_edge(PoseEdge::new(NodeId(n), NodeId(0), z, info, EdgeKind::Loop))
        .unwrap();
}

#[test]
fn pruning_a_loop_keeps_one_node_per_cell_and_the_optimum() {
    let mut storage = GraphStorage::<128, 256>::new();
    let mut g = storage.graph();
    square_loop(&mut g);
    let before: std::vec::Vec<Se2> = g.nodes().iter().map(|n| n.pose).collect();
    extern crate std;
    let mut scratch = PruneStorage::<128, 256>::new();
    let params = PruneParams {
        cells: CellParams {
            cell_size: 1.0,
            s: 0.5,
        },
        ..PruneParams::default()
    };
    let report = prune(&mut g, &params, &mut scratch.scratch()).unwrap();
    assert_eq!(report.nodes_before, 65);
    assert_eq!(
        report.nodes_after, report.cells,
        "one node per cell: {report:?}"
    );
    assert_eq!(report.kept_not_eliminable, 0);
    assert!(report.edges_after <= report.nodes_after + 1, "{report:?}");
    // The pruned graph is consistent: zero chi2 at the current estimate, and optimizing it
    // does not move anything.
    assert!(g.chi2() < 1e-12, "chi2 {}", g.chi2());
    let kept: std::vec::Vec<Se2> = g.nodes().iter().map(|n| n.pose).collect();
    for p in &kept {
        assert!(before
            .iter()
            .any(|b| (b.to_vector() - p.to_vector()).amax() < 1e-12));
    }
    let mut ws = SolverWorkspace::<128, 256, 2048>::new();
    solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    for (a, b) in kept.iter().zip(g.nodes()) {
        assert!((a.to_vector() - b.pose.to_vector()).amax() < 1e-9);
    }
}

#[test]
fn pruning_an_optimized_noisy_loop_barely_moves_the_kept_nodes() {
    extern crate std;
    let mut storage = GraphStorage::<128, 256>::new();
    let mut g = storage.graph();
    square_loop(&mut g);
    // Make the loop closure disagree with odometry by 20 cm and 2 degrees, plus a second
    // loop closure across the square, then optimize: every node carries some tension.
    let last = g.edge_count() - 1;
    let z = g.edges()[last]
        .measurement
        .compose(&Se2::new(0.2, -0.1, 0.035));
    g.edges_mut()[last].measurement = z;
    let cross = g
        .node(NodeId(8))
        .unwrap()
        .pose
        .between(&g.node(NodeId(40)).unwrap().pose);
    let info = Matrix3::from_diagonal(&Vector3::new(50.0, 50.0, 200.0));
    g.add_edge(PoseEdge::new(
        NodeId(8),
        NodeId(40),
        cross.compose(&Se2::new(0.1, 0.05, -0.02)),
        info,
        EdgeKind::Loop,
    ))
    .unwrap();
    let mut ws = SolverWorkspace::<128, 256, 4096>::new();
    solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    let full: std::vec::Vec<Se2> = g.nodes().iter().map(|n| n.pose).collect();
    let mut scratch = PruneStorage::<128, 256>::new();
    let params = PruneParams {
        cells: CellParams {
            cell_size: 1.0,
            s: 0.5,
        },
        ..PruneParams::default()
    };
    prune(&mut g, &params, &mut scratch.scratch()).unwrap();
    let remap: std::vec::Vec<u32> = scratch.order[..65].to_vec();
    solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    let mut worst: f64 = 0.0;
    for (old, &new) in remap.iter().enumerate() {
        if new != u32::MAX {
            let a = full[old];
            let b = g.node(NodeId(new)).unwrap().pose;
            worst = worst.max((a.x - b.x).hypot(a.y - b.y));
        }
    }
    // Tree edges measure the current estimate (the and Kretzschmar's choice; see
    // the module docs), so the residual pull of the eliminated edges is dropped and the kept
    // nodes relax a little: by a small fraction of the loop's 20 cm inconsistency.
    assert!(worst < 0.02, "kept nodes moved by up to {worst} m");
}

#[test]
fn pruned_graph_keeps_the_uncertainty_of_the_chain() {
    // A straight chain 0..8 with 0.5 m steps, cell 2 m: the kept nodes are linked by edges
    // whose covariance is the compounded covariance of the chain between them.
    let mut storage = GraphStorage::<16, 32>::new();
    let mut g = storage.graph();
    let info = Matrix3::from_diagonal(&Vector3::new(400.0, 400.0, 1000.0));
    g.add_node(Se2::new(0.1, 0.1, 0.0)).unwrap();
    for i in 0..8u32 {
        let p = Se2::new(0.1 + 0.5 * f64::from(i + 1), 0.1, 0.0);
        g.add_node(p).unwrap();
        g.add_edge(PoseEdge::new(
            NodeId(i),
            NodeId(i + 1),
            Se2::new(0.5, 0.0, 0.0),
            info,
            EdgeKind::Odometry,
        ))
        .unwrap();
    }
    let mut scratch = PruneStorage::<16, 32>::new();
    let params = PruneParams {
        cells: CellParams {
            cell_size: 2.0,
            s: 0.5,
        },
        ..PruneParams::default()
    };
    let report = prune(&mut g, &params, &mut scratch.scratch()).unwrap();
    assert_eq!(report.nodes_after, 3, "{report:?}");
    assert_eq!(report.edges_after, 2, "a chain stays a chain: {report:?}");
    // Along x the variance adds up: 1/400 per step.
    for e in g.edges() {
        let steps = libm::round(e.measurement.x / 0.5);
        let cov = spd_inverse(&e.information).unwrap();
        assert!(
            (cov[(0, 0)] - steps / 400.0).abs() < 1e-9,
            "{} steps: {}",
            steps,
            cov[(0, 0)]
        );
    }
}

#[test]
fn scratch_too_small_is_an_error_and_changes_nothing() {
    let mut storage = GraphStorage::<128, 256>::new();
    let mut g = storage.graph();
    square_loop(&mut g);
    let mut scratch = PruneStorage::<8, 8>::new();
    assert_eq!(
        prune(&mut g, &PruneParams::default(), &mut scratch.scratch()),
        Err(PruneError::ScratchTooSmall)
    );
    assert_eq!(g.node_count(), 65);
}
