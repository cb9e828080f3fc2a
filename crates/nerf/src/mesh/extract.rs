//! From a trained model to a coloured mesh: sample density on a grid over the scene box
//! (slab by slab, so memory stays at one grid of floats), marching cubes at a density
//! threshold, optionally keep the largest connected pieces, and colour every vertex by
//! rendering a short ray that arrives at it from outside along its normal.

use super::marching_cubes::{marching_cubes, Grid};
use super::Mesh;
use crate::engine::Engine;
use crate::views::{render_rays, RenderSettings};

/// The default surface density. With sigma = 25, 4 cm of material (a voxel at 96^3 over a
/// 3-unit box) stops 63% of the light: solid. Lower it (5-10) when thin or little-seen parts
/// go missing; raise it when fog or floaters wrap the object.
pub const DEFAULT_THRESHOLD: f32 = 25.0;

#[derive(Clone, Copy, Debug)]
pub struct ExtractOptions {
    /// Grid points per axis.
    pub resolution: usize,
    /// Density (sigma) at the surface.
    pub threshold: f32,
    /// Half-extent of the box `[-bound, bound]^3` that is sampled.
    pub bound: f32,
    /// Keep only this many largest connected pieces (by triangle count).
    pub keep_largest: Option<usize>,
    /// The moment of a moving scene to mesh (still scenes ignore it).
    pub time: f32,
}

/// Density on `resolution^3` grid points over the box; `on_slab(done, total)` after each
/// z slab.
pub fn density_grid(
    engine: &dyn Engine,
    opts: &ExtractOptions,
    on_slab: &mut dyn FnMut(usize, usize),
) -> (Vec<f32>, f32) {
    let r = opts.resolution.max(2);
    let spacing = 2.0 * opts.bound / (r - 1) as f32;
    let mut values = vec![0.0f32; r * r * r];
    let mut positions = Vec::with_capacity(r * r * 3);
    for (z, slab) in values.chunks_mut(r * r).enumerate() {
        positions.clear();
        for y in 0..r {
            for x in 0..r {
                positions.extend([x, y, z].map(|i| -opts.bound + i as f32 * spacing));
            }
        }
        engine.density(&positions, Some(opts.time), slab);
        on_slab(z + 1, r);
    }
    (values, spacing)
}

/// The mesh of the surface where density crosses `opts.threshold`.
pub fn extract(
    engine: &dyn Engine,
    opts: &ExtractOptions,
    on_slab: &mut dyn FnMut(usize, usize),
) -> Mesh {
    let (values, spacing) = density_grid(engine, opts, on_slab);
    let r = opts.resolution.max(2);
    let grid = Grid {
        values: &values,
        dims: [r; 3],
        origin: [-opts.bound; 3],
        spacing,
    };
    let mesh = marching_cubes(&grid, opts.threshold);
    match opts.keep_largest {
        Some(n) => keep_largest(&mesh, n),
        None => mesh,
    }
}

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        parent[i as usize] = parent[parent[i as usize] as usize];
        i = parent[i as usize];
    }
    i
}

/// The `n` connected pieces with the most triangles (pieces share no vertex).
pub fn keep_largest(mesh: &Mesh, n: usize) -> Mesh {
    let mut parent: Vec<u32> = (0..mesh.vertices.len() as u32).collect();
    for t in &mesh.triangles {
        for k in 1..3 {
            let (a, b) = (find(&mut parent, t[0]), find(&mut parent, t[k]));
            parent[a.max(b) as usize] = a.min(b);
        }
    }
    let mut size = std::collections::HashMap::<u32, usize>::new();
    for t in &mesh.triangles {
        *size.entry(find(&mut parent, t[0])).or_default() += 1;
    }
    let mut pieces: Vec<(u32, usize)> = size.into_iter().collect();
    pieces.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let kept: std::collections::HashSet<u32> = pieces.iter().take(n).map(|p| p.0).collect();
    let mut remap = vec![u32::MAX; mesh.vertices.len()];
    let mut out = Mesh::default();
    for t in &mesh.triangles {
        if !kept.contains(&find(&mut parent, t[0])) {
            continue;
        }
        let tri = t.map(|v| {
            if remap[v as usize] == u32::MAX {
                remap[v as usize] = out.vertices.len() as u32;
                out.vertices.push(mesh.vertices[v as usize]);
            }
            remap[v as usize]
        });
        out.triangles.push(tri);
    }
    out
}

/// Area-weighted vertex normals (unit length; zero for unused vertices).
pub fn vertex_normals(mesh: &Mesh) -> Vec<[f32; 3]> {
    let mut n = vec![[0f32; 3]; mesh.vertices.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        let (u, v) = (crate::math::sub(b, a), crate::math::sub(c, a));
        let face = crate::math::cross(u, v);
        for &i in t {
            for k in 0..3 {
                n[i as usize][k] += face[k];
            }
        }
    }
    for v in &mut n {
        let l = crate::math::length(*v);
        if l > 0.0 {
            *v = crate::math::scale(*v, 1.0 / l);
        }
    }
    n
}

/// Colours (straight RGB in [0, 1]) of the vertices: each is rendered along a ray that
/// starts `offset` outside the surface on its normal and looks back at it, so the colour is
/// what a camera there would see (view-dependent effects included).
pub fn colour_vertices(engine: &dyn Engine, mesh: &Mesh, offset: f32, time: f32) -> Vec<[f32; 3]> {
    let normals = vertex_normals(mesh);
    let mut origins = Vec::with_capacity(mesh.vertices.len() * 3);
    let mut dirs = Vec::with_capacity(mesh.vertices.len() * 3);
    for (p, n) in mesh.vertices.iter().zip(&normals) {
        origins.extend((0..3).map(|k| p[k] + offset * n[k]));
        dirs.extend(n.map(|v| -v));
    }
    let settings = RenderSettings {
        near: 0.0,
        far: 2.0 * offset,
        background: [0.0; 3],
        // The mesh lives in the model's own space already.
        space: crate::camera::ray_space::RaySpace::World,
        appearance: Default::default(),
        time: Some(time),
    };
    render_rays(engine, &origins, &dirs, &settings)
        .iter()
        .map(|o| {
            // Over black the result is premultiplied; undo that where anything was hit.
            let a = o.opacity.max(1e-3);
            o.rgb.map(|c| (c / a).clamp(0.0, 1.0))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keep_largest_drops_the_small_piece() {
        // A tetrahedron (4 triangles) and a lone triangle.
        let mesh = Mesh {
            vertices: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
                [5.0, 5.0, 5.0],
                [6.0, 5.0, 5.0],
                [5.0, 6.0, 5.0],
            ],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [4, 5, 6]],
        };
        let big = keep_largest(&mesh, 1);
        assert_eq!((big.triangles.len(), big.vertices.len()), (4, 4));
        assert!(big.is_watertight());
        assert_eq!(keep_largest(&mesh, 2).triangles.len(), 5);
        let n = vertex_normals(&big);
        // The corner at the origin points away from the tetrahedron.
        assert!(n[0].iter().all(|&c| c < 0.0), "{:?}", n[0]);
    }
}
