//! A GPU adapter through CubeCL's `wgpu` runtime, and what it can do.

use cubecl::client::Client;
use cubecl::device::WgpuDeviceKind;
use cubecl::ir::{ElemType, FloatKind, Type};

use crate::error::{NerfError, Result};

/// An opened adapter.
#[derive(Clone)]
pub struct Gpu {
    pub client: Client,
    /// How the adapter was found, for messages (`Wgpu(WgpuDevice { .. })`).
    pub name: String,
    /// Whether the adapter adds `f32` atomically in hardware; without it, gradients are
    /// scattered with a compare-and-swap loop on their bits.
    pub float_atomics: bool,
}

impl Gpu {
    /// The default Vulkan adapter (a discrete GPU before an integrated one before a
    /// software one such as lavapipe; `CUBECL_WGPU_DEFAULT_DEVICE` overrides).
    pub fn vulkan() -> Result<Gpu> {
        let device = cubecl::Device::vulkan(WgpuDeviceKind::default()).map_err(|e| {
            NerfError::Device(format!(
                "no Vulkan GPU adapter ({e}); install your GPU's Vulkan driver, or Mesa's \
                 lavapipe for a software one (Debian/Ubuntu: apt-get install mesa-vulkan-drivers)"
            ))
        })?;
        let client = device.client();
        let f32_atomic = Type::atomic(ElemType::Float(FloatKind::F32));
        let float_atomics = client
            .features()
            .atomic_type_usage(f32_atomic)
            .contains(cubecl::ir::features::AtomicUsage::Add);
        Ok(Gpu {
            client,
            name: format!("{device:?}"),
            float_atomics,
        })
    }
}

/// The adapter for a GPU test, or `None` (with the reason printed) where there is none.
#[cfg(test)]
pub fn test_gpu() -> Option<Gpu> {
    Gpu::vulkan()
        .map_err(|e| eprintln!("skipping the GPU kernel test: {e}"))
        .ok()
}
