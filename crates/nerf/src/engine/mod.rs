//! The engine seam: everything above it (the trainer, checkpoints, evaluation, view
//! rendering, meshes, the CLI) talks to a model through [`Engine`], one step or one batch
//! of rays at a time, and never sees its parameters' home or its kernels.
//!
//! An engine owns a model's parameters, optimiser state and buffers (a GPU engine keeps them
//! on the device) and runs whole stages: a training step, rendering a [`RayBatch`], density
//! queries. State crosses the seam only as host copies ([`EngineState`]) for checkpoints,
//! so every engine reads and writes the same checkpoint files. [`cpu::CpuEngine`] is the
//! reference engine; `gpu::engine::GpuEngine` (feature `wgpu`) is the second, and
//! [`open_on`] picks one for a [`Device`]. [`caps`] says which features each one runs.

pub mod caps;
pub mod cpu;
#[cfg(feature = "wgpu")]
pub mod gpu;

use serde::{Deserialize, Serialize};

use crate::camera::ray_space::RaySpace;
use crate::camera::Camera;
use crate::data::pixels::PixelSampling;
use crate::data::Dataset;
use crate::error::Result;
use crate::model::ModelConfig;
use crate::nn::adam::AdamConfig;
use crate::nn::ParamLayout;
use crate::stage::{Appearance, RayBatch, RayOutput};

/// How an engine is set up for a run.
#[derive(Clone, Copy, Debug)]
pub struct EngineOptions {
    pub adam: AdamConfig,
    /// Rays per work unit (bounds a thread's activation memory).
    pub chunk_rays: usize,
    /// Check every stage's outputs and gradients for NaN / infinity during training
    /// (`NERF_CHECK_FINITE`, see `stage::finite`).
    pub check_finite: bool,
}

/// One training step, as the trainer schedules it.
#[derive(Clone, Copy, Debug)]
pub struct StepSpec {
    /// Which rays the step draws (seed, step, crop, background).
    pub sampling: PixelSampling,
    pub lr: f32,
    /// Vanilla model: rays per step (the fast model fixes samples per step in its config).
    pub batch_rays: usize,
    /// How far through its schedule the run is, in [0, 1].
    pub progress: f32,
    /// Learning rate of the camera corrections (models that refine cameras).
    pub camera_lr: f32,
    /// Only the camera corrections learn; the field and its buffers (the occupancy grid)
    /// stay as they are (fitting test cameras to a trained model, `nerf eval
    /// --refine-test-poses`).
    pub frozen_field: bool,
}

/// What one step did.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct StepStats {
    /// Steps completed, this one included.
    pub step: u64,
    /// coarse MSE + fine MSE (the paper's loss).
    pub loss: f32,
    /// PSNR of the final (fine, else coarse) pass on this batch.
    pub psnr: f32,
    pub lr: f32,
    /// Rays and field samples in the step.
    pub rays: usize,
    pub samples: usize,
}

/// An engine's state as host copies: what a checkpoint holds besides the step.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EngineState {
    pub params: Vec<f32>,
    pub adam_m: Vec<f32>,
    pub adam_v: Vec<f32>,
    /// Adam steps taken.
    pub adam_t: u64,
    /// Non-trainable buffers (the occupancy grid), laid out by `buffer_layout`.
    pub buffers: Vec<f32>,
}

impl EngineState {
    /// Refuses a state whose sizes do not fit a model of `params` parameters and `buffers`
    /// buffer values (a checkpoint of another model), before anything is replaced.
    pub fn check_fits(&self, params: usize, buffers: usize) -> Result<()> {
        let n = params;
        if self.params.len() != n
            || self.adam_m.len() != n
            || self.adam_v.len() != n
            || self.buffers.len() != buffers
        {
            return Err(crate::error::NerfError::Config(format!(
                "state does not fit this model: {n} parameters and {buffers} buffer values \
                 expected, got {} and {}",
                self.params.len(),
                self.buffers.len()
            )));
        }
        Ok(())
    }
}

/// The error of step `step` (0-based) whose loss or gradients are not finite: `loss`, and
/// what is known of the gradients (`Some(k)`: `k` of them are not finite; `None`: some).
pub fn diverged(step: u64, loss: f32, bad_gradients: Option<usize>) -> crate::error::NerfError {
    let what = if !loss.is_finite() {
        format!("the loss is {loss}")
    } else {
        match bad_gradients {
            Some(k) => format!("{k} gradients are not finite (the loss was a finite {loss})"),
            None => format!("the gradients hold non-finite values (the loss was a finite {loss})"),
        }
    };
    crate::error::NerfError::Diverged {
        step: step + 1,
        what,
    }
}

/// Rays per [`Engine::render_rays`] call of a whole view, unless the engine takes more.
pub const RENDER_SLAB: usize = 1 << 16;

/// Rays per call of a caller that checks for cancellation between calls, unless the engine
/// takes more: a few milliseconds of a CPU's work.
pub const INTERACTIVE_SLAB: usize = 4096;

/// A camera's pixels to render, for an engine that casts their rays itself
/// ([`Engine::render_pixels`]); `views::render_pixels` makes the same rays on the host.
pub struct PixelRays<'a> {
    pub camera: &'a Camera,
    /// Row-major pixel indices.
    pub pixels: std::ops::Range<usize>,
    pub space: RaySpace,
    pub near: f32,
    pub far: f32,
    pub background: [f32; 3],
    pub appearance: Appearance,
    /// The moment a moving field is seen at (`None`: moment 0, as `RayBatch::times`).
    pub time: Option<f32>,
}

/// A model behind an engine.
pub trait Engine: Send + Sync {
    /// Which engine and device, for logs ("cpu, 2 threads").
    fn describe(&self) -> String;

    /// Which engine this is (what it runs: `caps`).
    fn kind(&self) -> caps::EngineKind;

    fn model_config(&self) -> &ModelConfig;

    /// Names and shapes of the parameters, in checkpoint order.
    fn param_layout(&self) -> &ParamLayout;

    /// Names and shapes of the non-trainable buffers.
    fn buffer_layout(&self) -> ParamLayout;

    /// One optimisation step on rays drawn from `data` (the same dataset every step: an
    /// engine may keep it on its device); `spec.sampling.step` is the index of the step
    /// (steps done so far). Fails, leaving the state untouched, when the loss or a gradient
    /// is not finite.
    fn train_step(&mut self, data: &Dataset, spec: &StepSpec) -> Result<StepStats>;

    /// Renders `rays` into `out` (one per ray); `on_progress` gets the rays done so far.
    fn render_rays(
        &self,
        rays: &RayBatch,
        out: &mut [RayOutput],
        on_progress: &(dyn Fn(usize) + Sync),
    );

    /// Renders `pixels` into `out` (one per pixel), casting their rays itself; false,
    /// leaving `out` as it was, where this engine does not (then the caller makes the rays
    /// and calls [`render_rays`](Self::render_rays)).
    fn render_pixels(&self, _pixels: &PixelRays, _out: &mut [RayOutput]) -> bool {
        false
    }

    /// Rays a whole view hands to [`render_rays`](Self::render_rays) at a time: bounds the
    /// memory of big views (a 4K frame is 8 M rays) while keeping the device busy.
    fn render_slab(&self) -> usize {
        RENDER_SLAB
    }

    /// Rays per call for a caller that checks between calls whether to stop (the viewer,
    /// whose camera moves on): as few as keep this engine efficient. A GPU takes its
    /// rendering chunk, a whole view: its every call waits on the device several times.
    fn interactive_slab(&self) -> usize {
        INTERACTIVE_SLAB
    }

    /// Views worth rendering at once (`views::render_views`), each on a thread of its own:
    /// more than one where a view's host work (waiting for the device, laying out its
    /// pixels) would otherwise leave the device idle. The CPU engine's views already
    /// take every core.
    fn views_in_flight(&self) -> usize {
        1
    }

    /// Densities at world `positions` (`n x 3`) into `out` (`n`), at moment `time` of a
    /// moving scene (`None`: any moment; still scenes ignore it).
    fn density(&self, positions: &[f32], time: Option<f32>, out: &mut [f32]);

    /// Host copies of the state.
    fn state(&self) -> EngineState;

    /// Replaces the state (sizes must match the layouts).
    fn set_state(&mut self, state: EngineState) -> Result<()>;

    /// Fraction of the scene box marked occupied, for models that skip empty space.
    fn occupancy(&self) -> Option<f64>;

    /// Fraction of gradient blocks the last step wrote (the rest skipped the optimiser).
    fn touched_fraction(&self) -> f64;
}

/// Which device an engine runs on (the command line's `--device`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Device {
    /// A hardware GPU if there is one (CUDA, then Vulkan/Metal/DX12), else the CPU.
    #[default]
    Auto,
    /// The CPU engine, on all cores.
    Cpu,
    /// The GPU engine through wgpu (Vulkan, Metal, DX12), any adapter, software ones
    /// such as Mesa's lavapipe included.
    Wgpu,
    /// The GPU engine on an NVIDIA GPU through CUDA.
    Cuda,
}

impl std::fmt::Debug for dyn Engine + '_ {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Engine({})", self.describe())
    }
}

/// The command line's `--device`, shared by every command that runs a model.
#[derive(Clone, Copy, Debug, Default, clap::Args)]
pub struct DeviceArg {
    /// Where the model runs: `auto` (a hardware GPU if there is one: CUDA, then Vulkan /
    /// Metal / DX12; else the CPU), `cpu`, `wgpu` (any wgpu adapter, software ones such as
    /// lavapipe included) or `cuda`. Checkpoints are the same files on every device.
    #[arg(long, value_enum, default_value = "auto")]
    pub device: Device,
}

/// The CPU engine for `model`, with fresh weights from `seed`.
pub fn open(model: &ModelConfig, options: EngineOptions, seed: u64) -> Box<dyn Engine> {
    cpu::open(model, options, seed)
}

/// The engine for `model` on `device`, with fresh weights from `seed` (the same weights on
/// every device). Fails when the device asked for is missing, saying what was looked for;
/// `Auto` falls back to the CPU.
pub fn open_on(
    device: Device,
    model: &ModelConfig,
    options: EngineOptions,
    seed: u64,
) -> Result<Box<dyn Engine>> {
    match device {
        Device::Cpu => Ok(open(model, options, seed)),
        #[cfg(feature = "wgpu")]
        Device::Wgpu | Device::Cuda | Device::Auto => gpu::open(device, model, options, seed),
        #[cfg(not(feature = "wgpu"))]
        Device::Auto => Ok(open(model, options, seed)),
        #[cfg(not(feature = "wgpu"))]
        Device::Wgpu | Device::Cuda => Err(crate::error::NerfError::Device(format!(
            "this build has no GPU engine (built without the `wgpu` feature); rebuild with \
             default features to use --device {}",
            if device == Device::Wgpu {
                "wgpu"
            } else {
                "cuda"
            }
        ))),
    }
}

/// Whether `--device auto` finds a hardware GPU here (probes the adapters, as opening one
/// does): CUDA, else a wgpu adapter that is not a software one.
pub fn hardware_gpu_present() -> bool {
    #[cfg(feature = "wgpu")]
    {
        gpu::device::Gpu::cuda().is_ok() || gpu::device::Gpu::wgpu_hardware().is_some()
    }
    #[cfg(not(feature = "wgpu"))]
    false
}

/// Why a run opened on `device` runs on the CPU engine although this machine has a GPU:
/// the features of `model` the GPU engine does not run yet (`caps`). `None` when the run
/// is on the GPU, was sent to the CPU by name, or this machine has no GPU.
pub fn cpu_fallback_note(
    device: Device,
    engine: &dyn Engine,
    model: &ModelConfig,
) -> Option<String> {
    if device != Device::Auto || engine.kind() != caps::EngineKind::Cpu {
        return None;
    }
    let missing = caps::EngineKind::Gpu.missing(model);
    if missing.is_empty() || !hardware_gpu_present() {
        return None;
    }
    Some(format!(
        "on the CPU engine: {} {} not run on the GPU engine yet",
        caps::list(&missing),
        if missing.len() == 1 { "does" } else { "do" }
    ))
}

/// Renders `rays` into `out` in chunks of `chunk` rays, in parallel, `render_chunk` doing
/// one chunk; `on_progress` hears how many rays are done after each chunk. Every engine's
/// `render_rays` is this loop around its own chunk renderer.
pub fn render_in_chunks(
    rays: &RayBatch,
    out: &mut [RayOutput],
    chunk: usize,
    on_progress: &(dyn Fn(usize) + Sync),
    render_chunk: impl Fn(&RayBatch, &mut [RayOutput]) + Sync,
) {
    use rayon::prelude::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let chunk = chunk.max(1);
    let done = AtomicUsize::new(0);
    out[..rays.len()]
        .par_chunks_mut(chunk)
        .enumerate()
        .for_each(|(c, out)| {
            let part = rays.slice(c * chunk..c * chunk + out.len());
            render_chunk(&part, out);
            on_progress(done.fetch_add(out.len(), Ordering::Relaxed) + out.len());
        });
}
