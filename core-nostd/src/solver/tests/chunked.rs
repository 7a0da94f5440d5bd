//! The resumable solve against the one-shot solve.

use super::*;

/// A circle with false max-mixture loops, as `max_mixture_rejects_many_false_loops_without_fill`
/// builds it, so the gated warm start, the admission rounds and the rejections all run.
fn mixed(storage: &mut GraphStorage<N, E>, false_loops: usize) -> PoseGraph<'_> {
    let mm = RobustKernel::max_mixture_with_null(1e-3, 1e-6);
    let mut g = circle(storage, 32, 0.01, 0.01);
    let info = Info3::new(50.0, 5.0, 0.0, 5.0, 80.0, 1.0, 0.0, 1.0, 300.0);
    let mut state: u64 = 777;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut added = 0;
    while added < false_loops {
        let (a, b) = ((next() * 32.0) as u32, (next() * 32.0) as u32);
        let z = Se2::new(6.0 * next() - 3.0, 6.0 * next() - 3.0, 2.0 * next() - 1.0);
        if a.abs_diff(b) > 1 {
            g.add_edge(PoseEdge::new(NodeId(a), NodeId(b), z, info, EdgeKind::Loop))
                .unwrap();
            added += 1;
        }
    }
    for e in g.edges_mut() {
        if e.kind == EdgeKind::Loop {
            e.robust = mm;
        }
    }
    g
}

/// Runs a chunked solve to the end with `budget` units per call; returns the outcome and the
/// calls it took.
fn run_chunked(
    g: &mut PoseGraph<'_>,
    ws: &mut Ws,
    options: &SolverOptions,
    budget: u64,
) -> (Result<SolveReport, SolveFailure>, u32) {
    let mut s = ChunkedSolve::start(g, &ws.buffers(), options).unwrap();
    let mut calls = 0;
    loop {
        calls += 1;
        if let Progress::Done(r) = s.advance(g, &mut ws.buffers(), budget) {
            return (r, calls);
        }
    }
}

fn options(gate_chi2: f64, max_iterations: u32) -> SolverOptions {
    SolverOptions {
        linear_init: false,
        gate_chi2,
        max_iterations,
        ..SolverOptions::default()
    }
}

#[test]
fn chunked_solve_with_a_tiny_budget_equals_the_one_shot_solve_to_the_bit() {
    for (gate, max_iterations, false_loops) in [(0.0, 100, 0), (16.27, 100, 6), (16.27, 3, 6)] {
        let opts = options(gate, max_iterations);
        let mut s1 = GraphStorage::new();
        let mut g1 = if false_loops == 0 {
            circle(&mut s1, 32, 0.05, 0.02)
        } else {
            mixed(&mut s1, false_loops)
        };
        let mut w1 = Ws::new();
        let one_shot = solve(&mut g1, &mut w1.buffers(), &opts);
        for budget in [1, 7, 50, u64::MAX] {
            let mut s2 = GraphStorage::new();
            let mut g = if false_loops == 0 {
                circle(&mut s2, 32, 0.05, 0.02)
            } else {
                mixed(&mut s2, false_loops)
            };
            let mut w2 = Ws::new();
            let (chunked, calls) = run_chunked(&mut g, &mut w2, &opts, budget);
            assert_eq!(chunked, one_shot, "gate {gate}, budget {budget}");
            if budget == 1 {
                assert!(calls > 100, "a tiny budget takes many calls: {calls}");
            }
            if budget == u64::MAX {
                assert_eq!(calls, 1);
            }
            for (a, b) in g.nodes().iter().zip(g1.nodes()) {
                assert_eq!(a.pose.x.to_bits(), b.pose.x.to_bits());
                assert_eq!(a.pose.y.to_bits(), b.pose.y.to_bits());
                assert_eq!(a.pose.theta.to_bits(), b.pose.theta.to_bits());
            }
        }
    }
}

#[test]
fn nodes_appended_mid_solve_are_carried_along_and_join_the_next_solve() {
    let opts = options(0.0, 100);
    let (mut s_ref, mut s) = (GraphStorage::new(), GraphStorage::new());
    let mut reference = circle(&mut s_ref, 24, 0.05, 0.03);
    let mut g = circle(&mut s, 24, 0.05, 0.03);
    let one_shot = solve(&mut reference, &mut Ws::new().buffers(), &opts).unwrap();
    let mut w = Ws::new();

    let info = Info3::new(50.0, 5.0, 0.0, 5.0, 80.0, 1.0, 0.0, 1.0, 300.0);
    let step = Se2::new(0.4, 0.0, 0.05);
    let mut solve_state = ChunkedSolve::start(&g, &w.buffers(), &opts).unwrap();
    assert_eq!(solve_state.prefix_nodes(), 24);
    let mut calls = 0;
    let report = loop {
        calls += 1;
        // Every few calls a frame node arrives, chained by odometry to the newest node, and
        // now and then a loop edge back to the start.
        if calls % 5 == 0 && g.node_count() < N {
            let last = g.node_count() - 1;
            let pose = g.nodes()[last].pose.compose(&step);
            let id = g.add_node(pose).unwrap();
            g.add_edge(PoseEdge::new(
                NodeId(last as u32),
                id,
                step,
                info,
                EdgeKind::Odometry,
            ))
            .unwrap();
            if calls % 15 == 0 {
                let z = pose.between(&g.nodes()[1].pose);
                g.add_edge(PoseEdge::new(id, NodeId(1), z, info, EdgeKind::Loop))
                    .unwrap();
            }
        }
        match solve_state.advance(&mut g, &mut w.buffers(), 40) {
            Progress::Working => {}
            Progress::Done(r) => break r.unwrap(),
        }
    };
    assert!(g.node_count() > 24, "nodes arrived during the solve");
    // The prefix was solved exactly as if nothing had arrived.
    assert_eq!(report, one_shot);
    for (a, b) in g.nodes().iter().zip(reference.nodes()) {
        assert_eq!(a.pose, b.pose);
    }
    // The appended nodes kept their odometry to the prefix's last node, hence their chain.
    let last = g.nodes()[23].pose;
    for (k, node) in g.nodes().iter().enumerate().skip(24) {
        let expected = (24..=k).fold(last, |p, _| p.compose(&step));
        let d = expected.between(&node.pose);
        assert!(
            d.x.abs() + d.y.abs() + d.theta.abs() < 1e-9,
            "node {k}: {d:?}"
        );
    }
    // They join the next solve, which converges over the whole graph.
    let (next, _) = run_chunked(&mut g, &mut w, &opts, 40);
    let next = next.unwrap();
    assert!(next.converged);
    assert!(next.final_chi2 <= next.initial_chi2);
}

#[test]
fn a_solve_whose_graph_shrank_ends_with_an_error_without_panicking() {
    let opts = options(0.0, 100);
    let mut s = GraphStorage::new();
    let mut g = circle(&mut s, 16, 0.05, 0.02);
    let mut w = Ws::new();
    let mut solve_state = ChunkedSolve::start(&g, &w.buffers(), &opts).unwrap();
    assert_eq!(
        solve_state.advance(&mut g, &mut w.buffers(), 5),
        Progress::Working
    );
    g.truncate_nodes(10);
    match solve_state.advance(&mut g, &mut w.buffers(), 5) {
        Progress::Done(Err(f)) => assert_eq!(f.error, SolveError::InvalidGraph),
        other => panic!("{other:?}"),
    }
}
