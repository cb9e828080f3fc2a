//! `nerf bench`: throughput of the training step and of rendering, against the peak of the
//! GEMM library measured in the same process, plus peak memory.

use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::camera::Camera;
use crate::data::synth::{self, SceneKind, SynthOptions};
use crate::data::Split;
use crate::error::{NerfError, Result};
use crate::nn::linalg::{matmul, matmul_parallel, MatRef};
use crate::train::{TrainConfig, Trainer};

#[derive(Clone, Debug)]
pub struct BenchOptions {
    pub rays: usize,
    pub steps: usize,
    pub render_size: usize,
    pub render_rows: usize,
    pub preset: String,
    pub device: crate::engine::Device,
}

#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    pub threads: usize,
    /// The engine measured (`cpu, 16 threads`, `wgpu/vulkan: NVIDIA H100 80GB HBM3`).
    pub engine: String,
    /// Whether the step ran on the CPU, the only engine the GEMM peak describes.
    pub on_cpu: bool,
    pub preset: String,
    /// GFLOP/s of one 16384x256 by 256x256 product on one thread.
    pub gemm_gflops_one_thread: f64,
    /// The better of: one product split by the library over all threads, or one independent
    /// product per thread (how training uses it).
    pub gemm_peak_gflops: f64,
    pub train_rays: usize,
    pub train_step_seconds_median: f64,
    pub train_rays_per_second: f64,
    pub train_samples_per_second: f64,
    /// MLP work of a step (forward + backward = 3x forward multiply-adds, x2 flops each).
    pub train_gflop_per_step: f64,
    pub train_gflops: f64,
    pub train_percent_of_gemm_peak: f64,
    pub render_size: usize,
    pub render_rows_measured: usize,
    pub render_rays_per_second: f64,
    pub render_samples_per_second: f64,
    pub render_gflops: f64,
    pub render_percent_of_gemm_peak: f64,
    /// Full-view time extrapolated from the measured rows.
    pub render_seconds_full_view: f64,
    pub peak_resident_mib: f64,
}

/// The median (NaN for an empty list).
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// GFLOP/s of `m x k` by `k x n` products: (one thread, best over all threads).
pub fn gemm_peak(m: usize, k: usize, n: usize, reps: usize) -> (f64, f64) {
    let threads = rayon::current_num_threads();
    let a: Vec<f32> = (0..m * k).map(|i| (i % 17) as f32 * 0.01).collect();
    let b: Vec<f32> = (0..k * n).map(|i| (i % 13) as f32 * 0.01).collect();
    let flop = 2.0 * (m * n * k) as f64;
    let mut c = vec![0.0f32; m * n];
    let time = |f: &mut dyn FnMut()| {
        f();
        median(
            (0..reps)
                .map(|_| {
                    let t = Instant::now();
                    f();
                    t.elapsed().as_secs_f64()
                })
                .collect(),
        )
    };
    let one = flop
        / time(&mut || matmul(&mut c, MatRef::new(&a, m, k), MatRef::new(&b, k, n), false))
        / 1e9;
    let split =
        flop / time(&mut || {
            matmul_parallel(
                &mut c,
                MatRef::new(&a, m, k),
                MatRef::new(&b, k, n),
                threads,
            )
        }) / 1e9;
    let mut outs: Vec<Vec<f32>> = (0..threads).map(|_| vec![0.0f32; m * n]).collect();
    let independent = threads as f64 * flop
        / time(&mut || {
            outs.par_iter_mut()
                .for_each(|c| matmul(c, MatRef::new(&a, m, k), MatRef::new(&b, k, n), false));
        })
        / 1e9;
    (one, split.max(independent))
}

/// Peak resident set size of this process in MiB (Linux; 0 elsewhere).
pub fn peak_resident_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<f64>().ok())
            })
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

/// Runs the benchmark, printing progress lines through `say`.
pub fn run(opts: &BenchOptions, say: &mut dyn FnMut(String)) -> Result<BenchReport> {
    let threads = rayon::current_num_threads();
    crate::camera::check_image_size(opts.render_size, opts.render_size)
        .map_err(|m| NerfError::Config(format!("--render-size: {m}")))?;
    say(format!(
        "measuring the GEMM peak (16384x256 by 256x256, {threads} threads)..."
    ));
    let (gemm_one, gemm_peak) = gemm_peak(16384, 256, 256, 5);
    say(format!(
        "  gemm: {gemm_one:.1} GFLOP/s on one thread, peak {gemm_peak:.1} GFLOP/s"
    ));

    say("rendering a small built-in scene to train on...".into());
    let synth_opts = SynthOptions {
        scene: SceneKind::Chair,
        size: 64,
        supersample: 1,
        ..Default::default()
    };
    let data = synth::dataset(&synth_opts, Split::Train, 16);
    let mut config = TrainConfig::from_preset("(in memory)".into(), &opts.preset)?;
    config.batch_rays = opts.rays;
    config.precrop_steps = 0;
    let mut trainer = Trainer::on(opts.device, config, data)?;
    let crate::model::ModelConfig::Vanilla(vanilla) = trainer.config.model.clone() else {
        unreachable!("presets build vanilla models");
    };
    let vanilla = crate::model::VanillaModel::new(vanilla);
    let macs_per_ray = vanilla.macs_per_ray() as f64;
    let evals_per_ray = vanilla.config.evals_per_ray() as f64;
    trainer.step()?;
    let mut times = Vec::new();
    for k in 0..opts.steps {
        let t = Instant::now();
        trainer.step()?;
        times.push(t.elapsed().as_secs_f64());
        say(format!(
            "  training step {}/{}: {:.3} s",
            k + 1,
            opts.steps,
            times[k]
        ));
    }
    let step_s = median(times);
    let gflop_step = opts.rays as f64 * macs_per_ray * 2.0 * 3.0 / 1e9;
    let train_gflops = gflop_step / step_s;

    let size = opts.render_size;
    let rows = opts.render_rows.clamp(1, size);
    say(format!("rendering {rows} rows of a {size}x{size} view..."));
    let full = Camera::from_fov_x(
        size,
        size,
        synth::FOV_X,
        crate::camera::look_at([0.0, -4.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]),
    );
    let band = Camera {
        height: rows,
        cy: full.cy - (size - rows) as f32 / 2.0,
        ..full
    };
    let settings = crate::views::RenderSettings {
        near: 2.0,
        far: 6.0,
        background: [1.0; 3],
        space: Default::default(),
        appearance: Default::default(),
        time: None,
    };
    let t = Instant::now();
    crate::views::render_view(trainer.engine.as_ref(), &band, &settings, &|_| {});
    let render_s = t.elapsed().as_secs_f64();
    let render_rays = (size * rows) as f64;
    let render_gflops = render_rays * macs_per_ray * 2.0 / render_s / 1e9;

    let engine = trainer.engine.describe();
    Ok(BenchReport {
        threads,
        on_cpu: trainer.engine.kind() == crate::engine::caps::EngineKind::Cpu,
        engine,
        preset: opts.preset.clone(),
        gemm_gflops_one_thread: gemm_one,
        gemm_peak_gflops: gemm_peak,
        train_rays: opts.rays,
        train_step_seconds_median: step_s,
        train_rays_per_second: opts.rays as f64 / step_s,
        train_samples_per_second: opts.rays as f64 * evals_per_ray / step_s,
        train_gflop_per_step: gflop_step,
        train_gflops,
        train_percent_of_gemm_peak: 100.0 * train_gflops / gemm_peak,
        render_size: size,
        render_rows_measured: rows,
        render_rays_per_second: render_rays / render_s,
        render_samples_per_second: render_rays * evals_per_ray / render_s,
        render_gflops,
        render_percent_of_gemm_peak: 100.0 * render_gflops / gemm_peak,
        render_seconds_full_view: render_s * size as f64 / rows as f64,
        peak_resident_mib: peak_resident_mib(),
    })
}
