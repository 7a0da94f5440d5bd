//! Synthetic test scenes for the visual front-end: overlapping rectangles of random grey
//! values, rendered by sampling the scene in continuous coordinates, so a rotated and shifted
//! view is rendered exactly (no resampling of another image) and the true position of every
//! scene point in every view is known.

extern crate std;

use std::vec::Vec;

use super::brief::{describe, Descriptor};
use super::camera::{CameraExtrinsic, CameraModel, Intrinsics, Kb4};
use super::fast::{detect, FastConfig, Keypoint};
use super::image::{smooth_into, GrayImage};

/// The default FAST corners (level 0, at most 300) of a `w` x `h` grey frame with their rotated
/// BRIEF descriptors (corners too near the border for one are left out): what the descriptor
/// and matching tests compare between views.
pub fn features_of(data: &[u8], w: usize, h: usize) -> Vec<(Keypoint, Descriptor)> {
    let img = GrayImage::new_checked(w, h, w, data).unwrap();
    let mut kps = [Keypoint::default(); 300];
    let n = detect(&img, 0, &FastConfig::default(), &mut kps).kept;
    let mut buf = std::vec![0u8; w * h];
    let smooth = smooth_into(&img, &mut buf).unwrap();
    kps[..n]
        .iter()
        .filter_map(|k| Some((*k, describe(&smooth, k)?)))
        .collect()
}

/// The cleaner's camera as the geometry tests use it: a quarter-VGA KB4 fisheye (focal length
/// 120 px), 10 cm ahead of the turning centre and 9 cm up, tilted 60 degrees to the ceiling.
pub fn cleaner_camera() -> (CameraModel, CameraExtrinsic) {
    let k = Intrinsics {
        fx: 120.0,
        fy: 120.0,
        cx: 160.0,
        cy: 120.0,
    };
    let model = CameraModel::Kb4(
        Kb4::new_checked(k, [0.02, -0.01, 0.003, -0.0005], 1.6).expect("valid lens"),
    );
    let mount = CameraExtrinsic::mounted([0.1, 0.0, 0.09], 0.0, 60f64.to_radians());
    (model, mount)
}

/// A deterministic generator (SplitMix64) for the tests.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
        let u = (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
        lo + (hi - lo) * u
    }
}

/// A rectangle: centre, half sizes, angle, grey value.
#[derive(Clone, Copy, Debug)]
struct Rect {
    c: [f32; 2],
    half: [f32; 2],
    cos: f32,
    sin: f32,
    value: f32,
}

/// Rectangles painted in order over a plain background.
pub struct Scene {
    rects: Vec<Rect>,
    background: f32,
}

/// A view of the scene: the scene rotated by `rot` about the image centre, then shifted.
#[derive(Clone, Copy, Debug)]
pub struct View {
    pub w: usize,
    pub h: usize,
    pub rot: f32,
    pub shift: [f32; 2],
}

impl View {
    pub fn new(w: usize, h: usize, rot: f32, shift: [f32; 2]) -> Self {
        Self { w, h, rot, shift }
    }

    fn centre(&self) -> [f32; 2] {
        [self.w as f32 / 2.0, self.h as f32 / 2.0]
    }

    /// Where a scene point appears in this view.
    pub fn image_of(&self, s: [f32; 2]) -> [f32; 2] {
        let c = self.centre();
        let (sn, cs) = self.rot.sin_cos();
        let d = [s[0] - c[0], s[1] - c[1]];
        [
            cs * d[0] - sn * d[1] + c[0] + self.shift[0],
            sn * d[0] + cs * d[1] + c[1] + self.shift[1],
        ]
    }

    /// The scene point seen at an image position.
    pub fn scene_of(&self, p: [f32; 2]) -> [f32; 2] {
        let c = self.centre();
        let (sn, cs) = self.rot.sin_cos();
        let d = [p[0] - c[0] - self.shift[0], p[1] - c[1] - self.shift[1]];
        [cs * d[0] + sn * d[1] + c[0], -sn * d[0] + cs * d[1] + c[1]]
    }

    /// Where a point of view `self` appears in view `other`.
    pub fn map_to(&self, other: &View, p: [f32; 2]) -> [f32; 2] {
        other.image_of(self.scene_of(p))
    }
}

impl Scene {
    /// `count` random rectangles over a `w` x `h` area (and a margin around it).
    pub fn random(seed: u64, w: usize, h: usize, count: usize) -> Self {
        let mut rng = Rng::new(seed);
        let rects = (0..count)
            .map(|_| {
                let angle = rng.uniform(0.0, core::f32::consts::PI);
                Rect {
                    c: [
                        rng.uniform(-30.0, w as f32 + 30.0),
                        rng.uniform(-30.0, h as f32 + 30.0),
                    ],
                    half: [rng.uniform(4.0, 16.0), rng.uniform(4.0, 16.0)],
                    cos: angle.cos(),
                    sin: angle.sin(),
                    value: rng.uniform(10.0, 245.0),
                }
            })
            .collect();
        Self {
            rects,
            background: 118.0,
        }
    }

    /// One rectangle (axis-aligned) of `value` on `background`.
    pub fn single(c: [f32; 2], half: [f32; 2], value: f32, background: f32) -> Self {
        Self {
            rects: std::vec![Rect {
                c,
                half,
                cos: 1.0,
                sin: 0.0,
                value,
            }],
            background,
        }
    }

    fn value(&self, s: [f32; 2]) -> f32 {
        for r in self.rects.iter().rev() {
            let d = [s[0] - r.c[0], s[1] - r.c[1]];
            let u = r.cos * d[0] + r.sin * d[1];
            let v = -r.sin * d[0] + r.cos * d[1];
            if u.abs() <= r.half[0] && v.abs() <= r.half[1] {
                return r.value;
            }
        }
        self.background
    }

    /// The view rendered with 3x3 samples per pixel (pixel centres at integer coordinates).
    pub fn render(&self, view: &View) -> Vec<u8> {
        let mut out = std::vec![0u8; view.w * view.h];
        for (i, px) in out.iter_mut().enumerate() {
            let (x, y) = ((i % view.w) as f32, (i / view.w) as f32);
            let mut sum = 0.0;
            for sy in 0..3 {
                for sx in 0..3 {
                    let p = [x + (sx as f32 - 1.0) / 3.0, y + (sy as f32 - 1.0) / 3.0];
                    sum += self.value(view.scene_of(p));
                }
            }
            *px = (sum / 9.0).round().clamp(0.0, 255.0) as u8;
        }
        out
    }
}

#[test]
fn views_invert() {
    let a = View::new(100, 80, 0.4, [3.0, -2.0]);
    let b = View::new(100, 80, -0.1, [0.0, 5.0]);
    let p = [12.0, 33.0];
    let q = b.map_to(&a, a.map_to(&b, p));
    assert!((q[0] - p[0]).abs() < 1e-4 && (q[1] - p[1]).abs() < 1e-4);
}
