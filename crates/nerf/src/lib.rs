//! `nerf`: neural radiance fields (Mildenhall et al., ECCV 2020) on a plain CPU.
//!
//! Data flows one way: [`data`] (posed images, training rays) -> [`render::sampling`] or
//! [`render::march`] (samples) -> a [`stage::Field`] ([`field`]) -> [`render::volume`]
//! (compositing, the volume renderer) -> [`render::loss`], and gradients flow back the same
//! way into [`nn::Adam`]. The values between these stages and the contract every
//! differentiable stage follows are in [`stage`]. Each [`model`] strings the stages into a
//! training pass and a renderer; an [`engine`] owns a model's parameters and runs it (the
//! CPU engine today; the seam where a GPU engine plugs in). Above the seam: [`train`] (the
//! schedule and the run folder), [`eval`] and [`metrics`], [`views`] (whole images),
//! [`mesh`], and [`data::synth`], which renders the built-in scenes.

pub mod args;
pub mod bench_fast;
pub mod bench_vanilla;
pub mod camera;
pub mod capture;
pub mod checkpoint;
pub mod data;
pub mod demo;
pub mod encoding;
pub mod engine;
pub mod error;
pub mod eval;
pub mod field;
pub mod frames;
pub mod io;
pub mod looks;
pub mod math;
pub mod mesh;
pub mod metrics;
pub mod model;
pub mod nn;
pub mod presets;
pub use train::refined_cameras;
pub mod render;
pub mod rng;
pub mod stage;
pub mod test_poses;
pub mod train;
pub mod video;
pub mod views;

pub use error::{NerfError, Result};
