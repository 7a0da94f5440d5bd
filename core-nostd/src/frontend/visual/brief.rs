//! Rotated BRIEF: a 256-bit binary descriptor of the patch around a keypoint (paper section
//! III-B.1).
//!
//! Each bit compares the intensities at two fixed points of the patch, rotated by the
//! keypoint's orientation (`fast.rs`), so the same ceiling corner gives the same bits when the
//! robot has turned. Comparing descriptors is then a XOR and a population count, which is what
//! lets the matcher try many candidates within the per-frame budget of the Cortex-A9.
//!
//! Why it is built this way:
//! * **Own pattern, generated at compile time.** The 256 point pairs are drawn by [`PATTERN`]'s
//!   const generator (SplitMix64 from a fixed seed, each coordinate the sum of three uniform
//!   integers in `[-6, 6]`, a rough Gaussian of deviation 6.5 px, points kept inside a disk of
//!   radius [`PATTERN_RADIUS`], pairs at least 2 px apart). Every build of every target holds
//!   the same table, and nothing is copied from other projects.
//! * **Radius 13 inside a patch of radius 15.** A rotated point moves by at most its radius
//!   plus half a pixel of rounding, so every test stays inside the patch that `fast.rs` keeps
//!   clear of the image border.
//! * **Smoothed input.** The caller passes a smoothed level (`image::smooth_into`); without it
//!   one pixel of sensor noise flips a bit.
//! * **Per-keypoint rotation with `libm`.** One sine and cosine per keypoint and 512 rounded
//!   rotations; no table of pre-rotated patterns (that would cost memory), and the same bits on
//!   x86-64 and ARMv7.

use super::fast::{Keypoint, PATCH_RADIUS};
use super::image::GrayImage;

/// Bits per descriptor.
pub const BITS: usize = 256;
/// Pattern points lie within this radius of the keypoint.
pub const PATTERN_RADIUS: i32 = 13;
/// The generator's seed (the bytes of "CLOi-BRF").
const PATTERN_SEED: u64 = 0x434C_4F69_2D42_5246;

/// A 256-bit binary descriptor.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Descriptor(pub [u32; 8]);

impl Descriptor {
    /// The number of differing bits.
    pub fn hamming(&self, other: &Self) -> u32 {
        self.0
            .iter()
            .zip(other.0.iter())
            .map(|(a, b)| (a ^ b).count_ones())
            .sum()
    }

    /// Bit `i` (false past [`BITS`]).
    pub fn bit(&self, i: usize) -> bool {
        self.0.get(i / 32).is_some_and(|w| (w >> (i % 32)) & 1 == 1)
    }
}

/// The sampling pattern: 256 pairs of points `[ax, ay, bx, by]` relative to the keypoint.
pub const PATTERN: [[i8; 4]; BITS] = generate_pattern(PATTERN_SEED);

const fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// One coordinate: the sum of three uniform integers in `[-6, 6]`.
const fn coordinate(state: &mut u64) -> i32 {
    let mut sum = 0;
    let mut k = 0;
    while k < 3 {
        sum += (splitmix(state) % 13) as i32 - 6;
        k += 1;
    }
    sum
}

/// A point of the disk of radius [`PATTERN_RADIUS`], by rejection sampling. The disk holds
/// most of the distribution, so a draw rarely fails; the tries are capped all the same, with
/// the centre as the (never reached for [`PATTERN_SEED`]) last resort. This runs when the
/// crate is compiled: [`PATTERN`] is a constant.
const fn disk_point(state: &mut u64) -> (i32, i32) {
    let mut tries = 0;
    while tries < 64 {
        let x = coordinate(state);
        let y = coordinate(state);
        if x * x + y * y <= PATTERN_RADIUS * PATTERN_RADIUS {
            return (x, y);
        }
        tries += 1;
    }
    (0, 0)
}

const fn generate_pattern(seed: u64) -> [[i8; 4]; BITS] {
    let mut out = [[0i8; 4]; BITS];
    let mut state = seed;
    let mut i = 0;
    while i < BITS {
        let a = disk_point(&mut state);
        let b = disk_point(&mut state);
        let (dx, dy) = (a.0 - b.0, a.1 - b.1);
        if dx * dx + dy * dy >= 4 {
            out[i] = [a.0 as i8, a.1 as i8, b.0 as i8, b.1 as i8];
            i += 1;
        }
    }
    out
}

/// A pattern point rotated by (cos, sin) and rounded, relative to the keypoint.
fn rotate(x: i8, y: i8, c: f32, s: f32) -> (i32, i32) {
    let (x, y) = (f32::from(x), f32::from(y));
    (
        libm::roundf(c * x - s * y) as i32,
        libm::roundf(s * x + c * y) as i32,
    )
}

/// The descriptor of `kp` on `smoothed` (the smoothed image of the keypoint's level), or
/// `None` when its patch leaves the image.
pub fn describe(smoothed: &GrayImage<'_>, kp: &Keypoint) -> Option<Descriptor> {
    let (x, y) = (libm::roundf(kp.x) as i32, libm::roundf(kp.y) as i32);
    if !smoothed.contains_patch(x, y, PATCH_RADIUS) {
        return None;
    }
    let (s, c) = (libm::sinf(kp.angle), libm::cosf(kp.angle));
    let mut d = Descriptor::default();
    for (i, p) in PATTERN.iter().enumerate() {
        let (ax, ay) = rotate(p[0], p[1], c, s);
        let (bx, by) = rotate(p[2], p[3], c, s);
        let a = smoothed.at(x + ax, y + ay)?;
        let b = smoothed.at(x + bx, y + by)?;
        if a < b {
            if let Some(word) = d.0.get_mut(i / 32) {
                *word |= 1 << (i % 32);
            }
        }
    }
    Some(d)
}

/// Descriptors of `keypoints` (all of one level, on its smoothed image) into `out`; entries
/// whose patch leaves the image are `None`. Returns how many were written.
pub fn describe_all(
    smoothed: &GrayImage<'_>,
    keypoints: &[Keypoint],
    out: &mut [Option<Descriptor>],
) -> usize {
    let mut n = 0;
    for (kp, slot) in keypoints.iter().zip(out.iter_mut()) {
        *slot = describe(smoothed, kp);
        n += 1;
    }
    n
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::super::synth::{Scene, View};
    use super::*;

    const W: usize = 256;
    const H: usize = 192;

    #[test]
    fn the_pattern_fits_the_patch_even_rotated() {
        let r = PATCH_RADIUS as f32;
        for p in PATTERN {
            for (x, y) in [(p[0], p[1]), (p[2], p[3])] {
                assert!(i32::from(x).pow(2) + i32::from(y).pow(2) <= PATTERN_RADIUS.pow(2));
                for k in 0..64 {
                    let a = k as f32 * core::f32::consts::TAU / 64.0;
                    let (rx, ry) = rotate(x, y, libm::cosf(a), libm::sinf(a));
                    assert!(rx.abs() as f32 <= r && ry.abs() as f32 <= r);
                }
            }
            let (dx, dy) = (
                i32::from(p[0]) - i32::from(p[2]),
                i32::from(p[1]) - i32::from(p[3]),
            );
            assert!(dx * dx + dy * dy >= 4);
        }
        // Spread over the disk, not stuck at its centre.
        let far = PATTERN
            .iter()
            .filter(|p| p[0].abs() >= 8 || p[1].abs() >= 8)
            .count();
        assert!(far > 40, "{far}");
        assert_eq!(PATTERN, generate_pattern(PATTERN_SEED));
    }

    #[test]
    fn hamming_counts_differing_bits() {
        let a = Descriptor([0; 8]);
        let mut b = a;
        b.0[0] = 0b1011;
        b.0[7] = 1 << 31;
        assert_eq!(a.hamming(&b), 4);
        assert_eq!(b.hamming(&b), 0);
        assert!(b.bit(0) && !b.bit(2) && b.bit(255) && !b.bit(256));
        assert_eq!(Descriptor([u32::MAX; 8]).hamming(&a), 256);
    }

    #[test]
    fn a_patch_at_the_border_has_no_descriptor() {
        let data = [100u8; 40 * 40];
        let img = GrayImage::new_checked(40, 40, 40, &data).unwrap();
        let kp = |x: f32, y: f32| Keypoint {
            x,
            y,
            ..Keypoint::default()
        };
        assert!(describe(&img, &kp(20.0, 20.0)).is_some());
        assert!(describe(&img, &kp(14.0, 20.0)).is_none());
        assert!(describe(&img, &kp(20.0, 25.0)).is_none());
        assert!(describe(&img, &kp(f32::NAN, -1e30)).is_none());
    }

    /// Keypoints and descriptors of one view.
    fn features(scene: &Scene, view: &View) -> std::vec::Vec<(Keypoint, Descriptor)> {
        super::super::synth::features_of(&scene.render(view), W, H)
    }

    #[test]
    fn the_same_corner_keeps_its_bits_when_the_view_turns() {
        let scene = Scene::random(23, W, H, 120);
        let a = View::new(W, H, 0.0, [0.0, 0.0]);
        let b = View::new(W, H, 1.1, [-5.0, 3.0]);
        let (fa, fb) = (features(&scene, &a), features(&scene, &b));
        let mut same = std::vec::Vec::new();
        let mut other = std::vec::Vec::new();
        for (ka, da) in &fa {
            let p = a.map_to(&b, [ka.x, ka.y]);
            for (kb, db) in &fb {
                let d2 = (kb.x - p[0]).powi(2) + (kb.y - p[1]).powi(2);
                if d2 <= 2.0 {
                    same.push(da.hamming(db));
                } else if d2 > 30.0f32.powi(2) {
                    other.push(da.hamming(db));
                }
            }
        }
        same.sort_unstable();
        other.sort_unstable();
        assert!(same.len() >= 20, "{}", same.len());
        let q = |v: &[u32], k: usize| v[v.len() * k / 10];
        // Corresponding corners differ in a few bits; unrelated ones in many more. (The
        // scene is flat between edges, and equal pixels all give 0 bits, so unrelated
        // descriptors share more than the half of bits they would on real texture.)
        assert!(q(&same, 5) <= 20, "{same:?}");
        assert!(
            q(&same, 9) < q(&other, 1),
            "{} vs {}",
            q(&same, 9),
            q(&other, 1)
        );
        assert!(q(&other, 5) >= 3 * q(&same, 5));
    }
}
