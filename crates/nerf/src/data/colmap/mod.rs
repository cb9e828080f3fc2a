//! COLMAP sparse models: [`model`] reads and writes the files (`cameras`, `images`,
//! `points3D`, binary or text), [`scene`] places a model as a trainable scene. Running
//! COLMAP itself on photos is the job of the `capture` module, above this one.

pub mod model;
pub mod scene;

pub use model::*;
