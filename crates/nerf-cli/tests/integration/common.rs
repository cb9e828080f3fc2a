//! What the command-line tests share.

use std::process::Output;

/// A finished command's stdout and stderr, as one text.
pub fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// Its text; fails the test, showing it, unless the command succeeded.
pub fn ok(out: &Output) -> String {
    let t = text(out);
    assert!(out.status.success(), "nerf failed:\n{t}");
    t
}
