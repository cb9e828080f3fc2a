//! The GPU engine: kernels written once in CubeCL and run through its `wgpu` runtime
//! (Vulkan, Metal, DX12; `cuda` behind the cargo feature of that name). Each kernel is
//! tested against the CPU engine's stage on the same inputs, on Mesa's lavapipe in CI.
//!
//! * [`open`]: which adapter (`--device`), with a clear error when the one asked for is
//!   missing; [`device`]: opening one, and what it can do (float atomics);
//! * [`engine`]: [`engine::GpuEngine`], the fast model's training step, rendering and
//!   density queries with parameters, gradients, Adam's moments and the occupancy grid on
//!   the device; [`vanilla`]: [`vanilla::GpuVanillaEngine`], the paper's model; [`params`]:
//!   the trainable state both keep on the device;
//! * [`vanilla_net`]: the paper's network forward and backward, its [`trunk`] shared with
//!   [`deformation`], D-NeRF's deformation before it; [`importance`]: its importance samples drawn from the coarse
//!   weights and packed for the fine pass;
//! * [`march`]: occupancy-grid marching with sample compaction (count, prefix sum, budget
//!   cut, packed write), for training steps and rendering rounds; [`occupancy`]: the
//!   grid's refresh;
//! * [`field`]: the fast field forward and backward, built from [`hash_grid`] (the
//!   multiresolution hash encoding; gradients scattered with float atomics, or a
//!   compare-and-swap loop where the adapter has none) and [`mlp`] (dense layers);
//!   [`fused`]: the same field's inference in one kernel per batch, for rendering and
//!   density queries (`NERF_GPU_FIELD=fused`), and with [`fused_backward`] its training
//!   forward and backward (`NERF_GPU_TRAIN=fused`); [`codes`]: per-photo appearance codes;
//!   [`antialias`]: sample footprints and the hash grid's level weights; [`harmonics`]: the
//!   view direction's spherical harmonics; [`space_time_grid`]: a moving field's encoding
//!   of space and time, and [`time_smoothness`]: its prior of smooth change in time;
//!   [`pose_grad`]: the samples' gradients carried back to their rays, for camera
//!   refinement, and [`camera_poses`]: the corrected cameras and each camera's gradient;
//! * [`volume`]: compositing over packed samples, forward and backward, one thread per ray;
//! * [`render`]: rendering in rounds (march, field, accumulate) with early termination;
//! * [`loss`]: the squared error per ray and its gradient; [`distortion`]: the distortion
//!   loss's gradient per ray; [`depth_smoothness`]: RegNeRF's depth smoothness on
//!   patches of rays from unseen poses;
//! * [`adam`]: the optimiser step over the whole parameter vector (lazy for hash tables);
//! * [`finite`]: counting non-finite gradients before the optimiser runs;
//! * [`rays`]: training rays made from pixel indices, with the images and cameras on the
//!   device (lens distortion through per-lens tables);
//! * [`launch`]: launch grids and host/device copies.
//!
//! Not on the device: the paper's model's stratified coarse samples, mip-NeRF's frustums
//! and rendering's fine samples (made on the host, uploaded; rendering's measured faster
//! there), the uniform draws of its importance samples, and the random choice of each
//! training ray's pixel (drawn on the host so both engines train on the same rays and
//! samples; 6 words a ray go up).

pub mod adam;
pub mod antialias;
pub mod camera_poses;
pub mod codes;
pub mod deformation;
pub mod depth_smoothness;
pub mod device;
pub mod device_field;
pub mod distortion;
pub mod engine;
pub mod field;
pub mod finite;
pub mod fused;
pub mod fused_backward;
pub mod gemm;
mod gemm_cmma;
mod gemm_epilogue;
mod gemm_wide;
pub mod harmonics;
pub mod hash_grid;
pub mod importance;
pub mod launch;
pub mod loss;
pub mod march;
pub mod mlp;
pub mod occupancy;
pub mod params;
pub mod pose_grad;
pub mod rays;
pub mod render;
pub mod space_time_grid;
pub mod time_smoothness;
pub mod trace;
pub mod trunk;
pub mod vanilla;
pub mod vanilla_net;
pub mod volume;

use crate::engine::{caps, Device, Engine, EngineOptions};
use crate::error::{NerfError, Result};
use crate::model::ModelConfig;

/// The GPU engine for `model` on `device` (`Auto`: CUDA, then a hardware wgpu adapter,
/// else the CPU engine); both models have one.
pub fn open(
    device: Device,
    model: &ModelConfig,
    options: EngineOptions,
    seed: u64,
) -> Result<Box<dyn Engine>> {
    // What the GPU engine does not run yet (`caps`): `auto` takes the CPU (the trainer
    // has said so: `train::defaults::engine_for`), an asked-for GPU refuses by name.
    let refusal = caps::refusal(caps::EngineKind::Gpu, model);
    if refusal.is_some() && device == Device::Auto {
        return Ok(super::open(model, options, seed));
    }
    let gpu = match device {
        Device::Cpu => return Ok(super::open(model, options, seed)),
        Device::Wgpu => device::Gpu::wgpu()?,
        Device::Cuda => device::Gpu::cuda()?,
        Device::Auto => match device::Gpu::cuda().ok().or_else(device::Gpu::wgpu_hardware) {
            Some(gpu) => gpu,
            None => return Ok(super::open(model, options, seed)),
        },
    };
    if let Some(why) = refusal {
        return Err(NerfError::Device(why));
    }
    match model {
        ModelConfig::Fast(config) if config.batch_samples > engine::MAX_DEVICE_SAMPLES => {
            Err(NerfError::Config(format!(
                "--samples {}: the GPU engine takes at most {} samples a step (more would \
                 overflow the adapter's largest storage buffer); lower --samples or use \
                 --device cpu",
                config.batch_samples,
                engine::MAX_DEVICE_SAMPLES
            )))
        }
        ModelConfig::Fast(config) => Ok(Box::new(engine::GpuEngine::new(
            gpu,
            config.clone(),
            options,
            seed,
        ))),
        ModelConfig::Vanilla(config) => Ok(Box::new(vanilla::GpuVanillaEngine::new(
            gpu,
            config.clone(),
            options,
            seed,
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FastModelConfig;

    #[test]
    fn a_step_larger_than_the_device_takes_is_refused() {
        if device::test_gpu().is_none() {
            return;
        }
        let config = FastModelConfig {
            batch_samples: engine::MAX_DEVICE_SAMPLES * 2,
            ..FastModelConfig::default()
        };
        let Err(e) = open(
            Device::Wgpu,
            &ModelConfig::Fast(config),
            EngineOptions {
                adam: crate::nn::adam::AdamConfig::default(),
                chunk_rays: 64,
                check_finite: false,
            },
            0,
        ) else {
            panic!("a step of 2^20 samples was accepted");
        };
        let text = e.to_string();
        assert!(
            text.contains("--samples 1048576") && text.contains("524288"),
            "{text}"
        );
    }
}
