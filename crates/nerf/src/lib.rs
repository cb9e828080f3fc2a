//! `nerf`: neural radiance fields (Mildenhall et al., ECCV 2020), trained and rendered on a
//! CPU or a GPU.
//!
//! Data flows one way: [`data`] (posed images, training rays) -> [`render::sampling`] or
//! [`render::march`] (samples) -> a [`stage::Field`] ([`field`]) -> [`render::volume`]
//! (compositing, the volume renderer) -> [`render::loss`], and gradients flow back the same
//! way into [`nn::Adam`]. The values between these stages and the contract every
//! differentiable stage follows are in [`stage`]. Each [`model`] strings the stages into a
//! training pass and a renderer; an [`engine`] owns a model's parameters and runs it (the
//! CPU engine, the reference, and the GPU engine, CubeCL kernels behind the same seam).
//! Above the seam: [`train`] (the schedule and the run folder), [`metrics`], [`views`]
//! (whole images), [`mesh`], and [`data::synth`], which renders the built-in scenes. On
//! the top floor, [`app`]: the pipelines each command runs (demo, eval, rendering paths,
//! benches, capture), which nothing below imports.

pub mod app;
pub mod args;
pub mod camera;
pub mod checkpoint;
pub mod data;
pub mod encoding;
pub mod engine;
pub mod error;
pub mod field;
pub mod io;
pub mod math;
pub mod mesh;
pub mod metrics;
pub mod model;
pub mod nn;
pub mod presets;
pub mod render;
pub mod rng;
pub mod simd;
pub mod stage;
pub mod step_clock;
pub mod train;
pub mod views;

pub use error::{NerfError, Result};
