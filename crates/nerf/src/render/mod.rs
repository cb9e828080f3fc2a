//! Pure rendering stages, from rays to pixels, for any [`Field`](crate::stage::Field):
//! where to sample along rays ([`sampling`]: the paper's stratified and hierarchical
//! samplers; [`march`] with [`occupancy`]: Instant-NGP's occupancy-grid marcher, with
//! [`contraction`] for unbounded scenes), how samples combine into a colour ([`volume`]:
//! compositing and its backward, the volume renderer), and what the colour is compared
//! with ([`loss`]; the [`distortion`] and [`depth_smoothness`] regularisers). Nothing here knows a model: each model's pass (`model::*`) strings
//! these stages together.

pub mod contraction;
pub mod depth_smoothness;
pub mod distortion;
pub mod loss;
pub mod march;
pub mod occupancy;
pub mod sampling;
pub mod volume;
