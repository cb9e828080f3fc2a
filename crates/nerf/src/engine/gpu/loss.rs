//! The photometric loss on the GPU: `render::loss::squared_error` per ray. Each ray's
//! squared error is written to its own slot (summed on the host, in ray order, in f64, so
//! the logged loss is the CPU's to rounding) with the gradient `dL/dC = 2 (C - target)`.
//! FreeNeRF's occlusion penalty adds its density gradient on the device too.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::volume::{GpuSamples, OUT_WORDS};
use crate::model::free_nerf::FreeNerf;

/// Threads per workgroup.
const GROUP: u32 = 256;

#[cube(launch_unchecked)]
fn squared_error(rendered: &[f32], targets: &[f32], sse: &mut [f32], d_out: &mut [f32]) {
    let r = ABSOLUTE_POS;
    if r < sse.len() {
        let mut sum = 0.0f32;
        #[unroll]
        for c in 0..3usize {
            let e = rendered[5 * r + c] - targets[3 * r + c];
            sum += e * e;
            d_out[3 * r + c] = 2.0 * e;
        }
        sse[r] = sum;
    }
}

/// Per ray of `rays`: the squared error of the rendered colour (`rendered`: `rays x 5`, as
/// compositing writes it) against `targets` (`rays x 3`) into `sse` (`rays`), and its
/// gradient into `d_out` (`rays x 3`).
pub fn squared_error_per_ray(
    gpu: &Gpu,
    rays: usize,
    rendered: &Handle,
    targets: &Handle,
    sse: &Handle,
    d_out: &Handle,
) {
    if rays == 0 {
        return;
    }
    // SAFETY: each buffer holds the stated number of floats per ray; the kernel
    // bounds-checks the ray index.
    unsafe {
        squared_error::launch_unchecked(
            &gpu.client,
            CubeCount::Static((rays as u32).div_ceil(GROUP), 1, 1),
            CubeDim::new_1d(GROUP),
            BufferArg::from_raw_parts(rendered.clone(), rays * OUT_WORDS),
            BufferArg::from_raw_parts(targets.clone(), rays * 3),
            BufferArg::from_raw_parts(sse.clone(), rays),
            BufferArg::from_raw_parts(d_out.clone(), rays * 3),
        );
    }
}

#[cube(launch_unchecked)]
fn occlusion(offsets: &[u32], d_sigma: &mut [f32], first: u32, weight: f32) {
    let r = ABSOLUTE_POS;
    if r + 1 < offsets.len() {
        let start = offsets[r] as usize;
        let end = u32::min(offsets[r + 1], offsets[r] + first) as usize;
        let gradient = weight / f32::cast_from(u32::max(1u32, (end - start) as u32));
        for i in start..end {
            d_sigma[i] += gradient;
        }
    }
}

/// Adds FreeNeRF's occlusion penalty's gradient to `d_sigma` (one per sample of
/// `samples`, sorted by depth along each ray): `FreeNerf::add_occlusion`'s, in the same
/// units (before the loss's `1 / (3 rays)`): the weight spread over each ray's first
/// `occlusion_samples` samples, or all of them where it has fewer.
pub fn add_occlusion(gpu: &Gpu, free: &FreeNerf, samples: &GpuSamples, d_sigma: &Handle) {
    let first = free.occlusion_samples;
    if samples.rays == 0 || first == 0 {
        return;
    }
    let weight = 3.0 * free.occlusion_weight;
    // SAFETY: `offsets` holds `rays + 1` ascending sample indices, all within `d_sigma`'s
    // `len` floats; the kernel bounds-checks the ray index.
    unsafe {
        let (count, dim) = grid(samples.rays, GROUP);
        occlusion::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(samples.offsets.clone(), samples.rays + 1),
            BufferArg::from_raw_parts(d_sigma.clone(), samples.len),
            first as u32,
            weight,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::loss;
    use crate::rng::Rng;
    use crate::stage::RayOutput;

    /// Against the CPU loss: the per-ray errors sum to its value (relative 1e-6) and the
    /// gradients agree exactly up to rounding (1e-6).
    #[test]
    fn loss_matches_the_cpu() {
        let Some(gpu) = crate::engine::gpu::device::test_gpu() else {
            return;
        };
        let rays = 1000;
        let mut rng = Rng::new(2);
        let out: Vec<RayOutput> = (0..rays)
            .map(|_| RayOutput {
                rgb: [
                    rng.range(0.0, 1.0),
                    rng.range(0.0, 1.0),
                    rng.range(0.0, 1.0),
                ],
                depth: rng.range(2.0, 6.0),
                opacity: rng.range(0.0, 1.0),
            })
            .collect();
        let targets: Vec<[f32; 3]> = (0..rays)
            .map(|_| {
                [
                    rng.range(0.0, 1.0),
                    rng.range(0.0, 1.0),
                    rng.range(0.0, 1.0),
                ]
            })
            .collect();
        let mut d_want = vec![[0.0; 3]; rays];
        let want = loss::squared_error(&out, &targets, &mut d_want);

        let flat: Vec<f32> = out
            .iter()
            .flat_map(|o| [o.rgb[0], o.rgb[1], o.rgb[2], o.depth, o.opacity])
            .collect();
        let upload = |v: &[f32]| gpu.client.create_from_slice(f32::as_bytes(v));
        let (r, t) = (upload(&flat), upload(targets.as_flattened()));
        let (sse, d) = (gpu.client.empty(rays * 4), gpu.client.empty(rays * 3 * 4));
        squared_error_per_ray(&gpu, rays, &r, &t, &sse, &d);
        let read = |h: Handle| f32::from_bytes(&gpu.client.read_one(h).expect("read")).to_vec();
        let got: f64 = read(sse).iter().map(|&e| f64::from(e)).sum();
        assert!((got - want).abs() <= 1e-6 * want, "{got} vs {want}");
        let d_got = read(d);
        let worst = d_got
            .iter()
            .zip(d_want.as_flattened())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-6, "gradient differs by {worst}");
    }

    /// FreeNeRF's occlusion gradient against the CPU's on the same densities: rays of 7
    /// samples (more than the 3 penalised) and of 2 (fewer).
    #[test]
    fn occlusion_matches_the_cpu() {
        let Some(gpu) = crate::engine::gpu::device::test_gpu() else {
            return;
        };
        let free = FreeNerf {
            occlusion_samples: 3,
            ..FreeNerf::default()
        };
        let mut rng = Rng::new(5);
        let mut want = Vec::new();
        let mut offsets = vec![0u32];
        for spr in [7usize, 2] {
            let rays = 50;
            let sigma: Vec<f32> = (0..rays * spr).map(|_| rng.range(0.0, 5.0)).collect();
            let mut d: Vec<f32> = (0..rays * spr).map(|_| rng.range(-1.0, 1.0)).collect();
            let before = d.clone();
            free.add_occlusion(&sigma, spr, &mut d);
            want.extend(before.iter().zip(&d).map(|(b, a)| (*b, *a)));
            for _ in 0..rays {
                offsets.push(offsets[offsets.len() - 1] + spr as u32);
            }
        }
        let len = want.len();
        let before: Vec<f32> = want.iter().map(|w| w.0).collect();
        let samples = GpuSamples {
            offsets: gpu.upload_u32(&offsets),
            t: gpu.floats(len),
            dt: gpu.floats(len),
            rays: offsets.len() - 1,
            len,
        };
        let d_sigma = gpu.upload(&before);
        add_occlusion(&gpu, &free, &samples, &d_sigma);
        let got = gpu.read(&d_sigma, len).expect("read");
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert!((g - w.1).abs() < 1e-6, "sample {i}: {g} vs {}", w.1);
        }
        assert!(
            want.iter().any(|w| w.0 != w.1),
            "the penalty adds something"
        );
    }
}
