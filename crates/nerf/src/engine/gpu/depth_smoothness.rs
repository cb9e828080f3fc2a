//! RegNeRF's depth smoothness on the GPU: `render::depth_smoothness` (whose docs give the
//! loss and its gradient) over packed samples whose rays are whole patches, one after
//! another. Two kernels, one thread per ray: each ray's opacity and expected depth, then
//! each ray's pull from its neighbours in its patch carried through its compositing
//! weights to its densities, added to `d_sigma`.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::volume::GpuSamples;
use crate::render::depth_smoothness::{NO_DEPTH, PATCH_RAYS, PATCH_SIDE};

/// Threads (rays) per workgroup.
const GROUP: u32 = 64;

/// Each ray's opacity `A` and expected depth `d` in units of `unit`, into `depths`
/// (`[A, d]` per ray; `d = 0` where nothing is hit), as `ray_depth` on the host.
#[cube(launch_unchecked)]
fn ray_depths(
    offsets: &[u32],
    t: &[f32],
    weights: &[f32],
    depths: &mut [f32],
    rays: u32,
    unit: f32,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let mut a = 0.0f32;
        let mut dw = 0.0f32;
        for k in offsets[r] as usize..offsets[r + 1] as usize {
            a += weights[k];
            dw += weights[k] * t[k];
        }
        let mut d = 0.0f32;
        if a > NO_DEPTH {
            d = dw / a / unit;
        }
        depths[2 * r] = a;
        depths[2 * r + 1] = d;
    }
}

/// `2 A_j (d - d_j)` for neighbour `j` of a ray of depth `d` (0 where `j` sees nothing).
#[cube]
fn pull_from(depths: &[f32], j: usize, d: f32) -> f32 {
    let a = depths[2 * j];
    let mut pull = 0.0f32;
    if a > NO_DEPTH {
        pull = 2.0f32 * a * (d - depths[2 * j + 1]);
    }
    pull
}

/// Adds `scale` times each ray's depth-smoothness gradient to `d_sigma`: its pull from the
/// rays left, right, above and below it in its patch, through `dd/dw_k = (t_k - d) / A`
/// (the `A` inside the pull) and the weights' backward (`render::distortion::weights_bwd`).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn depth_smoothness_bwd(
    offsets: &[u32],
    t: &[f32],
    dt: &[f32],
    weights: &[f32],
    depths: &[f32],
    d_sigma: &mut [f32],
    rays: u32,
    unit: f32,
    scale: f32,
    infinite_last: u32,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize && depths[2 * r] > NO_DEPTH {
        let d = depths[2 * r + 1];
        let i = r % PATCH_RAYS;
        let (row, col) = (i / PATCH_SIDE, i % PATCH_SIDE);
        let mut pull = 0.0f32;
        if col > 0 {
            pull += pull_from(depths, r - 1, d);
        }
        if col + 1 < PATCH_SIDE {
            pull += pull_from(depths, r + 1, d);
        }
        if row > 0 {
            pull += pull_from(depths, r - PATCH_SIDE, d);
        }
        if row + 1 < PATCH_SIDE {
            pull += pull_from(depths, r + PATCH_SIDE, d);
        }
        let g = scale * pull;
        let (start, end) = (offsets[r] as usize, offsets[r + 1] as usize);
        // sum_k dL/dw_k w_k, then the weights' backward.
        let mut dw_all = 0.0f32;
        for k in start..end {
            dw_all += g * (t[k] / unit - d) * weights[k];
        }
        let mut w_so_far = 0.0f32;
        let mut dw_so_far = 0.0f32;
        for k in start..end {
            let d_w = g * (t[k] / unit - d);
            w_so_far += weights[k];
            dw_so_far += d_w * weights[k];
            // A last step "to infinity" differentiates as 0 (`steps_for_backward`).
            let mut step = dt[k];
            if infinite_last == 1 && k + 1 == end {
                step = 0.0f32;
            }
            d_sigma[k] += step * (d_w * (1.0 - w_so_far) - (dw_all - dw_so_far));
        }
    }
}

/// How a ray's last step is differentiated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LastStep {
    /// As it is (the fast model's marched samples).
    Own,
    /// As 0: the paper model's rays end with a step "to infinity"
    /// (`render::depth_smoothness::steps_for_backward`).
    Infinite,
}

/// Adds to `d_sigma` (one per sample) `scale` times the gradient of the depth smoothness of
/// `samples`' rays, whole patches of `PATCH_RAYS` rays one after another, as
/// `PatchBackward::add_patches` adds it on the host: depths in units of `unit`, the
/// compositing `weights` differentiated by the samples' steps (the last as `last` says).
pub fn add_depth_smoothness(
    gpu: &Gpu,
    samples: &GpuSamples,
    (weights, d_sigma): (&Handle, &Handle),
    unit: f32,
    scale: f32,
    last: LastStep,
) {
    let (r, n) = (samples.rays, samples.len);
    debug_assert_eq!(r % PATCH_RAYS, 0, "rays in whole patches");
    if r == 0 || n == 0 {
        return;
    }
    let depths = gpu.floats(2 * r);
    let (count, dim) = grid(r, GROUP);
    // SAFETY: `offsets` holds `r + 1` CSR slots ending at `n`, the length of every
    // per-sample buffer; `depths` two floats per ray. Each kernel reads and writes only
    // the slots of rays below `r`, and a ray's neighbours are in its own patch (`r` is a
    // whole number of patches).
    unsafe {
        ray_depths::launch_unchecked(
            &gpu.client,
            count.clone(),
            dim,
            BufferArg::from_raw_parts(samples.offsets.clone(), r + 1),
            BufferArg::from_raw_parts(samples.t.clone(), n),
            BufferArg::from_raw_parts(weights.clone(), n),
            BufferArg::from_raw_parts(depths.clone(), 2 * r),
            r as u32,
            unit,
        );
        depth_smoothness_bwd::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(samples.offsets.clone(), r + 1),
            BufferArg::from_raw_parts(samples.t.clone(), n),
            BufferArg::from_raw_parts(samples.dt.clone(), n),
            BufferArg::from_raw_parts(weights.clone(), n),
            BufferArg::from_raw_parts(depths.clone(), 2 * r),
            BufferArg::from_raw_parts(d_sigma.clone(), n),
            r as u32,
            unit,
            scale,
            u32::from(last == LastStep::Infinite),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::render::depth_smoothness::PatchBackward;
    use crate::render::volume::composite_packed;
    use crate::rng::Rng;
    use crate::stage::{FieldOutput, PackedSamples, RayOutput};

    /// 12 patches of rays of 0 to 30 samples at random depths, steps and densities (some
    /// rays empty, some nearly transparent): the densities' gradient against the host's
    /// `PatchBackward::add_patches`, within 1e-4 relative, with each ray's last step as it
    /// is and as one to infinity (zeroed in the host's steps).
    #[test]
    fn the_depth_smoothness_gradient_matches_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let mut rng = Rng::new(23);
        let (unit, scale) = (1.7f32, 0.6f32);
        let mut samples = PackedSamples::default();
        samples.clear();
        let rays = 12 * PATCH_RAYS;
        for r in 0..rays {
            let n = if r % 7 == 3 { 0 } else { rng.below(31) };
            let mut at = rng.range(1.0, 3.0);
            for _ in 0..n {
                let step = rng.range(0.01, 0.05);
                at += step * (1.0 + (rng.uniform() * 3.0).floor());
                samples.t.push(at);
                samples.dt.push(step);
                samples.positions.push([0.0, 0.0, at]);
                samples.dirs.push([0.0, 0.0, 1.0]);
            }
            samples.end_ray();
        }
        let n = samples.len();
        let sigma: Vec<f32> = (0..n)
            .map(|k| match k % 11 {
                0 => 0.01,
                _ => rng.range(0.0, 40.0),
            })
            .collect();
        let rgb = vec![0.5f32; n * 3];
        let mut weights = vec![0.0; n];
        let mut out = vec![RayOutput::default(); rays];
        let field = FieldOutput {
            sigma: &sigma,
            rgb: &rgb,
        };
        composite_packed(
            &samples,
            field,
            &vec![[0.0; 3]; rays],
            &mut weights,
            &mut out,
        );
        let offsets: Vec<u32> = samples.offsets.iter().map(|&o| o as u32).collect();
        let device_samples = GpuSamples {
            offsets: gpu.upload_u32(&offsets),
            t: gpu.upload(&samples.t),
            dt: gpu.upload(&samples.dt),
            rays,
            len: n,
        };
        let device_weights = gpu.upload(&weights);
        for last in [LastStep::Own, LastStep::Infinite] {
            let mut steps = samples.dt.clone();
            if last == LastStep::Infinite {
                for r in 0..rays {
                    if let Some(k) = samples.ray(r).last() {
                        steps[k] = 0.0;
                    }
                }
            }
            let mut want = vec![0.0f32; n];
            PatchBackward::default().add_patches(
                &samples,
                0,
                (&steps, &weights),
                unit,
                scale,
                &mut want,
            );
            let d_sigma = gpu.zeros(n);
            add_depth_smoothness(
                &gpu,
                &device_samples,
                (&device_weights, &d_sigma),
                unit,
                scale,
                last,
            );
            let got = gpu.read(&d_sigma, n).expect("read");
            let e = worst(&got, &want);
            eprintln!("{last:?}: worst difference {e:.1e} over {n} samples");
            assert!(e < 1e-4, "{e}");
            // The term moved the gradient: something was compared.
            assert!(
                want.iter().any(|g| g.abs() > 1e-3),
                "no depth-smoothness gradient"
            );
        }
    }
}
