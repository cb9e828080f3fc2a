//! The photometric loss on the GPU: `render::loss::squared_error` per ray. Each ray's
//! squared error is written to its own slot (summed on the host, in ray order, in f64, so
//! the logged loss is the CPU's to rounding) with the gradient `dL/dC = 2 (C - target)`.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::volume::OUT_WORDS;

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
        let Some(gpu) = Gpu::vulkan()
            .map_err(|e| eprintln!("skipping the GPU kernel test: {e}"))
            .ok()
        else {
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
}
