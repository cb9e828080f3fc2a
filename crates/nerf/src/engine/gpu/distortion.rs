//! The distortion loss's gradient on the GPU: `render::loss::LossWorkspace::add_distortion`
//! (whose docs, and `render::distortion`'s, give the maths), one thread per ray over its
//! packed samples. Each ray measures its samples in its own field-space coordinate: the
//! middles are the distances walked from its first sample, divided by the box's diagonal,
//! every interval one marching step long. The gradient reaches the densities through the
//! compositing weights and is added to the photometric one.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::volume::GpuSamples;

/// Threads (rays) per workgroup.
const GROUP: u32 = 64;

/// Distance walked from sample `i - 1` to sample `i` (field space).
#[cube]
fn stride(positions: &[f32], i: usize) -> f32 {
    let dx = positions[3 * i] - positions[3 * i - 3];
    let dy = positions[3 * i + 1] - positions[3 * i - 2];
    let dz = positions[3 * i + 2] - positions[3 * i - 1];
    f32::sqrt(dx * dx + dy * dy + dz * dz)
}

/// Adds `per_ray` times each ray's distortion gradient to `d_sigma`; `d_w` is scratch of
/// one float per sample. `inv_scale` is one over the box's diagonal, `length` the
/// intervals' normalised length.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn distortion_bwd(
    offsets: &[u32],
    positions: &[f32],
    dt: &[f32],
    weights: &[f32],
    d_w: &mut [f32],
    d_sigma: &mut [f32],
    rays: u32,
    inv_scale: f32,
    length: f32,
    per_ray: f32,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let start = offsets[r] as usize;
        let end = offsets[r + 1] as usize;
        // The weights' sums over the ray: sum w and sum w m.
        let mut w_all = 0.0f32;
        let mut wm_all = 0.0f32;
        let mut walked = 0.0f32;
        for i in start..end {
            if i > start {
                walked += stride(positions, i);
            }
            w_all += weights[i];
            wm_all += weights[i] * (walked * inv_scale);
        }
        // dL/dw per sample (`render::distortion::distortion_bwd`), and sum d_w w.
        let mut w_before = 0.0f32;
        let mut wm_before = 0.0f32;
        let mut dw_all = 0.0f32;
        walked = 0.0f32;
        for k in start..end {
            if k > start {
                walked += stride(positions, k);
            }
            let m = walked * inv_scale;
            let w = weights[k];
            let w_after = w_all - w_before - w;
            let wm_after = wm_all - wm_before - w * m;
            let spread = m * w_before - wm_before + wm_after - m * w_after;
            let g = per_ray * (2.0f32 * spread + 2.0f32 / 3.0f32 * w * length);
            d_w[k] = g;
            dw_all += g * w;
            w_before += w;
            wm_before += w * m;
        }
        // Through the weights to the densities (`render::distortion::weights_bwd`).
        let mut w_so_far = 0.0f32;
        let mut dw_so_far = 0.0f32;
        for k in start..end {
            w_so_far += weights[k];
            dw_so_far += d_w[k] * weights[k];
            d_sigma[k] += dt[k] * (d_w[k] * (1.0 - w_so_far) - (dw_all - dw_so_far));
        }
    }
}

/// Adds to `d_sigma` (one per sample) the gradient of `weight` times the mean over rays of
/// the distortion loss, as the CPU engine adds it (`step`: the marching step; `diagonal`:
/// the box's); `positions` are the samples' field-space positions, `weights` compositing's.
#[allow(clippy::too_many_arguments)]
pub fn add_distortion(
    gpu: &Gpu,
    samples: &GpuSamples,
    positions: &Handle,
    weights: &Handle,
    d_sigma: &Handle,
    step: f32,
    diagonal: f32,
    weight: f32,
) {
    let (r, n) = (samples.rays, samples.len);
    if r == 0 || n == 0 {
        return;
    }
    let d_w = gpu.floats(n);
    let (count, dim) = grid(r, GROUP);
    // SAFETY: `offsets` holds `r + 1` CSR slots ending at `n`, the length of every
    // per-sample buffer (`3n` for positions); the kernel reads and writes only the slots of
    // rays below `r`.
    unsafe {
        distortion_bwd::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(samples.offsets.clone(), r + 1),
            BufferArg::from_raw_parts(positions.clone(), 3 * n),
            BufferArg::from_raw_parts(samples.dt.clone(), n),
            BufferArg::from_raw_parts(weights.clone(), n),
            BufferArg::from_raw_parts(d_w.clone(), n),
            BufferArg::from_raw_parts(d_sigma.clone(), n),
            r as u32,
            1.0 / diagonal,
            step / diagonal,
            // The step's gradients are scaled by 1 / (3 rays) before Adam: 3 `weight` per
            // ray makes the term `weight` times the mean over rays.
            3.0 * weight,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::render::loss::LossBackward;
    use crate::render::volume::composite_packed;
    use crate::rng::Rng;
    use crate::stage::{FieldOutput, PackedSamples, RayOutput};

    /// 200 rays of 0 to 40 samples with random gaps and densities, field-space positions
    /// along a random direction each: the densities' gradient against the CPU's
    /// `add_distortion` (after a photometric pass with nothing to correct), within 1e-4
    /// relative.
    #[test]
    fn the_distortion_gradient_matches_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let mut rng = Rng::new(17);
        let (step, diagonal, weight) = (0.01f32, 1.3f32, 3.0f32);
        let mut samples = PackedSamples::default();
        samples.clear();
        let rays = 200;
        for _ in 0..rays {
            let n = (rng.uniform() * 41.0) as usize;
            let dir = [
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(0.2, 1.0),
            ];
            let dir = crate::math::scale(dir, 1.0 / crate::math::length(dir));
            let mut t = rng.range(0.0, 1.0);
            for _ in 0..n {
                // One step on, or a few when empty cells were skipped.
                t += step * (1.0 + (rng.uniform() * 4.0).floor());
                samples.t.push(t);
                samples.dt.push(step);
                samples.positions.push(crate::math::scale(dir, t));
                samples.dirs.push(dir);
            }
            samples.end_ray();
        }
        let n = samples.len();
        let sigma: Vec<f32> = (0..n).map(|_| rng.range(0.0, 60.0)).collect();
        let rgb = vec![0.5f32; n * 3];
        let backgrounds = vec![[1.0f32; 3]; rays];
        let mut weights = vec![0.0; n];
        let mut out = vec![RayOutput::default(); rays];
        let field = FieldOutput {
            sigma: &sigma,
            rgb: &rgb,
        };
        composite_packed(&samples, field, &backgrounds, &mut weights, &mut out);
        let targets: Vec<[f32; 3]> = out.iter().map(|o| o.rgb).collect();
        let mut cpu = LossBackward::default();
        cpu.run(&samples, field, &backgrounds, &out, &targets);
        cpu.add_distortion(&samples, &weights, step, diagonal, weight);
        let want = cpu.field_grad().d_sigma.to_vec();

        let offsets: Vec<u32> = samples.offsets.iter().map(|&o| o as u32).collect();
        let device_samples = GpuSamples {
            offsets: gpu.upload_u32(&offsets),
            t: gpu.upload(&samples.t),
            dt: gpu.upload(&samples.dt),
            rays,
            len: n,
        };
        let d_sigma = gpu.zeros(n);
        add_distortion(
            &gpu,
            &device_samples,
            &gpu.upload(samples.positions.as_flattened()),
            &gpu.upload(&weights),
            &d_sigma,
            step,
            diagonal,
            weight,
        );
        let got = gpu.read(&d_sigma, n).expect("read");
        let e = worst(&got, &want);
        eprintln!("worst difference {e:.1e} over {n} samples");
        assert!(e < 1e-4, "{e}");
        // The term moved the gradient: something was compared.
        assert!(
            want.iter().any(|g| g.abs() > 1e-3),
            "no distortion gradient"
        );
    }
}
