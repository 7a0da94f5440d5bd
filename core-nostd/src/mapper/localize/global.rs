//! Global localization (see the parent module): one keyframe's scan searched in every saved
//! submap, per quarter turn of heading, each candidate refined against the map and ranked by
//! the whole scan's fit to the whole map; the best place is a hypothesis only when no distinct
//! place fits nearly as well.

use super::{GLOBAL_BUDGET, PLACES, SECTORS};
use crate::frontend::far_csm::{FarCsmConfig, FarMatch, FarStep};
use crate::frontend::lidar::{FrontendStep, Travel};
use crate::geom::Se2;
use crate::gpe::NodeTie;
use crate::mapper::far::{AMBIGUITY, BASE_LEVEL, DISTINCT_THETA, DISTINCT_XY};
use crate::mapper::loops::{submap_and_pyramid, MatchSource};
use crate::mapper::Mapper;

/// A global search of one keyframe's scan (kept as the far search's scan) over every submap,
/// spread over the keyframes that follow.
#[derive(Clone, Debug)]
pub(super) struct Sweep {
    /// The keyframe's front-end pose and travel.
    frontend: Se2,
    travel: Travel,
    /// Submap slots searched so far (the next one to search).
    searched: usize,
    /// The refined matches at distinct places, each with its score in the whole map.
    places: heapless::Vec<(Se2, f32), PLACES>,
    /// Where the robot can be, from the prior: the keyframe's pose predicted from it and
    /// how far (metres, radians) it can be from there; `None`: anywhere.
    region: Option<(Se2, f64, f64)>,
}

impl Mapper<'_> {
    /// Continues the global search, up to the keyframe's budget: a search begins with this
    /// keyframe's scan and covers every submap; when it has, the best place, if unique in the
    /// whole map, becomes the hypothesis (tied to the keyframe the search began with).
    pub(super) fn global_search(&mut self, front: &FrontendStep) {
        let lc = self.cfg.loops;
        let half = self.cfg.grid.side as f64 * self.cfg.grid.resolution as f64 * 0.5;
        let config = FarCsmConfig {
            base_level: BASE_LEVEL.min(lc.pyramid_levels.saturating_sub(2)),
            min_score: lc.min_score,
            ..FarCsmConfig::DEFAULT
        };
        let travel = self.st.frontend.travel();
        let Some(l) = self.st.localize.as_mut() else {
            return;
        };
        let prior = l.prior;
        let mut sweep = match l.sweep.take() {
            Some(s) => s,
            None => {
                self.st.far.keep_scan(self.scan.as_slice());
                let region = prior.map(|p| {
                    let (xy, theta) = self.uncertainty(&travel.since(&p.travel));
                    let centre = p.estimate.compose(&p.frontend.between(&front.pose));
                    (centre, xy, theta)
                });
                Sweep {
                    frontend: front.pose,
                    travel,
                    searched: 0,
                    places: heapless::Vec::new(),
                    region,
                }
            }
        };
        let slots = self.submaps.len();
        let mut spent = 0u64;
        while spent < GLOBAL_BUDGET && sweep.searched < slots {
            let slot = sweep.searched;
            sweep.searched += 1;
            let Some(m) = self.submaps.get(slot).filter(|m| m.in_use).copied() else {
                continue;
            };
            let Some(anchor) = m.anchor_estimate else {
                continue;
            };
            let reach = half * core::f64::consts::SQRT_2;
            if sweep
                .region
                .is_some_and(|(c, xy, _)| libm::hypot(anchor.x - c.x, anchor.y - c.y) > xy + reach)
            {
                continue;
            }
            let (found, evaluated) = self.search_whole(slot, &anchor, &config, half);
            spent += evaluated.max(1);
            for f in found {
                self.add_global_candidate(&mut sweep, &f);
            }
        }
        let hypothesis = if sweep.searched < slots {
            None
        } else {
            for p in &sweep.places {
                debug!(
                    "global search: place {} {} {} fits the map {}",
                    p.0.x, p.0.y, p.0.theta, p.1
                );
            }
            unique_place(&sweep.places)
        };
        let Some(l) = self.st.localize.as_mut() else {
            return;
        };
        if sweep.searched < slots {
            l.sweep = Some(sweep);
            return;
        }
        // A search within the prior's region that found nothing widens to the whole map.
        l.prior = None;
        let Some(estimate) = hypothesis else {
            return;
        };
        l.fix = Some(NodeTie {
            estimate,
            frontend: sweep.frontend,
            travel: sweep.travel,
        });
        l.support = 0;
        l.misses = 0;
        l.counters.hypotheses += 1;
    }

    /// A coarse match `f` (world frame) of the sweep's scan: refined by ICP against the map
    /// around it and, when it lies where the prior allows, kept among the sweep's places with
    /// its score in the whole map.
    fn add_global_candidate(&mut self, sweep: &mut Sweep, f: &FarMatch) {
        let Ok((world, _)) = self.match_map(MatchSource::Far, &f.pose) else {
            return;
        };
        let outside = sweep.region.is_some_and(|(c, xy, theta)| {
            let d = c.between(&world);
            libm::hypot(d.x, d.y) > xy || libm::fabs(d.theta) > theta
        });
        if outside {
            return;
        }
        let (score, _) = self.map_fit(MatchSource::Far, &world);
        debug!(
            "global candidate {} {} {}: coarse {} fits the map {}",
            world.x, world.y, world.theta, f.score, score
        );
        add_place(&mut sweep.places, world, score);
    }

    /// The far search of the kept scan over the whole submap in `slot`, one search per
    /// quarter turn of heading ([`SECTORS`]: a room that looks alike turned by a quarter or
    /// half turn gives each its own candidate, for the whole map to tell apart), each run to
    /// its end; the matches in the world frame, and the candidates evaluated.
    fn search_whole(
        &mut self,
        slot: usize,
        anchor: &Se2,
        config: &FarCsmConfig,
        half: f64,
    ) -> (heapless::Vec<FarMatch, SECTORS>, u64) {
        let mut found = heapless::Vec::new();
        let Some((submap, pyramid)) = submap_and_pyramid(
            self.cells,
            self.submaps,
            self.pyramid,
            &mut self.st.loops.pyramid_of,
            &self.cfg,
            slot,
        ) else {
            return (found, 0);
        };
        let Some(l) = self.st.localize.as_mut() else {
            return (found, 0);
        };
        l.counters.global_searches += 1;
        // Only the points within half a submap of the robot: with the robot near the submap's
        // middle, where it was when the submap was built, they fall inside it, while the
        // farther ones would land outside and score nothing even at the true pose.
        let r2 = (half * half) as f32;
        self.loop_scan.clear();
        for q in self.st.far.scan() {
            if q.p[0] * q.p[0] + q.p[1] * q.p[1] <= r2 {
                let _ = self.loop_scan.push(*q);
            }
        }
        let reach = self.cfg.submap_length.min(half);
        let sector = core::f64::consts::TAU / SECTORS as f64;
        let config = FarCsmConfig {
            window_theta: 0.5 * sector,
            ..*config
        };
        let mut evaluated = 0;
        for k in 0..SECTORS {
            let seed = Se2::new(0.0, 0.0, k as f64 * sector);
            if l.search
                .start(self.loop_scan.as_slice(), &seed, reach, &config)
                .is_err()
            {
                break;
            }
            let m = loop {
                match l.search.step(&submap, &pyramid, u32::MAX) {
                    Ok(FarStep::Working) => continue,
                    Ok(FarStep::Done(m)) => break m,
                    Err(_) => break None,
                }
            };
            evaluated += l.search.evaluated();
            l.search.cancel();
            if let Some(m) = m {
                let _ = found.push(FarMatch {
                    pose: anchor.compose(&m.pose),
                    ..m
                });
            }
        }
        (found, evaluated)
    }
}

/// Adds a refined match at `world` scoring `score` to the distinct `places` found for one
/// keyframe: one at the same place keeps the higher score; when all are taken, the lowest
/// scoring gives way to a higher one.
fn add_place(places: &mut heapless::Vec<(Se2, f32), PLACES>, world: Se2, score: f32) {
    if let Some(p) = places.iter_mut().find(|p| !distinct(&p.0, &world)) {
        if score > p.1 {
            *p = (world, score);
        }
        return;
    }
    if places.push((world, score)).is_ok() {
        return;
    }
    if let Some(low) = places.iter_mut().min_by(|a, b| a.1.total_cmp(&b.1)) {
        if score > low.1 {
            *low = (world, score);
        }
    }
}

/// The best scoring of `places`, unless a distinct one fits the whole map nearly as well (a
/// room like another, or one whose submap is too small to see what tells them apart).
fn unique_place(places: &[(Se2, f32)]) -> Option<Se2> {
    let &(best, score) = places.iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
    let rival = places
        .iter()
        .filter(|p| distinct(&p.0, &best))
        .map(|p| p.1)
        .fold(0.0f32, f32::max);
    (rival < AMBIGUITY * score).then_some(best)
}

/// Two world poses are distinct places (the far search's thresholds).
fn distinct(a: &Se2, b: &Se2) -> bool {
    let d = a.between(b);
    libm::hypot(d.x, d.y) > DISTINCT_XY || libm::fabs(d.theta) > DISTINCT_THETA
}
