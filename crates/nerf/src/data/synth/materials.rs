//! Procedural surface colours and their shininess.

use crate::math::V3;

/// How a surface looks.
#[derive(Clone, Copy, Debug)]
pub enum Pattern {
    Solid(V3),
    /// Rings around a line along `axis` through the origin, wobbled so they read as grain.
    Wood {
        light: V3,
        dark: V3,
        axis: usize,
    },
    /// A fabric-like checker of cell size `cell` with a fine weave modulation.
    Checker {
        a: V3,
        b: V3,
        cell: f32,
    },
    /// Multi-octave value noise between `a` and `b` with features of size `cell` and
    /// smaller: never repeats, which is what feature matching (COLMAP) needs.
    Noise {
        a: V3,
        b: V3,
        cell: f32,
    },
}

/// Smooth value noise in [0, 1] on the unit lattice (hashed corner values, smoothstep
/// blend).
fn value_noise(p: V3) -> f32 {
    let cell = p.map(|x| x.floor());
    let f = [p[0] - cell[0], p[1] - cell[1], p[2] - cell[2]].map(|t| t * t * (3.0 - 2.0 * t));
    let corner = |dx: i64, dy: i64, dz: i64| {
        let (x, y, z) = (
            cell[0] as i64 + dx,
            cell[1] as i64 + dy,
            cell[2] as i64 + dz,
        );
        let mut h = (x.wrapping_mul(0x8da6b343)
            ^ y.wrapping_mul(0xd8163841)
            ^ z.wrapping_mul(0xcb1ab31f)) as u64;
        h ^= h >> 29;
        h = h.wrapping_mul(0xbf58476d1ce4e5b9);
        h ^= h >> 32;
        (h & 0xffff) as f32 / 65535.0
    };
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), f[0]);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), f[0]);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), f[0]);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), f[0]);
    lerp(lerp(x00, x10, f[1]), lerp(x01, x11, f[1]), f[2])
}

#[derive(Clone, Copy, Debug)]
pub struct Material {
    pub pattern: Pattern,
    /// Blinn-Phong specular strength and exponent: the view-dependent part of the colour.
    pub specular: f32,
    pub shininess: f32,
}

fn mix(a: V3, b: V3, t: f32) -> V3 {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

impl Material {
    /// Diffuse colour at world point `p`.
    pub fn albedo(&self, p: V3) -> V3 {
        match self.pattern {
            Pattern::Solid(c) => c,
            Pattern::Wood { light, dark, axis } => {
                let (a, u, v) = (p[axis], p[(axis + 1) % 3], p[(axis + 2) % 3]);
                let r = (u * u + v * v).sqrt() * 22.0
                    + 1.3 * (a * 2.7 + u * 4.1).sin()
                    + 0.4 * (a * 11.0).sin();
                let ring = (0.5 + 0.5 * (r * std::f32::consts::TAU).sin()).powf(3.0);
                mix(light, dark, ring)
            }
            Pattern::Noise { a, b, cell } => {
                let (mut sum, mut weight, mut freq) = (0.0, 0.0, 1.0 / cell);
                for octave in 0..4 {
                    let w = 0.55f32.powi(octave);
                    sum += w * value_noise(p.map(|x| x * freq));
                    weight += w;
                    freq *= 2.3;
                }
                let t = (sum / weight - 0.5) * 2.5 + 0.5;
                mix(a, b, t.clamp(0.0, 1.0))
            }
            Pattern::Checker { a, b, cell } => {
                let k = (p[0] / cell).floor() as i64
                    + (p[1] / cell).floor() as i64
                    + (p[2] / cell).floor() as i64;
                let base = if k.rem_euclid(2) == 0 { a } else { b };
                let weave =
                    0.92 + 0.08 * ((p[0] + p[1]) * 180.0).sin() * ((p[1] - p[2]) * 180.0).sin();
                [base[0] * weave, base[1] * weave, base[2] * weave]
            }
        }
    }
}
