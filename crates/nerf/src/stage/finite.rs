//! The debug switch `NERF_CHECK_FINITE=1`: every stage's outputs and gradients are checked
//! for NaN and infinity during training, and the step stops at the first one found with
//! the stage, the buffer and the index named (`NerfError::NonFinite`), instead of the
//! usual "training diverged" after the step. Off by default: it reads every buffer once
//! more.

use std::sync::Mutex;

use crate::error::NerfError;

/// The environment variable that turns the checks on (`1`, `true` or `yes`).
pub const ENV: &str = "NERF_CHECK_FINITE";

/// Whether the environment asks for the checks.
pub fn from_env() -> bool {
    std::env::var(ENV).is_ok_and(|v| matches!(v.trim(), "1" | "true" | "yes"))
}

/// What was found first.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Found {
    stage: &'static str,
    buffer: &'static str,
    index: usize,
    value: f32,
}

/// A step's checks: shared by the step's workers; the first finding is kept.
#[derive(Debug, Default)]
pub struct FiniteCheck {
    enabled: bool,
    first: Mutex<Option<Found>>,
}

impl FiniteCheck {
    pub fn new(enabled: bool) -> Self {
        FiniteCheck {
            enabled,
            first: Mutex::new(None),
        }
    }

    pub fn enabled(&self) -> bool {
        self.enabled
    }

    /// Checks `values`, the `buffer` that `stage` produced (when enabled).
    pub fn check(&self, stage: &'static str, buffer: &'static str, values: &[f32]) {
        if !self.enabled {
            return;
        }
        if let Some(index) = values.iter().position(|v| !v.is_finite()) {
            let mut first = self.first.lock().unwrap_or_else(|p| p.into_inner());
            first.get_or_insert(Found {
                stage,
                buffer,
                index,
                value: values[index],
            });
        }
    }

    /// The first finding of step `step` as an error, clearing it for the next step.
    pub fn take(&self, step: u64) -> Option<NerfError> {
        let mut first = self.first.lock().unwrap_or_else(|p| p.into_inner());
        first.take().map(|f| NerfError::NonFinite {
            stage: f.stage,
            buffer: f.buffer,
            step,
            index: f.index,
            value: f.value,
        })
    }
}

/// Checks compositing's outputs: the sample weights and each ray's colour, depth and
/// opacity.
pub fn check_outputs(check: &FiniteCheck, weights: &[f32], outputs: &[super::RayOutput]) {
    if !check.enabled() {
        return;
    }
    check.check("render.composite", "weights", weights);
    let flat: Vec<f32> = outputs
        .iter()
        .flat_map(|o| [o.rgb[0], o.rgb[1], o.rgb[2], o.depth, o.opacity])
        .collect();
    check.check(
        "render.composite",
        "ray outputs (rgb, depth, opacity)",
        &flat,
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_finding_is_kept_and_named() {
        let off = FiniteCheck::new(false);
        off.check("field.forward", "sigma", &[f32::NAN]);
        assert!(off.take(1).is_none());

        let on = FiniteCheck::new(true);
        on.check("field.forward", "sigma", &[0.0, 1.0]);
        on.check("render.composite", "rgb", &[0.0, f32::INFINITY]);
        on.check("field.backward", "grads", &[f32::NAN]);
        let err = on.take(7).expect("found").to_string();
        assert!(
            err.contains("render.composite") && err.contains("rgb[1]") && err.contains("step 7"),
            "{err}"
        );
        assert!(on.take(8).is_none(), "cleared after it was taken");
    }
}
