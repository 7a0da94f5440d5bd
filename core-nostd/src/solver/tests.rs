use super::*;
use crate::geom::{Info3, Se2};
use crate::graph::{EdgeKind, GraphStorage, PoseEdge};

#[test]
fn ordering_is_a_permutation() {
    let mut storage = GraphStorage::<64, 256>::new();
    let mut g = storage.graph();
    let n = 40u32;
    for i in 0..n {
        g.add_node(Se2::new(i as f64, 0.0, 0.0)).unwrap();
    }
    for i in 0..n - 1 {
        g.add_edge(PoseEdge::new(
            NodeId(i),
            NodeId(i + 1),
            Se2::new(1.0, 0.0, 0.0),
            Info3::identity(),
            EdgeKind::Odometry,
        ))
        .unwrap();
    }
    for i in 0..n - 7 {
        g.add_edge(PoseEdge::new(
            NodeId(i),
            NodeId((i * 7 + 3) % n),
            Se2::new(5.0, 0.0, 0.0),
            Info3::identity(),
            EdgeKind::Loop,
        ))
        .ok();
    }
    let mut ws = SolverWorkspace::<64, 256, 2048>::new();
    let mut b = ws.buffers();
    let (nodes, edges) = g.split_mut();
    let r = ordering::analyze(nodes, edges, true, &mut b);
    extern crate std;
    std::println!("{:?} {:?}", r, &b.var_node[..n as usize]);
}
