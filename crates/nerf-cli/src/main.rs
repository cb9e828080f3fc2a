//! `nerf`: train and render neural radiance fields from the command line. Each subcommand
//! lives in its own file under `commands/`; the options of training, rendering, capture,
//! scenes and the demo are declared once, in the library, with their `--help`.

mod commands;
#[cfg(test)]
mod docs_check;
mod progress;
mod report;
mod signals;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "nerf",
    version,
    about = "Neural radiance fields (Mildenhall et al. 2020) on a CPU or a GPU"
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
    Synth(commands::synth::SynthArgs),
    /// Photos or a video -> camera poses with COLMAP -> a trainable scene folder.
    Capture(nerf::app::capture::CaptureOptions),
    /// What a scene folder holds, as training reads it (format, splits, bounds, box).
    Scene(commands::scene::SceneArgs),
    /// Train a radiance field on a scene (Blender, instant-ngp / nerfstudio, LLFF, COLMAP).
    // Boxed: its options outweigh every other command's.
    Train(Box<nerf::train::options::TrainOptions>),
    /// Render a split of the scene and report PSNR / SSIM per view and on average.
    Eval(commands::eval::EvalArgs),
    /// Render the test views or an orbit around the object to PNGs.
    Render(commands::render::RenderArgs),
    /// A coloured triangle mesh of a trained run (.ply, .obj or .glb).
    Mesh(commands::mesh::MeshArgs),
    /// A coloured point cloud (.ply) from rendered depth of the training views.
    Points(commands::points::PointsArgs),
    /// A run's training cameras (refined, with --refine-cameras) as a transforms.json.
    ExportCameras(commands::export_cameras::ExportCamerasArgs),
    /// Built-in scene -> train -> evaluate -> orbit, no data needed.
    Demo(nerf::app::demo::DemoOptions),
    /// Throughput of the training step and of rendering on this machine.
    Bench(commands::bench::BenchArgs),
    /// Fly around a trained run in the web browser; make and render camera paths.
    View(nerf_view::ViewOptions),
}

/// Mesa's Vulkan drivers print "error: XDG_RUNTIME_DIR is invalid or not set" (six
/// times) when a process without one (a container, a CI job, a service) looks for a GPU,
/// which every command does under `--device auto`. Nothing fails; the driver only wants a
/// private runtime folder, so one is given: `nerf-runtime-<uid>` under the temporary
/// folder, 0700, used only when it is ours and private. Called first, while the process
/// has one thread.
#[cfg(target_os = "linux")]
fn quiet_graphics_drivers() {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt};
    if std::env::var_os("XDG_RUNTIME_DIR").is_some() {
        return;
    }
    let Ok(me) = std::fs::metadata("/proc/self").map(|m| m.uid()) else {
        return;
    };
    let dir = std::env::temp_dir().join(format!("nerf-runtime-{me}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    if let Ok(m) = std::fs::metadata(&dir) {
        if m.is_dir() && m.uid() == me && m.mode() & 0o077 == 0 {
            std::env::set_var("XDG_RUNTIME_DIR", &dir);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn quiet_graphics_drivers() {}

fn main() {
    quiet_graphics_drivers();
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
        Command::Synth(a) => commands::synth::run(a),
        Command::Capture(a) => commands::capture::run(a),
        Command::Scene(a) => commands::scene::run(a),
        Command::Train(a) => commands::train::run(*a),
        Command::Eval(a) => commands::eval::run(a),
        Command::Render(a) => commands::render::run(a),
        Command::Mesh(a) => commands::mesh::run(a),
        Command::Points(a) => commands::points::run(a),
        Command::ExportCameras(a) => commands::export_cameras::run(a),
        Command::Demo(a) => commands::demo::run(a),
        Command::Bench(a) => commands::bench::run(a),
        Command::View(a) => nerf_view::run(&a),
    };
    if let Err(e) = result {
        eprintln!("error: {}", report::message(&e));
        std::process::exit(1);
    }
}
