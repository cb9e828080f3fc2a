//! `nerf bench`: throughput figures of this machine (training steps, rendering, memory).

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use nerf::model::ModelKind;

#[derive(Args)]
pub struct BenchArgs {
    /// Which model to measure.
    #[arg(long, value_enum, default_value = "fast")]
    model: ModelKind,
    /// Timed training steps (the median is reported). Default: 32 fast, 3 vanilla.
    #[arg(long)]
    steps: Option<usize>,
    /// Size of the rendered view (square; fast: unless --data has a test camera).
    #[arg(long, default_value_t = 400)]
    render_size: usize,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
    /// Fast: a scene to train on, any format read as `nerf train` would (default: the
    /// built-in chair).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Fast: untimed steps first, so the occupancy grid takes shape.
    #[arg(long, default_value_t = 300)]
    warmup_steps: u64,
    /// Fast: field samples per step.
    #[arg(long)]
    samples: Option<usize>,
    /// Fast: log2 of the hash-table entries per level.
    #[arg(long)]
    table_log2: Option<u32>,
    /// Fast: anti-aliased (the default but for forward-facing NDC scenes, as
    /// `nerf train`).
    #[arg(long, conflicts_with = "no_antialias")]
    antialias: bool,
    /// Fast: point samples (the default for forward-facing NDC scenes).
    #[arg(long)]
    no_antialias: bool,
    /// Fast: train with the distortion loss of this weight (as `nerf train`: the default
    /// for forward-facing NDC scenes).
    #[arg(long, value_name = "WEIGHT", conflicts_with = "no_distortion",
          value_parser = nerf::args::positive_f64)]
    distortion: Option<f64>,
    /// Fast: no distortion loss, whatever the scene (the figure to compare against).
    #[arg(long)]
    no_distortion: bool,
    /// Fast: the networks' products with bfloat16 inputs and f32 sums (as `nerf train`:
    /// the default on the CPU engine where the CPU has AVX-512 BF16).
    #[arg(long, conflicts_with = "no_bf16")]
    bf16: bool,
    /// Fast: the networks' products in f32 (the figure to compare against).
    #[arg(long)]
    no_bf16: bool,
    /// Vanilla: rays per training step.
    #[arg(long, default_value_t = 1024)]
    rays: usize,
    /// Vanilla: rows of the view actually rendered; the full-view time is extrapolated.
    #[arg(long, default_value_t = 8)]
    render_rows: usize,
    /// Vanilla: model preset to measure.
    #[arg(long, default_value = "paper", value_parser = nerf::presets::possible_values())]
    preset: String,
    #[command(flatten)]
    device: nerf::engine::DeviceArg,
}

pub fn run(a: BenchArgs) -> Result<()> {
    if a.model == ModelKind::Fast {
        return bench_fast(a);
    }
    let opts = nerf::app::bench_vanilla::BenchOptions {
        rays: a.rays,
        steps: a.steps.unwrap_or(3).max(1),
        render_size: a.render_size,
        render_rows: a.render_rows,
        preset: a.preset,
        device: a.device.device,
    };
    let report = nerf::app::bench_vanilla::run(&opts, &mut |line| eprintln!("{line}"))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    let r = &report;
    println!("\n{}, preset {}", r.engine, r.preset);
    // The CPU's GEMM peak describes only the CPU engine's work.
    let of_peak = |pct: f64| {
        if r.on_cpu {
            format!(" = {pct:.1}% of the GEMM peak")
        } else {
            String::new()
        }
    };
    if r.on_cpu {
        println!(
            "GEMM peak (gemm crate, 16384x256x256): {:.1} GFLOP/s ({:.1} on one thread)",
            r.gemm_peak_gflops, r.gemm_gflops_one_thread
        );
    }
    println!(
        "training step, {} rays: {:.3} s (median), {:.0} rays/s, {:.0} samples/s, {:.1} GFLOP/step, {:.1} GFLOP/s{}",
        r.train_rays, r.train_step_seconds_median, r.train_rays_per_second, r.train_samples_per_second, r.train_gflop_per_step, r.train_gflops, of_peak(r.train_percent_of_gemm_peak)
    );
    println!(
        "rendering {0}x{0} (from {1} rows): {2:.1} s per view, {3:.0} rays/s, {4:.0} samples/s, {5:.1} GFLOP/s{6}",
        r.render_size, r.render_rows_measured, r.render_seconds_full_view, r.render_rays_per_second, r.render_samples_per_second, r.render_gflops, of_peak(r.render_percent_of_gemm_peak)
    );
    println!("peak resident memory: {:.0} MiB", r.peak_resident_mib);
    Ok(())
}

fn bench_fast(a: BenchArgs) -> Result<()> {
    let mut model = nerf::model::FastModelConfig::default();
    model.samples_per_step = a.samples.unwrap_or(model.samples_per_step);
    model.field.grid.log2_table_size = a.table_log2.unwrap_or(model.field.grid.log2_table_size);
    // Unasked, both follow the scene as `nerf train` does (`None`).
    let antialias = match (a.antialias, a.no_antialias) {
        (true, _) => Some(true),
        (_, true) => Some(false),
        _ => None,
    };
    let distortion = match (a.distortion, a.no_distortion) {
        (Some(w), _) => Some(w as f32),
        (_, true) => Some(0.0),
        _ => None,
    };
    let bf16 = match (a.bf16, a.no_bf16) {
        (true, _) => Some(true),
        (_, true) => Some(false),
        _ => None,
    };
    let opts = nerf::app::bench_fast::FastBenchOptions {
        bf16,
        data: a.data,
        warmup_steps: a.warmup_steps,
        steps: a.steps.unwrap_or(32).max(1),
        render_size: a.render_size,
        model,
        antialias,
        distortion,
        device: a.device.device,
    };
    let r = nerf::app::bench_fast::run(&opts, &mut |line| eprintln!("{line}"))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    println!(
        "\n{}, fast model{}{} on {}, after {} warm-up steps ({:.1}% of the occupancy grid occupied)",
        r.engine,
        if r.antialias { " (anti-aliased)" } else { "" },
        if r.distortion > 0.0 {
            format!(" (distortion loss {})", r.distortion)
        } else {
            String::new()
        },
        r.scene,
        r.warmup_steps,
        100.0 * r.occupied_fraction
    );
    println!(
        "training step, {} samples ({:.0} rays): {:.3} s (median), {:.3} s with an occupancy refresh, {:.3} s amortised",
        r.samples_per_step, r.rays_per_step_median, r.step_seconds_median, r.refresh_step_seconds_median, r.step_seconds_amortised
    );
    println!(
        "  {:.2} M samples/s, {:.0} rays/s, {:.0} M hash-grid lookups/s (forward + backward)",
        r.train_samples_per_second / 1e6,
        r.train_rays_per_second,
        r.hash_lookups_per_second / 1e6
    );
    println!(
        "  {:.1}% of the gradient blocks touched per step (reduction and Adam skip the rest)",
        100.0 * r.touched_fraction
    );
    println!("  where a step without a refresh spends its time (as many steps again, clocked stage by stage):");
    for s in &r.stages {
        println!(
            "    {:<20} {:>7.1} ms  {:>5.1}%",
            s.stage,
            1e3 * s.seconds,
            100.0 * s.share
        );
    }
    println!(
        "rendering {}x{}: {:.2} s per view, {:.0} rays/s",
        r.render_width, r.render_height, r.render_seconds, r.render_rays_per_second
    );
    println!("peak resident memory: {:.0} MiB", r.peak_resident_mib);
    Ok(())
}
