//! From a field to pixels: where to sample along rays ([`sampling`]) and how samples combine
//! into a colour ([`volume`]), with the coarse-to-fine pipeline of the paper in
//! [`pipeline`].

pub mod pipeline;
pub mod sampling;
pub mod volume;
