//! Dense networks by hand: a flat parameter vector with named slices, matrix products via
//! the `gemm` crate, Adam, and Glorot initialisation.

pub mod activation;
pub mod adam;
pub mod bf16_kernels;
pub mod dense;
pub mod grads;
pub mod linalg;
pub mod params;
pub mod trunk;

pub use adam::Adam;
pub use grads::{GradBuffer, Grads};
pub use params::{ParamLayout, Tensor};

/// Lengthens a reused buffer to at least `len` values (zeros), never shortening it: the
/// workspaces grow to the largest call they see and then allocate no more.
pub fn grow(v: &mut Vec<f32>, len: usize) {
    if v.len() < len {
        v.resize(len, 0.0);
    }
}
