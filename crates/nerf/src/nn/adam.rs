//! Adam (Kingma & Ba 2015) over a flat parameter vector.

use serde::{Deserialize, Serialize};

/// Adam hyper-parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

impl Default for AdamConfig {
    /// The reference NeRF's TensorFlow defaults.
    fn default() -> Self {
        AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-7,
        }
    }
}

/// Optimiser state: first and second moments and the number of updates taken.
#[derive(Clone, Debug)]
pub struct Adam {
    pub config: AdamConfig,
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub t: u64,
}

impl Adam {
    pub fn new(config: AdamConfig, n: usize) -> Self {
        Adam {
            config,
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    /// One bias-corrected update `p -= lr * m_hat / (sqrt(v_hat) + eps)`.
    pub fn step(&mut self, params: &mut [f32], grads: &[f32], lr: f32) {
        assert_eq!(params.len(), grads.len());
        assert_eq!(params.len(), self.m.len());
        self.t += 1;
        let AdamConfig { beta1, beta2, eps } = self.config;
        let bc1 = 1.0 - beta1.powf(self.t as f32);
        let bc2 = 1.0 - beta2.powf(self.t as f32);
        let step = lr / bc1;
        let inv_bc2 = 1.0 / bc2;
        for (((p, &g), m), v) in params
            .iter_mut()
            .zip(grads)
            .zip(&mut self.m)
            .zip(&mut self.v)
        {
            *m = beta1 * *m + (1.0 - beta1) * g;
            *v = beta2 * *v + (1.0 - beta2) * g * g;
            *p -= step * *m / ((*v * inv_bc2).sqrt() + eps);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_step_moves_by_lr_against_gradient_sign() {
        let mut adam = Adam::new(AdamConfig::default(), 2);
        let mut p = vec![1.0, -1.0];
        adam.step(&mut p, &[3.0, -0.5], 0.1);
        assert!(
            (p[0] - 0.9).abs() < 1e-5 && (p[1] + 0.9).abs() < 1e-5,
            "{p:?}"
        );
    }

    #[test]
    fn minimises_a_quadratic() {
        let mut adam = Adam::new(AdamConfig::default(), 1);
        let mut p = vec![5.0];
        for _ in 0..2000 {
            let g = 2.0 * (p[0] - 2.0);
            adam.step(&mut p, &[g], 0.05);
        }
        assert!((p[0] - 2.0).abs() < 1e-2, "{p:?}");
    }
}
