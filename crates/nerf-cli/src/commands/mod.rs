//! One file per subcommand: argument glue between the command line and the library.

pub mod bench;
pub mod capture;
pub mod demo;
pub mod eval;
pub mod export_cameras;
pub mod mesh;
pub mod points;
pub mod render;
pub mod scene;
pub mod synth;
pub mod train;
