//! Where a training step's time goes: one clock per stage of the step, off unless a
//! benchmark turns them on (`nerf bench` prints what they measured).
//!
//! The clocks are process-wide, like a tracing subscriber, so the stages deep inside a
//! field or an engine need no handle threaded down to them. A stopped timer adds its
//! elapsed time with one relaxed atomic add; when the clocks are off, starting one reads
//! a flag and nothing else. Stages that run inside the CPU engine's workers measure
//! thread time (each worker's share adds up); [`Stage::per_worker`] says which, so a
//! report can turn them into wall time.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// The stages of a fast-model training step, in the order a step runs them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Drawing rays and marching them through the occupancy grid.
    Marching,
    /// Hash-grid lookups (and the space-time grid's, for moving scenes).
    Encoding,
    /// Anti-aliasing's per-level weights, forward and backward.
    LevelWeights,
    /// The density and colour networks (and the direction encoding).
    Networks,
    /// Compositing along the rays, the loss and its gradient back to the samples.
    Compositing,
    /// The networks' backward pass.
    NetworksBackward,
    /// Scattering gradients into the hash-grid tables.
    EncodingBackward,
    /// Summing the workers' gradient buffers.
    Reduction,
    /// The optimiser's update.
    Adam,
}

impl Stage {
    pub const ALL: [Stage; 9] = [
        Stage::Marching,
        Stage::Encoding,
        Stage::LevelWeights,
        Stage::Networks,
        Stage::Compositing,
        Stage::NetworksBackward,
        Stage::EncodingBackward,
        Stage::Reduction,
        Stage::Adam,
    ];

    /// A short name for reports.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Marching => "marching",
            Stage::Encoding => "hash grid",
            Stage::LevelWeights => "level weights",
            Stage::Networks => "networks",
            Stage::Compositing => "compositing + loss",
            Stage::NetworksBackward => "networks backward",
            Stage::EncodingBackward => "hash grid backward",
            Stage::Reduction => "gradient reduction",
            Stage::Adam => "Adam",
        }
    }

    /// Whether the CPU engine runs this stage inside its workers, each over its share of
    /// the samples (so its clock sums the workers' thread time); the others run once per
    /// step, parallel inside.
    pub fn per_worker(self) -> bool {
        matches!(
            self,
            Stage::Encoding
                | Stage::LevelWeights
                | Stage::Networks
                | Stage::Compositing
                | Stage::NetworksBackward
                | Stage::EncodingBackward
        )
    }
}

static ON: AtomicBool = AtomicBool::new(false);
static NANOS: [AtomicU64; Stage::ALL.len()] = [const { AtomicU64::new(0) }; Stage::ALL.len()];

/// Starts or stops the clocks (they keep what they hold: [`reset`] zeroes them). A
/// benchmark runs them over the steps it wants measured and stops them over the rest.
pub fn enable(on: bool) {
    ON.store(on, Ordering::Relaxed);
}

/// Whether the clocks run (an engine that must wait for a device to time a stage asks).
pub fn enabled() -> bool {
    ON.load(Ordering::Relaxed)
}

/// Zeroes every clock.
pub fn reset() {
    for n in &NANOS {
        n.store(0, Ordering::Relaxed);
    }
}

/// The time each stage's clock holds.
pub fn read() -> Vec<(Stage, Duration)> {
    Stage::ALL
        .iter()
        .map(|&s| {
            let nanos = NANOS[s as usize].load(Ordering::Relaxed);
            (s, Duration::from_nanos(nanos))
        })
        .collect()
}

/// A running stage: [`stop`](Timer::stop) (or dropping it) adds its time to the stage's
/// clock.
#[must_use = "a timer measures until it is stopped or dropped"]
pub struct Timer {
    stage: Stage,
    started: Option<Instant>,
}

/// Starts timing `stage` (a no-op unless the clocks are on).
#[inline]
pub fn start(stage: Stage) -> Timer {
    Timer {
        stage,
        started: enabled().then(Instant::now),
    }
}

impl Timer {
    /// Whether this timer measures (the clocks were on when it started).
    pub fn running(&self) -> bool {
        self.started.is_some()
    }

    /// Stops the timer now.
    #[inline]
    pub fn stop(self) {}
}

impl Drop for Timer {
    fn drop(&mut self) {
        if let Some(t) = self.started.take() {
            let nanos = u64::try_from(t.elapsed().as_nanos()).unwrap_or(u64::MAX);
            NANOS[self.stage as usize].fetch_add(nanos, Ordering::Relaxed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one test that turns the process-wide clocks on. Other tests may run timed
    /// stages meanwhile, in other threads, so it asserts lower bounds only.
    #[test]
    fn timers_add_only_while_the_clocks_run() {
        enable(false);
        reset();
        start(Stage::Adam).stop();
        std::thread::sleep(Duration::from_millis(2));
        assert!(read().iter().all(|(_, d)| d.is_zero()));

        enable(true);
        reset();
        let t = start(Stage::Adam);
        assert!(t.running());
        std::thread::sleep(Duration::from_millis(5));
        t.stop();
        {
            let _t = start(Stage::Marching);
            std::thread::sleep(Duration::from_millis(3));
        }
        let times = read();
        let of = |s: Stage| times.iter().find(|(t, _)| *t == s).map(|(_, d)| *d);
        assert!(of(Stage::Adam) >= Some(Duration::from_millis(5)));
        assert!(of(Stage::Marching) >= Some(Duration::from_millis(3)));
        enable(false);
        assert!(!start(Stage::Adam).running());
        assert_eq!(Stage::ALL.len(), NANOS.len());
        assert!(Stage::ALL
            .iter()
            .enumerate()
            .all(|(i, &s)| s as usize == i && !s.name().is_empty()));
    }
}
