//! Volume rendering on the GPU: `render::volume`'s quadrature and its closed-form backward
//! (see that module for the maths), one thread per ray over its packed samples (CSR
//! offsets). Ray outputs are 5 floats: rgb, depth, opacity.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;

/// Threads per workgroup.
const GROUP: u32 = 64;
/// Floats per ray output: rgb, depth, opacity.
pub const OUT_WORDS: usize = 5;

#[cube(launch_unchecked)]
fn composite_fwd(
    offsets: &[u32],
    t: &[f32],
    dt: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    backgrounds: &[f32],
    weights: &mut [f32],
    out: &mut [f32],
) {
    let r = ABSOLUTE_POS;
    if r + 1 < offsets.len() {
        let start = offsets[r] as usize;
        let end = offsets[r + 1] as usize;
        let mut trans = 1.0f32;
        let mut c0 = 0.0f32;
        let mut c1 = 0.0f32;
        let mut c2 = 0.0f32;
        let mut depth = 0.0f32;
        let mut opacity = 0.0f32;
        for i in start..end {
            let alpha = 1.0 - f32::exp(-sigma[i] * dt[i]);
            let w = trans * alpha;
            c0 += w * rgb[3 * i];
            c1 += w * rgb[3 * i + 1];
            c2 += w * rgb[3 * i + 2];
            depth += w * t[i];
            opacity += w;
            trans *= 1.0 - alpha;
            weights[i] = w;
        }
        out[5 * r] = c0 + (1.0 - opacity) * backgrounds[3 * r];
        out[5 * r + 1] = c1 + (1.0 - opacity) * backgrounds[3 * r + 1];
        out[5 * r + 2] = c2 + (1.0 - opacity) * backgrounds[3 * r + 2];
        out[5 * r + 3] = depth;
        out[5 * r + 4] = opacity;
    }
}

/// One colour channel's share of `dC/dsigma_i`: `d (T_{i+1} c_i - S_i)`, with the last
/// sample's suffix `T_{N+1} bg` taken directly (as on the CPU, to keep a 1e10 delta from
/// magnifying rounding error).
#[cube]
fn channel(d: f32, trans: f32, c: f32, rendered: f32, prefix: f32, bg: f32, last: bool) -> f32 {
    let suffix = select(last, trans * bg, rendered - prefix);
    d * (trans * c - suffix)
}

#[cube(launch_unchecked)]
fn composite_bwd(
    offsets: &[u32],
    dt: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    backgrounds: &[f32],
    rendered: &[f32],
    d_out: &[f32],
    d_sigma: &mut [f32],
    d_rgb: &mut [f32],
) {
    let r = ABSOLUTE_POS;
    if r + 1 < offsets.len() {
        let start = offsets[r] as usize;
        let end = offsets[r + 1] as usize;
        let (g0, g1, g2) = (d_out[3 * r], d_out[3 * r + 1], d_out[3 * r + 2]);
        let mut trans = 1.0f32;
        let mut p0 = 0.0f32;
        let mut p1 = 0.0f32;
        let mut p2 = 0.0f32;
        for i in start..end {
            let alpha = 1.0 - f32::exp(-sigma[i] * dt[i]);
            let w = trans * alpha;
            trans *= 1.0 - alpha;
            let (k0, k1, k2) = (rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]);
            p0 += w * k0;
            p1 += w * k1;
            p2 += w * k2;
            let last = i + 1 == end;
            let ds = channel(g0, trans, k0, rendered[5 * r], p0, backgrounds[3 * r], last)
                + channel(
                    g1,
                    trans,
                    k1,
                    rendered[5 * r + 1],
                    p1,
                    backgrounds[3 * r + 1],
                    last,
                )
                + channel(
                    g2,
                    trans,
                    k2,
                    rendered[5 * r + 2],
                    p2,
                    backgrounds[3 * r + 2],
                    last,
                );
            d_rgb[3 * i] = w * g0;
            d_rgb[3 * i + 1] = w * g1;
            d_rgb[3 * i + 2] = w * g2;
            d_sigma[i] = dt[i] * ds;
        }
    }
}

/// Packed samples on the device: `rays + 1` offsets (`u32`) and `n` depths and lengths.
pub struct GpuSamples {
    pub offsets: Handle,
    pub t: Handle,
    pub dt: Handle,
    pub rays: usize,
    pub len: usize,
}

fn launch_size(rays: usize) -> (CubeCount, CubeDim) {
    (
        CubeCount::Static((rays as u32).div_ceil(GROUP), 1, 1),
        CubeDim::new_1d(GROUP),
    )
}

/// Composites every ray of `samples` (field output `sigma`: `n`, `rgb`: `n x 3`) over its
/// background (`rays x 3`) into `out` (`rays x 5`), writing the weights (`n`).
#[allow(clippy::too_many_arguments)]
pub fn composite(
    gpu: &Gpu,
    samples: &GpuSamples,
    sigma: &Handle,
    rgb: &Handle,
    backgrounds: &Handle,
    weights: &Handle,
    out: &Handle,
) {
    if samples.rays == 0 {
        return;
    }
    let (count, dim) = launch_size(samples.rays);
    let (r, n) = (samples.rays, samples.len);
    // SAFETY: every length is the one its buffer was made with (see the arguments' docs);
    // the kernel reads ray r's samples between offsets r and r + 1, which the caller's CSR
    // keeps within n.
    unsafe {
        composite_fwd::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(samples.offsets.clone(), r + 1),
            BufferArg::from_raw_parts(samples.t.clone(), n),
            BufferArg::from_raw_parts(samples.dt.clone(), n),
            BufferArg::from_raw_parts(sigma.clone(), n),
            BufferArg::from_raw_parts(rgb.clone(), n * 3),
            BufferArg::from_raw_parts(backgrounds.clone(), r * 3),
            BufferArg::from_raw_parts(weights.clone(), n),
            BufferArg::from_raw_parts(out.clone(), r * OUT_WORDS),
        );
    }
}

/// Backward of [`composite`]: from `d_out` (`dL/dC`, `rays x 3`) and the forward's `out`,
/// writes `d_sigma` (`n`) and `d_rgb` (`n x 3`).
#[allow(clippy::too_many_arguments)]
pub fn composite_backward(
    gpu: &Gpu,
    samples: &GpuSamples,
    sigma: &Handle,
    rgb: &Handle,
    backgrounds: &Handle,
    out: &Handle,
    d_out: &Handle,
    d_sigma: &Handle,
    d_rgb: &Handle,
) {
    if samples.rays == 0 {
        return;
    }
    let (count, dim) = launch_size(samples.rays);
    let (r, n) = (samples.rays, samples.len);
    // SAFETY: as in `composite`.
    unsafe {
        composite_bwd::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(samples.offsets.clone(), r + 1),
            BufferArg::from_raw_parts(samples.dt.clone(), n),
            BufferArg::from_raw_parts(sigma.clone(), n),
            BufferArg::from_raw_parts(rgb.clone(), n * 3),
            BufferArg::from_raw_parts(backgrounds.clone(), r * 3),
            BufferArg::from_raw_parts(out.clone(), r * OUT_WORDS),
            BufferArg::from_raw_parts(d_out.clone(), r * 3),
            BufferArg::from_raw_parts(d_sigma.clone(), n),
            BufferArg::from_raw_parts(d_rgb.clone(), n * 3),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::render::volume::{composite_packed, composite_packed_bwd};
    use crate::rng::Rng;
    use crate::stage::{FieldOutput, PackedSamples, RayOutput};

    fn read(gpu: &Gpu, h: Handle) -> Vec<f32> {
        gpu.read(&h, usize::MAX).expect("read back")
    }

    /// Rays of 0 to 40 samples (the paper's sampler's last "infinite" delta on some),
    /// random densities and colours: forward and backward against the CPU stage, within
    /// 1e-5 relative.
    #[test]
    fn compositing_matches_the_cpu_forward_and_backward() {
        let Some(gpu) = test_gpu() else { return };
        let mut rng = Rng::new(5);
        let mut samples = PackedSamples::default();
        samples.clear();
        let rays = 300;
        for r in 0..rays {
            let n = (r * 7) % 41;
            let mut t = 2.0;
            for i in 0..n {
                let dt = rng.range(0.001, 0.05);
                samples.t.push(t);
                samples
                    .dt
                    .push(if r % 5 == 0 && i + 1 == n { 1e10 } else { dt });
                samples.positions.push([0.0; 3]);
                samples.dirs.push([0.0, 0.0, 1.0]);
                t += dt;
            }
            samples.end_ray();
        }
        let n = samples.len();
        let sigma: Vec<f32> = (0..n).map(|_| rng.range(0.0, 60.0)).collect();
        let rgb: Vec<f32> = (0..n * 3).map(|_| rng.range(0.0, 1.0)).collect();
        let bgs: Vec<[f32; 3]> = (0..rays).map(|_| [rng.range(0.0, 1.0); 3]).collect();
        let d_out: Vec<[f32; 3]> = (0..rays)
            .map(|_| {
                [
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                ]
            })
            .collect();
        let field = FieldOutput {
            sigma: &sigma,
            rgb: &rgb,
        };
        let mut weights = vec![0.0; n];
        let mut out = vec![RayOutput::default(); rays];
        composite_packed(&samples, field, &bgs, &mut weights, &mut out);
        let (mut d_sigma, mut d_rgb) = (vec![0.0; n], vec![0.0; n * 3]);
        composite_packed_bwd(
            &samples,
            field,
            &bgs,
            &out,
            &d_out,
            &mut d_sigma,
            &mut d_rgb,
        );

        let offsets: Vec<u32> = samples.offsets.iter().map(|&o| o as u32).collect();
        let gs = GpuSamples {
            offsets: gpu.upload_u32(&offsets),
            t: gpu.upload(&samples.t),
            dt: gpu.upload(&samples.dt),
            rays,
            len: n,
        };
        let (s, c) = (gpu.upload(&sigma), gpu.upload(&rgb));
        let b = gpu.upload(bgs.as_flattened());
        let (w, o) = (
            gpu.client.empty(n * 4),
            gpu.client.empty(rays * OUT_WORDS * 4),
        );
        composite(&gpu, &gs, &s, &c, &b, &w, &o);
        let d = gpu.upload(d_out.as_flattened());
        let (ds, dc) = (gpu.client.empty(n * 4), gpu.client.empty(n * 3 * 4));
        composite_backward(&gpu, &gs, &s, &c, &b, &o, &d, &ds, &dc);

        let want_out: Vec<f32> = out
            .iter()
            .flat_map(|o| [o.rgb[0], o.rgb[1], o.rgb[2], o.depth, o.opacity])
            .collect();
        assert!(worst(&read(&gpu, w), &weights) < 1e-5, "weights");
        assert!(worst(&read(&gpu, o), &want_out) < 1e-5, "ray outputs");
        let got = read(&gpu, ds);
        assert!(
            worst(&got, &d_sigma) < 1e-4,
            "d_sigma: {}",
            worst(&got, &d_sigma)
        );
        assert!(worst(&read(&gpu, dc), &d_rgb) < 1e-5, "d_rgb");
    }
}
