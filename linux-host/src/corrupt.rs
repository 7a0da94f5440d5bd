//! `cloi corrupt`: adds seeded random false loop closures to a pose graph, for robustness
//! tests of the back-end (the outlier model of the max-mixture literature: uniform random node
//! pairs, uniform random relative poses, the information of a real loop closure).

use std::io::Write;
use std::path::PathBuf;

use anyhow::{bail, Result};
use cloi_core::geom::Se2;
use cloi_core::graph::EdgeKind;
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

use crate::graph_io::{self, FileEdge, GraphFile, GraphFormat};
use crate::io::atomic;

/// Options of `cloi corrupt`.
#[derive(Debug, Clone, clap::Args)]
pub struct CorruptArgs {
    /// Input pose graph (g2o or TORO).
    pub input: PathBuf,
    /// Output g2o file (vertices: the input's initial guess).
    #[arg(long)]
    pub out: PathBuf,
    /// Input format (default: from the file's first record).
    #[arg(long, value_enum)]
    pub format: Option<GraphFormat>,
    /// Number of false loop closures to add.
    #[arg(long, default_value_t = 100)]
    pub outliers: usize,
    /// Seed of the generator (PCG64): the same seed gives the same file.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Half-width of the uniform box for the false relative translation, metres.
    #[arg(long, default_value_t = 10.0)]
    pub span: f64,
}

/// Appends `count` false loops to `graph`: node pairs uniform among non-consecutive pairs,
/// translation uniform in `[-span, span]^2`, heading uniform in `[-pi, pi)`, information of the
/// first real loop closure (else of the first edge).
///
/// # Errors
/// The graph has fewer than three nodes or no edges.
pub fn add_false_loops(graph: &mut GraphFile, count: usize, seed: u64, span: f64) -> Result<()> {
    let n = graph.node_count();
    if n < 3 || graph.edges.is_empty() {
        bail!("a graph needs at least 3 nodes and one edge to be corrupted");
    }
    let information = graph
        .edges
        .iter()
        .find(|e| e.kind() == EdgeKind::Loop)
        .unwrap_or(&graph.edges[0])
        .information;
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut added = 0;
    while added < count {
        let a = rng.random_range(0..n);
        let b = rng.random_range(0..n);
        if a.abs_diff(b) <= 1 {
            continue;
        }
        let z = Se2::new(
            rng.random_range(-span..span),
            rng.random_range(-span..span),
            rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
        );
        graph.edges.push(FileEdge {
            from: a,
            to: b,
            measurement: z,
            information,
        });
        added += 1;
    }
    Ok(())
}

/// Runs `cloi corrupt`.
///
/// # Errors
/// Unreadable input or unwritable output.
pub fn run(args: &CorruptArgs, out: &mut dyn Write) -> Result<()> {
    let mut graph = graph_io::read_graph(&args.input, args.format)?;
    add_false_loops(&mut graph, args.outliers, args.seed, args.span)?;
    let poses = graph.poses.clone();
    atomic::write_file(&args.out, graph_io::write_g2o(&graph, &poses).as_bytes())?;
    writeln!(
        out,
        "{}: {} nodes, {} edges ({} false loops, seed {})",
        args.out.display(),
        graph.node_count(),
        graph.edges.len(),
        args.outliers,
        args.seed
    )?;
    Ok(())
}
