//! The paper's network (`field::vanilla`, whose docs draw it) on the GPU: the positional
//! encodings and the trunk with its skip (`trunk`), the density head, and the view branch
//! (or the single output layer of the "no view dependence" ablation), forward and
//! backward, built from [`Dense`] layers, after D-NeRF's deformation where it has one. A concatenated input (the skip layer's `[h, gamma(x)]`, the view
//! layer's `[feature, gamma(d)]`) is built as one buffer, so each layer is one product
//! with the single weight matrix the CPU stores for it.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::codes::SampleCodes;
use super::deformation::{position_encoding_bwd, DeformActs, GpuDeformation};
use super::device::Gpu;
use super::device_field::{DeviceField, DeviceInput, DeviceMoments, DeviceOutput, FieldNeeds};
use super::field::{sigmoid_bwd, sigmoid_in_place};
use super::launch::grid;
use super::mlp::Dense;
use super::trunk::{
    add_into, concat, copy, encode, relu_grad, trunk_backward, trunk_forward, Trunk, TrunkActs,
};
use crate::encoding::FrequencyEncoding;
use crate::field::VanillaNet;

const GROUP: u32 = 256;

/// The "no view dependence" head's 4 outputs into `rgb = sigmoid(o_0..3)`, `sigma =
/// max(o_3, 0)`.
#[cube(launch_unchecked)]
fn direct_head(raw: &[f32], rgb: &mut [f32], sigma: &mut [f32], n: u32) {
    let s = ABSOLUTE_POS;
    if s < n as usize {
        for c in 0..3usize {
            rgb[3 * s + c] = 1.0 / (1.0 + f32::exp(-raw[4 * s + c]));
        }
        sigma[s] = f32::max(raw[4 * s + 3], 0.0);
    }
}

#[cube(launch_unchecked)]
fn direct_head_bwd(
    raw: &[f32],
    rgb: &[f32],
    d_rgb: &[f32],
    d_sigma: &[f32],
    d_raw: &mut [f32],
    n: u32,
) {
    let s = ABSOLUTE_POS;
    if s < n as usize {
        for c in 0..3usize {
            let y = rgb[3 * s + c];
            d_raw[4 * s + c] = d_rgb[3 * s + c] * y * (1.0 - y);
        }
        d_raw[4 * s + 3] = select(raw[4 * s + 3] > 0.0, d_sigma[s], 0.0);
    }
}

enum Heads {
    ViewDependent {
        sigma: Dense,
        feature: Dense,
        view: Dense,
        rgb: Dense,
        dir: FrequencyEncoding,
    },
    Direct {
        output: Dense,
    },
}

/// One vanilla network on the device, its layers at `base +` their offsets in the net's
/// own layout (the fine net follows the coarse one in the model's vector).
pub struct GpuVanillaNet {
    pe: FrequencyEncoding,
    trunk: Trunk,
    heads: Heads,
    /// D-NeRF's deformation before the network, where it has one.
    deformation: Option<GpuDeformation>,
    n_params: usize,
    /// Each position band's visibility (FreeNeRF's reveal); `None`: every band whole.
    band_mask: Option<Handle>,
}

/// The activations of one batch, kept by the forward for the backward.
pub struct VanillaActs {
    pub n: usize,
    /// The trunk's, its input the encoded (moved) points.
    trunk: TrunkActs,
    /// The deformation's, where it ran.
    deform: Option<DeformActs>,
    /// View-dependent heads: `[feature, gamma(d)]` and the view layer's output; the direct
    /// head: its raw 4 outputs in `view_in`.
    view_in: Handle,
    view_hidden: Handle,
    pub sigma: Handle,
    pub rgb: Handle,
}

impl GpuVanillaNet {
    /// `net`'s layers, its parameters starting at `base` in a vector of `n_params`.
    pub fn new(net: &VanillaNet, base: usize, n_params: usize) -> Self {
        let c = &net.config;
        let find = |name: &str, relu: bool| {
            let w = net
                .layout
                .tensors
                .iter()
                .find(|t| t.name.ends_with(&format!("{name}.weight")))
                .expect("every vanilla layer has a weight");
            let b = net
                .layout
                .tensors
                .iter()
                .find(|t| t.name.ends_with(&format!("{name}.bias")))
                .expect("every vanilla layer has a bias");
            Dense {
                inputs: w.shape[0],
                outputs: w.shape[1],
                weight: base + w.offset,
                bias: Some(base + b.offset),
                relu,
            }
        };
        // The canonical layers precede the deformation's (`time_pts_*`) in the layout.
        let trunk = (0..c.depth)
            .map(|l| find(&format!("pts_{l}"), true))
            .collect();
        let heads = match c.direction_encoding {
            Some(dir) => Heads::ViewDependent {
                sigma: find("sigma", true),
                feature: find("feature", false),
                view: find("view", true),
                rgb: find("rgb", false),
                dir,
            },
            None => Heads::Direct {
                output: find("output", false),
            },
        };
        let deformation = GpuDeformation::new(
            c.deformation.as_ref(),
            c.position_encoding,
            &net.layout,
            base,
            n_params,
        );
        GpuVanillaNet {
            pe: c.position_encoding,
            trunk: Trunk {
                layers: trunk,
                width: c.width,
                skip: c.skip,
            },
            heads,
            deformation,
            n_params,
            band_mask: None,
        }
    }

    /// Scales the position encoding's bands by `mask` (one value per band, as
    /// `field::vanilla`'s `band_mask`) from the next forward on; empty: every band whole.
    pub fn set_band_mask(&mut self, gpu: &Gpu, mask: &[f32]) {
        self.band_mask = (!mask.is_empty()).then(|| gpu.upload(mask));
    }

    /// Density (`n`, after ReLU) and colour (`n x 3`) of `n` samples at `positions` seen
    /// along unit `dirs` (both `n x 3`); with `variances` (`n x 3`), each sample is the
    /// Gaussian of its conical frustum (mip-NeRF); with `times` (`n`) and a deformation,
    /// each point is first carried into the canonical scene from its moment (none: all at
    /// the canonical moment).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_points(
        &self,
        gpu: &Gpu,
        params: &Handle,
        positions: &Handle,
        variances: Option<&Handle>,
        times: Option<&Handle>,
        dirs: &Handle,
        n: usize,
    ) -> VanillaActs {
        let (np, w, in_x) = (self.n_params, self.trunk.width, self.pe.dims());
        let deform = match (&self.deformation, times) {
            (Some(d), Some(times)) => Some(d.forward(gpu, params, positions, times, n)),
            _ => None,
        };
        let points = deform.as_ref().map_or(positions, |d| &d.moved);
        let enc = encode(gpu, self.pe, points, variances, self.band_mask.as_ref(), n);
        let trunk = trunk_forward(gpu, params, np, &self.trunk, enc, in_x, n);
        let h = trunk.last.clone();
        let (sigma, rgb) = (gpu.floats(n), gpu.floats(n * 3));
        let (view_in, view_hidden) = match &self.heads {
            Heads::ViewDependent {
                sigma: s,
                feature,
                view,
                rgb: r,
                dir,
            } => {
                s.forward(gpu, params, np, &h, &sigma, n);
                let feat = gpu.floats(n * w);
                feature.forward(gpu, params, np, &h, &feat, n);
                let dir_enc = encode(gpu, *dir, dirs, None, None, n);
                let view_in = concat(gpu, &feat, w, &dir_enc, dir.dims(), n);
                let hidden = gpu.floats(n * view.outputs);
                view.forward(gpu, params, np, &view_in, &hidden, n);
                r.forward(gpu, params, np, &hidden, &rgb, n);
                // SAFETY: `rgb` holds `n x 3` floats.
                unsafe {
                    let (c, d) = grid(n * 3, GROUP);
                    sigmoid_in_place::launch_unchecked(
                        &gpu.client,
                        c,
                        d,
                        BufferArg::from_raw_parts(rgb.clone(), n * 3),
                    );
                }
                (view_in, hidden)
            }
            Heads::Direct { output } => {
                let raw = gpu.floats(n * 4);
                output.forward(gpu, params, np, &h, &raw, n);
                // SAFETY: `raw` holds `n x 4` floats, `rgb` `n x 3`, `sigma` `n`.
                unsafe {
                    let (c, d) = grid(n, GROUP);
                    direct_head::launch_unchecked(
                        &gpu.client,
                        c,
                        d,
                        BufferArg::from_raw_parts(raw.clone(), n * 4),
                        BufferArg::from_raw_parts(rgb.clone(), n * 3),
                        BufferArg::from_raw_parts(sigma.clone(), n),
                        n as u32,
                    );
                }
                (raw, gpu.floats(1))
            }
        };
        VanillaActs {
            n,
            trunk,
            deform,
            view_in,
            view_hidden,
            sigma,
            rgb,
        }
    }
}

impl DeviceOutput for VanillaActs {
    fn sigma(&self) -> &Handle {
        &self.sigma
    }
    fn rgb(&self) -> &Handle {
        &self.rgb
    }
}

impl DeviceField for GpuVanillaNet {
    type Activations = VanillaActs;
    type InputGradients = ();

    fn num_params(&self) -> usize {
        self.n_params
    }

    fn needs(&self) -> FieldNeeds {
        FieldNeeds {
            moments: self.deformation.is_some(),
            ..FieldNeeds::default()
        }
    }

    /// [`forward_points`](Self::forward_points) of `input`'s samples (their variances
    /// where the encoding is integrated; their moments where the net deforms).
    fn forward(&self, gpu: &Gpu, params: &Handle, input: &DeviceInput) -> VanillaActs {
        let at_one;
        let times = match input.moments {
            DeviceMoments::Each(times) => Some(times),
            // The canonical moment, where D-NeRF's deformation is zero; the paper's model
            // keeps no occupancy grid to ask for any moment.
            DeviceMoments::At(0.0) | DeviceMoments::Any => None,
            DeviceMoments::At(t) => {
                at_one = gpu.upload(&vec![t; input.n]);
                Some(&at_one)
            }
        };
        let (positions, dirs) = (input.positions, input.dirs);
        self.forward_points(
            gpu,
            params,
            positions,
            input.variances,
            times,
            dirs,
            input.n,
        )
    }

    /// Backward of [`forward`](DeviceField::forward): from `d_sigma` (`n`) and `d_rgb` (`n x 3`),
    /// adds every parameter's gradient into `grads`.
    fn backward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        grads: &Handle,
        a: &VanillaActs,
        d_sigma: &Handle,
        d_rgb: &Handle,
    ) {
        let (np, n, w) = (self.n_params, a.n, self.trunk.width);
        if n == 0 {
            return;
        }
        // d(last trunk output), already through the last trunk layer's ReLU.
        let d_last = gpu.floats(n * w);
        match &self.heads {
            Heads::ViewDependent {
                sigma,
                feature,
                view,
                rgb,
                ..
            } => {
                let d_logit = gpu.floats(n * 3);
                // SAFETY: every buffer holds `n x 3` floats.
                unsafe {
                    let (c, d) = grid(n * 3, GROUP);
                    sigmoid_bwd::launch_unchecked(
                        &gpu.client,
                        c,
                        d,
                        BufferArg::from_raw_parts(d_rgb.clone(), n * 3),
                        BufferArg::from_raw_parts(a.rgb.clone(), n * 3),
                        BufferArg::from_raw_parts(d_logit.clone(), n * 3),
                    );
                }
                let d_hidden = gpu.floats(n * view.outputs);
                rgb.backward(
                    gpu,
                    params,
                    grads,
                    np,
                    &a.view_hidden,
                    &d_logit,
                    Some((&d_hidden, true)),
                    n,
                );
                let d_view_in = gpu.floats(n * view.inputs);
                view.backward(
                    gpu,
                    params,
                    grads,
                    np,
                    &a.view_in,
                    &d_hidden,
                    Some((&d_view_in, false)),
                    n,
                );
                let d_feat = gpu.floats(n * w);
                copy(gpu, &d_view_in, &d_feat, n, w, (view.inputs, 0), (w, 0));
                feature.backward(
                    gpu,
                    params,
                    grads,
                    np,
                    &a.trunk.last,
                    &d_feat,
                    Some((&d_last, true)),
                    n,
                );
                // The density head: through its ReLU, then into the trunk as well.
                let d_raw = gpu.floats(n);
                let d_from_sigma = gpu.floats(n * w);
                // SAFETY: `d_sigma`, `sigma` and `d_raw` hold `n` floats; `d_last` and
                // `d_from_sigma` `n x w`.
                unsafe {
                    let (c, d) = grid(n, GROUP);
                    relu_grad::launch_unchecked(
                        &gpu.client,
                        c,
                        d,
                        BufferArg::from_raw_parts(d_sigma.clone(), n),
                        BufferArg::from_raw_parts(a.sigma.clone(), n),
                        BufferArg::from_raw_parts(d_raw.clone(), n),
                        n as u32,
                    );
                }
                sigma.backward(
                    gpu,
                    params,
                    grads,
                    np,
                    &a.trunk.last,
                    &d_raw,
                    Some((&d_from_sigma, true)),
                    n,
                );
                // SAFETY: as above.
                unsafe {
                    let (c, d) = grid(n * w, GROUP);
                    add_into::launch_unchecked(
                        &gpu.client,
                        c,
                        d,
                        BufferArg::from_raw_parts(d_last.clone(), n * w),
                        BufferArg::from_raw_parts(d_from_sigma.clone(), n * w),
                        (n * w) as u32,
                    );
                }
            }
            Heads::Direct { output } => {
                let d_raw = gpu.floats(n * 4);
                // SAFETY: `raw` and `d_raw` hold `n x 4` floats, `rgb` and `d_rgb` `n x 3`,
                // `d_sigma` `n`.
                unsafe {
                    let (c, d) = grid(n, GROUP);
                    direct_head_bwd::launch_unchecked(
                        &gpu.client,
                        c,
                        d,
                        BufferArg::from_raw_parts(a.view_in.clone(), n * 4),
                        BufferArg::from_raw_parts(a.rgb.clone(), n * 3),
                        BufferArg::from_raw_parts(d_rgb.clone(), n * 3),
                        BufferArg::from_raw_parts(d_sigma.clone(), n),
                        BufferArg::from_raw_parts(d_raw.clone(), n * 4),
                        n as u32,
                    );
                }
                output.backward(
                    gpu,
                    params,
                    grads,
                    np,
                    &a.trunk.last,
                    &d_raw,
                    Some((&d_last, true)),
                    n,
                );
            }
        }
        let in_x = self.pe.dims();
        // Through a deformation the trunk's input gradient goes on, through the encoding,
        // to the moved points.
        let d_enc = a.deform.is_some().then(|| gpu.floats(n * in_x));
        let io = (in_x, d_enc.as_ref());
        trunk_backward(
            gpu,
            (params, grads, np),
            &self.trunk,
            &a.trunk,
            d_last,
            io,
            n,
        );
        if let (Some(deformation), Some(deform), Some(d_enc)) =
            (&self.deformation, &a.deform, &d_enc)
        {
            let mask = self.band_mask.as_ref();
            let d_moved = position_encoding_bwd(gpu, self.pe, &deform.moved, d_enc, mask, n);
            deformation.backward(gpu, (params, grads), deform, &d_moved, n);
        }
    }

    /// The densities of a forward seen along +z, as the CPU net's `density_at` (a
    /// density does not depend on the direction).
    fn density(
        &self,
        gpu: &Gpu,
        params: &Handle,
        positions: &Handle,
        moments: DeviceMoments,
        n: usize,
    ) -> Handle {
        let along_z: Vec<f32> = (0..n).flat_map(|_| [0.0, 0.0, 1.0]).collect();
        let dirs = gpu.upload(&along_z);
        let codes = SampleCodes::all(gpu, crate::stage::MEAN_APPEARANCE);
        let input = DeviceInput {
            positions,
            dirs: &dirs,
            codes: &codes,
            footprints: None,
            variances: None,
            moments,
            n,
        };
        self.forward(gpu, params, &input).sigma
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::worst;
    use crate::engine::gpu::device::Path;
    use crate::field::deformation::DeformationConfig;
    use crate::field::{VanillaConfig, VanillaWorkspace};
    use crate::nn::GradBuffer;
    use crate::rng::Rng;
    use crate::stage::{Field, FieldGrad, FieldInput};

    /// Small networks of both head kinds, with a skip, both encoding forms, and with a small
    /// deformation (D-NeRF, samples at random moments, a sixth at 0): sigma, rgb and every
    /// parameter's gradient against the CPU network on the same 96 samples (16 rays of 6),
    /// within 1e-4 relative to (1 + |value|) (the deformation's gradients within 1e-3). The net sits after 5 other parameters (as the
    /// fine net sits after the coarse one).
    #[test]
    fn the_paper_network_matches_the_cpu_forward_and_backward() {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        // The paper's network both ways, and mip-NeRF's integrated encoding.
        for (view, paper_form, integrated, moving) in [
            (true, false, false, false),
            (false, true, false, false),
            (true, false, true, false),
            (true, false, false, true),
            (false, true, false, true),
        ] {
            let config = VanillaConfig {
                depth: 4,
                width: 16,
                skip: Some(1),
                position_encoding: FrequencyEncoding {
                    frequencies: 6,
                    paper_form,
                },
                direction_encoding: view.then_some(FrequencyEncoding {
                    frequencies: 2,
                    paper_form,
                }),
                view_width: 8,
                deformation: moving.then_some(DeformationConfig {
                    depth: 3,
                    width: 8,
                    skip: Some(1),
                    time_frequencies: 4,
                }),
            };
            let net = VanillaNet::new(config, "fine.");
            let mut rng = Rng::new(4);
            // Random weights everywhere, the deformation's last layer included (a fresh
            // one starts at zero, which would leave its gradient below untested).
            let params: Vec<f32> = (0..net.num_params())
                .map(|_| rng.range(-0.4, 0.4))
                .collect();
            let (rays, spr) = (16, 6);
            let n = rays * spr;
            let times: Vec<f32> = match moving {
                true => (0..n)
                    .map(|s| if s % 6 == 0 { 0.0 } else { rng.uniform() })
                    .collect(),
                false => Vec::new(),
            };
            let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.5, 1.5)).collect();
            let ray_dirs: Vec<f32> = (0..rays)
                .flat_map(|_| {
                    let d = [
                        rng.range(-1.0, 1.0),
                        rng.range(-1.0, 1.0),
                        rng.range(0.2, 1.0),
                    ];
                    crate::math::scale(d, 1.0 / crate::math::length(d))
                })
                .collect();
            let d_sigma: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
            let d_rgb: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
            // Frustums from much finer than the highest frequency to coarser than a few.
            let var: Vec<f32> = if integrated {
                (0..n * 3)
                    .map(|_| 10f32.powf(rng.range(-6.0, -1.0)))
                    .collect()
            } else {
                Vec::new()
            };
            let mut ws = VanillaWorkspace::default();
            let input = FieldInput {
                positions: &pos,
                dirs: &ray_dirs,
                samples_per_dir: spr,
                appearance: &[],
                footprints: &[],
                variances: &var,
                times: &times,
            };
            let out = net.forward(&params, input, &mut ws);
            let (want_sigma, want_rgb) = (out.sigma.to_vec(), out.rgb.to_vec());
            let mut grads = GradBuffer::new(net.num_params());
            net.backward(
                &params,
                &mut ws,
                FieldGrad {
                    d_sigma: &d_sigma,
                    d_rgb: &d_rgb,
                },
                &mut grads.all(),
            );

            let base = 5;
            let mut all = vec![0.5; base];
            all.extend_from_slice(&params);
            for path in [Path::Plain, Path::Tiled, Path::Blocked, Path::Wide] {
                let gpu = Gpu {
                    matmul: path,
                    ..gpu.clone()
                };
                let gn = GpuVanillaNet::new(&net, base, all.len());
                let dirs: Vec<f32> = (0..n)
                    .flat_map(|s| ray_dirs[3 * (s / spr)..][..3].to_vec())
                    .collect();
                let p = gpu.upload(&all);
                let g = gpu.zeros(all.len());
                let var_h = integrated.then(|| gpu.upload(&var));
                let times_h = moving.then(|| gpu.upload(&times));
                let (pos_h, dirs_h) = (gpu.upload(&pos), gpu.upload(&dirs));
                let codes = SampleCodes::all(&gpu, crate::stage::MEAN_APPEARANCE);
                let input = DeviceInput {
                    positions: &pos_h,
                    dirs: &dirs_h,
                    codes: &codes,
                    footprints: None,
                    variances: var_h.as_ref(),
                    moments: DeviceMoments::each_if_any(times_h.as_ref()),
                    n,
                };
                let acts = gn.forward(&gpu, &p, &input);
                gn.backward(
                    &gpu,
                    &p,
                    &g,
                    &acts,
                    &gpu.upload(&d_sigma),
                    &gpu.upload(&d_rgb),
                );
                let sigma = gpu.read(&acts.sigma, n).expect("read");
                let rgb = gpu.read(&acts.rgb, n * 3).expect("read");
                let got = gpu.read(&g, all.len()).expect("read");
                assert!(
                    worst(&sigma, &want_sigma) < 1e-4,
                    "sigma {}",
                    worst(&sigma, &want_sigma)
                );
                assert!(
                    worst(&rgb, &want_rgb) < 1e-4,
                    "rgb {}",
                    worst(&rgb, &want_rgb)
                );
                assert!(got[..base].iter().all(|&v| v == 0.0), "outside the net");
                for t in &net.layout.tensors {
                    let r = t.range();
                    let e = worst(&got[base + r.start..base + r.end], &grads.values[r]);
                    // The deformation's gradients come through the encoding's derivative,
                    // whose factors reach 2^(L-1) pi: rounding grows by as much.
                    let tolerance = if t.name.contains("time_") { 1e-3 } else { 1e-4 };
                    assert!(e < tolerance, "gradient of {} (view {view}): {e}", t.name);
                }
                // Densities alone (through the deformation at one moment where it moves),
                // as the CPU net's density query.
                let moment = moving.then_some(0.3);
                let mut want = vec![0.0; n];
                net.density_at(&params, &pos, moment, &mut ws, &mut want);
                let at = DeviceMoments::At(moment.unwrap_or(0.0));
                let alone = gpu.read(&gn.density(&gpu, &p, &pos_h, at, n), n);
                let e = worst(&alone.expect("read"), &want);
                assert!(
                    e < 1e-4,
                    "density alone (view {view}, moving {moving}): {e}"
                );
            }
        }
    }
}
