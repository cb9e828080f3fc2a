//! Progress bars for long work, and the training display.

use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use nerf::model::ModelConfig;
use nerf::train::run::Event;

/// A bar counting `total` items of `what`, with rate and ETA.
pub fn bar(total: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(total);
    let template =
        format!("{{spinner}} {what} [{{bar:30}}] {{pos}}/{{len}} {{per_sec}} ETA {{eta}} {{msg}}");
    if let Ok(style) = ProgressStyle::with_template(&template) {
        pb.set_style(style.progress_chars("=> "));
    }
    pb
}

/// The training display: a header, a bar with loss, PSNR and rays/s, validation lines, and
/// a line every 30 s when there is no terminal (logs, CI).
pub struct TrainProgress {
    pb: Option<ProgressBar>,
    steps: u64,
    last: (Instant, u64),
    rays_per_s: f64,
    rays_since: usize,
    last_line: Instant,
}

impl Default for TrainProgress {
    fn default() -> Self {
        TrainProgress {
            pb: None,
            steps: 0,
            last: (Instant::now(), 0),
            rays_per_s: 0.0,
            rays_since: 0,
            last_line: Instant::now(),
        }
    }
}

impl TrainProgress {
    /// The run's step target (0 before it started).
    pub fn steps(&self) -> u64 {
        self.steps
    }

    pub fn on_event(&mut self, event: Event) {
        match event {
            Event::Started {
                config,
                views,
                width,
                height,
                params,
                resumed_from,
            } => {
                println!(
                    "training {} on {} ({views} views, {width}x{height}): {}{}, {params} parameters",
                    config.preset,
                    config.data.display(),
                    config.model.describe(),
                    match config.model {
                        ModelConfig::Vanilla(_) => format!(", {} rays/step", config.batch_rays),
                        ModelConfig::Fast(_) => String::new(),
                    }
                );
                if let Some(step) = resumed_from {
                    println!("resuming from the checkpoint at step {step}");
                }
                let p = bar(config.steps, "train");
                p.set_position(resumed_from.unwrap_or(0));
                p.reset_eta();
                self.steps = config.steps;
                self.last = (Instant::now(), resumed_from.unwrap_or(0));
                self.pb = Some(p);
            }
            Event::Step(s) => {
                let Some(p) = &self.pb else { return };
                let dt = self.last.0.elapsed().as_secs_f64();
                self.rays_since += s.rays;
                if dt > 1.0 || s.step == self.last.1 + 1 {
                    self.rays_per_s = self.rays_since as f64 / dt.max(1e-9);
                    self.rays_since = 0;
                    self.last = (Instant::now(), s.step);
                }
                p.set_position(s.step);
                p.set_message(format!(
                    "loss {:.4} psnr {:.2} {:.0} rays/s",
                    s.loss, s.psnr, self.rays_per_s
                ));
                if p.is_hidden() && self.last_line.elapsed().as_secs_f64() >= 30.0 {
                    println!(
                        "step {}: loss {:.4}, batch PSNR {:.2} dB, {:.0} rays/s",
                        s.step, s.loss, s.psnr, self.rays_per_s
                    );
                    self.last_line = Instant::now();
                }
            }
            Event::Validation { step, psnr, image } => {
                if let Some(p) = &self.pb {
                    p.println(format!(
                        "step {step}: validation PSNR {psnr:.2} dB ({})",
                        image.display()
                    ));
                }
            }
            Event::Checkpoint { .. } => {}
        }
    }

    /// Clears the bar.
    pub fn finish(&mut self) {
        if let Some(p) = self.pb.take() {
            p.finish_and_clear();
        }
    }
}
