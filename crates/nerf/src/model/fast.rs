//! The fast model: one hash-grid field, its occupancy grid, and how rays are marched and
//! batched through it.

use serde::{Deserialize, Serialize};

use crate::field::{FastField, FastFieldConfig};
use crate::render::marched::Marcher;
use crate::render::occupancy::{OccupancyConfig, OccupancyGrid};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FastModelConfig {
    pub field: FastFieldConfig,
    pub occupancy: OccupancyConfig,
    /// Field samples per training step; the number of rays follows from it.
    pub samples_per_step: usize,
    /// Samples evaluated per network call (bounds a thread's activation memory).
    pub batch_samples: usize,
    /// Marching steps along the scene box's diagonal (1024: step `sqrt(3) * 2 bound / 1024`).
    pub steps_per_diagonal: f32,
    /// Samples per ray at most.
    pub max_samples_per_ray: usize,
    /// L2 penalty on the MLP weights.
    pub weight_decay: f32,
    /// Unbounded scenes: the field's box `[-B, B]^3` holds the world cube of half-extent
    /// `B / 2` as it is and all space beyond, contracted (see `render::contraction`).
    #[serde(default)]
    pub contract: bool,
}

impl Default for FastModelConfig {
    fn default() -> Self {
        FastModelConfig {
            field: FastFieldConfig::default(),
            occupancy: OccupancyConfig::default(),
            samples_per_step: 1 << 16,
            batch_samples: 1 << 13,
            steps_per_diagonal: 1024.0,
            max_samples_per_ray: 1024,
            weight_decay: 1e-6,
            contract: false,
        }
    }
}

impl FastModelConfig {
    /// The marching step (metric).
    pub fn step_length(&self) -> f32 {
        3f32.sqrt() * 2.0 * self.field.bound / self.steps_per_diagonal
    }
}

#[derive(Clone, Debug)]
pub struct FastModel {
    pub config: FastModelConfig,
    pub field: FastField,
    /// Which cells of the scene box hold anything; refreshed during training and saved
    /// with the checkpoint (rendering needs it).
    pub grid: OccupancyGrid,
}

impl FastModel {
    pub fn new(config: FastModelConfig) -> Self {
        let field = FastField::new(config.field.clone());
        let grid = OccupancyGrid::new(config.occupancy.resolution, config.field.bound);
        FastModel {
            config,
            field,
            grid,
        }
    }

    /// How rays between `near` and `far` are marched.
    pub fn marcher(&self, near: f32, far: f32) -> Marcher {
        Marcher {
            dt: self.config.step_length(),
            max_samples: self.config.max_samples_per_ray,
            near,
            far,
            contract: self
                .config
                .contract
                .then_some(0.5 * self.config.field.bound),
        }
    }
}
