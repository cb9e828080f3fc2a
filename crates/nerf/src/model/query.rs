//! Point queries of a trained model, the same call for both models: densities on a grid
//! (for meshes) and rendered colours of arbitrary rays (for mesh colours and point clouds).
//! The vanilla model answers with its fine network (its coarse one without a fine pass).

use rayon::prelude::*;

use super::Model;
use crate::field::VanillaWorkspace;

/// Points per work unit.
const CHUNK: usize = 4096;

impl Model {
    /// Densities at packed world `positions` (`n x 3`) into `out` (`n`), in parallel.
    pub fn density(&self, params: &[f32], positions: &[f32], out: &mut [f32]) {
        assert_eq!(positions.len(), out.len() * 3);
        thread_local! {
            static VANILLA: std::cell::RefCell<VanillaWorkspace> =
                std::cell::RefCell::default();
        }
        out.par_chunks_mut(CHUNK)
            .zip(positions.par_chunks(CHUNK * 3))
            .for_each(|(out, pos)| match self {
                Model::Fast(m) => m.field.density_into(params, pos, out),
                Model::Vanilla(m) => VANILLA.with(|ws| {
                    let ws = &mut ws.borrow_mut();
                    let (coarse, fine) = m.split(params);
                    let (net, p) = match &m.fine {
                        Some(f) => (f, fine),
                        None => (&m.coarse, coarse),
                    };
                    // Density does not depend on the direction: one "ray" of all points.
                    net.forward(p, pos, &[0.0, 0.0, 1.0], out.len(), ws);
                    out.copy_from_slice(&ws.sigma[..out.len()]);
                }),
            });
    }
}

#[cfg(test)]
mod tests {
    use crate::model::{FastModelConfig, Model, ModelConfig};

    #[test]
    fn density_matches_the_fields_own_forward_for_both_models() {
        let (vanilla, _) = crate::presets::build("demo").expect("preset");
        let pos: Vec<f32> = (0..5000 * 3)
            .map(|i| ((i % 17) as f32 - 8.0) * 0.1)
            .collect();
        for config in [
            ModelConfig::Vanilla(vanilla),
            ModelConfig::Fast(FastModelConfig::default()),
        ] {
            let model = Model::new(config);
            let params = model.init_params(1);
            let mut sigma = vec![0.0; 5000];
            model.density(&params, &pos, &mut sigma);
            // The last point, evaluated alone, gives the same value.
            let mut one = [0.0];
            model.density(&params, &pos[4999 * 3..], &mut one);
            assert!((one[0] - sigma[4999]).abs() <= 1e-5 * (1.0 + one[0].abs()));
            assert!(sigma.iter().all(|s| s.is_finite() && *s >= 0.0));
        }
    }
}
