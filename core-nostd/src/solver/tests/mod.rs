use super::*;
use crate::geom::{Info3, Se2};
use crate::graph::{EdgeKind, GraphStorage, PoseEdge, RobustKernel};
use crate::storage::NodeId;
use proptest::prelude::*;

const N: usize = 40;
const E: usize = 80;
type Ws = SolverWorkspace<N, E, 400>;

/// A circle of `n` poses with odometry and a few chords; `noise` scales a fixed perturbation
/// of the measurements and `drift` of the initial guess.
fn circle(storage: &mut GraphStorage<N, E>, n: usize, noise: f64, drift: f64) -> PoseGraph<'_> {
    let truth = |i: usize| {
        let a = i as f64 * 2.0 * core::f64::consts::PI / n as f64;
        Se2::new(
            5.0 * libm::cos(a),
            5.0 * libm::sin(a),
            a + core::f64::consts::FRAC_PI_2,
        )
    };
    let wiggle = |k: usize| {
        let t = k as f64;
        Se2::new(
            noise * libm::sin(1.3 * t),
            noise * libm::cos(0.7 * t),
            noise * 0.5 * libm::sin(2.1 * t),
        )
    };
    let mut g = storage.graph();
    for i in 0..n {
        let t = i as f64;
        g.add_node(truth(i).compose(&Se2::new(drift * t, -drift * t, drift * 0.3 * t)))
            .unwrap();
    }
    let info = Info3::new(50.0, 5.0, 0.0, 5.0, 80.0, 1.0, 0.0, 1.0, 300.0);
    for i in 0..n {
        let j = (i + 1) % n;
        let z = truth(i).between(&truth(j)).compose(&wiggle(i));
        let kind = if j == 0 {
            EdgeKind::Loop
        } else {
            EdgeKind::Odometry
        };
        g.add_edge(PoseEdge::new(
            NodeId(i as u32),
            NodeId(j as u32),
            z,
            info,
            kind,
        ))
        .unwrap();
    }
    for k in 0..n / 4 {
        let (a, b) = (k, (k + n / 2) % n);
        let z = truth(a).between(&truth(b)).compose(&wiggle(100 + k));
        g.add_edge(PoseEdge::new(
            NodeId(a as u32),
            NodeId(b as u32),
            z,
            info,
            EdgeKind::Loop,
        ))
        .unwrap();
    }
    g
}

/// Numeric gradient of the chi2 with respect to every free coordinate, largest magnitude.
fn numeric_gradient_norm(g: &mut PoseGraph<'_>) -> f64 {
    let mut worst: f64 = 0.0;
    let h = 1e-6;
    for i in 1..g.node_count() {
        for c in 0..3 {
            let orig = g.nodes()[i].pose;
            let set = |d: f64, g: &mut PoseGraph<'_>| {
                let mut p = orig;
                match c {
                    0 => p.x += d,
                    1 => p.y += d,
                    _ => p.theta += d,
                }
                g.nodes_mut()[i].pose = p;
                g.chi2()
            };
            let up = set(h, g);
            let down = set(-h, g);
            g.nodes_mut()[i].pose = orig;
            worst = worst.max(libm::fabs(up - down) / (2.0 * h));
        }
    }
    worst
}

#[test]
fn gauss_newton_reaches_a_stationary_point() {
    let mut storage = GraphStorage::new();
    let mut g = circle(&mut storage, 32, 0.02, 0.01);
    let mut ws = Ws::new();
    let r = solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    assert!(r.converged && r.analyzed);
    assert!(r.final_chi2 < r.initial_chi2 * 1e-2, "{r:?}");
    assert_eq!(r.variables, 31, "the first node holds the gauge");
    assert!(numeric_gradient_norm(&mut g) < 1e-4);
    assert_eq!(
        g.nodes()[0].pose,
        Se2::new(0.0, 0.0, 0.0).compose(&g.nodes()[0].pose)
    );
}

#[test]
fn levenberg_marquardt_agrees_with_gauss_newton() {
    let mut s1 = GraphStorage::new();
    let mut s2 = GraphStorage::new();
    let mut g1 = circle(&mut s1, 32, 0.05, 0.02);
    let mut g2 = circle(&mut s2, 32, 0.05, 0.02);
    let mut ws = Ws::new();
    let gn = solve(&mut g1, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    let lm_opts = SolverOptions {
        method: Method::LevenbergMarquardt,
        linear_init: false,
        ..SolverOptions::default()
    };
    let lm = solve(&mut g2, &mut ws.buffers(), &lm_opts).unwrap();
    assert!(!lm.analyzed, "same structure: the analysis is reused");
    assert!((gn.final_chi2 - lm.final_chi2).abs() < 1e-6 * gn.final_chi2.max(1.0));
    for (a, b) in g1.nodes().iter().zip(g2.nodes()) {
        assert!((a.pose.x - b.pose.x).abs() < 1e-5 && (a.pose.y - b.pose.y).abs() < 1e-5);
    }
}

#[test]
fn noise_free_graph_is_recovered_exactly() {
    let mut storage = GraphStorage::new();
    let mut g = circle(&mut storage, 20, 0.0, 0.03);
    let mut ws = Ws::new();
    let r = solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    assert!(r.final_chi2 < 1e-16, "{r:?}");
}

#[test]
fn repeated_solves_are_bit_identical() {
    let run = || {
        let mut storage = GraphStorage::new();
        let mut g = circle(&mut storage, 36, 0.04, 0.02);
        let mut ws = Ws::new();
        solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
        g.nodes()
            .iter()
            .map(|n| n.pose.x.to_bits() ^ n.pose.theta.to_bits())
            .fold(0, |a, b| a ^ b.rotate_left(7))
    };
    assert_eq!(run(), run());
}

#[test]
fn typed_errors_instead_of_panics() {
    // Factor capacity too small.
    let mut storage = GraphStorage::new();
    let mut g = circle(&mut storage, 32, 0.02, 0.01);
    let mut small = SolverWorkspace::<N, E, 8>::new();
    let err = solve(&mut g, &mut small.buffers(), &SolverOptions::default()).unwrap_err();
    assert!(matches!(
        err.error,
        SolveError::Capacity {
            what: "factor blocks",
            ..
        }
    ));
    // Node capacity too small.
    let mut tiny = SolverWorkspace::<4, E, 400>::new();
    let err = solve(&mut g, &mut tiny.buffers(), &SolverOptions::default()).unwrap_err();
    assert!(matches!(
        err.error,
        SolveError::Capacity { what: "nodes", .. }
    ));
    // Iteration limit: the last estimate is kept and better than the start.
    let mut ws = Ws::new();
    let opts = SolverOptions {
        max_iterations: 1,
        linear_init: false,
        ..SolverOptions::default()
    };
    let err = solve(&mut g, &mut ws.buffers(), &opts).unwrap_err();
    assert_eq!(err.error, SolveError::MaxIterations);
    assert!(err.report.final_chi2 < err.report.initial_chi2);
    // A node without constraints.
    let mut s2 = GraphStorage::<N, E>::new();
    let mut g2 = s2.graph();
    g2.add_node(Se2::IDENTITY).unwrap();
    g2.add_node(Se2::IDENTITY).unwrap();
    let err = solve(&mut g2, &mut ws.buffers(), &SolverOptions::default()).unwrap_err();
    assert_eq!(err.error, SolveError::NotPositiveDefinite(NodeId(1)));
}

#[test]
fn a_prior_replaces_the_gauge() {
    let mut storage = GraphStorage::new();
    let mut g = circle(&mut storage, 16, 0.0, 0.0);
    let target = Se2::new(1.0, 2.0, 0.3);
    let info = Info3::identity() * 1e3;
    g.add_edge(PoseEdge::prior(NodeId(0), target, info))
        .unwrap();
    let mut ws = Ws::new();
    let r = solve(&mut g, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    assert_eq!(r.variables, 16);
    let p = g.nodes()[0].pose;
    assert!((p.x - 1.0).abs() < 1e-9 && (p.y - 2.0).abs() < 1e-9 && (p.theta - 0.3).abs() < 1e-9);
}

#[test]
fn max_mixture_ignores_a_false_loop() {
    let solve_with = |kernel: RobustKernel| {
        let mut storage = GraphStorage::new();
        let mut g = circle(&mut storage, 32, 0.01, 0.0);
        let info = Info3::new(50.0, 5.0, 0.0, 5.0, 80.0, 1.0, 0.0, 1.0, 300.0);
        let mut bad = PoseEdge::new(
            NodeId(3),
            NodeId(20),
            Se2::new(0.5, 0.2, 1.0),
            info,
            EdgeKind::Loop,
        );
        bad.robust = kernel;
        g.add_edge(bad).unwrap();
        let mut ws = Ws::new();
        let r = solve(&mut g, &mut ws.buffers(), &SolverOptions::default());
        let r = match r {
            Ok(r) => r,
            Err(f) => f.report,
        };
        (r, g.nodes()[16].pose)
    };
    let (plain, p_plain) = solve_with(RobustKernel::None);
    let (mm, p_mm) = solve_with(RobustKernel::max_mixture_with_null(1e-3, 1e-6));
    let truth = Se2::new(-5.0, 0.0, -core::f64::consts::FRAC_PI_2);
    let err = |p: Se2| libm::hypot(p.x - truth.x, p.y - truth.y);
    assert!(err(p_mm) < 0.05, "max-mixture error {}", err(p_mm));
    assert!(
        err(p_plain) > 5.0 * err(p_mm),
        "plain {} vs mm {}",
        err(p_plain),
        err(p_mm)
    );
    assert!(mm.final_cost < plain.final_cost);
}

#[test]
fn huber_and_cauchy_downweight_a_false_loop() {
    for kernel in [
        RobustKernel::Huber { delta: 1.0 },
        RobustKernel::Cauchy { c: 1.0 },
    ] {
        let mut storage = GraphStorage::new();
        let mut g = circle(&mut storage, 32, 0.01, 0.0);
        let info = Info3::identity() * 20.0;
        let mut bad = PoseEdge::new(
            NodeId(3),
            NodeId(20),
            Se2::new(0.5, 0.2, 1.0),
            info,
            EdgeKind::Loop,
        );
        bad.robust = kernel;
        g.add_edge(bad).unwrap();
        let mut ws = Ws::new();
        let r = solve(&mut g, &mut ws.buffers(), &SolverOptions::default());
        let r = r.unwrap_or_else(|f| f.report);
        assert!(r.final_cost < r.final_chi2, "{kernel:?}: {r:?}");
    }
}

#[test]
fn auto_is_gauss_newton_on_a_consistent_graph() {
    let mut s1 = GraphStorage::new();
    let mut s2 = GraphStorage::new();
    let mut g1 = circle(&mut s1, 32, 0.05, 0.02);
    let mut g2 = circle(&mut s2, 32, 0.05, 0.02);
    let mut ws = Ws::new();
    let gn = solve(&mut g1, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    let auto = SolverOptions {
        method: Method::Auto,
        ..SolverOptions::default()
    };
    let r = solve(&mut g2, &mut ws.buffers(), &auto).unwrap();
    assert_eq!(gn.iterations, r.iterations, "no fallback");
    assert_eq!(gn.final_chi2, r.final_chi2);
    for (a, b) in g1.nodes().iter().zip(g2.nodes()) {
        assert_eq!(a.pose, b.pose);
    }
}

#[test]
fn auto_falls_back_and_never_ends_worse_than_gauss_newton() {
    // Noise far above what the information claims: every minimum fails the chi2 test, so the
    // fallback runs; its result replaces Gauss-Newton's only when it is lower.
    let mut s1 = GraphStorage::new();
    let mut s2 = GraphStorage::new();
    let mut g1 = circle(&mut s1, 32, 0.3, 0.02);
    let mut g2 = circle(&mut s2, 32, 0.3, 0.02);
    let mut ws = Ws::new();
    let gn = solve(&mut g1, &mut ws.buffers(), &SolverOptions::default()).unwrap();
    let auto = SolverOptions {
        method: Method::Auto,
        ..SolverOptions::default()
    };
    let r = solve(&mut g2, &mut ws.buffers(), &auto).unwrap();
    assert!(r.iterations > gn.iterations, "the fallback ran: {r:?}");
    assert!(
        r.final_chi2 <= gn.final_chi2 * (1.0 + 1e-9),
        "{r:?} vs {gn:?}"
    );
    assert!((g2.chi2() - r.final_chi2).abs() <= 1e-9 * r.final_chi2);
}

#[test]
fn max_mixture_rejects_many_false_loops_without_fill() {
    const FALSE_LOOPS: usize = 30;
    let mm = RobustKernel::max_mixture_with_null(1e-3, 1e-6);
    let opts = SolverOptions {
        gate_chi2: 16.27,
        ..SolverOptions::default()
    };
    let mut clean_storage = GraphStorage::new();
    let mut clean = circle(&mut clean_storage, 32, 0.01, 0.01);
    for e in clean.edges_mut() {
        if e.kind == EdgeKind::Loop {
            e.robust = mm;
        }
    }
    let mut ws = Ws::new();
    let reference = solve(&mut clean, &mut ws.buffers(), &opts).unwrap();
    assert_eq!(reference.rejected_loops, 0);
    let mut storage = GraphStorage::new();
    let mut g = circle(&mut storage, 32, 0.01, 0.01);
    let info = Info3::new(50.0, 5.0, 0.0, 5.0, 80.0, 1.0, 0.0, 1.0, 300.0);
    // A fixed linear congruential sequence: random node pairs and relative poses.
    let mut state: u64 = 12345;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut added = 0;
    while added < FALSE_LOOPS {
        let a = (next() * 32.0) as u32;
        let b = (next() * 32.0) as u32;
        let z = Se2::new(
            6.0 * next() - 3.0,
            6.0 * next() - 3.0,
            (2.0 * next() - 1.0) * core::f64::consts::PI,
        );
        if a.abs_diff(b) <= 1 {
            continue;
        }
        let mut e = PoseEdge::new(NodeId(a), NodeId(b), z, info, EdgeKind::Loop);
        e.robust = mm;
        g.add_edge(e).unwrap();
        added += 1;
    }
    for e in g.edges_mut() {
        if e.kind == EdgeKind::Loop {
            e.robust = mm;
        }
    }
    let r = solve(&mut g, &mut ws.buffers(), &opts).unwrap();
    assert_eq!(r.rejected_loops, FALSE_LOOPS, "{r:?}");
    assert_eq!(
        r.factor_blocks, reference.factor_blocks,
        "no fill from false loops"
    );
    for (a, b) in g.nodes().iter().zip(clean.nodes()) {
        assert!(libm::hypot(a.pose.x - b.pose.x, a.pose.y - b.pose.y) < 1e-6);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    #[test]
    fn solve_never_increases_the_cost(noise in 0.0f64..0.2, drift in 0.0f64..0.05, n in 8usize..36, lm in any::<bool>()) {
        let mut storage = GraphStorage::new();
        let mut g = circle(&mut storage, n, noise, drift);
        let mut ws = Ws::new();
        let opts = SolverOptions {
            method: if lm { Method::LevenbergMarquardt } else { Method::GaussNewton },
            ..SolverOptions::default()
        };
        let r = solve(&mut g, &mut ws.buffers(), &opts).unwrap();
        prop_assert!(r.final_chi2 <= r.initial_chi2 + 1e-9);
        prop_assert!((g.chi2() - r.final_chi2).abs() <= 1e-9 * r.final_chi2.max(1.0));
        prop_assert!(numeric_gradient_norm(&mut g) < 1e-3 * (1.0 + r.final_chi2));
    }
}

mod chunked;
