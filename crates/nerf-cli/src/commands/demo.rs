//! `nerf demo`: the library's demo pipeline with progress bars.

use anyhow::Result;
use indicatif::ProgressBar;
use nerf::app::demo::{DemoHooks, DemoOptions};
use nerf::app::frames::FrameProgress;
use nerf::train::run::Event;

use crate::progress::{bar, TrainProgress};

/// One bar per stage, created when the stage starts.
struct Bars {
    synth: ProgressBar,
    train: TrainProgress,
    eval: ProgressBar,
    frames: ProgressBar,
}

impl DemoHooks for Bars {
    fn say(&self, line: &str) {
        self.synth.finish_and_clear();
        println!("{line}");
    }
    fn synth_progress(&self, done: usize, total: usize) {
        self.synth.set_length(total as u64);
        self.synth.set_position(done as u64);
    }
    fn train_event(&mut self, event: Event) {
        let finished = matches!(event, Event::Checkpoint { step } if step >= self.train.steps());
        self.train.on_event(event);
        if finished {
            self.train.finish();
        }
    }
    fn eval_progress(&self, done: usize, total: usize) {
        self.eval.set_length(total as u64);
        self.eval.set_position(done as u64);
    }
    fn frames_progress(&self, p: FrameProgress) {
        self.eval.finish_and_clear();
        super::render::show(&self.frames, p);
    }
}

pub fn run(opts: DemoOptions) -> Result<()> {
    let mut bars = Bars {
        synth: bar(0, "synth chair"),
        train: TrainProgress::default(),
        eval: bar(0, "eval test rays"),
        frames: bar(0, "render rays"),
    };
    let report = nerf::app::demo::run(&opts, &mut bars);
    bars.train.finish();
    bars.eval.finish_and_clear();
    bars.frames.finish_and_clear();
    let r = report?;
    println!(
        "trained {} steps in {:.1} s",
        r.training.steps, r.training.seconds
    );
    super::eval::print_report(&r.eval, &r.eval_dir);
    super::render::print_report(&r.orbit, &r.orbit_dir);
    println!("\ndemo finished in {:.1} s", r.seconds);
    println!("  scene:       {}", r.scene.display());
    println!(
        "  run:         {} (config.json, checkpoint.safetensors, metrics.jsonl, val/)",
        r.run.display()
    );
    println!("  test images: {} (metrics.json)", r.eval_dir.display());
    let video = r.orbit.video.as_ref().map(|v| v.path.display().to_string());
    println!(
        "  orbit:       {} (frames), {}",
        r.orbit_dir.display(),
        video.unwrap_or_default()
    );
    Ok(())
}
