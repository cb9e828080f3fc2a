//! A GPU adapter through CubeCL's `wgpu` runtime, and what it can do.

use cubecl::client::Client;
use cubecl::device::WgpuDeviceKind;
use cubecl::ir::{ElemType, FloatKind, Type};

use crate::error::{NerfError, Result};
use crate::step_clock;

/// Which kernels the dense layers run (`mlp`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Path {
    /// One thread per output value, a dot product from global memory.
    Plain,
    /// Products in 16 x 16 tiles through workgroup memory, an output a thread (`gemm`).
    Tiled,
    /// The same with a block of outputs a thread (`gemm`'s blocked kernel).
    Blocked,
    /// Up to 8 x 8 outputs a thread read through `vec4`s (`gemm_wide`) for layers wider
    /// than 32, the blocked kernel for narrower ones.
    Wide,
    /// Tensor cores (`gemm_cmma`: `f16` operands, `f32` sums) for the forward products of
    /// layers wider than 32, where the adapter has them; the gradients' products are wide.
    Cmma,
}

/// An opened adapter.
#[derive(Clone)]
pub struct Gpu {
    pub client: Client,
    /// The runtime and the adapter's name, for messages (`wgpu/vulkan: llvmpipe (LLVM 15.0.6, 256 bits) (software)`).
    pub name: String,
    /// A software adapter (lavapipe, llvmpipe, WARP): correct, but slower than the CPU
    /// engine.
    pub software: bool,
    /// The dense layers' kernels: wide products, the fastest measured on a hardware GPU
    /// and on lavapipe alike (docs/benchmarks.md);
    /// `NERF_GPU_MATMUL=plain|tiled|blocked|wide|cmma` overrides, for measuring.
    pub matmul: Path,
    /// Whether the adapter adds `f32` atomically in hardware; without it, gradients are
    /// scattered with a compare-and-swap loop on their bits.
    pub float_atomics: bool,
    /// Whether rendering and density queries evaluate the fast field in one kernel per
    /// batch (`fused`) rather than layer by layer: off unless `NERF_GPU_FIELD=fused`, since
    /// on a data-centre GPU it rendered no faster than the layers while marching rounds
    /// set the pace, and its compilation delays the first frame (docs/benchmarks.md).
    pub fused_field: bool,
    /// Whether training runs the fast field's networks in one forward and one backward
    /// kernel per batch (`fused`, `fused_backward`; the weights' gradients stay products):
    /// off unless `NERF_GPU_TRAIN=fused`, until a GPU's measurement chooses.
    pub fused_training: bool,
    /// Consecutive samples a thread of the hash grid's backward takes (`hash_grid`), its
    /// sums kept while they share a cell; `NERF_GPU_GRID_RUN` overrides, for measuring.
    pub grid_run: usize,
    /// Whether the adapter multiplies 16 x 16 x 16 `f16` matrices into `f32` on warps of
    /// [`WARP`] threads (cooperative matrices: a `spirv` build on a GPU with tensor cores).
    pub tensor_cores: bool,
}

/// See [`Gpu::grid_run`].
pub const GRID_RUN: usize = 8;

/// Threads a warp (plane) as the tensor-core kernel takes them.
pub const WARP: u32 = 32;

/// Kernels CubeCL's wgpu runtime queues before it hands them to the device in one
/// submission (its own default is 32). Smaller batches start the device sooner while the
/// host is still queueing a step's later kernels: with 16, the fastest of 4, 8, 16, 32 and
/// 128 on a data-centre GPU (docs/benchmarks.md). `CUBECL_WGPU_MAX_TASKS` overrides, for
/// measuring.
pub const TASKS_PER_SUBMISSION: usize = 8;

/// Opens the wgpu runtime on `device` with [`TASKS_PER_SUBMISSION`] (or the environment's
/// count), unless a client for it is open already, which keeps the options it opened with.
fn open_wgpu(device: &cubecl::wgpu::WgpuDevice) {
    use cubecl::wgpu::{try_init_setup_async, AutoGraphicsApi, RuntimeOptions};
    use std::collections::HashSet;
    use std::sync::{Mutex, OnceLock};
    // Each adapter is opened once a process: a second attempt would make a device only
    // to find the client there.
    static OPENED: OnceLock<Mutex<HashSet<cubecl::wgpu::WgpuDevice>>> = OnceLock::new();
    let mut opened = OPENED
        .get_or_init(Default::default)
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    if !opened.insert(device.clone()) {
        return;
    }
    let options = match std::env::var_os("CUBECL_WGPU_MAX_TASKS") {
        Some(_) => RuntimeOptions::try_default(),
        None => RuntimeOptions::with_tasks_max(Some(TASKS_PER_SUBMISSION)),
    };
    if let Ok(options) = options {
        // An error is a client opened elsewhere, or an adapter that cannot open, which
        // `device.client()` then reports.
        let _ = cubecl::future::block_on(try_init_setup_async::<AutoGraphicsApi>(device, options));
    }
}

/// See [`Gpu::tensor_cores`].
fn has_tensor_cores(client: &Client) -> bool {
    let props = client.properties();
    let f16 = ElemType::Float(FloatKind::F16);
    let f32 = ElemType::Float(FloatKind::F32);
    props.hardware.plane_size_min == WARP
        && props.hardware.plane_size_max == WARP
        && props.features.matmul.cmma.iter().any(|c| {
            (c.a_type, c.b_type, c.cd_type) == (f16, f16, f32) && (c.m, c.n, c.k) == (16, 16, 16)
        })
}

impl Gpu {
    /// Stops a stage's clock once the device has done the work queued so far (waiting
    /// for it only while the clocks run: kernels are queued, not run, when launched).
    pub fn stage_done(&self, clock: step_clock::Timer) {
        if clock.running() {
            // A device error surfaces at the step's next read; the clock just stops.
            let _ = cubecl::future::block_on(self.client.sync());
        }
        clock.stop();
    }

    /// The client of an opened CubeCL device, described.
    fn from_device(device: cubecl::Device, runtime: &str) -> Gpu {
        if let cubecl::Device::Wgpu(wgpu_device) = &device {
            open_wgpu(wgpu_device);
        }
        let client = device.client();
        let f32_atomic = Type::atomic(ElemType::Float(FloatKind::F32));
        let float_atomics = client
            .features()
            .atomic_type_usage(f32_atomic)
            .contains(cubecl::ir::features::AtomicUsage::Add);
        let identity = &client.properties().identity;
        let software = identity.physical.is_none();
        let tensor_cores = has_tensor_cores(&client);
        let matmul = match std::env::var("NERF_GPU_MATMUL").as_deref() {
            Ok("plain") => Path::Plain,
            Ok("tiled") => Path::Tiled,
            Ok("blocked") => Path::Blocked,
            Ok("cmma") if tensor_cores => Path::Cmma,
            Ok("cmma") => {
                eprintln!(
                    "NERF_GPU_MATMUL=cmma: this adapter has no f16 cooperative matrices (they \
                     need a build with the `spirv` feature); the wide kernels run"
                );
                Path::Wide
            }
            _ => Path::Wide,
        };
        let fused_field = std::env::var("NERF_GPU_FIELD").as_deref() == Ok("fused");
        let fused_training = std::env::var("NERF_GPU_TRAIN").as_deref() == Ok("fused");
        let grid_run = std::env::var("NERF_GPU_GRID_RUN")
            .ok()
            .and_then(|v| v.parse::<usize>().ok())
            .filter(|&r| (1..=256).contains(&r))
            .unwrap_or(GRID_RUN);
        Gpu {
            grid_run,
            matmul,
            fused_field,
            fused_training,
            tensor_cores,
            name: format!(
                "{runtime}: {}{}",
                identity.name,
                if software { " (software)" } else { "" }
            ),
            software,
            client,
            float_atomics,
        }
    }

    /// The default Vulkan adapter (a discrete GPU before an integrated one before a
    /// software one such as lavapipe; `CUBECL_WGPU_DEFAULT_DEVICE` overrides).
    pub fn vulkan() -> Result<Gpu> {
        let device = cubecl::Device::vulkan(WgpuDeviceKind::default()).map_err(|e| {
            NerfError::Device(format!(
                "no Vulkan GPU adapter ({e}); install your GPU's Vulkan driver, or Mesa's \
                 lavapipe for a software one (Debian/Ubuntu: apt-get install mesa-vulkan-drivers)"
            ))
        })?;
        Gpu::from_device(device, "wgpu/vulkan").runs_spirv()
    }

    /// This adapter, unless this build compiles Vulkan kernels to SPIR-V (the `spirv`
    /// feature) and the adapter is a software one: lavapipe crashes on CubeCL's SPIR-V, so
    /// such builds refuse it with a reason rather than fault.
    fn runs_spirv(self) -> Result<Gpu> {
        if cfg!(feature = "spirv") && self.software && self.name.starts_with("wgpu/vulkan") {
            return Err(NerfError::Device(format!(
                "{}: this build compiles the GPU kernels to SPIR-V (the `spirv` feature), \
                 which software Vulkan adapters crash on; use a build without it (the \
                 default) or --device cpu",
                self.name
            )));
        }
        Ok(self)
    }

    /// `--device wgpu`: the best adapter on Vulkan, else Metal, else DirectX 12 (never
    /// OpenGL, whose shaders lack the atomics the hash grid's backward needs).
    pub fn wgpu() -> Result<Gpu> {
        let kind = WgpuDeviceKind::default;
        let tried = [
            ("wgpu/vulkan", cubecl::Device::vulkan(kind())),
            ("wgpu/metal", cubecl::Device::metal_msl(kind())),
            ("wgpu/dx12", cubecl::Device::dx12(kind())),
        ];
        let mut reasons = Vec::new();
        for (api, device) in tried {
            match device {
                Ok(d) => return Gpu::from_device(d, api).runs_spirv(),
                Err(e) => reasons.push(format!("{api}: {e}")),
            }
        }
        Err(NerfError::Device(format!(
            "no GPU adapter on Vulkan, Metal or DirectX 12 ({}); install your GPU's driver \
             (Linux: its Vulkan driver, or Mesa's lavapipe for a software adapter: \
             apt-get install mesa-vulkan-drivers)",
            reasons.join("; ")
        )))
    }

    /// A hardware adapter through wgpu, for `--device auto`: the best adapter each API
    /// offers (wgpu ranks discrete before integrated before software), taken unless it is
    /// a software one, which is slower than the CPU engine.
    pub fn wgpu_hardware() -> Option<Gpu> {
        let kind = WgpuDeviceKind::default;
        [
            ("wgpu/vulkan", cubecl::Device::vulkan(kind())),
            ("wgpu/metal", cubecl::Device::metal_msl(kind())),
            ("wgpu/dx12", cubecl::Device::dx12(kind())),
        ]
        .into_iter()
        .filter_map(|(api, d)| d.ok().map(|d| (api, d)))
        .map(|(api, d)| Gpu::from_device(d, api))
        .find(|gpu| !gpu.software)
    }

    /// `--device cuda`: the first CUDA GPU (kernels compiled at run time by NVRTC, loaded
    /// dynamically: no CUDA toolkit is needed to build).
    pub fn cuda() -> Result<Gpu> {
        #[cfg(feature = "cuda")]
        {
            cubecl::Device::cuda(0)
                .map(|d| Gpu::from_device(d, "cuda"))
                .map_err(|e| {
                    NerfError::Device(format!(
                        "no CUDA GPU ({e}); install the NVIDIA driver and NVRTC \
                         (libnvrtc, in the CUDA runtime packages), or use --device wgpu"
                    ))
                })
        }
        #[cfg(not(feature = "cuda"))]
        Err(NerfError::Device(
            "this build has no CUDA runtime (built without the `cuda` feature); rebuild \
             with `--features cuda`, or use --device wgpu"
                .into(),
        ))
    }
}

/// The adapter for a GPU test, or `None` (with the reason printed) where there is none.
#[cfg(test)]
pub fn test_gpu() -> Option<Gpu> {
    Gpu::vulkan()
        .map_err(|e| eprintln!("skipping the GPU kernel test: {e}"))
        .ok()
}

/// The largest difference of two equally long vectors relative to `1 + |b|`: the
/// tolerance measure of the GPU kernel tests.
#[cfg(test)]
pub fn worst(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| {
            if x == y || (x.is_nan() && y.is_nan()) {
                return 0.0;
            }
            // A NaN here (one side NaN, or an infinity against a finite value) is as
            // wrong as can be; `max` would drop it.
            let e = (x - y).abs() / (1.0 + y.abs());
            if e.is_nan() {
                f32::INFINITY
            } else {
                e
            }
        })
        .fold(0.0, f32::max)
}
