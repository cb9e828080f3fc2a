//! The fast field's backward through its networks in one kernel, the training partner of
//! the fused forward (`fused`): one thread per sample carries the colour's and the
//! density's gradients back through the colour network, the geometry features and the
//! density network to the hash features (weighed as the forward weighed them) and a moving
//! field's space-time features, every weight staged once per workgroup in workgroup
//! memory. It writes each layer's output gradient on the way, and the weights' gradients
//! are then the products `x^T dy` of the layer-by-layer path (`mlp::Dense::backward`
//! without its input gradient), which sum over samples.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::fused::{stage_weights, FusedShape, LayerOffsets, Staged};
use super::launch::grid;
use crate::field::fast::LOG_SIGMA_MAX;

/// Threads (samples) per workgroup, as the forward's.
const GROUP: u32 = 128;

/// `dx = dy W^T` for one sample, `W` (`n_in x n_out`, row-major) at `off` in `w`: the
/// outputs unroll into registers, the loop over `dy` stays a loop.
#[cube]
fn dense_t(
    dy: &Array<f32>,
    dx: &mut Array<f32>,
    w: &[f32],
    #[comptime] off: usize,
    #[comptime] n_in: usize,
    #[comptime] n_out: usize,
) {
    let mut acc = Array::<f32>::new(n_in);
    #[unroll]
    for i in 0..n_in {
        acc[i] = 0.0;
    }
    for o in 0..n_out {
        let g = dy[o];
        #[unroll]
        for i in 0..n_in {
            acc[i] += g * w[off + i * n_out + o];
        }
    }
    #[unroll]
    for i in 0..n_in {
        dx[i] = acc[i];
    }
}

/// `v` masked by the ReLU whose outputs are row `s` of `relu_out` (`len` wide), written to
/// row `s` of `out`.
#[cube]
fn mask_and_write(
    v: &mut Array<f32>,
    relu_out: &[f32],
    out: &mut [f32],
    s: usize,
    #[comptime] len: usize,
) {
    #[unroll]
    for k in 0..len {
        v[k] = select(relu_out[s * len + k] > 0.0, v[k], 0.0);
        out[s * len + k] = v[k];
    }
}

/// `len` values of `v` into row `s` of `out`.
#[cube]
fn write_row(v: &Array<f32>, out: &mut [f32], s: usize, #[comptime] len: usize) {
    #[unroll]
    for k in 0..len {
        out[s * len + k] = v[k];
    }
}

/// From `d_sigma` (`n`) and `d_rgb` (`n x 3`) and the forward's kept activations, each
/// sample's gradients of the colour logits, the colour network's two hidden layers, its
/// input, the geometry features, the density network's hidden layer, the hash features
/// (times the level weights of an anti-aliased field) and the space-time features.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn field_bwd(
    params: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    h: &[f32],
    geo_out: &[f32],
    c1: &[f32],
    c2: &[f32],
    level_weights: &[f32],
    d_sigma: &[f32],
    d_rgb: &[f32],
    d_logit: &mut [f32],
    d_c2: &mut [f32],
    d_c1: &mut [f32],
    d_colour_in: &mut [f32],
    d_geo: &mut [f32],
    d_h: &mut [f32],
    d_enc: &mut [f32],
    d_motion: &mut [f32],
    at: LayerOffsets,
    n: u32,
    log_max: f32,
    #[comptime] n_levels: usize,
    #[comptime] hidden: usize,
    #[comptime] geo: usize,
    #[comptime] code_dims: usize,
    #[comptime] motion_levels: usize,
    #[comptime] antialias: bool,
) {
    let e = n_levels * 2;
    let md = motion_levels * 2;
    let ci = 15 + geo + code_dims;
    let at_w = comptime!(Staged::new(e, md, ci, hidden, geo));
    let mut w = Shared::<[f32]>::new_slice(at_w.total);
    stage_weights(params, &mut w, at, e, md, ci, hidden, geo, true);

    let s = ABSOLUTE_POS;
    if s < n as usize {
        let mut dl = Array::<f32>::new(3usize);
        #[unroll]
        for c in 0..3usize {
            let y = rgb[3 * s + c];
            dl[c] = d_rgb[3 * s + c] * y * (1.0 - y);
        }
        write_row(&dl, d_logit, s, 3usize);
        let mut a = Array::<f32>::new(hidden);
        dense_t(&dl, &mut a, &w, at_w.c2, hidden, 3usize);
        mask_and_write(&mut a, c2, d_c2, s, hidden);
        let mut b = Array::<f32>::new(hidden);
        dense_t(&a, &mut b, &w, at_w.c1, hidden, hidden);
        mask_and_write(&mut b, c1, d_c1, s, hidden);
        let mut dc = Array::<f32>::new(ci);
        dense_t(&b, &mut dc, &w, at_w.c0, ci, hidden);
        write_row(&dc, d_colour_in, s, ci);
        let mut dg = Array::<f32>::new(geo);
        dg[0] = select(geo_out[s * geo] < log_max, d_sigma[s] * sigma[s], 0.0f32);
        #[unroll]
        for j in 1..geo {
            dg[j] = dc[15 + j];
        }
        write_row(&dg, d_geo, s, geo);
        let mut dh = Array::<f32>::new(hidden);
        dense_t(&dg, &mut dh, &w, at_w.d1, hidden, geo);
        mask_and_write(&mut dh, h, d_h, s, hidden);
        let mut de = Array::<f32>::new(e);
        dense_t(&dh, &mut de, &w, 0usize, e, hidden);
        if antialias {
            #[unroll]
            for l in 0..n_levels {
                let weight = level_weights[s * n_levels + l];
                de[2 * l] *= weight;
                de[2 * l + 1] *= weight;
            }
        }
        write_row(&de, d_enc, s, e);
        if motion_levels > 0 {
            let mut dm = Array::<f32>::new(md);
            dense_t(&dh, &mut dm, &w, at_w.motion, md, hidden);
            write_row(&dm, d_motion, s, md);
        }
    }
}

/// What the backward reads of its forward (`fused::FusedShape::forward`'s outputs and kept
/// buffers): densities, colours, the density network's hidden layer and outputs, the
/// colour network's hidden layers, and an anti-aliased field's level weights.
pub struct Forward<'a> {
    pub sigma: &'a Handle,
    pub rgb: &'a Handle,
    pub h: &'a Handle,
    pub geo: &'a Handle,
    pub c1: &'a Handle,
    pub c2: &'a Handle,
    pub level_weights: Option<&'a Handle>,
}

/// Each sample's gradients, a row each, as the layer-by-layer backward makes them: of
/// the colour logits (`3`), the colour network's hidden layers, its input, the geometry
/// features, the density network's hidden layer, the hash features (after the level
/// weights: the features' own) and a moving field's space-time features.
pub struct Gradients {
    pub d_logit: Handle,
    pub d_c2: Handle,
    pub d_c1: Handle,
    pub d_colour_in: Handle,
    pub d_geo: Handle,
    pub d_h: Handle,
    pub d_enc: Handle,
    pub d_motion: Option<Handle>,
}

impl FusedShape {
    /// The networks' backward for `n` samples of `forward`, from `d_sigma` (`n`) and
    /// `d_rgb` (`n x 3`): every input and output gradient of the layers, none of the
    /// weights' (the caller sums them from these).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        n_params: usize,
        forward: &Forward,
        d_sigma: &Handle,
        d_rgb: &Handle,
        n: usize,
    ) -> Gradients {
        let (e, md, ci) = self.widths();
        let w = self.hidden;
        let rows = |width: usize| gpu.floats((n * width).max(1));
        let out = Gradients {
            d_logit: rows(3),
            d_c2: rows(w),
            d_c1: rows(w),
            d_colour_in: rows(ci),
            d_geo: rows(self.geo),
            d_h: rows(w),
            d_enc: rows(e),
            d_motion: self.motion.map(|_| rows(md)),
        };
        if n == 0 {
            return out;
        }
        let one = gpu.floats(1);
        let weights = forward.level_weights.unwrap_or(&one);
        let d_motion = out.d_motion.as_ref().unwrap_or(&one);
        let (count, dim) = grid(n, GROUP);
        let buf = |h: &Handle, len: usize| {
            // SAFETY: every buffer passed through here holds `len` floats: the forward's
            // and the gradients' `n` rows of their widths, the stand-in one (unread and
            // unwritten where the field has no such part).
            unsafe { BufferArg::from_raw_parts(h.clone(), len) }
        };
        let weights_len = if forward.level_weights.is_some() {
            n * self.levels
        } else {
            1
        };
        let motion_len = if out.d_motion.is_some() { n * md } else { 1 };
        // SAFETY: the buffers hold what `buf` says; the parameter vector holds every layer
        // at its offset; the kernel reads and writes sample rows below `n` only, and stages
        // the workgroup memory the forward's `fits` checked.
        unsafe {
            field_bwd::launch_unchecked(
                &gpu.client,
                count,
                dim,
                buf(params, n_params),
                buf(forward.sigma, n),
                buf(forward.rgb, n * 3),
                buf(forward.h, n * w),
                buf(forward.geo, n * self.geo),
                buf(forward.c1, n * w),
                buf(forward.c2, n * w),
                buf(weights, weights_len),
                buf(d_sigma, n),
                buf(d_rgb, n * 3),
                buf(&out.d_logit, n * 3),
                buf(&out.d_c2, n * w),
                buf(&out.d_c1, n * w),
                buf(&out.d_colour_in, n * ci),
                buf(&out.d_geo, n * self.geo),
                buf(&out.d_h, n * w),
                buf(&out.d_enc, n * e),
                buf(d_motion, motion_len),
                self.offsets(),
                n as u32,
                LOG_SIGMA_MAX,
                self.levels,
                w,
                self.geo,
                self.codes.map_or(0, |c| c.dims),
                self.motion.map_or(0, |m| m.levels),
                forward.level_weights.is_some(),
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use crate::engine::gpu::codes::SampleCodes;
    use crate::engine::gpu::device::{test_gpu, worst, Gpu};
    use crate::engine::gpu::device_field::{DeviceField, DeviceInput, DeviceMoments};
    use crate::engine::gpu::field::tests::small_field_with_every_input;
    use crate::engine::gpu::field::GpuFastField;
    use crate::field::fast::FastWorkspace;
    use crate::field::FastField;
    use crate::nn::GradBuffer;
    use crate::rng::Rng;
    use crate::stage::{Field, FieldGrad, FieldInput, MEAN_APPEARANCE};

    /// A training forward and backward of `field` through the fused kernels against the
    /// CPU field and against the layer-by-layer path on the same device: densities and
    /// colours, every parameter's gradient, and the hash features' and colour input's
    /// gradients (which camera refinement reads), on 700 random samples with a footprint
    /// each (`footprints`), a code each with the mean among them (`codes`) and a moment
    /// each (`moving`).
    fn trains_as_the_layers(
        gpu: &Gpu,
        field: &FastField,
        footprints: bool,
        codes: bool,
        moving: bool,
    ) {
        let n = 700;
        let mut rng = Rng::new(31);
        let params: Vec<f32> = (0..field.num_params())
            .map(|_| rng.range(-0.8, 0.8))
            .collect();
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.6, 1.6)).collect();
        let dirs = rng.unit_directions(n);
        let d_sigma: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
        let d_rgb: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        let fp: Vec<f32> = match footprints {
            true => (0..n).map(|_| 10f32.powf(rng.range(-3.5, -0.5))).collect(),
            false => Vec::new(),
        };
        let times: Vec<f32> = match moving {
            true => (0..n).map(|_| rng.uniform()).collect(),
            false => Vec::new(),
        };
        let indices: Vec<u32> = match codes {
            true => (0..n)
                .map(|_| match (rng.uniform() * 6.0) as u32 {
                    5 => MEAN_APPEARANCE,
                    i => i,
                })
                .collect(),
            false => Vec::new(),
        };
        let mut ws = FastWorkspace::default();
        let input = FieldInput {
            positions: &pos,
            dirs: &dirs,
            samples_per_dir: 1,
            appearance: &indices,
            footprints: &fp,
            variances: &[],
            times: &times,
        };
        let want = field.forward(&params, input, &mut ws);
        let (want_sigma, want_rgb) = (want.sigma.to_vec(), want.rgb.to_vec());
        let mut cpu_grads = GradBuffer::new(field.num_params());
        let d = FieldGrad {
            d_sigma: &d_sigma,
            d_rgb: &d_rgb,
        };
        field.backward(&params, &mut ws, d, &mut cpu_grads.all());

        // Each path: densities, colours, parameter gradients, d_enc, d_colour_in.
        let run = |fused: bool| {
            let gpu = Gpu {
                fused_training: fused,
                ..gpu.clone()
            };
            let gf = GpuFastField::new(&gpu, field);
            let p = gpu.upload(&params);
            let g = gpu.zeros(field.num_params());
            let sample_codes = match codes {
                true => SampleCodes {
                    index: gpu.upload_u32(&indices),
                    per_sample: true,
                },
                false => SampleCodes::all(&gpu, MEAN_APPEARANCE),
            };
            let (pos_h, dirs_h, times_h) =
                (gpu.upload(&pos), gpu.upload(&dirs), gpu.upload(&times));
            let fp_h = footprints.then(|| gpu.upload(&fp));
            let input = DeviceInput {
                positions: &pos_h,
                dirs: &dirs_h,
                codes: &sample_codes,
                footprints: fp_h.as_ref(),
                variances: None,
                moments: match moving {
                    true => DeviceMoments::Each(&times_h),
                    false => DeviceMoments::At(0.0),
                },
                n,
            };
            let acts = gf.forward(&gpu, &p, &input);
            let inputs = gf.backward(
                &gpu,
                &p,
                &g,
                &acts,
                &gpu.upload(&d_sigma),
                &gpu.upload(&d_rgb),
            );
            let read = |h, len| gpu.read(h, len).expect("read");
            let e = field.grid.dims();
            (
                read(&acts.sigma, n),
                read(&acts.rgb, n * 3),
                read(&g, field.num_params()),
                read(&inputs.d_enc, n * e),
                read(&inputs.d_colour_in, n * inputs.colour_columns),
            )
        };
        let fused = run(true);
        let layers = run(false);
        assert!(worst(&fused.0, &want_sigma) < 1e-4, "sigma against the CPU");
        assert!(worst(&fused.1, &want_rgb) < 1e-5, "rgb against the CPU");
        let mut largest = 0.0f32;
        for t in &field.layout.tensors {
            let r = t.range();
            let cpu = worst(&fused.2[r.clone()], &cpu_grads.values[r.clone()]);
            let dev = worst(&fused.2[r.clone()], &layers.2[r.clone()]);
            largest = largest.max(
                cpu_grads.values[r]
                    .iter()
                    .fold(0.0f32, |m, v| m.max(v.abs())),
            );
            assert!(cpu < 1e-4, "gradient of {} against the CPU: {cpu}", t.name);
            assert!(
                dev < 1e-4,
                "gradient of {} against the layers: {dev}",
                t.name
            );
        }
        let (d_enc, d_colour_in) = (worst(&fused.3, &layers.3), worst(&fused.4, &layers.4));
        eprintln!(
            "gradients up to {largest:.2}; against the layers: densities {:.1e}, colours \
             {:.1e}, parameters {:.1e}, hash features {d_enc:.1e}, colour input {d_colour_in:.1e}",
            worst(&fused.0, &layers.0),
            worst(&fused.1, &layers.1),
            worst(&fused.2, &layers.2),
        );
        assert!(largest > 0.1, "gradients too small to compare: {largest}");
        assert!(
            d_enc < 1e-4 && d_colour_in < 1e-4,
            "input gradients {d_enc} {d_colour_in}"
        );
    }

    /// A field with every input at once: anti-aliased (a footprint a sample), codes (a
    /// code a sample, the mean among them), moving (a moment a sample), four harmonics.
    #[test]
    fn the_fused_training_pair_matches_the_layers_and_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        trains_as_the_layers(&gpu, &small_field_with_every_input(), true, true, true);
    }
}
