//! Monochrome cameras tilted up towards the ceiling, rendered by ray casting.
//!
//! **Geometry.** The body frame has x forward, y left, z up. A camera sits at `mount` (body
//! frame), looks along the body heading `yaw`, pitched up by `tilt` (45 or 60 deg). Its optical
//! frame has z along the optical axis, x to the image right and y to the image bottom.
//!
//! **Lens models** for a point `(X, Y, Z)` in the optical frame:
//! * pinhole: `u = fx X/Z + cx`, `v = fy Y/Z + cy` (only `Z > 0`);
//! * Kannala-Brandt (equidistant fisheye with odd polynomial): `θ = atan2(√(X²+Y²), Z)`,
//!   `d(θ) = θ + k1 θ³ + k2 θ⁵ + k3 θ⁷ + k4 θ⁹`, `u = fx d X/√(X²+Y²) + cx`, likewise `v`.
//!
//! **Rendering.** Every pixel's ray (unprojected once per camera) is cast from the camera
//! centre: it hits the first wall part below the wall's top edge (glass is see-through), or else
//! the ceiling plane (rays going up) or the floor. Surfaces are procedurally textured
//! ([`crate::texture`]); lights are emissive and saturate. Per frame, an exposure gain
//! `exp(N(0, gain_sigma²))` scales the image; each pixel then gets read noise and shot noise
//! `N(0, read_noise² + shot_noise² · I)` (in grey levels) before rounding to 8 bits. Optional
//! motion blur averages three renders spread over the exposure time. A dirty lens blurs, lowers
//! contrast and adds dark smudges.

use cloi_core::frontend::visual::{
    CameraError, CameraExtrinsic, CameraModel, Intrinsics, Kb4, Pinhole,
};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::texture;
use crate::world::{Material, World};

/// Lens model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Lens {
    /// Ideal pinhole.
    Pinhole,
    /// Kannala-Brandt fisheye with coefficients `k1..k4`.
    KannalaBrandt([f64; 4]),
}

/// Camera parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraParams {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Lens model.
    pub lens: Lens,
    /// Upward tilt of the optical axis from the floor plane, radians.
    pub tilt: f64,
    /// Heading of the optical axis in the body frame, radians (0 = forward).
    pub yaw: f64,
    /// Optical centre in the body frame, metres.
    pub mount: [f64; 3],
    /// Frames per second.
    pub rate_hz: f64,
    /// Exposure time, seconds (used by motion blur).
    pub exposure: f64,
    /// Exposure gain fluctuation (1 sigma, log scale).
    pub gain_sigma: f64,
    /// Read noise, grey levels (1 sigma).
    pub read_noise: f64,
    /// Shot noise factor: variance adds `shot_noise² · I`.
    pub shot_noise: f64,
    /// Average three sub-exposures.
    pub motion_blur: bool,
}

impl CameraParams {
    /// A camera with a lens covering about 90 deg (pinhole) or 190 deg (fisheye) horizontally.
    pub fn new(width: u32, height: u32, fisheye: bool, tilt_deg: f64, yaw_deg: f64) -> Self {
        let w = f64::from(width);
        let (f, lens) = if fisheye {
            (w / 3.4, Lens::KannalaBrandt([0.02, -0.004, 0.0006, 0.0]))
        } else {
            (w / 2.0, Lens::Pinhole)
        };
        CameraParams {
            width,
            height,
            fx: f,
            fy: f,
            cx: w / 2.0 - 0.5,
            cy: f64::from(height) / 2.0 - 0.5,
            lens,
            tilt: tilt_deg.to_radians(),
            yaw: yaw_deg.to_radians(),
            mount: [
                0.1 * yaw_deg.to_radians().cos(),
                0.1 * yaw_deg.to_radians().sin(),
                0.35,
            ],
            rate_hz: 10.0,
            exposure: 0.015,
            gain_sigma: 0.05,
            read_noise: 2.0,
            shot_noise: 0.3,
            motion_blur: false,
        }
    }

    /// Columns of the rotation from the optical frame to the body frame: (right, down, axis).
    pub fn body_from_optical(&self) -> [[f64; 3]; 3] {
        let (ct, st) = (self.tilt.cos(), self.tilt.sin());
        let (cy, sy) = (self.yaw.cos(), self.yaw.sin());
        let axis = [ct * cy, ct * sy, st];
        let right = [sy, -cy, 0.0];
        // down = axis x right
        let down = [
            axis[1] * right[2] - axis[2] * right[1],
            axis[2] * right[0] - axis[0] * right[2],
            axis[0] * right[1] - axis[1] * right[0],
        ];
        [right, down, axis]
    }

    /// Projects a point in the optical frame to pixel coordinates.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        match self.lens {
            Lens::Pinhole => (p[2] > 1e-9).then(|| {
                [
                    self.fx * p[0] / p[2] + self.cx,
                    self.fy * p[1] / p[2] + self.cy,
                ]
            }),
            Lens::KannalaBrandt(k) => {
                let r = p[0].hypot(p[1]);
                if r < 1e-12 {
                    return (p[2] > 0.0).then_some([self.cx, self.cy]);
                }
                let th = r.atan2(p[2]);
                let t2 = th * th;
                let d = th * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))));
                Some([
                    self.fx * d * p[0] / r + self.cx,
                    self.fy * d * p[1] / r + self.cy,
                ])
            }
        }
    }

    /// The unit ray (optical frame) through a pixel position, or `None` outside the lens's
    /// field of view (fisheye beyond 100 deg off axis).
    pub fn unproject(&self, u: f64, v: f64) -> Option<[f64; 3]> {
        let mx = (u - self.cx) / self.fx;
        let my = (v - self.cy) / self.fy;
        match self.lens {
            Lens::Pinhole => {
                let n = (mx * mx + my * my + 1.0).sqrt();
                Some([mx / n, my / n, 1.0 / n])
            }
            Lens::KannalaBrandt(k) => {
                let d = mx.hypot(my);
                if d < 1e-12 {
                    return Some([0.0, 0.0, 1.0]);
                }
                // Newton on d(θ) = d.
                let mut th = d;
                for _ in 0..20 {
                    let t2 = th * th;
                    let f = th * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - d;
                    let df = 1.0
                        + t2 * (3.0 * k[0]
                            + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
                    let step = f / df;
                    th -= step;
                    if step.abs() < 1e-12 {
                        break;
                    }
                }
                if !(0.0..=FISHEYE_MAX_THETA_DEG.to_radians()).contains(&th) {
                    return None;
                }
                let s = th.sin();
                Some([s * mx / d, s * my / d, th.cos()])
            }
        }
    }
}

/// The fisheye field ends this far from the optical axis (radians): pixels beyond it are black.
pub const FISHEYE_MAX_THETA_DEG: f64 = 100.0;

impl CameraParams {
    /// The same lens as a `cloi-core` camera model, for the front-end to run on these frames.
    ///
    /// # Errors
    /// [`CameraError`] when the parameters make no valid core model.
    pub fn core_model(&self) -> Result<CameraModel, CameraError> {
        let k = Intrinsics {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        };
        Ok(match self.lens {
            Lens::Pinhole => CameraModel::Pinhole(Pinhole::new_checked(k)?),
            Lens::KannalaBrandt(d) => {
                CameraModel::Kb4(Kb4::new_checked(k, d, FISHEYE_MAX_THETA_DEG.to_radians())?)
            }
        })
    }

    /// The mounting as a `cloi-core` extrinsic (camera pose in the body frame).
    pub fn core_extrinsic(&self) -> CameraExtrinsic {
        CameraExtrinsic::mounted(self.mount, self.yaw, self.tilt)
    }
}

/// A pixel's ray in the body frame, split into what ray casting needs: the unit horizontal
/// direction, and the inverse slope (horizontal metres per metre of rise; 0 for a ray that
/// leaves the lens's field of view).
#[derive(Clone, Copy, Debug, PartialEq)]
struct PixelRay {
    dir: [f64; 2],
    inv_slope: f64,
    kind: RayKind,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum RayKind {
    Invalid,
    Up,
    Down,
    Level,
    Vertical,
}

impl PixelRay {
    fn new(d: [f64; 3]) -> PixelRay {
        if d[0].is_nan() {
            return PixelRay {
                dir: [0.0; 2],
                inv_slope: 0.0,
                kind: RayKind::Invalid,
            };
        }
        let h = (d[0] * d[0] + d[1] * d[1]).sqrt();
        if h < 1e-9 {
            return PixelRay {
                dir: [1.0, 0.0],
                inv_slope: 0.0,
                kind: if d[2] > 0.0 {
                    RayKind::Vertical
                } else {
                    RayKind::Invalid
                },
            };
        }
        let slope = d[2] / h;
        let kind = if slope > 1e-9 {
            RayKind::Up
        } else if slope < -1e-9 {
            RayKind::Down
        } else {
            RayKind::Level
        };
        PixelRay {
            dir: [d[0] / h, d[1] / h],
            inv_slope: if kind == RayKind::Level {
                0.0
            } else {
                1.0 / slope
            },
            kind,
        }
    }
}

/// A camera with its pixel rays precomputed in the body frame.
#[derive(Clone, Debug)]
pub struct Camera {
    /// Parameters.
    pub params: CameraParams,
    rays: Vec<PixelRay>,
}

/// A rendered 8-bit monochrome frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Row-major grey levels.
    pub pixels: Vec<u8>,
}

/// A lens contamination to apply to a frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DirtyLens {
    /// Blur radius at 320 pixels width.
    pub blur: f64,
    /// Seed for the smudge pattern.
    pub seed: u64,
}

impl Camera {
    /// Precomputes the rays of every pixel (pixel centres).
    pub fn new(params: CameraParams) -> Camera {
        let r = params.body_from_optical();
        let mut rays = Vec::with_capacity((params.width * params.height) as usize);
        for v in 0..params.height {
            for u in 0..params.width {
                let ray = params
                    .unproject(f64::from(u), f64::from(v))
                    .map_or([f64::NAN; 3], |o| {
                        [
                            r[0][0] * o[0] + r[1][0] * o[1] + r[2][0] * o[2],
                            r[0][1] * o[0] + r[1][1] * o[1] + r[2][1] * o[2],
                            r[0][2] * o[0] + r[1][2] * o[1] + r[2][2] * o[2],
                        ]
                    });
                rays.push(PixelRay::new(ray));
            }
        }
        Camera { params, rays }
    }

    /// Renders the noise-free radiance image (linear, 1.0 = white) seen from robot pose
    /// `(x, y, theta)`.
    pub fn radiance(&self, world: &World, x: f64, y: f64, theta: f64, out: &mut [f32]) {
        let (c, s) = (theta.cos(), theta.sin());
        let m = self.params.mount;
        let o = [x + c * m[0] - s * m[1], y + s * m[0] + c * m[1], m[2]];
        let up = world.ceiling_height - o[2];
        for (px, ray) in out.iter_mut().zip(&self.rays) {
            let d = [
                c * ray.dir[0] - s * ray.dir[1],
                s * ray.dir[0] + c * ray.dir[1],
            ];
            *px = match ray.kind {
                RayKind::Invalid => 0.0,
                RayKind::Vertical => texture::ceiling(world, [o[0], o[1]]),
                RayKind::Up => {
                    trace_horizontal(world, o, d, 1.0 / ray.inv_slope, up * ray.inv_slope, true)
                }
                RayKind::Down => trace_horizontal(
                    world,
                    o,
                    d,
                    1.0 / ray.inv_slope,
                    -o[2] * ray.inv_slope,
                    false,
                ),
                RayKind::Level => trace_horizontal(world, o, d, 0.0, 1e4, false),
            };
        }
    }

    /// Renders a complete 8-bit frame at `t` using `pose_at` for the robot pose (several poses
    /// when motion blur is on), with exposure noise from `rng` and an optional dirty lens.
    pub fn render(
        &self,
        world: &World,
        pose_at: impl Fn(f64) -> (f64, f64, f64),
        t: f64,
        dirty: Option<DirtyLens>,
        rng: &mut ChaCha8Rng,
    ) -> Frame {
        let p = &self.params;
        let n = (p.width * p.height) as usize;
        let mut acc = vec![0f32; n];
        let offsets: &[f64] = if p.motion_blur {
            &[-0.5, 0.0, 0.5]
        } else {
            &[0.0]
        };
        let mut tmp = vec![0f32; n];
        for off in offsets {
            let (x, y, th) = pose_at(t + off * p.exposure);
            self.radiance(world, x, y, th, &mut tmp);
            for (a, v) in acc.iter_mut().zip(&tmp) {
                *a += *v / offsets.len() as f32;
            }
        }
        if let Some(d) = dirty {
            apply_dirty_lens(&mut acc, p.width as usize, p.height as usize, d);
        }
        let gain = (p.gain_sigma * rng.sample::<f64, _>(StandardNormal)).exp() as f32;
        let pixels = acc
            .iter()
            .map(|&r| {
                let i = (r * gain * 200.0).min(255.0);
                let sd = (p.read_noise.powi(2) + p.shot_noise.powi(2) * f64::from(i)).sqrt();
                let n: f64 = rng.sample(StandardNormal);
                (f64::from(i) + sd * n + 0.5).clamp(0.0, 255.0) as u8
            })
            .collect();
        Frame {
            width: p.width,
            height: p.height,
            pixels,
        }
    }
}

/// Radiance along one ray from `o` (world, metres) in direction `d` (need not be unit).
pub fn trace(world: &World, o: [f64; 3], d: [f64; 3]) -> f32 {
    let h = (d[0] * d[0] + d[1] * d[1]).sqrt();
    let ceiling = world.ceiling_height;
    if h < 1e-9 {
        return if d[2] > 0.0 {
            texture::ceiling(world, [o[0], o[1]])
        } else {
            texture::floor([o[0], o[1]])
        };
    }
    let slope = d[2] / h;
    let dir = [d[0] / h, d[1] / h];
    let s_end = if slope > 1e-9 {
        (ceiling - o[2]) / slope
    } else if slope < -1e-9 {
        -o[2] / slope
    } else {
        1e4
    };
    trace_horizontal(world, o, dir, slope, s_end, slope > 0.0)
}

/// Radiance along a ray given by its unit horizontal direction `dir`, its `slope` (rise per
/// horizontal metre) and the horizontal distance `s_end` at which it meets the ceiling
/// (`up`) or the floor.
#[inline]
fn trace_horizontal(
    world: &World,
    o: [f64; 3],
    dir: [f64; 2],
    slope: f64,
    s_end: f64,
    up: bool,
) -> f32 {
    let hit = world.cast([o[0], o[1]], dir, s_end, |seg, s| {
        let z = o[2] + slope * s;
        seg.material != Material::Glass && z <= seg.height
    });
    match hit {
        Some(hit) => {
            let z = o[2] + slope * hit.s;
            texture::wall(world, hit.segment, hit.u, z)
        }
        None => {
            let p = [o[0] + dir[0] * s_end, o[1] + dir[1] * s_end];
            if up {
                texture::ceiling(world, p)
            } else {
                texture::floor(p)
            }
        }
    }
}

fn box_blur(img: &mut [f32], w: usize, h: usize, r: usize) {
    if r == 0 {
        return;
    }
    let mut tmp = vec![0f32; img.len()];
    let norm = 1.0 / (2 * r + 1) as f32;
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for k in 0..=2 * r {
                let xx = (x + k).saturating_sub(r).min(w - 1);
                s += img[y * w + xx];
            }
            tmp[y * w + x] = s * norm;
        }
    }
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for k in 0..=2 * r {
                let yy = (y + k).saturating_sub(r).min(h - 1);
                s += tmp[yy * w + x];
            }
            img[y * w + x] = s * norm;
        }
    }
}

fn apply_dirty_lens(img: &mut [f32], w: usize, h: usize, d: DirtyLens) {
    let r = (d.blur * w as f64 / 320.0).round().max(1.0) as usize;
    box_blur(img, w, h, r);
    box_blur(img, w, h, r);
    let mean = img.iter().sum::<f32>() / img.len().max(1) as f32;
    // A fixed smudge pattern per fault: a few dark blobs.
    let blobs: Vec<[f64; 3]> = (0..5u64)
        .map(|k| {
            let hsh =
                |i: u64| texture::hash01(d.seed.wrapping_add(k * 7919 + i) as i64, 17, 99) as f64;
            [
                hsh(1) * w as f64,
                hsh(2) * h as f64,
                (0.08 + 0.12 * hsh(3)) * w as f64,
            ]
        })
        .collect();
    for y in 0..h {
        for x in 0..w {
            let mut attenuation = 1.0;
            for b in &blobs {
                let dd = ((x as f64 - b[0]).powi(2) + (y as f64 - b[1]).powi(2)) / (b[2] * b[2]);
                attenuation *= 1.0 - 0.6 * (-dd).exp();
            }
            let v = &mut img[y * w + x];
            *v = (0.6 * *v + 0.4 * mean) * attenuation as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::WorldFile;
    use rand::SeedableRng;

    /// Camera at the origin of an empty room heading +x; body (x, y, z) of a point.
    fn optical_of(p: &CameraParams, body: [f64; 3]) -> [f64; 3] {
        let r = p.body_from_optical();
        let q = [
            body[0] - p.mount[0],
            body[1] - p.mount[1],
            body[2] - p.mount[2],
        ];
        [
            r[0][0] * q[0] + r[0][1] * q[1] + r[0][2] * q[2],
            r[1][0] * q[0] + r[1][1] * q[1] + r[1][2] * q[2],
            r[2][0] * q[0] + r[2][1] * q[1] + r[2][2] * q[2],
        ]
    }

    #[test]
    fn known_ceiling_points_project_to_the_right_pixel() {
        // Ceiling 2.5 m, camera at height 0.35 m tilted 45 deg: the optical axis meets the
        // ceiling 2.15 m ahead of the camera.
        for fisheye in [false, true] {
            let p = CameraParams::new(320, 240, fisheye, 45.0, 0.0);
            let ahead = [p.mount[0] + 2.15, 0.0, 2.5];
            let uv = p.project(optical_of(&p, ahead)).expect("visible");
            assert!((uv[0] - p.cx).abs() < 1e-9 && (uv[1] - p.cy).abs() < 1e-9);
            // A point straight above the camera: 45 deg off axis, image top centre.
            let above = [p.mount[0], 0.0, 2.5];
            let uv = p.project(optical_of(&p, above)).expect("visible");
            let th = std::f64::consts::FRAC_PI_4;
            let expect_v = match p.lens {
                Lens::Pinhole => p.cy - p.fy * th.tan(),
                Lens::KannalaBrandt(k) => {
                    let t2 = th * th;
                    p.cy - p.fy
                        * th
                        * (1.0 + k[0] * t2 + k[1] * t2 * t2 + k[2] * t2.powi(3) + k[3] * t2.powi(4))
                }
            };
            assert!((uv[0] - p.cx).abs() < 1e-9, "{uv:?}");
            assert!((uv[1] - expect_v).abs() < 1e-9, "{uv:?} vs {expect_v}");
            // A point 1 m to the left on the axis's ceiling spot lands right of... no: left of
            // the centre (image x grows to the robot's right).
            let left = [p.mount[0] + 2.15, 1.0, 2.5];
            let uv = p.project(optical_of(&p, left)).expect("visible");
            assert!(uv[0] < p.cx);
            // Unprojection inverts projection.
            let ray = p.unproject(uv[0], uv[1]).expect("in view");
            let back = p.project(ray).expect("visible");
            assert!((back[0] - uv[0]).abs() < 1e-6 && (back[1] - uv[1]).abs() < 1e-6);
        }
    }

    /// The core's models and extrinsic, built from these parameters, put every body-frame
    /// point on the pixel the renderer uses, so the core can be tested on rendered frames.
    #[test]
    fn the_core_camera_agrees_with_the_renderer() {
        for (fisheye, tilt, yaw) in [(true, 60.0, 0.0), (false, 45.0, 0.0), (true, 45.0, 180.0)] {
            let p = CameraParams::new(320, 240, fisheye, tilt, yaw);
            let model = p.core_model().expect("valid");
            let ext = p.core_extrinsic();
            let mut checked = 0;
            for i in 0..200 {
                let f = f64::from(i);
                let body = [
                    3.0 * (f * 0.37).sin() + 0.5,
                    2.0 * (f * 0.91).cos(),
                    2.4 - 1.5 * (f * 0.13).sin().abs(),
                ];
                let mine = p.project(optical_of(&p, body));
                let core = model.project(&ext.robot_to_camera(&body.into()));
                if let (Some(a), Some(b)) = (mine, core) {
                    assert!((a[0] - b.x).abs() < 1e-9 && (a[1] - b.y).abs() < 1e-9);
                    checked += 1;
                }
            }
            assert!(checked > 100, "{checked}");
        }
    }

    #[test]
    fn rendered_light_appears_at_the_projected_pixel() {
        for fisheye in [false, true] {
            let mut p = CameraParams::new(160, 120, fisheye, 60.0, 0.0);
            p.read_noise = 0.0;
            p.shot_noise = 0.0;
            p.gain_sigma = 0.0;
            // A small light 1.0 m ahead and 0.5 m left of the camera on a plain ceiling.
            let c = [p.mount[0] + 1.0, 0.5];
            let text = format!(
                "name = \"dark\"\nceiling_height = 2.5\n[ceiling]\nbrightness = 0.2\ntexture = 0.0\n\
                 [[feature]]\nkind = \"light\"\nmin = [{}, {}]\nmax = [{}, {}]\n\
                 [[wall]]\npoints = [[-20, -20], [20, -20], [20, 20], [-20, 20]]\nclosed = true\n\
                 [route]\nstart = [0, 0]\nlegs = [{{ type = \"waypoints\", points = [[1, 0]] }}]\n",
                c[0] - 0.05,
                c[1] - 0.05,
                c[0] + 0.05,
                c[1] + 0.05
            );
            let world = World::from_file(&WorldFile::parse(&text, "dark.toml").expect("valid"));
            let cam = Camera::new(p);
            let mut rng = ChaCha8Rng::seed_from_u64(0);
            let f = cam.render(&world, |_| (0.0, 0.0, 0.0), 0.0, None, &mut rng);
            let (mut su, mut sv, mut n) = (0.0, 0.0, 0.0);
            for (i, &g) in f.pixels.iter().enumerate() {
                if g > 150 {
                    su += (i % 160) as f64;
                    sv += (i / 160) as f64;
                    n += 1.0;
                }
            }
            assert!(n >= 1.0, "light not seen");
            let uv = p
                .project(optical_of(&p, [c[0], c[1], 2.5]))
                .expect("visible");
            assert!(
                (su / n - uv[0]).abs() < 1.0 && (sv / n - uv[1]).abs() < 1.0,
                "{} {} vs {uv:?}",
                su / n,
                sv / n
            );
        }
    }
}
