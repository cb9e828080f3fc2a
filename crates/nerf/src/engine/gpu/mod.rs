//! The GPU engine, under construction (issue 12): kernels written once in CubeCL and run
//! through its `wgpu` runtime (Vulkan, Metal, DX12). Each kernel is tested against the CPU
//! engine's stage on the same inputs, on Mesa's lavapipe in CI.
//!
//! Here so far:
//! * [`device`]: opening an adapter, with a clear error when there is none, and what it
//!   can do (float atomics);
//! * [`hash_grid`]: the multiresolution hash encoding, forward and backward (gradients
//!   scattered with float atomics, or a compare-and-swap loop where the adapter has none);
//! * [`volume`]: compositing over packed samples, forward and backward, one thread per ray;
//! * [`loss`]: the squared error per ray and its gradient;
//! * [`adam`]: the optimiser step over the whole parameter vector (lazy for hash tables).
//!
//! Still to come before `engine::open` can hand out a GPU engine: ray generation, marching
//! with compaction, the fused MLPs and the occupancy refresh, then the engine that strings
//! the kernels into a step with its data on the device.

pub mod adam;
pub mod device;
pub mod engine;
pub mod field;
pub mod finite;
pub mod hash_grid;
pub mod launch;
pub mod loss;
pub mod mlp;
pub mod volume;

use crate::engine::{Device, Engine, EngineOptions};
use crate::error::{NerfError, Result};
use crate::model::ModelConfig;

/// The GPU engine for `model` on `device` (`Auto`: CUDA, then a hardware wgpu adapter,
/// else the CPU engine).
pub fn open(
    device: Device,
    model: &ModelConfig,
    options: EngineOptions,
    seed: u64,
) -> Result<Box<dyn Engine>> {
    let gpu = match device {
        Device::Cpu => return Ok(super::open(model, options, seed)),
        Device::Wgpu => device::Gpu::wgpu()?,
        Device::Cuda => device::Gpu::cuda()?,
        Device::Auto => match device::Gpu::cuda().ok().or_else(device::Gpu::wgpu_hardware) {
            Some(gpu) => gpu,
            None => return Ok(super::open(model, options, seed)),
        },
    };
    match model {
        ModelConfig::Fast(config) => Ok(Box::new(engine::GpuEngine::new(
            gpu,
            config.clone(),
            options,
            seed,
        ))),
        // Auto keeps such a model on the CPU; asking for a GPU by name is an error.
        ModelConfig::Vanilla(_) if device == Device::Auto => Ok(super::open(model, options, seed)),
        ModelConfig::Vanilla(_) => Err(NerfError::Device(format!(
            "the paper's (vanilla) model has no GPU engine yet; train it with --device cpu \
             (found {})",
            gpu.name
        ))),
    }
}
