//! `nerf`: train and render neural radiance fields from the command line.

mod capture_cmd;
mod commands;
mod mesh_cmd;
mod progress;

use std::path::PathBuf;

use clap::{builder::PossibleValue, Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "nerf",
    version,
    about = "Neural radiance fields (Mildenhall et al. 2020) on a CPU"
)]
struct Cli {
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a built-in scene (procedural furniture) as a Blender-format dataset.
    Synth(commands::SynthArgs),
    /// Photos or a video -> camera poses with COLMAP -> a trainable scene folder.
    Capture(capture_cmd::CaptureArgs),
    /// What a scene folder holds, as training reads it (format, splits, bounds, box).
    Scene(capture_cmd::SceneArgs),
    /// Train a radiance field on a scene (Blender, instant-ngp / nerfstudio, LLFF, COLMAP).
    Train(commands::TrainArgs),
    /// Render a split of the scene and report PSNR / SSIM per view and on average.
    Eval(commands::EvalArgs),
    /// Render the test views or an orbit around the object to PNGs.
    Render(commands::RenderArgs),
    /// A coloured triangle mesh of a trained run (.ply, .obj or .glb).
    Mesh(mesh_cmd::MeshArgs),
    /// A coloured point cloud (.ply) from rendered depth of the training views.
    Points(mesh_cmd::PointsArgs),
    /// Built-in scene -> train -> evaluate -> orbit, no data needed.
    Demo(commands::DemoArgs),
    /// Throughput of the training step and of rendering on this machine.
    Bench(commands::BenchArgs),
}

/// `--preset` values with their one-line descriptions (for `--help`).
pub fn preset_values() -> Vec<PossibleValue> {
    nerf::presets::PRESETS
        .iter()
        .map(|p| PossibleValue::new(p.name).help(p.help))
        .collect()
}

/// `PathBuf` of the default run folder for a scene.
pub fn default_run(data: &std::path::Path, preset: &str) -> PathBuf {
    let scene = data
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into());
    PathBuf::from("runs").join(format!("{scene}-{preset}"))
}

fn main() {
    let cli = Cli::parse();
    if let Some(n) = cli.threads {
        if let Err(e) = rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build_global()
        {
            eprintln!("warning: could not set {n} threads: {e}");
        }
    }
    let result = match cli.command {
        Command::Synth(a) => commands::synth(a),
        Command::Capture(a) => capture_cmd::capture(a),
        Command::Scene(a) => capture_cmd::scene(a),
        Command::Train(a) => commands::train(a),
        Command::Eval(a) => commands::eval(a),
        Command::Render(a) => commands::render(a),
        Command::Mesh(a) => mesh_cmd::mesh(a),
        Command::Points(a) => mesh_cmd::points(a),
        Command::Demo(a) => commands::demo(a),
        Command::Bench(a) => commands::bench(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
