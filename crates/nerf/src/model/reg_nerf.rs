//! RegNeRF (Niemeyer et al., CVPR 2022) for the paper's model: two of its regularisers for
//! training from a few photos, with nothing downloaded (its third, a colour likelihood,
//! needs a flow network trained on other photos).
//!
//! - **Depth smoothness** on patches rendered from poses between the training cameras
//!   (`model::unseen_patches`, `render::depth_smoothness`), as many patch rays as photo
//!   rays a step. RegNeRF starts its weight high and lowers it log-linearly to its final
//!   value over the first steps; that ramp is a setting here, off by default.
//! - **Sample-space annealing.** Early in training the samples are drawn from a range
//!   shrunk about the middle of `[near, far]`, widened to the whole range over the first
//!   steps: a field that starts with density everywhere would otherwise settle on a
//!   degenerate answer at the ends of the range (a wall at the near plane explains every
//!   photo from its own viewpoint).

use serde::{Deserialize, Serialize};

use crate::render::depth_smoothness::{PATCH_RAYS, PATCH_SIDE};

/// RegNeRF's settings (`--preset regnerf`); the defaults are its LLFF settings but for the
/// depth smoothness's weight, which stays at RegNeRF's final 0.1 from the first step: its
/// ramp from 400 over 512 steps, a sliver of its 70,000-step runs, is most of a CPU run of
/// the paper's model, and there it measured worse (see the benchmarks).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RegNerf {
    /// Steps over which the sampled range widens to the whole `[near, far]` (RegNeRF: 256).
    pub anneal_steps: u64,
    /// The share of the range sampled at the first step (RegNeRF: 0.5).
    pub anneal_start: f32,
    /// The depth smoothness's weight at the first step (RegNeRF: 400; ours 0.1) ...
    pub smoothness_start: f32,
    /// ... and from `smoothness_steps` on (RegNeRF: 0.1).
    pub smoothness_end: f32,
    /// Steps of the weight's log-linear fall (RegNeRF: 512).
    pub smoothness_steps: u64,
}

impl Default for RegNerf {
    fn default() -> Self {
        RegNerf {
            anneal_steps: 256,
            anneal_start: 0.5,
            smoothness_start: 0.1,
            smoothness_end: 0.1,
            smoothness_steps: 512,
        }
    }
}

impl RegNerf {
    /// The range sampled at `step`: `[near, far]` shrunk about its middle to the share
    /// `min(max(step / anneal_steps, anneal_start), 1)`.
    pub fn sampled_range(&self, near: f32, far: f32, step: u64) -> (f32, f32) {
        if step >= self.anneal_steps {
            return (near, far);
        }
        let share = (step as f32 / self.anneal_steps as f32).clamp(self.anneal_start, 1.0);
        let mid = 0.5 * (near + far);
        (mid + (near - mid) * share, mid + (far - mid) * share)
    }

    /// The depth smoothness's weight at `step`.
    pub fn smoothness_weight(&self, step: u64) -> f32 {
        let progress = match self.smoothness_steps {
            0 => 1.0,
            n => (step as f32 / n as f32).min(1.0),
        };
        let (a, b) = (self.smoothness_start.ln(), self.smoothness_end.ln());
        (a + (b - a) * progress).exp()
    }

    /// The factor of the depth smoothness's gradient for one of a step's `patches` patches,
    /// at `step` of a step of `photo_rays` rays, in the photometric loss's units before
    /// its normalisation (`render::loss::mean_scale`, `1 / (3 rays)`), so that the loss is
    /// the weight times the mean over patches. RegNeRF's patch loss is the mean over its
    /// pixels of their two squared differences with the next pixel to the right and below,
    /// ours the sum over a patch's neighbouring pairs (24 in a 4 x 4 patch), so its weights
    /// carry over divided by 12.
    pub fn smoothness_scale(&self, step: u64, photo_rays: usize, patches: usize) -> f32 {
        let pairs = 2 * PATCH_SIDE * (PATCH_SIDE - 1);
        let per_pixel = 2.0 / pairs as f32;
        self.smoothness_weight(step) * per_pixel * (3 * photo_rays) as f32 / patches.max(1) as f32
    }

    /// Patches a step of `photo_rays` rays renders: as many patch rays as photo rays
    /// (RegNeRF draws its random-pose rays in batches the size of its photo batches).
    pub fn patches(&self, photo_rays: usize) -> usize {
        photo_rays.div_ceil(PATCH_RAYS)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_range_widens_from_its_middle_and_the_weight_falls_log_linearly() {
        let reg = RegNerf::default();
        // Half the range about its middle at first, the whole of it after 256 steps.
        assert_eq!(reg.sampled_range(2.0, 6.0, 0), (3.0, 5.0));
        assert_eq!(reg.sampled_range(2.0, 6.0, 128), (3.0, 5.0));
        let (near, far) = reg.sampled_range(2.0, 6.0, 192);
        assert!((near - 2.5).abs() < 1e-6 && (far - 5.5).abs() < 1e-6);
        assert_eq!(reg.sampled_range(2.0, 6.0, 256), (2.0, 6.0));
        assert_eq!(reg.sampled_range(2.0, 6.0, 10_000), (2.0, 6.0));
        // By default a constant 0.1.
        assert!((0..2000).all(|s| (reg.smoothness_weight(s) - 0.1).abs() < 1e-6));
        // RegNeRF's ramp: 400 at first, 0.1 from step 512 on, the geometric mean half way.
        let ramp = RegNerf {
            smoothness_start: 400.0,
            ..reg
        };
        assert!((ramp.smoothness_weight(0) - 400.0).abs() < 1e-2);
        assert!((ramp.smoothness_weight(256) - (400.0f32 * 0.1).sqrt()).abs() < 1e-3);
        assert!((ramp.smoothness_weight(512) - 0.1).abs() < 1e-6);
        assert!((ramp.smoothness_weight(5000) - 0.1).abs() < 1e-6);
        assert_eq!(reg.patches(1024), 64);
        assert_eq!(reg.patches(1000), 63);
        // 1024 photo rays, 64 patches, weight 0.1: 0.1 / 12 * 3 * 1024 / 64.
        assert!((reg.smoothness_scale(600, 1024, 64) - 0.4).abs() < 1e-5);
    }
}
