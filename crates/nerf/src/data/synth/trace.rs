//! Sphere tracing of the built-in scenes and their shading: two directional lights with
//! soft shadows, an ambient term, Lambert diffuse and Blinn-Phong highlights (so colour
//! depends on the view direction, which the NeRF must model).

use super::scenes::Part;
use crate::math::{add, dot, length, normalize_or_zero, scale, sub, V3};

/// A scene ready for tracing.
pub struct Scene {
    parts: Vec<Part>,
    center: V3,
    radius: f32,
}

struct Light {
    dir: V3,
    colour: V3,
}

const AMBIENT: f32 = 0.22;
const HIT_EPS: f32 = 2e-4;

fn lights() -> [Light; 2] {
    [
        Light {
            dir: normalize_or_zero([0.55, -0.45, 0.75]),
            colour: [0.85, 0.8, 0.72],
        },
        Light {
            dir: normalize_or_zero([-0.6, 0.5, 0.45]),
            colour: [0.3, 0.36, 0.45],
        },
    ]
}

fn bounds_of(parts: &[Part]) -> (V3, V3) {
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in parts {
        let (a, b) = p.shape.bounds();
        for c in 0..3 {
            lo[c] = lo[c].min(a[c]);
            hi[c] = hi[c].max(b[c]);
        }
    }
    (lo, hi)
}

/// A primary-ray hit: distance along the unit direction and shaded colour.
pub struct Hit {
    pub t: f32,
    pub colour: V3,
}

impl Scene {
    pub fn new(parts: Vec<Part>) -> Scene {
        let (lo, hi) = bounds_of(&parts);
        let center = scale(add(lo, hi), 0.5);
        Scene {
            parts,
            center,
            radius: 0.5 * length(sub(hi, lo)) + 0.01,
        }
    }

    /// Axis-aligned bounds of all parts.
    pub fn bounds(&self) -> (V3, V3) {
        bounds_of(&self.parts)
    }

    fn distance(&self, p: V3) -> (f32, usize) {
        let mut best = (f32::MAX, 0);
        for (i, part) in self.parts.iter().enumerate() {
            let d = part.shape.distance(p);
            if d < best.0 {
                best = (d, i);
            }
        }
        best
    }

    /// The ray's parameter interval inside the bounding sphere, if it meets it.
    fn enter_exit(&self, o: V3, d: V3) -> Option<(f32, f32)> {
        let oc = sub(o, self.center);
        let b = dot(oc, d);
        let disc = b * b - (dot(oc, oc) - self.radius * self.radius);
        if disc < 0.0 {
            return None;
        }
        let s = disc.sqrt();
        Some(((-b - s).max(0.0), -b + s))
    }

    /// First surface along the unit direction `d`.
    fn march(&self, o: V3, d: V3) -> Option<(f32, usize)> {
        let (mut t, exit) = self.enter_exit(o, d)?;
        for _ in 0..256 {
            let (dist, idx) = self.distance(add(o, scale(d, t)));
            if dist < HIT_EPS {
                return Some((t, idx));
            }
            t += dist;
            if t > exit {
                return None;
            }
        }
        None
    }

    /// Soft shadow factor in [0, 1] towards a directional light (1 = fully lit).
    fn shadow(&self, p: V3, l: V3) -> f32 {
        let Some((_, exit)) = self.enter_exit(p, l) else {
            return 1.0;
        };
        let (mut t, mut lit) = (0.01f32, 1.0f32);
        while t < exit {
            let (dist, _) = self.distance(add(p, scale(l, t)));
            if dist < HIT_EPS {
                return 0.0;
            }
            lit = lit.min(12.0 * dist / t);
            t += dist.max(0.005);
        }
        lit.clamp(0.0, 1.0)
    }

    fn normal(&self, p: V3) -> V3 {
        let e = 1e-4;
        let g = |c: usize| {
            let (mut a, mut b) = (p, p);
            a[c] += e;
            b[c] -= e;
            self.distance(a).0 - self.distance(b).0
        };
        normalize_or_zero([g(0), g(1), g(2)])
    }

    /// Traces and shades the ray from `o` along the unit direction `d`.
    pub fn trace(&self, o: V3, d: V3) -> Option<Hit> {
        let (t, idx) = self.march(o, d)?;
        let p = add(o, scale(d, t));
        let n = self.normal(p);
        let m = &self.parts[idx].material;
        let albedo = m.albedo(p);
        let view = scale(d, -1.0);
        let lifted = add(p, scale(n, 4.0 * HIT_EPS));
        let mut colour = scale(albedo, AMBIENT);
        for light in lights() {
            let diffuse = dot(n, light.dir);
            if diffuse <= 0.0 {
                continue;
            }
            let lit = self.shadow(lifted, light.dir);
            let half = normalize_or_zero(add(light.dir, view));
            let spec = m.specular * dot(n, half).max(0.0).powf(m.shininess);
            for c in 0..3 {
                colour[c] += lit * light.colour[c] * (albedo[c] * diffuse + spec);
            }
        }
        Some(Hit {
            t,
            colour: colour.map(|c| c.clamp(0.0, 1.0)),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::synth::materials::{Material, Pattern};
    use crate::data::synth::scenes::Part;
    use crate::data::synth::shapes::Shape;

    fn ball(specular: f32) -> Scene {
        Scene::new(vec![Part {
            shape: Shape::Sphere {
                center: [0.0; 3],
                radius: 1.0,
            },
            material: Material {
                pattern: Pattern::Solid([0.5, 0.5, 0.5]),
                specular,
                shininess: 20.0,
            },
        }])
    }

    #[test]
    fn hits_sphere_at_its_surface() {
        let s = ball(0.0);
        let hit = s.trace([0.0, 0.0, 4.0], [0.0, 0.0, -1.0]).expect("hit");
        assert!((hit.t - 3.0).abs() < 1e-3);
        assert!(s.trace([0.0, 0.0, 4.0], [0.0, 1.0, 0.0]).is_none());
    }

    #[test]
    fn highlight_depends_on_view() {
        let s = ball(0.8);
        // The same surface point (top of the sphere) seen from two directions.
        let p = [0.0, 0.0, 1.0];
        let from = |dir: V3| {
            let d = normalize_or_zero(dir);
            s.trace(sub(p, scale(d, 3.0)), d).expect("hit").colour
        };
        let a = from([0.55, -0.45, -0.75]); // viewer at the key light's mirror: highlight
        let b = from([-0.55, 0.45, -0.75]);
        assert!(a[0] > b[0] + 0.1, "{a:?} vs {b:?}");
    }
}
