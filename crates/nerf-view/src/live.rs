//! `nerf train --view`: the viewer of a run while it trains. The viewer renders from a
//! CPU copy of the model; while a page is open it takes the trainer's weights every
//! [`SNAPSHOT_SECONDS`] and shows step, loss, PSNR and rays/s as they come. With no page
//! open it takes nothing, so training runs at full speed.

use std::net::{IpAddr, Ipv4Addr};
use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use nerf::engine::Device;
use nerf::train::folder::LoadedRun;
use nerf::train::run::Event;
use nerf::train::TrainConfig;

use crate::protocol::ServerMessage;
use crate::{start, Running, Viewer};

/// How often an open page gets the newest weights.
pub const SNAPSHOT_SECONDS: f64 = 5.0;
/// How often an open page gets training figures.
const PROGRESS_SECONDS: f64 = 0.25;

/// A viewer fed by a training run's events.
pub struct LiveView {
    pub running: Running,
    steps: u64,
    last_snapshot: Option<Instant>,
    last_progress: Option<Instant>,
    last_step: Option<(u64, Instant)>,
    rays_per_second: f64,
}

impl LiveView {
    /// Serves the run `config` trains into `out`, on this machine's `port`.
    pub fn start(config: &TrainConfig, out: &Path, port: u16) -> anyhow::Result<LiveView> {
        let engine = nerf::engine::open_on(
            Device::Cpu,
            &config.model,
            config.engine_options(),
            config.seed,
        )?;
        let run = LoadedRun {
            config: config.clone(),
            engine,
            step: 0,
        };
        let viewer = Viewer::new(run, out.to_path_buf(), None, true)
            .with_context(|| format!("the live view of {}", out.display()))?;
        let running = start(viewer, IpAddr::V4(Ipv4Addr::LOCALHOST), port)?;
        Ok(LiveView {
            running,
            // 0: a timed run has no step target.
            steps: if config.time_budget_s.is_some() {
                0
            } else {
                config.steps
            },
            last_snapshot: None,
            last_progress: None,
            last_step: None,
            rays_per_second: 0.0,
        })
    }

    /// Shows the run's final checkpoint (after training stopped).
    pub fn show_checkpoint(&self, out: &Path) -> anyhow::Result<()> {
        let run = LoadedRun::open(out)?;
        self.running.viewer.update(run.step, run.engine.state())?;
        Ok(())
    }

    /// Takes what the page needs from one training event.
    pub fn on_event(&mut self, event: &Event) {
        let viewer = &self.running.viewer;
        match event {
            Event::Step(stats) => {
                let now = Instant::now();
                if let Some((step, then)) = self.last_step {
                    let dt = now.duration_since(then).as_secs_f64();
                    if stats.step > step && dt > 0.0 {
                        let rate = stats.rays as f64 * (stats.step - step) as f64 / dt;
                        self.rays_per_second = if self.rays_per_second > 0.0 {
                            0.9 * self.rays_per_second + 0.1 * rate
                        } else {
                            rate
                        };
                    }
                }
                self.last_step = Some((stats.step, now));
                if viewer.watched() && due(&mut self.last_progress, PROGRESS_SECONDS) {
                    let _ = viewer.training.send(ServerMessage::Training {
                        step: stats.step,
                        steps: self.steps,
                        loss: stats.loss,
                        psnr: f64::from(stats.psnr),
                        rays_per_second: self.rays_per_second,
                    });
                }
            }
            Event::Model { step, engine }
                if viewer.watched() && due(&mut self.last_snapshot, SNAPSHOT_SECONDS) =>
            {
                if let Err(e) = viewer.update(*step, engine.state()) {
                    eprintln!("warning: the live view could not take the weights: {e}");
                }
            }
            _ => {}
        }
    }
}

/// Whether `seconds` have passed since `last` (and if so, now is the new `last`).
fn due(last: &mut Option<Instant>, seconds: f64) -> bool {
    let now = Instant::now();
    if last.is_some_and(|t| now.duration_since(t).as_secs_f64() < seconds) {
        return false;
    }
    *last = Some(now);
    true
}
