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
        resize_reused(v, len, 0.0);
    }
}

/// Sets a reused buffer's length to `len` (new values `fill`), keeping at most a sixteenth
/// more room than its largest length: `Vec`'s own growth doubles, and a step's buffers,
/// whose sizes vary by a few percent from step to step, would then hold up to twice the
/// memory they use.
pub fn resize_reused<T: Clone>(v: &mut Vec<T>, len: usize, fill: T) {
    if v.capacity() < len {
        v.reserve_exact(len + len / 16 - v.len());
    }
    v.resize(len, fill);
}
