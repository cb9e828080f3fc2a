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
