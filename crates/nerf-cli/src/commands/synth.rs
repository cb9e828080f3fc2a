//! `nerf synth`: a built-in scene rendered as a Blender- or LLFF-format dataset.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Result;
use clap::{Args, ValueEnum};
use nerf::data::synth::{self, SceneKind, SynthOptions};

use crate::progress::bar;

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Layout {
    Blender,
    Llff,
}

#[derive(Args)]
pub struct SynthArgs {
    /// Which piece of furniture (rug: the chair on a patterned rug, texture for `nerf
    /// capture`).
    #[arg(long, value_enum, default_value = "chair")]
    scene: SceneKind,
    /// Output folder (Blender format: transforms_*.json + train/ val/ test/).
    #[arg(long)]
    out: PathBuf,
    /// `blender`: 360-degree views in Blender format. `llff`: a forward-facing capture
    /// (a 5 x 6 grid of cameras in front of the object, 4:3 images) in LLFF format, trained
    /// in NDC space.
    #[arg(long, value_enum, default_value = "blender")]
    layout: Layout,
    /// Image size in pixels (square; the width for --layout llff).
    #[arg(long, default_value_t = 100)]
    size: usize,
    #[arg(long, default_value_t = 100)]
    train_views: usize,
    #[arg(long, default_value_t = 10)]
    val_views: usize,
    #[arg(long, default_value_t = 40)]
    test_views: usize,
    /// Anti-aliasing: rays per pixel along each axis.
    #[arg(long, default_value_t = 2)]
    supersample: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A moving scene: the furniture turns a quarter turn over the capture, one photo per
    /// moment (each frame with its `time`, as D-NeRF's scenes), --layout blender only.
    #[arg(long)]
    animate: bool,
}

pub fn run(a: SynthArgs) -> Result<()> {
    if a.layout == Layout::Llff && a.animate {
        anyhow::bail!("--animate makes Blender-format scenes only (drop --layout llff)");
    }
    if a.layout == Layout::Llff {
        let cameras = synth::llff::forward_facing_cameras(a.size, a.size * 3 / 4, 5, 6);
        let pb = bar(
            cameras.len() as u64,
            &format!("synth {} (LLFF)", a.scene.name()),
        );
        let t0 = Instant::now();
        synth::llff::write(
            a.scene,
            &cameras,
            a.supersample,
            &nerf::data::poses::Similarity::IDENTITY,
            &a.out,
            &mut |done, _| pb.set_position(done as u64),
        )?;
        pb.finish_and_clear();
        println!(
            "wrote {} forward-facing views (LLFF) to {} in {:.1} s",
            cameras.len(),
            a.out.display(),
            t0.elapsed().as_secs_f64()
        );
        return Ok(());
    }
    let opts = SynthOptions {
        scene: a.scene,
        size: a.size,
        train_views: a.train_views,
        val_views: a.val_views,
        test_views: a.test_views,
        supersample: a.supersample,
        seed: a.seed,
        animate: a.animate,
    };
    write(&opts, &a.out)
}

fn write(opts: &SynthOptions, out: &Path) -> Result<()> {
    let total = (opts.train_views + opts.val_views + opts.test_views) as u64;
    let pb = bar(total, &format!("synth {}", opts.scene.name()));
    let t0 = Instant::now();
    let n = synth::generate(opts, out, &mut |done, _| pb.set_position(done as u64))?;
    pb.finish_and_clear();
    println!(
        "wrote {n} views of the {} ({}x{}) to {} in {:.1} s",
        opts.scene.name(),
        opts.size,
        opts.size,
        out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
