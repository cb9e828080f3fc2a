//! Adam (Kingma & Ba 2015) over a flat parameter vector.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::grads::{GradBuffer, SEGMENT};
use crate::simd::{in_width, Width};

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

    /// One bias-corrected update `p -= lr * m_hat / (sqrt(v_hat) + eps)` of every parameter.
    pub fn step(&mut self, params: &mut [f32], grads: &[f32], lr: f32) {
        assert_eq!(params.len(), grads.len());
        assert_eq!(params.len(), self.m.len());
        let step = self.begin_step(lr);
        self.update(params, grads, 0..params.len(), step, Rule::default());
    }

    /// Starts an update that [`update`](Self::update) then applies range by range.
    pub fn begin_step(&mut self, lr: f32) -> AdamStep {
        self.t += 1;
        self.step_at(lr)
    }

    /// The factors of the update under way (`t` already counted) at learning rate `lr`.
    pub fn step_at(&self, lr: f32) -> AdamStep {
        let AdamConfig { beta1, beta2, .. } = self.config;
        AdamStep {
            lr_over_bc1: lr / (1.0 - beta1.powf(self.t as f32)),
            inv_bc2: 1.0 / (1.0 - beta2.powf(self.t as f32)),
        }
    }

    /// Applies `step` to `params[range]` with gradients `grads[range]`.
    pub fn update(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        range: std::ops::Range<usize>,
        step: AdamStep,
        rule: Rule,
    ) {
        let r = range;
        update_slices(
            &self.config,
            step,
            Slices {
                params: &mut params[r.clone()],
                grads: &grads[r.clone()],
                m: &mut self.m[r.clone()],
                v: &mut self.v[r],
            },
            rule,
        );
    }
}

/// Matching pieces of parameters, gradients and both moments.
pub struct Slices<'a> {
    pub params: &'a mut [f32],
    pub grads: &'a [f32],
    pub m: &'a mut [f32],
    pub v: &'a mut [f32],
}

/// The update of [`Adam::update`] on slices, so disjoint pieces can be updated in parallel,
/// in the widest vectors the CPU has (see [`update_slices_in`]).
pub fn update_slices(config: &AdamConfig, step: AdamStep, s: Slices, rule: Rule) {
    update_slices_in(Width::widest(), config, step, s, rule);
}

in_width! {
    /// [`update_slices`] in the vectors of `width`: branch-free (a lazy skip is a select),
    /// so it vectorises, and the same bits in every width (`crate::simd`).
    pub fn update_slices_in(config: &AdamConfig, step: AdamStep, s: Slices, rule: Rule) => update_slices_baseline
}

/// The loop of [`update_slices_in`], in the vectors of whatever function it is inlined
/// into.
#[inline(always)]
fn update_slices_baseline(config: &AdamConfig, step: AdamStep, s: Slices, rule: Rule) {
    let AdamConfig { beta1, beta2, eps } = *config;
    for (((p, &g), m), v) in s
        .params
        .iter_mut()
        .zip(s.grads)
        .zip(s.m.iter_mut())
        .zip(s.v.iter_mut())
    {
        let g = g * rule.scale;
        let keep = rule.lazy && g == 0.0;
        let g = g + rule.weight_decay * *p;
        let m_new = beta1 * *m + (1.0 - beta1) * g;
        let v_new = beta2 * *v + (1.0 - beta2) * g * g;
        let p_new = *p - step.lr_over_bc1 * m_new / ((v_new * step.inv_bc2).sqrt() + eps);
        *m = if keep { *m } else { m_new };
        *v = if keep { *v } else { v_new };
        *p = if keep { *p } else { p_new };
    }
}

/// How [`Adam::step_dirty`] treats the gradient it is given.
#[derive(Clone, Copy, Debug)]
pub struct DirtyStep {
    /// Factor applied to every gradient value first.
    pub scale: f32,
    /// Parameters before this index update lazily (hash tables), with `table_decay` on
    /// the entries the step touches; the rest densely with `weight_decay` (MLP weights).
    pub lazy_end: usize,
    pub table_decay: f32,
    pub weight_decay: f32,
    /// A group of its own at the end of the vector, `(start, learning rate)`: updated
    /// densely, without weight decay, at its own learning rate (camera corrections).
    pub group: Option<(usize, f32)>,
}

impl Adam {
    /// One update of the parameters whose blocks `grads` marks dirty, in parallel over
    /// segments of the parameter vector; leaves `grads` zeroed and clean.
    pub fn step_dirty(
        &mut self,
        params: &mut [f32],
        grads: &mut GradBuffer,
        lr: f32,
        how: DirtyStep,
    ) {
        let step = self.begin_step(lr);
        let config = self.config;
        let DirtyStep {
            scale,
            lazy_end,
            table_decay,
            weight_decay,
            group,
        } = how;
        let (group_start, group_lr) = group.unwrap_or((params.len(), lr));
        let group_step = self.step_at(group_lr);
        params
            .par_chunks_mut(SEGMENT)
            .zip(self.m.par_chunks_mut(SEGMENT))
            .zip(self.v.par_chunks_mut(SEGMENT))
            .zip(grads.segments_mut(SEGMENT).collect::<Vec<_>>())
            .enumerate()
            .for_each(|(k, (((p, m), v), mut g))| {
                let base = k * SEGMENT;
                g.drain_dirty(|r, grads| {
                    // Split the run where the lazy part ends and where the group begins.
                    let split = lazy_end.clamp(base + r.start, base + r.end) - base;
                    let own = group_start.clamp(base + split, base + r.end) - base;
                    let lazy = Rule {
                        lazy: true,
                        weight_decay: table_decay,
                        scale,
                    };
                    let dense = Rule {
                        lazy: false,
                        weight_decay,
                        scale,
                    };
                    let group = Rule {
                        scale,
                        ..Rule::default()
                    };
                    let parts = [
                        (r.start..split, lazy, step),
                        (split..own, dense, step),
                        (own..r.end, group, group_step),
                    ];
                    for (part, rule, step) in parts {
                        let o = part.start - r.start;
                        let s = Slices {
                            params: &mut p[part.clone()],
                            grads: &grads[o..o + part.len()],
                            m: &mut m[part.clone()],
                            v: &mut v[part],
                        };
                        update_slices(&config, step, s, rule);
                    }
                });
            });
    }
}

/// The bias-corrected factors of one update.
#[derive(Clone, Copy, Debug)]
pub struct AdamStep {
    lr_over_bc1: f32,
    inv_bc2: f32,
}

impl AdamStep {
    /// `(lr / (1 - beta1^t), 1 / (1 - beta2^t))`, for engines that apply the update
    /// themselves (the GPU kernel), so the schedule is computed in one place.
    pub fn factors(self) -> (f32, f32) {
        (self.lr_over_bc1, self.inv_bc2)
    }
}

/// How a range of parameters is updated.
#[derive(Clone, Copy, Debug)]
pub struct Rule {
    /// Leave parameters whose gradient is exactly zero (and their moments) untouched: hash
    /// table entries no sample reached this step (as instant-ngp does).
    pub lazy: bool,
    /// L2 penalty `weight_decay / 2 * p^2` added to the loss (with `lazy`, on the
    /// parameters the step touches only).
    pub weight_decay: f32,
    /// Factor applied to each gradient first (1: none).
    pub scale: f32,
}

impl Default for Rule {
    fn default() -> Self {
        Rule {
            lazy: false,
            weight_decay: 0.0,
            scale: 1.0,
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
    fn lazy_rule_skips_zero_gradients_and_decay_pulls_to_zero() {
        let mut adam = Adam::new(AdamConfig::default(), 2);
        let mut p = vec![1.0, 1.0];
        let s = adam.begin_step(0.1);
        let lazy = Rule {
            lazy: true,
            ..Rule::default()
        };
        adam.update(&mut p, &[0.0, 0.0], 0..1, s, lazy);
        assert_eq!((p[0], adam.m[0], adam.v[0]), (1.0, 0.0, 0.0));
        let decay = Rule {
            weight_decay: 1.0,
            ..Rule::default()
        };
        adam.update(&mut p, &[0.0, 0.0], 1..2, s, decay);
        assert!((p[1] - 0.9).abs() < 1e-5, "{p:?}");
    }

    /// The tables' decay pulls the entries a step touches towards zero and leaves the
    /// others (and the dense part) alone: a gradient too small to matter pushes every
    /// touched entry up without decay and down with it.
    #[test]
    fn table_decay_pulls_touched_entries_only() {
        let n = 8;
        let step_with = |table_decay: f32| {
            let mut adam = Adam::new(AdamConfig::default(), n);
            let mut params = vec![1.0f32; n];
            let mut grads = crate::nn::GradBuffer::new(n);
            // Entries 0..4 are a table: 0 and 2 touched, 1 and 3 not.
            grads
                .values
                .copy_from_slice(&[-1e-8, 0.0, -1e-8, 0.0, -1e-8, -1e-8, -1e-8, -1e-8]);
            grads.mark(0..n);
            let how = DirtyStep {
                scale: 1.0,
                lazy_end: 4,
                table_decay,
                weight_decay: 0.0,
                group: None,
            };
            adam.step_dirty(&mut params, &mut grads, 0.1, how);
            params
        };
        let plain = step_with(0.0);
        let decayed = step_with(1.0);
        for i in [0, 2] {
            assert!(
                plain[i] > 1.0 && decayed[i] < 0.95,
                "entry {i}: {plain:?} {decayed:?}"
            );
        }
        for i in [1, 3] {
            assert_eq!((plain[i], decayed[i]), (1.0, 1.0), "untouched entry {i}");
        }
        assert_eq!(
            plain[4..],
            decayed[4..],
            "the dense part takes its own decay only"
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

    /// Every vector width the CPU offers gives the plain loop's bits, on each rule (a lazy
    /// part with zero gradients among the rest, decay, a scale), tails included.
    #[test]
    fn vectorised_updates_match_the_plain_one_bit_for_bit() {
        let n = 1000 + 13;
        let mut rng = crate::rng::Rng::new(5);
        let mut draw =
            |k: usize| -> Vec<f32> { (0..n).map(|_| rng.range(-1.0, 1.0) * k as f32).collect() };
        let params = draw(1);
        let mut grads = draw(2);
        grads.iter_mut().step_by(3).for_each(|g| *g = 0.0);
        let m0 = draw(1);
        let v0: Vec<f32> = draw(1).iter().map(|v| v * v).collect();
        let mut adam = Adam::new(AdamConfig::default(), n);
        adam.t = 7;
        let step = adam.step_at(0.01);
        let rules = [
            Rule {
                lazy: true,
                ..Rule::default()
            },
            Rule {
                weight_decay: 0.1,
                scale: 0.37,
                ..Rule::default()
            },
            Rule {
                lazy: true,
                weight_decay: 0.1,
                ..Rule::default()
            },
        ];
        let run = |update: &dyn Fn(Slices)| {
            let (mut p, mut m, mut v) = (params.clone(), m0.clone(), v0.clone());
            update(Slices {
                params: &mut p,
                grads: &grads,
                m: &mut m,
                v: &mut v,
            });
            (p, m, v)
        };
        let config = adam.config;
        for rule in rules {
            let want = run(&|s| update_slices_baseline(&config, step, s, rule));
            assert_ne!(want.0, params);
            let mut got = vec![(
                "dispatched".to_string(),
                run(&|s| update_slices(&config, step, s, rule)),
            )];
            for width in Width::available() {
                let name = format!("{width:?}");
                got.push((
                    name,
                    run(&|s| update_slices_in(width, &config, step, s, rule)),
                ));
            }
            let same =
                |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
            for (name, got) in got {
                assert!(
                    same(&got.0, &want.0) && same(&got.1, &want.1) && same(&got.2, &want.2),
                    "{name} differs from the plain loop under {rule:?}"
                );
            }
        }
    }
}
