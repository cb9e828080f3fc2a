//! The applications: pipelines that string the core (data, cameras, fields, models, engines,
//! training) into the jobs people run. Each command of the `nerf` binary is a thin front end
//! over one of these; nothing in the core imports them.

pub mod bench_fast;
pub mod bench_vanilla;
pub mod capture;
pub mod demo;
pub mod eval;
pub mod frames;
pub mod looks;
pub mod test_poses;
pub mod video;
