//! Procedural textures: albedo (0 = black, 1 = white, > 1 = emissive light) of the ceiling,
//! walls, posters and floor, as pure functions of position so frames are deterministic.

use crate::world::{FeatureKind, Material, World, P2};

/// A hash of an integer lattice point to `[0, 1)`.
#[inline]
pub fn hash01(x: i64, y: i64, seed: u32) -> f32 {
    let mut h = (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ u64::from(seed).wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// `floor` without a library call (baseline x86-64 has no rounding instruction).
#[inline]
fn fast_floor(x: f64) -> i64 {
    let i = x as i64;
    if (i as f64) > x {
        i - 1
    } else {
        i
    }
}

/// Smooth value noise in `[0, 1)` with unit lattice spacing.
#[inline]
pub fn value_noise(x: f64, y: f64, seed: u32) -> f32 {
    let (ix, iy) = (fast_floor(x), fast_floor(y));
    let (fx, fy) = (ix as f64, iy as f64);
    let (tx, ty) = ((x - fx) as f32, (y - fy) as f32);
    let (sx, sy) = (tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty));
    let a = hash01(ix, iy, seed);
    let b = hash01(ix + 1, iy, seed);
    let c = hash01(ix, iy + 1, seed);
    let d = hash01(ix + 1, iy + 1, seed);
    let top = a + (b - a) * sx;
    let bottom = c + (d - c) * sx;
    top + (bottom - top) * sy
}

/// Ceiling albedo at a point.
pub fn ceiling(world: &World, p: P2) -> f32 {
    for f in world.features_near(p) {
        if p[0] >= f.min[0] && p[0] <= f.max[0] && p[1] >= f.min[1] && p[1] <= f.max[1] {
            let (lx, ly) = (p[0] - f.min[0], p[1] - f.min[1]);
            let (w, h) = (f.max[0] - f.min[0], f.max[1] - f.min[1]);
            let edge = lx.min(ly).min(w - lx).min(h - ly);
            return match f.kind {
                FeatureKind::Light => {
                    if edge < 0.02 {
                        0.9
                    } else {
                        1.6
                    }
                }
                FeatureKind::Vent => {
                    if edge < 0.03 {
                        0.85
                    } else if ((if w > h { lx } else { ly }) / 0.04).fract() < 0.5 {
                        0.15
                    } else {
                        0.7
                    }
                }
                FeatureKind::Beam => {
                    let along = if w > h { lx } else { ly };
                    if edge < 0.02 {
                        0.2
                    } else {
                        0.35 + 0.1 * value_noise(along * 4.0, 0.0, f.seed)
                    }
                }
                FeatureKind::Spot => {
                    let r = 0.5 * w.min(h);
                    let d = ((lx - 0.5 * w).powi(2) + (ly - 0.5 * h).powi(2)).sqrt();
                    if d < 0.4 * r {
                        0.1
                    } else if d < r {
                        0.95
                    } else {
                        plain_ceiling(world, p)
                    }
                }
            };
        }
    }
    plain_ceiling(world, p)
}

fn plain_ceiling(world: &World, p: P2) -> f32 {
    let c = &world.ceiling;
    let tex = c.texture as f32;
    let mut a = c.brightness as f32
        + tex * (value_noise(p[0] * 1.5, p[1] * 1.5, 11) - 0.5)
        + 0.6 * tex * (value_noise(p[0] * 7.0, p[1] * 7.0, 12) - 0.5);
    if c.tile > 0.0 {
        let (tx, ty) = (p[0] / c.tile, p[1] / c.tile);
        let fx = tx - fast_floor(tx) as f64;
        let fy = ty - fast_floor(ty) as f64;
        let e = 0.015 / c.tile;
        if fx < e || fx > 1.0 - e || fy < e || fy > 1.0 - e {
            a *= 0.65;
        }
    }
    a.max(0.0)
}

/// Wall albedo at fraction `u` along segment `seg`, height `z`.
pub fn wall(world: &World, seg: usize, u: f64, z: f64) -> f32 {
    let s = &world.segments[seg];
    let len = ((s.b[0] - s.a[0]).powi(2) + (s.b[1] - s.a[1]).powi(2)).sqrt();
    let along = u * len;
    for p in world.posters_on(seg) {
        if u >= p.u[0] && u <= p.u[1] && z >= p.z[0] && z <= p.z[1] {
            let pu = (u - p.u[0]) / (p.u[1] - p.u[0]);
            let pz = (z - p.z[0]) / (p.z[1] - p.z[0]);
            if !(0.04..=0.96).contains(&pu) || !(0.04..=0.96).contains(&pz) {
                return 0.9;
            }
            let cell = hash01((pu * 6.0) as i64, (pz * 8.0) as i64, p.seed);
            return 0.08 + 0.85 * cell;
        }
    }
    let n = value_noise(along * 2.0, z * 2.0, s.texture);
    match s.material {
        Material::Wall => {
            if z < 0.08 {
                0.25
            } else {
                0.55 + 0.12 * (n - 0.5)
            }
        }
        Material::Furniture => 0.3 + 0.25 * n,
        Material::Pillar => 0.5 + 0.2 * value_noise(along * 6.0, z * 0.5, s.texture),
        Material::Glass => 0.4,
    }
}

/// Floor albedo.
pub fn floor(p: P2) -> f32 {
    0.25 + 0.1 * value_noise(p[0] * 3.0, p[1] * 3.0, 21)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_bounded_and_continuous() {
        for i in 0..1000 {
            let x = i as f64 * 0.0137 - 3.0;
            let a = value_noise(x, 2.0 * x, 5);
            let b = value_noise(x + 1e-6, 2.0 * x, 5);
            assert!((0.0..1.0).contains(&a));
            assert!((a - b).abs() < 1e-3);
        }
    }
}
