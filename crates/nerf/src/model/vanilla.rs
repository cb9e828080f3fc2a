//! The vanilla NeRF model: a coarse and (optionally) a fine network of the same shape with
//! separate weights, sharing one flat parameter vector `[coarse | fine]`.

use serde::{Deserialize, Serialize};

use crate::field::{VanillaConfig, VanillaNet};
use crate::nn::ParamLayout;
use crate::rng::Rng;

/// Network shape and samples per ray.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VanillaModelConfig {
    pub net: VanillaConfig,
    /// Stratified samples per ray for the coarse network (paper: 64).
    pub n_coarse: usize,
    /// Importance samples per ray for the fine network (paper: 128); 0 disables the fine
    /// network (the "no hierarchical sampling" ablation).
    pub n_fine: usize,
}

impl VanillaModelConfig {
    pub fn hierarchical(&self) -> bool {
        self.n_fine > 0
    }
    /// Field evaluations per ray: coarse samples plus, with a fine network, all of them again.
    pub fn evals_per_ray(&self) -> usize {
        if self.hierarchical() {
            2 * self.n_coarse + self.n_fine
        } else {
            self.n_coarse
        }
    }
}

#[derive(Clone, Debug)]
pub struct VanillaModel {
    pub config: VanillaModelConfig,
    pub coarse: VanillaNet,
    pub fine: Option<VanillaNet>,
    /// Names of all tensors, with offsets into the flat vector.
    pub layout: ParamLayout,
}

impl VanillaModel {
    pub fn new(config: VanillaModelConfig) -> Self {
        let coarse = VanillaNet::new(config.net.clone(), "coarse.");
        let fine = config
            .hierarchical()
            .then(|| VanillaNet::new(config.net.clone(), "fine."));
        let mut layout = coarse.layout.clone();
        if let Some(f) = &fine {
            for t in &f.layout.tensors {
                layout.push(t.name.clone(), &t.shape);
            }
        }
        VanillaModel {
            config,
            coarse,
            fine,
            layout,
        }
    }

    /// Fresh weights: Glorot-uniform, zero biases, deterministic in `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        self.layout.init_glorot(&mut Rng::new(seed ^ 0x5eed))
    }

    /// Splits a flat vector (parameters or gradients) into its coarse and fine parts.
    pub fn split<'a>(&self, v: &'a [f32]) -> (&'a [f32], &'a [f32]) {
        v.split_at(self.coarse.num_params())
    }
    pub fn split_mut<'a>(&self, v: &'a mut [f32]) -> (&'a mut [f32], &'a mut [f32]) {
        v.split_at_mut(self.coarse.num_params())
    }

    /// Forward multiply-adds per ray.
    pub fn macs_per_ray(&self) -> usize {
        self.coarse.macs_per_sample() * self.config.evals_per_ray()
    }
}
