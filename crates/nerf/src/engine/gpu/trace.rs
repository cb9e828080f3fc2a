//! Where the host's time goes in the GPU engine, told on stderr when `NERF_GPU_TRACE` is
//! set: for rendering, each call's rounds and waits (`render`); for training, each
//! [`STEPS`] steps' mean time per phase ([`StepTrace`]). A phase that is mostly waiting
//! says the device sets the pace there; one that is mostly host work says it does not.

use std::time::{Duration, Instant};

/// Whether `NERF_GPU_TRACE` asks for the engine's timings.
pub fn tracing() -> bool {
    std::env::var_os("NERF_GPU_TRACE").is_some()
}

/// Steps a training report averages over.
pub const STEPS: u32 = 100;

/// The phases of a training step, in the order a step runs them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// The schedule's weights, and the cameras corrected where they are refined (read
    /// back only where the photos are not on the device).
    Prepare,
    /// Choosing the step's pixels, making their rays and queueing their marching count.
    Drawing,
    /// Waiting for the count's cut at the sample budget (the device runs what was queued).
    Cut,
    /// Queueing the samples, the field, the loss and the backward.
    Queueing,
    /// Camera refinement's per-ray gradients carried to the cameras (read back only where
    /// the photos are not on the device).
    Cameras,
    /// Queueing Adam, then waiting for the step's errors.
    End,
    /// The occupancy grid's refresh, when the schedule has one.
    Refresh,
}

/// Each phase's name in a report, in [`Phase`]'s order (a phase's index is `phase as usize`).
const PHASES: [&str; 7] = [
    "preparing",
    "drawing rays",
    "waiting for the cut",
    "queueing",
    "camera gradients",
    "Adam and waiting for the end",
    "refresh",
];
const _: () = assert!(Phase::Refresh as usize + 1 == PHASES.len());

/// A training step's host time by phase, summed over the steps since the last report.
pub struct StepTrace {
    on: bool,
    last: Instant,
    spent: [Duration; PHASES.len()],
    steps: u32,
}

impl Default for StepTrace {
    fn default() -> Self {
        StepTrace::new(tracing())
    }
}

impl StepTrace {
    /// A trace that times (`on`) or does nothing.
    pub fn new(on: bool) -> Self {
        StepTrace {
            on,
            last: Instant::now(),
            spent: [Duration::ZERO; PHASES.len()],
            steps: 0,
        }
    }

    /// A step begins now.
    pub fn begin(&mut self) {
        if self.on {
            self.last = Instant::now();
        }
    }

    /// The time since the last mark (or the step's beginning) went to `phase`.
    pub fn mark(&mut self, phase: Phase) {
        if self.on {
            let now = Instant::now();
            self.spent[phase as usize] += now - self.last;
            self.last = now;
        }
    }

    /// A step ended: every [`STEPS`] steps, the mean per phase on stderr.
    pub fn step_done(&mut self) {
        if let Some(line) = self.step_report() {
            eprintln!("{line}");
        }
    }

    /// Counts a step; the report once [`STEPS`] have been counted since the last one.
    fn step_report(&mut self) -> Option<String> {
        if !self.on {
            return None;
        }
        self.steps += 1;
        if self.steps < STEPS {
            return None;
        }
        let per_step = |d: Duration| d.as_secs_f64() * 1e3 / f64::from(self.steps);
        let total: Duration = self.spent.iter().sum();
        let phases: Vec<String> = PHASES
            .iter()
            .zip(&self.spent)
            .filter(|(_, d)| !d.is_zero())
            .map(|(name, d)| format!("{name} {:.2}", per_step(*d)))
            .collect();
        let line = format!(
            "gpu training, mean of {} steps: {:.2} ms a step: {}",
            self.steps,
            per_step(total),
            phases.join(", ")
        );
        self.spent = [Duration::ZERO; PHASES.len()];
        self.steps = 0;
        Some(line)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trace_reports_each_phase_once_every_hundred_steps() {
        let mut trace = StepTrace::new(true);
        for step in 1..=2 * STEPS {
            trace.begin();
            std::thread::sleep(Duration::from_micros(if step % 2 == 0 { 200 } else { 0 }));
            trace.mark(Phase::Drawing);
            trace.mark(Phase::End);
            let report = trace.step_report();
            assert_eq!(report.is_some(), step % STEPS == 0, "step {step}");
            if let Some(line) = report {
                assert!(
                    line.starts_with("gpu training, mean of 100 steps: "),
                    "{line}"
                );
                assert!(line.contains("drawing rays "), "{line}");
                // Half the steps slept 0.2 ms in drawing: a mean of at least 0.1 ms.
                let drawing: f64 = line
                    .split("drawing rays ")
                    .nth(1)
                    .and_then(|rest| rest.split(',').next())
                    .and_then(|ms| ms.trim().parse().ok())
                    .expect("a figure after the phase");
                assert!(drawing >= 0.1, "{line}");
                assert!(
                    !line.contains("refresh"),
                    "a phase with no time is left out: {line}"
                );
            }
        }
    }

    #[test]
    fn a_trace_that_is_off_reports_nothing() {
        let mut trace = StepTrace::new(false);
        for _ in 0..2 * STEPS {
            trace.begin();
            trace.mark(Phase::Cut);
            assert_eq!(trace.step_report(), None);
        }
    }
}
