//! The moving field's prior that the scene changes smoothly in time, on the GPU: as
//! `FastField::time_smoothness_bwd`, every `SMOOTH_STRIDE`-th sample of a forward is paired
//! with the same point one cell of the finest time level later (earlier at the last
//! moment), the pair's space-time features compared, and the squared difference's gradient
//! scattered into both points' corners. Only the gradient is made: the value is not read.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::hash_grid::Scatter;
use super::launch::grid;
use super::space_time_grid::GpuSpaceTimeGrid;
use crate::field::fast::SMOOTH_STRIDE;

/// Threads per workgroup.
const GROUP: u32 = 256;

/// The `pairs` points compared (`now`, `later`: `pairs x 4`): sample `j * stride` of
/// `points` as it is, and one step `dt` later in time (earlier past the last moment).
#[cube(launch_unchecked)]
fn pair_points(
    points: &[f32],
    now: &mut [f32],
    later: &mut [f32],
    pairs: u32,
    stride: u32,
    dt: f32,
) {
    let j = ABSOLUTE_POS;
    if j < pairs as usize {
        let s = j * stride as usize;
        for a in 0..3usize {
            let v = points[4 * s + a];
            now[4 * j + a] = v;
            later[4 * j + a] = v;
        }
        let t = points[4 * s + 3];
        now[4 * j + 3] = t;
        let up = t + dt;
        if up <= 1.0f32 {
            later[4 * j + 3] = up;
        } else {
            later[4 * j + 3] = t - dt;
        }
    }
}

/// The squared difference's gradient for each pair and feature: `scale (x - y)` at the
/// sample's features `x` (`enc`, sample `j * stride`) and its negation at the later point's
/// `y` (`enc_later`, pair `j`).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn pair_gradients(
    enc: &[f32],
    enc_later: &[f32],
    d_now: &mut [f32],
    d_later: &mut [f32],
    pairs: u32,
    features: u32,
    stride: u32,
    scale: f32,
) {
    let i = ABSOLUTE_POS;
    if i < (pairs * features) as usize {
        let j = i / features as usize;
        let f = i % features as usize;
        let x = enc[j * stride as usize * features as usize + f];
        let d = scale * (x - enc_later[i]);
        d_now[i] = d;
        d_later[i] = -d;
    }
}

/// The motion encoding a forward made and what the prior needs to pair its samples.
pub struct MotionForward<'a> {
    pub grid: &'a GpuSpaceTimeGrid,
    pub scatter: Scatter,
    /// Its samples' points of space and time (`n x 4`).
    pub points: &'a Handle,
    /// Their features (`n x features`).
    pub enc: &'a Handle,
    pub features: usize,
    pub n: usize,
    /// One cell of the finest time level.
    pub dt: f32,
}

/// Adds `weight` times the prior's gradient over `forward`'s samples into `grads` (laid
/// out as the parameter vector `params`, `num_params` floats each).
pub fn add_time_smoothness(
    gpu: &Gpu,
    forward: &MotionForward,
    (params, grads, num_params): (&Handle, &Handle, usize),
    weight: f32,
) {
    let (n, md) = (forward.n, forward.features);
    if weight == 0.0 || n == 0 {
        return;
    }
    let pairs = n.div_ceil(SMOOTH_STRIDE);
    let (now, later) = (gpu.floats(pairs * 4), gpu.floats(pairs * 4));
    let (count, dim) = grid(pairs, GROUP);
    // SAFETY: `points` holds `n x 4` floats and `j * stride < n` for every pair; `now`
    // and `later` hold `pairs x 4`; the kernel bounds-checks its pair.
    unsafe {
        pair_points::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(forward.points.clone(), n * 4),
            BufferArg::from_raw_parts(now.clone(), pairs * 4),
            BufferArg::from_raw_parts(later.clone(), pairs * 4),
            pairs as u32,
            SMOOTH_STRIDE as u32,
            forward.dt,
        );
    }
    let enc_later = gpu.floats(pairs * md);
    forward
        .grid
        .encode(gpu, (params, num_params), &later, pairs, &enc_later);
    let (d_now, d_later) = (gpu.floats(pairs * md), gpu.floats(pairs * md));
    let (count, dim) = grid(pairs * md, GROUP);
    // SAFETY: `enc` holds `n x md` floats, read at samples `j * stride < n`; the other
    // buffers hold `pairs x md`; the kernel bounds-checks its slot.
    unsafe {
        pair_gradients::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(forward.enc.clone(), n * md),
            BufferArg::from_raw_parts(enc_later.clone(), pairs * md),
            BufferArg::from_raw_parts(d_now.clone(), pairs * md),
            BufferArg::from_raw_parts(d_later.clone(), pairs * md),
            pairs as u32,
            md as u32,
            SMOOTH_STRIDE as u32,
            2.0 * weight,
        );
    }
    let grads = (grads, num_params);
    let bwd = |points: &Handle, d: &Handle| {
        forward
            .grid
            .encode_bwd(gpu, forward.scatter, points, d, pairs, grads)
    };
    bwd(&now, &d_now);
    bwd(&later, &d_later);
}

#[cfg(test)]
mod tests {
    use crate::engine::gpu::codes::SampleCodes;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::engine::gpu::device_field::{DeviceField, DeviceInput, DeviceMoments};
    use crate::engine::gpu::field::tests::small_moving_field;
    use crate::engine::gpu::field::GpuFastField;
    use crate::field::fast::{FastWorkspace, SMOOTH_STRIDE};
    use crate::nn::GradBuffer;
    use crate::rng::Rng;
    use crate::stage::{Field, FieldInput};

    /// The prior's gradient on the device against the CPU field's, over one forward's
    /// samples at random moments (some at the last moment, where the pair looks back).
    #[test]
    fn the_prior_matches_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let field = small_moving_field();
        let mut rng = Rng::new(5);
        let params: Vec<f32> = (0..field.num_params())
            .map(|_| rng.range(-0.5, 0.5))
            .collect();
        let n = 701;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.4, 1.4)).collect();
        let dirs = rng.unit_directions(n);
        let mut times: Vec<f32> = (0..n).map(|_| rng.uniform()).collect();
        // Paired samples at and near the last moment, whose pairs look back in time.
        times[2 * SMOOTH_STRIDE] = 1.0;
        times[3 * SMOOTH_STRIDE] = 0.95;
        let (weight, input) = (
            0.7,
            FieldInput {
                positions: &pos,
                dirs: &dirs,
                samples_per_dir: 1,
                appearance: &[],
                footprints: &[],
                variances: &[],
                times: &times,
            },
        );
        let mut ws = FastWorkspace::default();
        field.forward(&params, input, &mut ws);
        let mut want = GradBuffer::new(field.num_params());
        let value = field.time_smoothness_bwd(&params, &mut ws, n, weight, &mut want.all());
        assert!(value > 0.0, "the prior saw no change");

        let gf = GpuFastField::new(&gpu, &field);
        let (p, g) = (gpu.upload(&params), gpu.zeros(field.num_params()));
        let (pos_h, dirs_h, times_h) = (gpu.upload(&pos), gpu.upload(&dirs), gpu.upload(&times));
        let codes = SampleCodes::all(&gpu, crate::stage::MEAN_APPEARANCE);
        let acts = gf.forward(
            &gpu,
            &p,
            &DeviceInput {
                positions: &pos_h,
                dirs: &dirs_h,
                codes: &codes,
                footprints: None,
                variances: None,
                moments: DeviceMoments::Each(&times_h),
                n,
            },
        );
        gf.time_smoothness_bwd(&gpu, (&p, &g), &acts, weight);
        let got = gpu.read(&g, field.num_params()).expect("read");
        let largest = want.values.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(largest > 1e-3, "no gradient to compare: {largest}");
        let e = worst(&got, &want.values);
        assert!(
            e < 1e-5 * largest.max(1.0),
            "gradients apart by {e} of {largest}"
        );
    }
}
