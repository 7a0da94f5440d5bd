//! `cloi vocab`: training the place-recognition vocabulary from images (`train`), and
//! measuring the place recognition against a ground-truth loop matrix (`eval`).
//!
//! The clustering, the weights, the bags and the file format are the core's
//! (`cloi_core::frontend::visual::vocab`); the host lists and decodes the images, lends the
//! storage, and writes the file.

pub mod eval;
pub mod images;

use std::io::Write;
use std::path::PathBuf;

use anyhow::{anyhow, Context, Result};
use cloi_core::frontend::visual::vocab::{
    counter_len, document_counter_len, file, node_count, set_weights, train, Bag, Node,
    TrainConfig, TrainStats, Vocabulary,
};
use cloi_core::frontend::visual::Descriptor;

/// The `cloi vocab` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum VocabCommand {
    /// Train a vocabulary of binary words on the features of a set of images and write it.
    Train(TrainArgs),
    /// Measure place recognition on an image sequence with a ground-truth loop matrix and
    /// print the precision/recall curve.
    Eval(EvalArgs),
}

/// Options of `cloi vocab train`.
#[derive(Debug, Clone, clap::Args)]
pub struct TrainArgs {
    /// A folder (its JPEG and PNG files) or a pattern such as `dir/*.jpg`.
    #[arg(long)]
    pub images: String,
    /// The vocabulary file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Children per tree node (2 to 16).
    #[arg(long, default_value_t = TrainConfig::default().branching)]
    pub branching: usize,
    /// Tree levels (1 to 6): up to branching^depth words.
    #[arg(long, default_value_t = TrainConfig::default().depth)]
    pub depth: usize,
    /// Seed of the cluster centres' draws.
    #[arg(long, default_value_t = TrainConfig::default().seed)]
    pub seed: u64,
}

/// Options of `cloi vocab eval`.
#[derive(Debug, Clone, clap::Args)]
pub struct EvalArgs {
    /// A folder (its JPEG and PNG files) or a pattern, in sequence order.
    #[arg(long)]
    pub images: String,
    /// The ground-truth loop matrix (8-bit BMP, white where image i revisits image j).
    #[arg(long)]
    pub truth: PathBuf,
    /// A vocabulary file; without it one is trained on the evaluated images themselves.
    #[arg(long)]
    pub vocab: Option<PathBuf>,
    /// The recent images that are the reference of the normalised score and never matches.
    #[arg(long, default_value_t = 10)]
    pub recent: usize,
}

/// A trained vocabulary in host memory.
#[derive(Debug, Clone)]
pub struct Trained {
    /// The tree's slots.
    pub nodes: Vec<Node>,
    /// Children per slot.
    pub branching: usize,
    /// Levels.
    pub depth: usize,
    /// Training images.
    pub documents: u32,
    /// What the clustering did (zero when read from a file).
    pub stats: TrainStats,
}

impl Trained {
    /// The vocabulary over the slots.
    ///
    /// # Errors
    /// Slots that do not fit the shape.
    pub fn vocabulary(&self) -> Result<Vocabulary<'_>> {
        Vocabulary::new(self.branching, self.depth, &self.nodes)
            .map_err(|e| anyhow!("vocabulary shape: {e:?}"))
    }

    /// The file's bytes.
    ///
    /// # Errors
    /// Slots that do not fit the shape.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let vocab = self.vocabulary()?;
        let mut out = vec![0u8; file::file_len(self.nodes.len())];
        file::write(&vocab, self.documents, &mut out)
            .map_err(|e| anyhow!("vocabulary not written: {e:?}"))?;
        Ok(out)
    }

    /// A vocabulary file's contents, every length and value checked.
    ///
    /// # Errors
    /// A damaged or foreign file.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let header =
            file::read_header(bytes).map_err(|e| anyhow!("not a valid vocabulary: {e:?}"))?;
        let mut nodes = vec![Node::EMPTY; header.nodes];
        file::read(bytes, &mut nodes).map_err(|e| anyhow!("not a valid vocabulary: {e:?}"))?;
        Ok(Trained {
            nodes,
            branching: header.branching,
            depth: header.depth,
            documents: header.documents,
            stats: TrainStats::default(),
        })
    }
}

/// Trains a vocabulary of `cfg` on `images` (one descriptor list per image), which are also
/// the documents of the weights.
///
/// # Errors
/// A shape the core refuses, or no descriptor at all.
pub fn train_on(cfg: &TrainConfig, images: &[Vec<Descriptor>]) -> Result<Trained> {
    let n = node_count(cfg.branching, cfg.depth).ok_or_else(|| {
        anyhow!(
            "unsupported branching {} and depth {}",
            cfg.branching,
            cfg.depth
        )
    })?;
    let mut nodes = vec![Node::EMPTY; n];
    let mut all: Vec<Descriptor> = images.iter().flatten().copied().collect();
    let mut counters = vec![0u32; counter_len(cfg.branching)];
    let stats = train(cfg, &mut all, &mut counters, &mut nodes)
        .map_err(|e| anyhow!("training failed: {e:?}"))?;
    let words = Vocabulary::new(cfg.branching, cfg.depth, &nodes)
        .map_err(|e| anyhow!("vocabulary shape: {e:?}"))?
        .word_count();
    let mut doc_counters = vec![0u32; document_counter_len(words)];
    let documents = set_weights(
        cfg.branching,
        cfg.depth,
        &mut nodes,
        images.iter().map(Vec::as_slice),
        &mut doc_counters,
    )
    .map_err(|e| anyhow!("weighting failed: {e:?}"))?;
    Ok(Trained {
        nodes,
        branching: cfg.branching,
        depth: cfg.depth,
        documents: u32::try_from(documents).unwrap_or(u32::MAX),
        stats,
    })
}

/// The bag of each image's descriptors.
///
/// # Errors
/// Slots that do not fit the shape.
pub fn bags_of(trained: &Trained, images: &[Vec<Descriptor>]) -> Result<Vec<Bag>> {
    let vocab = trained.vocabulary()?;
    Ok(images
        .iter()
        .map(|d| {
            let mut b = Bag::new();
            b.transform(&vocab, d);
            b
        })
        .collect())
}

/// Runs a `cloi vocab` subcommand.
///
/// # Errors
/// Unreadable images or files, or a vocabulary the core refuses.
pub fn run(cmd: &VocabCommand, out: &mut dyn Write) -> Result<()> {
    match cmd {
        VocabCommand::Train(args) => run_train(args, out),
        VocabCommand::Eval(args) => run_eval(args, out),
    }
}

fn run_train(args: &TrainArgs, out: &mut dyn Write) -> Result<()> {
    let paths = images::list_images(&args.images)?;
    let described = images::describe_images(&paths)?;
    let cfg = TrainConfig {
        branching: args.branching,
        depth: args.depth,
        seed: args.seed,
        ..TrainConfig::default()
    };
    let trained = train_on(&cfg, &described)?;
    let bytes = trained.to_bytes()?;
    crate::io::atomic::write_file(&args.out, &bytes)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let s = &trained.stats;
    writeln!(
        out,
        "{} images, {} descriptors, {} clusters ({} at the iteration cap), {} of {} words used; \
         wrote {} ({} bytes)",
        paths.len(),
        s.descriptors,
        s.clusters,
        s.unconverged,
        s.words,
        trained.vocabulary()?.word_count(),
        args.out.display(),
        bytes.len()
    )?;
    Ok(())
}

fn run_eval(args: &EvalArgs, out: &mut dyn Write) -> Result<()> {
    // The files first: a bad one fails before the images are read.
    let truth_bytes =
        std::fs::read(&args.truth).with_context(|| format!("reading {}", args.truth.display()))?;
    let truth = eval::LoopTruth::from_bmp(&truth_bytes)
        .with_context(|| args.truth.display().to_string())?;
    let loaded = match &args.vocab {
        Some(p) => Some(
            Trained::from_bytes(
                &std::fs::read(p).with_context(|| format!("reading {}", p.display()))?,
            )
            .with_context(|| p.display().to_string())?,
        ),
        None => None,
    };
    let paths = images::list_images(&args.images)?;
    let described = images::describe_images(&paths)?;
    let trained = match loaded {
        Some(t) => t,
        None => train_on(&TrainConfig::default(), &described)?,
    };
    let bags = bags_of(&trained, &described)?;
    let result = eval::evaluate(&bags, &truth, args.recent)?;
    write_curve(&result, out)
}

/// Prints the curve and the recall at full precision.
///
/// # Errors
/// Writing failed.
pub fn write_curve(result: &eval::Evaluation, out: &mut dyn Write) -> Result<()> {
    writeln!(
        out,
        "{} queries with a best match, {} revisits in the ground truth",
        result.matches.len(),
        result.positives
    )?;
    writeln!(out, "threshold  accepted  correct  precision  recall")?;
    for p in &result.curve {
        writeln!(
            out,
            "{:9.3}  {:8}  {:7}  {:9.3}  {:6.3}",
            p.threshold, p.accepted, p.correct, p.precision, p.recall
        )?;
    }
    let mut wrong: Vec<_> = result.matches.iter().filter(|m| !m.correct).collect();
    wrong.sort_by(|a, b| b.candidate.normalised.total_cmp(&a.candidate.normalised));
    write!(
        out,
        "wrong best matches (image -> match: normalised score, 1-based):"
    )?;
    for m in wrong.iter().take(10) {
        write!(
            out,
            " {} -> {}: {:.3};",
            m.query + 1,
            m.candidate.entry + 1,
            m.candidate.normalised
        )?;
    }
    writeln!(out)?;
    match result.recall_at_full_precision() {
        Some(p) => writeln!(
            out,
            "recall at precision 1: {:.3} ({} of {}) at threshold {:.3}",
            p.recall, p.correct, result.positives, p.threshold
        )?,
        None => writeln!(
            out,
            "recall at precision 1: 0 (the best-scored match is wrong)"
        )?,
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_vocabulary_round_trips_through_its_bytes_and_garbage_is_an_error() {
        let images: Vec<Vec<Descriptor>> = (0..6u32)
            .map(|i| {
                (0..40u32)
                    .map(|j| {
                        Descriptor([i.wrapping_mul(0x9E37_79B9) ^ j.wrapping_mul(0x85EB_CA6B); 8])
                    })
                    .collect()
            })
            .collect();
        let cfg = TrainConfig {
            branching: 4,
            depth: 2,
            ..TrainConfig::default()
        };
        let trained = train_on(&cfg, &images).unwrap();
        let bytes = trained.to_bytes().unwrap();
        let back = Trained::from_bytes(&bytes).unwrap();
        assert_eq!((back.nodes, back.documents), (trained.nodes, 6));
        assert!(Trained::from_bytes(b"not a vocabulary").is_err());
        assert!(Trained::from_bytes(&bytes[..bytes.len() - 1]).is_err());
        assert!(Trained::from_bytes(&[]).is_err());
    }
}
