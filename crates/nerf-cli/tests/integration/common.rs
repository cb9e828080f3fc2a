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

/// `nerf synth` of the built-in `scene` at 16 pixels into `scene`, with these many
/// training, validation and test views.
pub fn synth_args<'a>(scene: &'a str, [train, val, test]: [&'a str; 3]) -> Vec<&'a str> {
    vec![
        "synth",
        "--scene",
        scene,
        "--out",
        "scene",
        "--size",
        "16",
        "--train-views",
        train,
        "--val-views",
        val,
        "--test-views",
        test,
    ]
}

/// A quick fast-model training command on `scene` into `<out>`.
pub fn train_args<'a>(out: &'a str, steps: &'a str, more: &[&'a str]) -> Vec<&'a str> {
    let mut a = vec![
        "--threads",
        "2",
        "train",
        "--data",
        "scene",
        "--out",
        out,
        "--steps",
        steps,
        "--samples",
        "1024",
        "--table-log2",
        "10",
        "--val-every",
        "3",
    ];
    a.extend_from_slice(more);
    a
}
