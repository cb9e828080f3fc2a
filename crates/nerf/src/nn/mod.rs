//! Dense networks by hand: a flat parameter vector with named slices, matrix products via
//! the `gemm` crate, Adam, and Glorot initialisation.

pub mod activation;
pub mod adam;
pub mod dense;
pub mod grads;
pub mod linalg;
pub mod params;
pub mod trunk;

pub use adam::Adam;
pub use grads::{GradBuffer, Grads};
pub use params::{ParamLayout, Tensor};
