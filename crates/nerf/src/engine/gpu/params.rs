//! A model's trainable state on the device: parameters, their gradient buffer and Adam's
//! moments, with the end of every training step (refuse a diverged step, else one Adam
//! update) and the host copies checkpoints need. Both GPU engines keep theirs here.

use cubecl::server::Handle;

use super::adam;
use super::device::Gpu;
use super::finite::add_nonfinite;
use crate::engine::EngineState;
use crate::error::{NerfError, Result};
use crate::model::UpdateRule;
use crate::nn::adam::{Adam, AdamConfig, DirtyStep};
use crate::stage::finite::FiniteCheck;
use crate::stage::RayOutput;

pub struct DeviceParams {
    pub n: usize,
    pub values: Handle,
    /// Gradients of the summed squared error; Adam clears them.
    pub grads: Handle,
    m: Handle,
    v: Handle,
    /// Adam's configuration and step count (its moments are `m` and `v`).
    adam: Adam,
}

impl DeviceParams {
    pub fn new(gpu: &Gpu, init: &[f32], adam: AdamConfig) -> Self {
        let n = init.len();
        DeviceParams {
            n,
            values: gpu.upload(init),
            grads: gpu.zeros(n),
            m: gpu.zeros(n),
            v: gpu.zeros(n),
            adam: Adam::new(adam, 0),
        }
    }

    /// Ends step `step` (0-based) whose squared errors are the first `rays` floats of
    /// `errors` (their sum, via `scale`, is the mean loss): one Adam update under `rule`,
    /// refused (gradients cleared; parameters, moments and Adam's step count untouched) when
    /// an error or a gradient is not finite. The update is queued behind the device's count
    /// of non-finite values, and the errors and the count come back in one read after it,
    /// so the device runs the check and the update without waiting for the host. Returns
    /// the summed squared error, added in ray order in `f64`. The rule's group (camera
    /// corrections) learns at `group_lr`.
    #[allow(clippy::too_many_arguments)]
    pub fn finish_step(
        &mut self,
        gpu: &Gpu,
        step: u64,
        errors: &Handle,
        rays: usize,
        (lr, group_lr): (f32, f32),
        scale: f32,
        rule: UpdateRule,
    ) -> Result<f64> {
        let nonfinite = gpu.upload_u32(&[0]);
        add_nonfinite(gpu, errors, rays, &nonfinite);
        add_nonfinite(gpu, &self.grads, self.n, &nonfinite);
        let counted_before = self.adam.t;
        let update = self.adam.begin_step(lr);
        adam::step(
            gpu,
            &self.adam.config,
            update,
            self.adam.step_at(group_lr),
            DirtyStep {
                scale,
                lazy_end: rule.lazy_end,
                table_decay: rule.table_decay,
                weight_decay: rule.weight_decay,
                group: rule.group_start.map(|at| (at, group_lr)),
            },
            self.n,
            &self.values,
            &self.m,
            &self.v,
            &self.grads,
            &nonfinite,
        );
        let (errors, bad) = gpu.read_with_count(errors, rays, &nonfinite)?;
        let sse: f64 = errors.iter().map(|&e| e as f64).sum();
        if bad > 0 {
            self.adam.t = counted_before;
            self.clear_grads(gpu);
            let loss = (sse * scale as f64) as f32;
            // A finite loss means every error was finite: the count is the gradients'.
            return Err(crate::engine::diverged(step, loss, Some(bad as usize)));
        }
        Ok(sse)
    }

    pub fn clear_grads(&mut self, gpu: &Gpu) {
        self.grads = gpu.zeros(self.n);
    }

    /// Host copies, with the model's non-trainable `buffers`. A failed read (a lost
    /// device) is reported once and reads as NaN, which a checkpoint refuses to save.
    pub fn state(&self, gpu: &Gpu, buffers: Vec<f32>) -> EngineState {
        let read = |h: &Handle| {
            gpu.read(h, self.n).unwrap_or_else(|e| {
                report_device_failure(&e);
                vec![f32::NAN; self.n]
            })
        };
        EngineState {
            params: read(&self.values),
            adam_m: read(&self.m),
            adam_v: read(&self.v),
            adam_t: self.adam.t,
            buffers,
        }
    }

    /// Replaces the state from host copies, checking the sizes (`buffers` values of the
    /// model's own buffers expected).
    pub fn set_state(&mut self, gpu: &Gpu, state: &EngineState, buffers: usize) -> Result<()> {
        let n = self.n;
        state.check_fits(n, buffers)?;
        self.values = gpu.upload(&state.params);
        self.m = gpu.upload(&state.adam_m);
        self.v = gpu.upload(&state.adam_v);
        self.grads = gpu.zeros(n);
        self.adam.t = state.adam_t;
        Ok(())
    }
}

/// NERF_CHECK_FINITE on the device: reads `n` floats of `h` back and checks them.
pub fn check_device(
    gpu: &Gpu,
    check: &FiniteCheck,
    stage: &'static str,
    buffer: &'static str,
    h: &Handle,
    n: usize,
) -> Result<()> {
    if check.enabled() {
        check.check(stage, buffer, &gpu.read(h, n)?);
    }
    Ok(())
}

/// Rendering and density queries cannot return an error through the engine seam: a failed
/// device read is reported once on stderr and its values come back as NaN.
pub fn report_device_failure(e: &NerfError) {
    static SAID: std::sync::Once = std::sync::Once::new();
    SAID.call_once(|| eprintln!("error: {e}; the affected values are NaN"));
}

/// Rays whose device work failed: reported (once) and NaN.
pub fn fail_rays(e: &NerfError, out: &mut [RayOutput]) {
    report_device_failure(e);
    out.fill(RayOutput {
        rgb: [f32::NAN; 3],
        depth: f32::NAN,
        opacity: f32::NAN,
    });
}

/// Density queries in device calls of at most `chunk` points, `query` answering one;
/// a failed call's densities are NaN (reported once).
pub fn density_in_chunks(
    positions: &[f32],
    out: &mut [f32],
    chunk: usize,
    query: impl Fn(&[f32], &mut [f32]) -> Result<()>,
) {
    assert_eq!(positions.len(), out.len() * 3);
    for (p, o) in positions.chunks(chunk * 3).zip(out.chunks_mut(chunk)) {
        if let Err(e) = query(p, o) {
            report_device_failure(&e);
            o.fill(f32::NAN);
        }
    }
}
