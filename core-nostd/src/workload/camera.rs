//! The camera sections of the workload: the visual front-end of section III-B.1 (grey copy,
//! pyramid, FAST with grid bucketing, orientation, smoothing, BRIEF, matching to the previous
//! frame) on two synthetic quarter-VGA frames, and the drawing of those frames, timed apart so
//! that the front-end's count is its own.
//!
//! The frames show a ceiling: a plain background with 36 axis-aligned panels (lights, vents,
//! tiles) of different grey levels drawn from a fixed integer generator, the second frame
//! shifted by (7, 4) pixels as a robot at 0.3 m/s would see it between two frames at 10 Hz.
//! Everything is integer until the checksum, so the Cortex-A9 and x86-64 agree.

use crate::frontend::visual::frame::{scratch_bytes, MAX_FEATURES};
use crate::frontend::visual::matching::Match;
use crate::frontend::visual::{CameraTrack, Keypoint, TrackConfig, TrackScratch};
use crate::sensor::{ImageView, PixelFormat, Timestamp};

/// Frame width, pixels (the simulator's and many robot cameras' quarter VGA).
pub const WIDTH: usize = 320;
/// Frame height, pixels.
pub const HEIGHT: usize = 240;
/// Panels drawn on the ceiling.
const PANELS: u32 = 36;
/// Grey level of the bare ceiling.
const BACKGROUND: u8 = 128;
/// Image motion between the two frames, pixels.
const SHIFT: (i32, i32) = (7, 4);

/// The storage of the camera sections (about 370 kB: a static on the firmware).
#[derive(Debug)]
pub struct CameraStorage {
    frames: [[u8; WIDTH * HEIGHT]; 2],
    bytes: [u8; scratch_bytes(WIDTH, HEIGHT)],
    track: CameraTrack,
    corners: [Keypoint; MAX_FEATURES],
    matches: [Match; MAX_FEATURES],
}

impl Default for CameraStorage {
    fn default() -> Self {
        Self::new()
    }
}

impl CameraStorage {
    /// Blank frames and an empty track.
    pub const fn new() -> Self {
        const K: Keypoint = Keypoint {
            x: 0.0,
            y: 0.0,
            level: 0,
            score: 0.0,
            angle: 0.0,
        };
        const M: Match = Match {
            query: 0,
            train: 0,
            distance: 0,
        };
        CameraStorage {
            frames: [[0; WIDTH * HEIGHT]; 2],
            bytes: [0; scratch_bytes(WIDTH, HEIGHT)],
            track: CameraTrack::new(),
            corners: [K; MAX_FEATURES],
            matches: [M; MAX_FEATURES],
        }
    }
}

/// A small linear congruential generator (Numerical Recipes' constants): enough to place
/// panels, and the same on every target.
struct Lcg(u32);

impl Lcg {
    fn below(&mut self, n: u32) -> u32 {
        self.0 = self.0.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (self.0 >> 8) % n.max(1)
    }
}

/// Draws both frames; the checksum is the sum of their pixels.
pub fn render(s: &mut CameraStorage) -> f64 {
    let mut sum = 0u64;
    for (k, frame) in s.frames.iter_mut().enumerate() {
        let k = k as i32;
        frame.fill(BACKGROUND);
        let mut rng = Lcg(0x00C1_0151);
        for _ in 0..PANELS {
            let x0 = rng.below(WIDTH as u32 + 40) as i32 - 20 - k * SHIFT.0;
            let y0 = rng.below(HEIGHT as u32 + 40) as i32 - 20 - k * SHIFT.1;
            let w = 8 + rng.below(33) as i32;
            let h = 8 + rng.below(33) as i32;
            // Never the background's level, so every panel has edges.
            let value = (30 + rng.below(200)) as u8 | 1;
            let xs = x0.clamp(0, WIDTH as i32) as usize..(x0 + w).clamp(0, WIDTH as i32) as usize;
            let ys = y0.clamp(0, HEIGHT as i32) as usize..(y0 + h).clamp(0, HEIGHT as i32) as usize;
            for y in ys {
                if let Some(row) = frame.get_mut(y * WIDTH + xs.start..y * WIDTH + xs.end) {
                    row.fill(value);
                }
            }
        }
        sum += frame.iter().map(|&p| u64::from(p)).sum::<u64>();
    }
    sum as f64
}

/// Tracks the first frame, then the second against it, with the default settings; the
/// checksum folds in the feature counts, the matches and every kept keypoint's position.
/// Call [`render`] first.
pub fn track(s: &mut CameraStorage) -> f64 {
    s.track.reset();
    let cfg = TrackConfig::default();
    let mut checksum = 0.0;
    for (k, frame) in s.frames.iter().enumerate() {
        let stamp = k as i64 * 100_000_000;
        let Ok(view) = ImageView::new_checked(
            Timestamp::from_nanos(stamp),
            WIDTH,
            HEIGHT,
            WIDTH,
            PixelFormat::Mono8,
            frame,
        ) else {
            return -1.0;
        };
        let mut scratch = TrackScratch {
            bytes: &mut s.bytes,
            corners: &mut s.corners,
            matches: &mut s.matches,
        };
        let Ok(step) = s.track.track(stamp, &view, &cfg, &mut scratch) else {
            return -2.0;
        };
        checksum = checksum * 1e3 + step.features as f64 + 1e-3 * step.tracked as f64;
    }
    let positions = s.track.newest().map_or(0.0, |f| {
        f.keypoints()
            .iter()
            .map(|k| f64::from(k.x) + 0.5 * f64::from(k.y) + f64::from(k.level))
            .sum()
    });
    checksum + 1e-6 * positions
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;

    #[test]
    fn the_shifted_ceiling_is_tracked() {
        let mut s = std::boxed::Box::new(CameraStorage::new());
        assert!(render(&mut s) > 0.0);
        let c = track(&mut s);
        let stats = s.track.stats();
        assert_eq!(stats.frames, 2);
        // 36 panels, most with four corners in view.
        let second = s.track.newest().map_or(0, |f| f.len());
        assert!(second >= 60, "{second} features");
        assert!(2 * stats.tracked >= second as u64, "{stats:?}");
        assert_eq!(c.to_bits(), track(&mut s).to_bits());
    }
}
