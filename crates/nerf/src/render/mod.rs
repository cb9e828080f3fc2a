//! From a field to pixels: where to sample along rays ([`sampling`]) and how samples combine
//! into a colour ([`volume`]), with the coarse-to-fine pipeline of the paper in
//! [`pipeline`] and the fast field's occupancy-grid ray marching in [`occupancy`] and
//! [`marched`].

pub mod contraction;
pub mod marched;
pub mod occupancy;
pub mod pipeline;
pub mod sampling;
pub mod volume;
