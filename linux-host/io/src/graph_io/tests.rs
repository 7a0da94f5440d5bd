use std::path::Path;

use super::*;

fn p() -> &'static Path {
    Path::new("test.g2o")
}

const SMALL: &str = "\
# a comment
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1.0 0.0 0.1\r
VERTEX_SE2 2 2.0 0.5 7.0

EDGE_SE2 0 1 1.0 0.0 0.1 100 0 0 100 0 400
EDGE_SE2 1 2 1.0 0.5 -0.2 100 1 2 90 3 300
EDGE_SE2 2 0 -2.0 -0.5 1e-320 50 0 0 50 0 200
EDGE_SE2 0 1 1.0 0.0 0.1 100 0 0 100 0 400
FIX 0
";

#[test]
fn g2o_quirks_are_handled() {
    let g = read_g2o(SMALL, p()).unwrap();
    assert_eq!(g.node_count(), 3);
    assert_eq!(g.edges.len(), 4);
    assert_eq!(g.duplicate_pairs, 1, "0-1 measured twice, both kept");
    assert!(g.fixed[0] && !g.fixed[1]);
    // 7 rad wrapped into (-pi, pi].
    assert!((g.poses[2].theta - (7.0 - 2.0 * std::f64::consts::PI)).abs() < 1e-12);
    // Denormal junk flushed to zero.
    assert_eq!(g.edges[2].measurement.theta, 0.0);
    // Information order: I11 I12 I13 I22 I23 I33, symmetric.
    let m = g.edges[1].information;
    assert_eq!(
        (
            m[(0, 1)],
            m[(1, 0)],
            m[(0, 2)],
            m[(1, 1)],
            m[(1, 2)],
            m[(2, 2)]
        ),
        (1.0, 1.0, 2.0, 90.0, 3.0, 300.0)
    );
    assert_eq!(g.edges[0].kind(), EdgeKind::Odometry);
    assert_eq!(g.edges[2].kind(), EdgeKind::Loop);
}

#[test]
fn g2o_round_trip_is_exact() {
    let g = read_g2o(SMALL, p()).unwrap();
    let text = write_g2o(&g, &g.poses);
    let back = read_g2o(&text, p()).unwrap();
    assert_eq!(back.poses, g.poses);
    assert_eq!(back.edges, g.edges);
    assert_eq!(back.fixed, g.fixed);
    assert_eq!(back.ids, g.ids);
}

#[test]
fn toro_round_trip_and_information_order() {
    let text = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 1 5 1 1 0 0\n";
    let g = read_toro(text, Path::new("t.graph")).unwrap_err();
    // I12 = 5 with I11 = I22 = 1 is not positive definite: the error names file and line.
    assert!(format!("{g:#}").contains("t.graph:3"), "{g:#}");
    let text = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 100 1 90 300 2 3\n";
    let g = read_toro(text, Path::new("t.graph")).unwrap();
    let m = g.edges[0].information;
    assert_eq!(
        (
            m[(0, 0)],
            m[(0, 1)],
            m[(1, 1)],
            m[(2, 2)],
            m[(0, 2)],
            m[(1, 2)]
        ),
        (100.0, 1.0, 90.0, 300.0, 2.0, 3.0)
    );
    let back = read_toro(&write_toro(&g, &g.poses), Path::new("t.graph")).unwrap();
    assert_eq!(back.edges, g.edges);
    assert_eq!(back.poses, g.poses);
    // The same graph through g2o.
    let via = read_g2o(&write_g2o(&g, &g.poses), p()).unwrap();
    assert_eq!(via.edges, g.edges);
    assert_eq!(GraphFormat::sniff(text), GraphFormat::Toro);
    assert_eq!(GraphFormat::sniff(SMALL), GraphFormat::G2o);
}

#[test]
fn edges_only_files_chain_odometry() {
    let text = "EDGE_SE2 0 1 1 0 1.5707963267948966 1 0 0 1 0 1\n\
                EDGE_SE2 2 1 -1 0 0 1 0 0 1 0 1\n\
                EDGE_SE2 2 0 5 5 0 1 0 0 1 0 1\n";
    let g = read_g2o(text, p()).unwrap();
    assert!(!g.has_vertices);
    assert_eq!(g.node_count(), 3);
    assert_eq!(g.poses[0], Se2::IDENTITY);
    assert!((g.poses[1].x - 1.0).abs() < 1e-12 && g.poses[1].y.abs() < 1e-12);
    // Node 2 from the inverse of the edge 2 -> 1: one metre further along the new heading.
    assert!((g.poses[2].x - 1.0).abs() < 1e-12 && (g.poses[2].y - 1.0).abs() < 1e-12);
}

#[test]
fn bad_input_names_file_and_line() {
    let cases = [
        ("VERTEX_SE2 0 0 0\n", ":1: missing theta"),
        ("VERTEX_SE2 0 0 0 0 9\n", ":1: unexpected extra value"),
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 1 1\n",
            ":2: vertex 0 already defined on line 1",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 5 1 0 0 1 0 0 1 0 1\n",
            ":2: edge refers to vertex 5",
        ),
        ("VERTEX_SE2 0 0 nan 0\n", ":1: y is not finite"),
        ("VERTEX_SE2 0 0 abc 0\n", ":1: y is not a number"),
        (
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n",
            ":1: unsupported g2o record",
        ),
        (
            "\n\nEDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n",
            ":3: information matrix is not positive definite",
        ),
        (
            "EDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n",
            ":1: edge joins vertex 0 to itself",
        ),
        (
            "EDGE_SE2 x 1 1 0 0 1 0 0 1 0 1\n",
            ":1: first vertex id is not an integer",
        ),
        ("FIX\n", ":1: FIX without a vertex id"),
    ];
    for (text, want) in cases {
        let err = read_g2o(text, Path::new("bad.g2o")).unwrap_err();
        let msg = format!("{err:#}");
        assert!(
            msg.starts_with("bad.g2o:") && msg.contains(want),
            "{text:?}: {msg}"
        );
    }
    let err = read_graph(Path::new("/nonexistent/x.g2o"), None).unwrap_err();
    assert!(format!("{err:#}").contains("/nonexistent/x.g2o"));
}

#[test]
fn ground_truth_reads_both_forms_and_aligns() {
    let dir = std::env::temp_dir().join(format!("cloi-gt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let plain = dir.join("gt.dat");
    std::fs::write(&plain, "0 0 0\n1 0 0\n2 0 0\n").unwrap();
    let gt = read_ground_truth(&plain).unwrap();
    assert_eq!(gt.len(), 3);
    let g2o = dir.join("gt.g2o");
    std::fs::write(
        &g2o,
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n",
    )
    .unwrap();
    assert_eq!(read_ground_truth(&g2o).unwrap(), gt);
    std::fs::write(&plain, "0 0 0\n1 0\n").unwrap();
    assert!(format!("{:#}", read_ground_truth(&plain).unwrap_err()).contains("gt.dat:2"));
    // An estimate that is the truth moved rigidly has zero error after alignment.
    let moved: Vec<_> = gt
        .iter()
        .map(|p| Se2::new(3.0, -1.0, 0.7).compose(p))
        .collect();
    assert!(aligned_rmse(&moved, &gt).unwrap() < 1e-12);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn csail_g2o_and_toro_agree_where_they_should() {
    let (Some(g2o), Some(toro)) = (
        crate::dataset::shared_file("g2o/CSAIL.g2o"),
        crate::dataset::shared_file("g2o/CSAIL.toro.graph"),
    ) else {
        return;
    };
    let a = read_graph(&g2o, None).unwrap();
    let b = read_graph(&toro, None).unwrap();
    assert_eq!((a.node_count(), a.edges.len()), (1045, 1172));
    assert_eq!((b.node_count(), b.edges.len()), (1045, 1172));
    assert_eq!(a.duplicate_pairs, 1);
    assert!(!a.has_vertices && b.has_vertices);
    for (x, y) in a.edges.iter().zip(&b.edges) {
        assert_eq!((x.from, x.to), (y.from, y.to));
        assert!((x.measurement.x - y.measurement.x).abs() < 1e-9);
    }
}
