//! What camera refinement needs of a training step on the GPU, after the field's backward:
//! each sample's gradient with respect to its position (through the hash grid's trilinear
//! weights, as `HashGrid::encode_input_bwd`) and to its view direction (through the
//! spherical harmonics, as `encoding::spherical_harmonics::sh4_bwd`), then each ray's sums
//! of them: at its origin, along its unit direction (each sample's weighted by its depth)
//! and at its view direction, back through contraction where space is contracted, as
//! `FastModel::camera_gradients` sums them. Nine floats a ray are what the host reads back
//! and carries into the ray's camera correction (`CameraStep::accumulate_drawn`).

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::hash_grid::{cell_at, corner, level_words, GpuHashGrid, LEVEL_WORDS};
use super::launch::grid;
use super::volume::GpuSamples;
use crate::encoding::hash_grid::FEATURES;

/// Threads per workgroup.
const GROUP: u32 = 64;
/// Floats a ray's gradients take: origin, unit direction, view direction.
pub const RAY_WORDS: usize = 9;

/// `dL/d point` of each sample (world units: `to_world` per unit-cube unit), from the
/// features' gradient `d_enc` (`n x levels x 2`), each level's share scaled by
/// `level_scale` (the straight-through schedule's weights of the position gradient). A
/// coordinate clamped at the cube's face gets none along its axis.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments, clippy::manual_range_contains)]
fn position_bwd(
    params: &[f32],
    levels: &[u32],
    points: &[f32],
    d_enc: &[f32],
    level_scale: &[f32],
    d_points: &mut [f32],
    n_levels: u32,
    n: u32,
    to_world: f32,
) {
    let s = ABSOLUTE_POS;
    if s < n as usize {
        let nl = n_levels as usize;
        let x = points[3 * s];
        let y = points[3 * s + 1];
        let z = points[3 * s + 2];
        let mut gx = 0.0f32;
        let mut gy = 0.0f32;
        let mut gz = 0.0f32;
        for l in 0..nl {
            let g0 = d_enc[(s * nl + l) * 2] * level_scale[l];
            let g1 = d_enc[(s * nl + l) * 2 + 1] * level_scale[l];
            let (res, entries, dense, offset) = level_words(levels, l);
            let (cx, cy, cz, fx, fy, fz) = cell_at(x, y, z, res);
            let rf = f32::cast_from(res);
            let ix = select(x >= 0.0 && x <= 1.0, rf, 0.0);
            let iy = select(y >= 0.0 && y <= 1.0, rf, 0.0);
            let iz = select(z >= 0.0 && z <= 1.0, rf, 0.0);
            #[unroll]
            for k in 0..8u32 {
                let v = corner(k, cx, cy, cz, res, entries, dense);
                let ge = g0 * params[offset + 2 * v] + g1 * params[offset + 2 * v + 1];
                let up_x = (k & 1) == 1;
                let up_y = ((k >> 1) & 1) == 1;
                let up_z = ((k >> 2) & 1) == 1;
                let wx = select(up_x, fx, 1.0 - fx);
                let wy = select(up_y, fy, 1.0 - fy);
                let wz = select(up_z, fz, 1.0 - fz);
                gx += ge * select(up_x, 1.0f32, -1.0f32) * (wy * wz) * ix;
                gy += ge * select(up_y, 1.0f32, -1.0f32) * (wz * wx) * iy;
                gz += ge * select(up_z, 1.0f32, -1.0f32) * (wx * wy) * iz;
            }
        }
        d_points[3 * s] = gx * to_world;
        d_points[3 * s + 1] = gy * to_world;
        d_points[3 * s + 2] = gz * to_world;
    }
}

/// `dL/d direction` of each sample's unit view direction from the gradient of its colour
/// network's input (`n x columns`, the 16 harmonics first).
#[cube(launch_unchecked)]
fn direction_bwd(dirs: &[f32], d_colour_in: &[f32], d_dirs: &mut [f32], columns: u32, n: u32) {
    let s = ABSOLUTE_POS;
    if s < n as usize {
        let x = dirs[3 * s];
        let y = dirs[3 * s + 1];
        let z = dirs[3 * s + 2];
        let (xx, yy, zz) = (x * x, y * y, z * z);
        let g = s * columns as usize;
        let a = 0.488_602_5f32;
        let b = 1.092_548_4f32;
        let c = 0.946_174_7f32;
        let e = 0.546_274_2f32;
        let f = 0.590_043_6f32;
        let h = 0.457_045_8f32;
        let i = 0.373_176_33f32;
        let j = 1.445_305_7f32;
        let k = 2.890_611_4f32;
        // Each harmonic's partial derivatives, as `sh4_bwd`'s rows.
        let g1 = d_colour_in[g + 1];
        let g2 = d_colour_in[g + 2];
        let g3 = d_colour_in[g + 3];
        let g4 = d_colour_in[g + 4];
        let g5 = d_colour_in[g + 5];
        let g6 = d_colour_in[g + 6];
        let g7 = d_colour_in[g + 7];
        let g8 = d_colour_in[g + 8];
        let g9 = d_colour_in[g + 9];
        let g10 = d_colour_in[g + 10];
        let g11 = d_colour_in[g + 11];
        let g12 = d_colour_in[g + 12];
        let g13 = d_colour_in[g + 13];
        let g14 = d_colour_in[g + 14];
        let g15 = d_colour_in[g + 15];
        let dx = 0.0f32 - g3 * a + g4 * (b * y) - g7 * (b * z) + g8 * (2.0 * e * x)
            - g9 * (6.0 * f * x * y)
            + g10 * (k * y * z)
            + g13 * (h * (1.0 - 5.0 * zz))
            + g14 * (2.0 * j * x * z)
            + g15 * (3.0 * f * (yy - xx));
        let dy = 0.0f32 - g1 * a + g4 * (b * x) - g5 * (b * z) - g8 * (2.0 * e * y)
            + g9 * (3.0 * f * (yy - xx))
            + g10 * (k * x * z)
            + g11 * (h * (1.0 - 5.0 * zz))
            - g14 * (2.0 * j * y * z)
            + g15 * (6.0 * f * x * y);
        let dz = g2 * a - g5 * (b * y) + g6 * (2.0 * c * z) - g7 * (b * x) + g10 * (k * x * y)
            - g11 * (10.0 * h * y * z)
            + g12 * (i * (15.0 * zz - 3.0))
            - g13 * (10.0 * h * x * z)
            + g14 * (j * (xx - yy));
        d_dirs[3 * s] = dx;
        d_dirs[3 * s + 1] = dy;
        d_dirs[3 * s + 2] = dz;
    }
}

/// Each ray's sums over its samples (`offsets`: CSR, `rays + 1`): the position gradients
/// (back through contraction of radius `contract`, 0 for none, at the world point
/// `origin + t unit`), the same weighted by the samples' depths `t`, and the direction
/// gradients, into `out` (`rays x 9`).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn ray_bwd(
    offsets: &[u32],
    t: &[f32],
    d_points: &[f32],
    d_dirs: &[f32],
    origins: &[f32],
    units: &[f32],
    out: &mut [f32],
    rays: u32,
    contract: f32,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let ox = origins[3 * r];
        let oy = origins[3 * r + 1];
        let oz = origins[3 * r + 2];
        let ux = units[3 * r];
        let uy = units[3 * r + 1];
        let uz = units[3 * r + 2];
        let mut o0 = 0.0f32;
        let mut o1 = 0.0f32;
        let mut o2 = 0.0f32;
        let mut d0 = 0.0f32;
        let mut d1 = 0.0f32;
        let mut d2 = 0.0f32;
        let mut v0 = 0.0f32;
        let mut v1 = 0.0f32;
        let mut v2 = 0.0f32;
        let start = offsets[r] as usize;
        let end = offsets[r + 1] as usize;
        for s in start..end {
            let ts = t[s];
            let mut gx = d_points[3 * s];
            let mut gy = d_points[3 * s + 1];
            let mut gz = d_points[3 * s + 2];
            if contract > 0.0f32 {
                // `render::contraction::contract_bwd` at the world point.
                let px = ox + ts * ux;
                let py = oy + ts * uy;
                let pz = oz + ts * uz;
                let ax = f32::abs(px);
                let ay = f32::abs(py);
                let az = f32::abs(pz);
                let m = f32::max(f32::max(ax, ay), az) / contract;
                if m > 1.0f32 {
                    let scale = (2.0f32 - 1.0f32 / m) / m;
                    let ds_dn = 2.0f32 / (m * m * m) - 2.0f32 / (m * m);
                    let along = (gx * px + gy * py + gz * pz) * ds_dn / contract;
                    gx *= scale;
                    gy *= scale;
                    gz *= scale;
                    // The largest coordinate alone sets the norm (the last of equals, as
                    // the host's `max_by` picks).
                    if az >= ax && az >= ay {
                        gz += along * select(pz >= 0.0, 1.0f32, -1.0f32);
                    } else if ay >= ax {
                        gy += along * select(py >= 0.0, 1.0f32, -1.0f32);
                    } else {
                        gx += along * select(px >= 0.0, 1.0f32, -1.0f32);
                    }
                }
            }
            o0 += gx;
            o1 += gy;
            o2 += gz;
            d0 += ts * gx;
            d1 += ts * gy;
            d2 += ts * gz;
            v0 += d_dirs[3 * s];
            v1 += d_dirs[3 * s + 1];
            v2 += d_dirs[3 * s + 2];
        }
        let w = 9 * r;
        out[w] = o0;
        out[w + 1] = o1;
        out[w + 2] = o2;
        out[w + 3] = d0;
        out[w + 4] = d1;
        out[w + 5] = d2;
        out[w + 6] = v0;
        out[w + 7] = v1;
        out[w + 8] = v2;
    }
}

/// Each sample's position gradient (`n x 3`, world units) from the hash grid's feature
/// gradient `d_enc` of unit-cube `points` (`half_extent`: the field's bound), each level's
/// share scaled by `level_scale` (one per level; all 1 for the plain gradient).
#[allow(clippy::too_many_arguments)]
pub fn position_gradients(
    gpu: &Gpu,
    encoding: &GpuHashGrid,
    params: &Handle,
    num_params: usize,
    points: &Handle,
    d_enc: &Handle,
    level_scale: &[f32],
    n: usize,
    half_extent: f32,
) -> Handle {
    assert_eq!(level_scale.len(), encoding.n_levels, "one scale per level");
    let d_points = gpu.floats(3 * n.max(1));
    if n == 0 {
        return d_points;
    }
    let nl = encoding.n_levels;
    let scale = gpu.upload(level_scale);
    let (count, dim) = grid(n, GROUP);
    // SAFETY: `params` holds every level's table (the whole parameter vector,
    // `num_params`), `levels` LEVEL_WORDS per level, `points` and `d_points` 3 floats per
    // sample, `d_enc` 2 per sample and level; the kernel bounds-checks its sample.
    unsafe {
        position_bwd::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(params.clone(), num_params),
            BufferArg::from_raw_parts(encoding.levels.clone(), nl * LEVEL_WORDS),
            BufferArg::from_raw_parts(points.clone(), 3 * n),
            BufferArg::from_raw_parts(d_enc.clone(), n * nl * FEATURES),
            BufferArg::from_raw_parts(scale.clone(), nl),
            BufferArg::from_raw_parts(d_points.clone(), 3 * n),
            nl as u32,
            n as u32,
            0.5 / half_extent,
        );
    }
    d_points
}

/// Each sample's view-direction gradient (`n x 3`) from its unit direction (`dirs`) and
/// its colour network's input gradient (`n x columns`, the harmonics first).
pub fn direction_gradients(
    gpu: &Gpu,
    dirs: &Handle,
    d_colour_in: &Handle,
    columns: usize,
    n: usize,
) -> Handle {
    assert!(columns >= 16, "the colour input starts with 16 harmonics");
    let d_dirs = gpu.floats(3 * n.max(1));
    if n == 0 {
        return d_dirs;
    }
    let (count, dim) = grid(n, GROUP);
    // SAFETY: `dirs` and `d_dirs` hold 3 floats per sample, `d_colour_in` `columns`; the
    // kernel bounds-checks its sample.
    unsafe {
        direction_bwd::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(dirs.clone(), 3 * n),
            BufferArg::from_raw_parts(d_colour_in.clone(), n * columns),
            BufferArg::from_raw_parts(d_dirs.clone(), 3 * n),
            columns as u32,
            n as u32,
        );
    }
    d_dirs
}

/// Each ray's gradients (`rays x` [`RAY_WORDS`]: origin, unit direction, view direction)
/// from its samples' (`samples`' first `rays` rays); `origins` and `units` are the rays'
/// world origins and unit directions, `contract` the contraction's radius where space is
/// contracted.
pub fn ray_gradients(
    gpu: &Gpu,
    samples: &GpuSamples,
    d_points: &Handle,
    d_dirs: &Handle,
    origins: &Handle,
    units: &Handle,
    contract: Option<f32>,
) -> Handle {
    let (r, n) = (samples.rays, samples.len);
    let out = gpu.floats(RAY_WORDS * r.max(1));
    if r == 0 {
        return out;
    }
    let (count, dim) = grid(r, GROUP);
    // SAFETY: `offsets` holds `r + 1` CSR slots ending at `n`, the length of the
    // per-sample buffers (`3n` for the gradients), the rays' buffers 3 floats per ray and
    // `out` RAY_WORDS; the kernel bounds-checks its ray.
    unsafe {
        ray_bwd::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(samples.offsets.clone(), r + 1),
            BufferArg::from_raw_parts(samples.t.clone(), n.max(1)),
            BufferArg::from_raw_parts(d_points.clone(), 3 * n.max(1)),
            BufferArg::from_raw_parts(d_dirs.clone(), 3 * n.max(1)),
            BufferArg::from_raw_parts(origins.clone(), 3 * r),
            BufferArg::from_raw_parts(units.clone(), 3 * r),
            BufferArg::from_raw_parts(out.clone(), RAY_WORDS * r),
            r as u32,
            contract.unwrap_or(0.0),
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::spherical_harmonics::sh4_bwd;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::render::contraction::contract_bwd;
    use crate::rng::Rng;

    /// The kernel against `HashGrid::encode_input_bwd` on the hash grid tests' random
    /// tables and points (some outside the unit cube, clamped), random feature gradients,
    /// each level scaled, some samples' gradients zero: within 1e-5 relative.
    #[test]
    fn position_gradients_match_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let (grid, params, points) = crate::engine::gpu::hash_grid::tests::setup();
        let n = points.len() / 3;
        let mut rng = Rng::new(11);
        let d = grid.dims();
        let mut d_enc: Vec<f32> = (0..n * d).map(|_| rng.range(-1.0, 1.0)).collect();
        d_enc[..3 * d].fill(0.0);
        let scale: Vec<f32> = (0..grid.levels.len())
            .map(|l| 1.0 / (1 + l) as f32)
            .collect();
        let half_extent = 1.5;
        let scaled: Vec<f32> = d_enc
            .chunks_exact(FEATURES)
            .enumerate()
            .flat_map(|(i, g)| {
                let w = scale[i % (d / FEATURES)];
                g.iter().map(move |v| v * w)
            })
            .collect();
        let mut want = vec![0.0; n * 3];
        grid.encode_input_bwd(&params, &points, &scaled, &mut want);
        want.iter_mut().for_each(|v| *v *= 0.5 / half_extent);
        assert!(want.iter().any(|&v| v.abs() > 1.0), "gradients to compare");
        let got = position_gradients(
            &gpu,
            &GpuHashGrid::new(&gpu, &grid),
            &gpu.upload(&params),
            params.len(),
            &gpu.upload(&points),
            &gpu.upload(&d_enc),
            &scale,
            n,
            half_extent,
        );
        let got = gpu.read(&got, n * 3).expect("read");
        let e = worst(&got, &want);
        assert!(e < 1e-5, "largest difference {e}");
    }

    /// The kernel against `sh4_bwd` on random unit directions and input gradients (a
    /// colour input wider than the harmonics).
    #[test]
    fn direction_gradients_match_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let (n, columns) = (300, 31);
        let mut rng = Rng::new(12);
        let dirs = rng.unit_directions(n);
        let d_in: Vec<f32> = (0..n * columns).map(|_| rng.range(-1.0, 1.0)).collect();
        let want: Vec<f32> = (0..n)
            .flat_map(|s| {
                let d = &dirs[3 * s..][..3];
                sh4_bwd([d[0], d[1], d[2]], &d_in[s * columns..][..16])
            })
            .collect();
        let got = direction_gradients(&gpu, &gpu.upload(&dirs), &gpu.upload(&d_in), columns, n);
        let got = gpu.read(&got, n * 3).expect("read");
        let e = worst(&got, &want);
        assert!(e < 1e-5, "largest difference {e}");
    }

    /// Each ray's sums against the host's loop (`FastModel::camera_gradients`), with and
    /// without contraction (rays from inside and far outside the inner cube), a ray
    /// without samples among them.
    #[test]
    fn ray_gradients_match_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let mut rng = Rng::new(13);
        let counts: Vec<usize> = (0..40)
            .map(|r| if r == 7 { 0 } else { 1 + r % 9 })
            .collect();
        let rays = counts.len();
        let mut offsets = vec![0u32];
        for c in &counts {
            offsets.push(offsets.last().copied().unwrap_or(0) + *c as u32);
        }
        let n = offsets[rays] as usize;
        let origins: Vec<f32> = (0..rays * 3).map(|_| rng.range(-4.0, 4.0)).collect();
        let units = rng.unit_directions(rays);
        let t: Vec<f32> = (0..n).map(|_| rng.range(0.1, 9.0)).collect();
        let d_points: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        let d_dirs: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        for contract in [None, Some(0.75f32)] {
            let mut want = vec![0.0f32; rays * RAY_WORDS];
            for r in 0..rays {
                let o = [origins[3 * r], origins[3 * r + 1], origins[3 * r + 2]];
                let u = [units[3 * r], units[3 * r + 1], units[3 * r + 2]];
                let w = &mut want[r * RAY_WORDS..][..RAY_WORDS];
                for s in offsets[r] as usize..offsets[r + 1] as usize {
                    let q = &d_points[3 * s..][..3];
                    let mut d_p = [q[0], q[1], q[2]];
                    if let Some(radius) = contract {
                        let p = [0, 1, 2].map(|a| o[a] + t[s] * u[a]);
                        d_p = contract_bwd(p, radius, d_p);
                    }
                    for a in 0..3 {
                        w[a] += d_p[a];
                        w[3 + a] += t[s] * d_p[a];
                        w[6 + a] += d_dirs[3 * s + a];
                    }
                }
            }
            let samples = GpuSamples {
                offsets: gpu.upload_u32(&offsets),
                t: gpu.upload(&t),
                dt: gpu.upload(&t),
                rays,
                len: n,
            };
            let got = ray_gradients(
                &gpu,
                &samples,
                &gpu.upload(&d_points),
                &gpu.upload(&d_dirs),
                &gpu.upload(&origins),
                &gpu.upload(&units),
                contract,
            );
            let got = gpu.read(&got, rays * RAY_WORDS).expect("read");
            assert!(got[7 * RAY_WORDS..8 * RAY_WORDS].iter().all(|&v| v == 0.0));
            let e = worst(&got, &want);
            assert!(e < 1e-5, "contraction {contract:?}: largest difference {e}");
        }
    }
}
