//! The library's integration tests, one module per subject. They are one test binary, so
//! `cargo test` links the library into it once and runs the slow tests of every subject
//! side by side instead of one subject after another.

mod common;

mod antialias;
mod dynamic;
mod end_to_end;
mod fast_model;
mod few_view;
#[cfg(feature = "wgpu")]
mod gpu_engine;
mod layers;
mod mesh;
mod real_formats;
mod scene_checks;
mod stuck_cameras;
mod thread_count;
