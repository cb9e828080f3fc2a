//! The command line's tests, one module per subject, run against the built `nerf` binary.
//! One test binary: `cargo test` runs the slow tests of every subject side by side.

mod common;

mod capture;
mod cli;
mod hardening;
