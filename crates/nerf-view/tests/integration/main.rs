//! The viewer's tests: its server over HTTP, and its page in a headless browser. One test
//! binary: `cargo test` runs them side by side.

mod common;

mod browser;
mod server;
