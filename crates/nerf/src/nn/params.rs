//! A flat parameter vector with named tensors.
//!
//! All weights of a model live in one `Vec<f32>`; a layout maps names to ranges. This makes
//! Adam, gradient reduction across threads and checkpointing one loop each.

use serde::{Deserialize, Serialize};

use crate::rng::Rng;

/// One named tensor inside a flat parameter vector.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tensor {
    pub name: String,
    pub shape: Vec<usize>,
    pub offset: usize,
}

impl Tensor {
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn range(&self) -> std::ops::Range<usize> {
        self.offset..self.offset + self.len()
    }
}

/// The named tensors of a model, in order, packed without gaps.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParamLayout {
    pub tensors: Vec<Tensor>,
    pub total: usize,
}

impl ParamLayout {
    /// Appends a tensor and returns its offset.
    pub fn push(&mut self, name: impl Into<String>, shape: &[usize]) -> usize {
        let offset = self.total;
        let t = Tensor {
            name: name.into(),
            shape: shape.to_vec(),
            offset,
        };
        self.total += t.len();
        self.tensors.push(t);
        offset
    }

    /// Glorot-uniform weights (`U(+-sqrt(6 / (in + out)))`, TensorFlow's default that the
    /// reference code used) for every 2-D tensor, zeros for biases.
    pub fn init_glorot(&self, rng: &mut Rng) -> Vec<f32> {
        let mut p = vec![0.0; self.total];
        for t in &self.tensors {
            if let [fan_in, fan_out] = t.shape[..] {
                let limit = (6.0 / (fan_in + fan_out) as f32).sqrt();
                for v in &mut p[t.range()] {
                    *v = rng.range(-limit, limit);
                }
            }
        }
        p
    }
}
