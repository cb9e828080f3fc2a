//! Coloured point clouds: every pixel of some views whose ray is (nearly) opaque becomes a
//! point at its expected depth, coloured with what the pixel shows.

use crate::camera::Camera;
use crate::engine::Engine;
use crate::views::{render_view, RenderSettings};

/// Points (and straight RGB colours) from rendering `cameras`; pixels with opacity below
/// `min_opacity` (background, soft edges) are skipped. `on_view` is called after each view.
pub fn from_views(
    engine: &dyn Engine,
    cameras: &[Camera],
    settings: &RenderSettings,
    min_opacity: f32,
    on_view: &mut dyn FnMut(usize),
) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let (mut points, mut colours) = (Vec::new(), Vec::new());
    for (k, camera) in cameras.iter().enumerate() {
        let view = render_view(engine, camera, settings, &|_| {});
        for j in 0..view.height {
            for i in 0..view.width {
                let p = j * view.width + i;
                let a = view.opacity[p];
                if a < min_opacity || a <= 0.0 {
                    continue;
                }
                // Depth is along the camera ray's direction, weighted by opacity.
                // (in ray space: NDC points are mapped back to the world).
                let ray = camera.ray(i, j);
                let (o, d) = settings.space.warp(ray.origin, ray.dir);
                let t = view.depth[p] / a;
                points.push(
                    settings
                        .space
                        .to_world(std::array::from_fn(|c| o[c] + t * d[c])),
                );
                colours.push(std::array::from_fn(|c| {
                    ((view.rgb[3 * p + c] - (1.0 - a) * settings.background[c]) / a).clamp(0.0, 1.0)
                }));
            }
        }
        on_view(k + 1);
    }
    (points, colours)
}
