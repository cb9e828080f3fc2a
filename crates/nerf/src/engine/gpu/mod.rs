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
pub mod field;
pub mod hash_grid;
pub mod launch;
pub mod loss;
pub mod mlp;
pub mod volume;
