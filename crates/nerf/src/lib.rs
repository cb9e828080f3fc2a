//! `nerf`: neural radiance fields (Mildenhall et al., ECCV 2020) on a plain CPU.
//!
//! Data flows one way: [`data`] (posed images) -> [`camera`] rays -> [`render::sampling`]
//! -> [`field`] (the MLP) -> [`render::volume`] (compositing) -> loss, and gradients flow
//! back the same way into [`nn::Adam`]. [`train`] runs that loop with checkpoints;
//! [`eval`] measures PSNR / SSIM; [`data::synth`] renders the built-in scenes.

pub mod bench;
pub mod bench_fast;
pub mod camera;
pub mod camera_path;
pub mod capture;
pub mod checkpoint;
pub mod data;
pub mod distortion;
pub mod encoding;
pub mod error;
pub mod eval;
pub mod field;
pub mod io;
pub mod math;
pub mod mesh;
pub mod model;
pub mod nn;
pub mod presets;
pub mod ray_space;
pub mod render;
pub mod renderer;
pub mod rng;
pub mod train;
pub mod video;

pub use error::{NerfError, Result};
