//! The keyframes' bags and the place query: which earlier keyframe looks most like the
//! current one, relative to how much the current one looks like its own recent neighbours.
//!
//! The bags live in caller-lent storage and a query scans them all, merging two sorted lists
//! per keyframe (a few hundred entries each). For the few hundred keyframes a low-cost robot
//! keeps, that bounded scan costs less than an inverted index, which would need per-word
//! posting lists of unknown lengths in fixed memory.
//!
//! Raw scores depend on the place (a textured room shares more words between any two frames
//! than a bare corridor), so a candidate's score is divided by the best score of the query
//! against the most recent keyframes: a revisit should look about as much like the query as
//! the frames just before it do. The recent keyframes are never candidates themselves.

use super::bag::Bag;

/// Query parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct QueryConfig {
    /// The last `recent` keyframes are the reference and are not candidates.
    pub recent: usize,
    /// A candidate needs `score / reference` at least this.
    pub min_normalised: f32,
    /// The reference is at least this, so a query unlike its neighbours (a blur, a turn)
    /// does not make every weak candidate pass.
    pub min_reference: f32,
}

impl Default for QueryConfig {
    fn default() -> Self {
        QueryConfig {
            recent: 10,
            min_normalised: 0.5,
            min_reference: 0.02,
        }
    }
}

/// A loop candidate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Candidate {
    /// The keyframe's index in the database (its insertion order).
    pub entry: usize,
    /// Its similarity to the query.
    pub score: f32,
    /// The similarity divided by the reference.
    pub normalised: f32,
}

/// What a query found.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct QueryResult {
    /// The reference score (after the floor).
    pub reference: f32,
    /// Candidates written to the output, best first.
    pub candidates: usize,
    /// Keyframes that passed, including those that did not fit the output.
    pub passed: usize,
}

/// The storage is full.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DatabaseFull;

/// Keyframe bags in insertion order over caller-lent storage.
#[derive(Debug)]
pub struct Database<'a> {
    bags: &'a mut [Bag],
    len: usize,
}

impl<'a> Database<'a> {
    /// An empty database holding at most `storage.len()` keyframes.
    pub fn new(storage: &'a mut [Bag]) -> Self {
        Database {
            bags: storage,
            len: 0,
        }
    }

    /// Keyframes held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether none is held.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Most keyframes it can hold.
    pub fn capacity(&self) -> usize {
        self.bags.len()
    }

    /// The bag of keyframe `entry`.
    pub fn get(&self, entry: usize) -> Option<&Bag> {
        self.bags.get(..self.len)?.get(entry)
    }

    /// Appends a keyframe's bag and returns its entry.
    ///
    /// # Errors
    /// [`DatabaseFull`] when the storage is full; nothing changes.
    pub fn add(&mut self, bag: &Bag) -> Result<usize, DatabaseFull> {
        let slot = self.bags.get_mut(self.len).ok_or(DatabaseFull)?;
        slot.clone_from(bag);
        self.len += 1;
        Ok(self.len - 1)
    }

    /// The keyframes older than the `cfg.recent` last ones whose score against `query`,
    /// divided by the reference (the best score against those recent ones, at least
    /// `cfg.min_reference`), reaches `cfg.min_normalised`: the best `out.len()` of them in
    /// `out`, by decreasing score (the older keyframe first on a tie).
    pub fn query(&self, query: &Bag, cfg: &QueryConfig, out: &mut [Candidate]) -> QueryResult {
        let held = self.bags.get(..self.len).unwrap_or(&[]);
        let split = held.len().saturating_sub(cfg.recent);
        let (older, recent) = held.split_at(split);
        let best_recent = recent.iter().map(|b| b.score(query)).fold(0.0f32, f32::max);
        let reference = best_recent.max(cfg.min_reference).max(f32::MIN_POSITIVE);
        let mut result = QueryResult {
            reference,
            ..QueryResult::default()
        };
        for (entry, bag) in older.iter().enumerate() {
            let score = bag.score(query);
            let normalised = score / reference;
            if normalised < cfg.min_normalised || score <= 0.0 {
                continue;
            }
            result.passed += 1;
            insert_best(
                out,
                &mut result.candidates,
                Candidate {
                    entry,
                    score,
                    normalised,
                },
            );
        }
        result
    }
}

/// Inserts `c` into the first `*len` entries of `out`, kept by decreasing score, dropping the
/// last one when full.
fn insert_best(out: &mut [Candidate], len: &mut usize, c: Candidate) {
    let held = out.get(..*len).unwrap_or(&[]);
    let at = held
        .iter()
        .position(|o| c.score > o.score)
        .unwrap_or(held.len());
    if at >= out.len() {
        return;
    }
    let end = (*len + 1).min(out.len());
    if let Some(tail) = out.get_mut(at..end) {
        tail.rotate_right(1);
        if let Some(first) = tail.first_mut() {
            *first = c;
        }
    }
    *len = end;
}
