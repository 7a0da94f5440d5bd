//! Descriptor matching between a frame and known features (paper section III-B.1).
//!
//! The visual odometry reprojects known points into the new frame, `p_k = pi(M_k, P_{k-1})`,
//! with `M_k` predicted from the wheel odometry and gyro. Two matchers use that:
//! * [`match_guided`]: each known feature is searched only within `radius` pixels of its
//!   predicted position. The prediction of a ground robot is good, so the search is small,
//!   and a repeated pattern elsewhere in the image (the office's identical lights and tiles)
//!   cannot be picked.
//! * [`match_brute_force`]: every pair, for when there is no trustworthy prediction (start-up,
//!   a kidnapped or slipping robot, a camera coming back after an outage). Only mutual best
//!   matches are kept.
//!
//! Both accept a match only when its Hamming distance is at most `max_distance` and clearly
//! better than the second best (`best < ratio * second`): on a plain ceiling a weak unique
//! match is worth more than a strong ambiguous one. No train feature is given to two queries.
//! The work is bounded by the product of the input sizes, matches go into a caller-provided
//! slice, and nothing allocates.

use super::brief::Descriptor;

/// One accepted match.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Match {
    /// Index into the query (known) features.
    pub query: usize,
    /// Index into the train (new frame) features.
    pub train: usize,
    /// Hamming distance of the two descriptors.
    pub distance: u32,
}

/// Acceptance rules shared by both matchers.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MatchConfig {
    /// Largest Hamming distance accepted.
    pub max_distance: u32,
    /// The best distance must be below `ratio` times the second best.
    pub ratio: f32,
}

impl Default for MatchConfig {
    fn default() -> Self {
        Self {
            max_distance: 64,
            ratio: 0.8,
        }
    }
}

/// What a matcher did with its queries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MatchStats {
    /// Matches written.
    pub matched: usize,
    /// Queries with no candidate (none in the radius, or nothing to match).
    pub no_candidate: usize,
    /// Queries whose best candidate was farther than `max_distance`.
    pub too_far: usize,
    /// Queries refused by the ratio test.
    pub ambiguous: usize,
    /// Matches refused because another query took the same train feature with a better
    /// distance (guided), or because the best was not mutual (brute force).
    pub not_unique: usize,
    /// Matches lost because the output was full.
    pub dropped: usize,
}

/// The best and second-best distances among candidates, and the index of the best.
#[derive(Clone, Copy, Debug)]
struct Best {
    index: usize,
    first: u32,
    second: u32,
}

impl Best {
    const NONE: Self = Self {
        index: usize::MAX,
        first: u32::MAX,
        second: u32::MAX,
    };

    fn offer(&mut self, index: usize, d: u32) {
        if d < self.first {
            self.second = self.first;
            self.first = d;
            self.index = index;
        } else if d < self.second {
            self.second = d;
        }
    }

    /// Applies the acceptance rules, counting refusals.
    fn accept(&self, cfg: &MatchConfig, stats: &mut MatchStats) -> bool {
        if self.index == usize::MAX {
            stats.no_candidate += 1;
            false
        } else if self.first > cfg.max_distance {
            stats.too_far += 1;
            false
        } else if self.second != u32::MAX && self.first as f32 >= cfg.ratio * self.second as f32 {
            stats.ambiguous += 1;
            false
        } else {
            true
        }
    }
}

/// Matches each known feature (`query`, with its `predicted` position in the new frame) to
/// the new frame's features (`train`, at `train_pos`) within `radius` pixels.
///
/// Queries and positions are paired by index (extra entries of the longer slice are ignored).
/// When two queries take the same train feature, the closer descriptor keeps it.
pub fn match_guided(
    query: &[Descriptor],
    predicted: &[[f32; 2]],
    train: &[Descriptor],
    train_pos: &[[f32; 2]],
    radius: f32,
    cfg: &MatchConfig,
    out: &mut [Match],
) -> MatchStats {
    let mut stats = MatchStats::default();
    let r2 = radius * radius;
    for (qi, (qd, qp)) in query.iter().zip(predicted).enumerate() {
        let mut best = Best::NONE;
        for (ti, (td, tp)) in train.iter().zip(train_pos).enumerate() {
            let (dx, dy) = (tp[0] - qp[0], tp[1] - qp[1]);
            if dx * dx + dy * dy <= r2 {
                best.offer(ti, qd.hamming(td));
            }
        }
        if !best.accept(cfg, &mut stats) {
            continue;
        }
        let m = Match {
            query: qi,
            train: best.index,
            distance: best.first,
        };
        let taken = out
            .get_mut(..stats.matched)
            .and_then(|done| done.iter_mut().find(|o| o.train == m.train));
        match taken {
            Some(other) => {
                stats.not_unique += 1;
                if m.distance < other.distance {
                    *other = m;
                }
            }
            None => match out.get_mut(stats.matched) {
                Some(slot) => {
                    *slot = m;
                    stats.matched += 1;
                }
                None => stats.dropped += 1,
            },
        }
    }
    stats
}

/// The best train index and distances for descriptor `d`.
fn best_among(d: &Descriptor, candidates: &[Descriptor]) -> Best {
    let mut best = Best::NONE;
    for (i, c) in candidates.iter().enumerate() {
        best.offer(i, d.hamming(c));
    }
    best
}

/// Matches every query against every train descriptor, keeping mutual best matches that
/// pass the distance and ratio tests.
pub fn match_brute_force(
    query: &[Descriptor],
    train: &[Descriptor],
    cfg: &MatchConfig,
    out: &mut [Match],
) -> MatchStats {
    let mut stats = MatchStats::default();
    for (qi, qd) in query.iter().enumerate() {
        let best = best_among(qd, train);
        if !best.accept(cfg, &mut stats) {
            continue;
        }
        let Some(td) = train.get(best.index) else {
            continue;
        };
        if best_among(td, query).index != qi {
            stats.not_unique += 1;
            continue;
        }
        let m = Match {
            query: qi,
            train: best.index,
            distance: best.first,
        };
        match out.get_mut(stats.matched) {
            Some(slot) => {
                *slot = m;
                stats.matched += 1;
            }
            None => stats.dropped += 1,
        }
    }
    stats
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::vec::Vec;

    use super::super::fast::Keypoint;
    use super::super::synth::{Scene, View};
    use super::*;

    const W: usize = 256;
    const H: usize = 192;

    fn desc(words: [u32; 8]) -> Descriptor {
        Descriptor(words)
    }

    #[test]
    fn the_rules_refuse_far_and_ambiguous_matches() {
        let q = [desc([0; 8]), desc([u32::MAX; 8]), desc([0xFF; 8])];
        // Train 0 is q0 with 3 bits flipped; 1 and 2 are equally close to q2.
        let t = [
            desc([0b111, 0, 0, 0, 0, 0, 0, 0]),
            desc([0xFE; 8]),
            desc([0x7F; 8]),
        ];
        let cfg = MatchConfig::default();
        let mut out = [Match::default(); 4];
        let s = match_brute_force(&q, &t, &cfg, &mut out);
        assert_eq!(s.matched, 1);
        assert_eq!(
            out[0],
            Match {
                query: 0,
                train: 0,
                distance: 3
            }
        );
        assert_eq!(s.too_far, 1); // q1 is 256 - 56 bits from everything
        assert_eq!(s.ambiguous, 1); // q2: 8 and 8
        let none = match_brute_force(&q, &[], &cfg, &mut out);
        assert_eq!(none.no_candidate, 3);
        let nothing = match_brute_force(&[], &t, &cfg, &mut out);
        assert_eq!(nothing, MatchStats::default());
    }

    #[test]
    fn brute_force_keeps_only_mutual_best() {
        // q0 and q1 both prefer t0, which prefers q1.
        let q = [
            desc([0b11, 0, 0, 0, 0, 0, 0, 0]),
            desc([0b1, 0, 0, 0, 0, 0, 0, 0]),
        ];
        let t = [desc([0; 8]), desc([u32::MAX; 8])];
        let cfg = MatchConfig {
            ratio: 1.0,
            ..MatchConfig::default()
        };
        let mut out = [Match::default(); 4];
        let s = match_brute_force(&q, &t, &cfg, &mut out);
        assert_eq!((s.matched, s.not_unique), (1, 1));
        assert_eq!(out[0].query, 1);
    }

    #[test]
    fn guided_search_stays_in_its_radius_and_gives_each_feature_once() {
        let d = desc([0x0F0F; 8]);
        let q = [d, d];
        let predicted = [[10.0, 10.0], [12.0, 10.0]];
        // The identical feature far away must not be taken; the near one only once.
        let t = [d, d];
        let pos = [[11.0, 10.0], [90.0, 90.0]];
        let cfg = MatchConfig::default();
        let mut out = [Match::default(); 4];
        let s = match_guided(&q, &predicted, &t, &pos, 5.0, &cfg, &mut out);
        assert_eq!((s.matched, s.not_unique), (1, 1));
        assert_eq!((out[0].query, out[0].train), (0, 0));
        let mut full: [Match; 0] = [];
        let s = match_guided(&q, &predicted, &t, &pos, 200.0, &cfg, &mut full);
        assert_eq!(s.ambiguous, 2);
        let s = match_guided(&q[..1], &predicted[..1], &t, &pos, 5.0, &cfg, &mut full);
        assert_eq!(s.dropped, 1);
    }

    /// Level-0 keypoints and descriptors of one view.
    fn features(scene: &Scene, view: &View) -> (Vec<Keypoint>, Vec<Descriptor>) {
        features_of(&scene.render(view))
    }

    fn features_of(data: &[u8]) -> (Vec<Keypoint>, Vec<Descriptor>) {
        super::super::synth::features_of(data, W, H)
            .into_iter()
            .unzip()
    }

    /// Matches whose train position is within 2 px of where the query's corner went (a
    /// corner of a turned view can be found a pixel away from its true place).
    fn inliers(a: &View, b: &View, ka: &[Keypoint], kb: &[Keypoint], ms: &[Match]) -> usize {
        ms.iter()
            .filter(|m| {
                let p = a.map_to(b, ka[m.query].position());
                let q = kb[m.train].position();
                (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) <= 2.0f32.powi(2)
            })
            .count()
    }

    #[test]
    fn brute_force_recovers_a_shift_and_a_turn() {
        let scene = Scene::random(31, W, H, 120);
        let a = View::new(W, H, 0.0, [0.0, 0.0]);
        let (ka, da) = features(&scene, &a);
        for b in [
            View::new(W, H, 0.0, [12.0, -7.0]),
            View::new(W, H, 0.6, [4.0, 2.0]),
        ] {
            let (kb, db) = features(&scene, &b);
            let mut out = [Match::default(); 300];
            let s = match_brute_force(&da, &db, &MatchConfig::default(), &mut out);
            let ms = &out[..s.matched];
            let good = inliers(&a, &b, &ka, &kb, ms);
            // The bits only see the sign of intensity differences, so corners of two
            // rectangles of the same shape and angle look alike wherever they are: without a
            // prediction a few such pairs pass, which is what the guided matcher is for.
            assert!(ms.len() >= 30, "{s:?}");
            assert!(good * 100 >= ms.len() * 85, "{good} of {}", ms.len());
        }
        // The shift itself, as the median displacement of the matches.
        let b = View::new(W, H, 0.0, [12.0, -7.0]);
        let (kb, db) = features(&scene, &b);
        let mut out = [Match::default(); 300];
        let n = match_brute_force(&da, &db, &MatchConfig::default(), &mut out).matched;
        let mut dx: Vec<f32> = out[..n]
            .iter()
            .map(|m| kb[m.train].x - ka[m.query].x)
            .collect();
        let mut dy: Vec<f32> = out[..n]
            .iter()
            .map(|m| kb[m.train].y - ka[m.query].y)
            .collect();
        dx.sort_by(f32::total_cmp);
        dy.sort_by(f32::total_cmp);
        assert_eq!((dx[n / 2], dy[n / 2]), (12.0, -7.0));
    }

    #[test]
    fn guided_matching_with_an_imperfect_prediction_finds_the_shift() {
        let scene = Scene::random(37, W, H, 120);
        let a = View::new(W, H, 0.0, [0.0, 0.0]);
        let b = View::new(W, H, 0.15, [9.0, 5.0]);
        let (ka, da) = features(&scene, &a);
        let (kb, db) = features(&scene, &b);
        // The prediction is off by about 2 px, as from wheel odometry.
        let predicted: Vec<[f32; 2]> = ka
            .iter()
            .map(|k| {
                let p = a.map_to(&b, k.position());
                [p[0] + 1.5, p[1] - 1.2]
            })
            .collect();
        let pos: Vec<[f32; 2]> = kb.iter().map(Keypoint::position).collect();
        let mut out = [Match::default(); 300];
        let cfg = MatchConfig::default();
        let s = match_guided(&da, &predicted, &db, &pos, 8.0, &cfg, &mut out);
        let ms = &out[..s.matched];
        let good = inliers(&a, &b, &ka, &kb, ms);
        assert!(ms.len() >= 30, "{s:?}");
        assert!(good * 20 >= ms.len() * 19, "{good} of {}", ms.len());
    }

    #[test]
    fn a_darker_noisy_exposure_still_matches() {
        use super::super::synth::Rng;
        let scene = Scene::random(41, W, H, 120);
        let a = View::new(W, H, 0.0, [0.0, 0.0]);
        let b = View::new(W, H, 0.2, [-6.0, 4.0]);
        let (ka, da) = features(&scene, &a);
        // Gain 0.6 and an offset (an auto-exposure step), then noise of +-4 grey levels.
        let mut rng = Rng::new(43);
        let dark: Vec<u8> = scene
            .render(&b)
            .iter()
            .map(|&v| {
                let noisy = 0.6 * f32::from(v) + 12.0 + rng.uniform(-4.0, 4.0);
                noisy.round().clamp(0.0, 255.0) as u8
            })
            .collect();
        let (kb, db) = features_of(&dark);
        let mut out = [Match::default(); 300];
        let s = match_brute_force(&da, &db, &MatchConfig::default(), &mut out);
        let ms = &out[..s.matched];
        let good = inliers(&a, &b, &ka, &kb, ms);
        assert!(ms.len() >= 25, "{s:?}");
        assert!(good * 100 >= ms.len() * 85, "{good} of {}", ms.len());
    }
}
