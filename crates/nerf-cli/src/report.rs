//! How a failed command is reported: the error and each cause once.
//!
//! Library errors print their cause in their own message ("cannot read x.json: No such file
//! or directory") and also expose it as `source()`, as typed errors should; printing the
//! whole chain would then say the cause twice. A cause whose text the message already
//! holds is left out.

/// The error and every cause not already spelled out by the text before it.
pub fn message(e: &anyhow::Error) -> String {
    let mut text = e.to_string();
    for cause in e.chain().skip(1) {
        let cause = cause.to_string();
        if !text.contains(&cause) {
            text.push_str(": ");
            text.push_str(&cause);
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An I/O error named its cause twice.
    #[test]
    fn each_cause_is_said_once() {
        let missing = nerf::io::read_json::<serde_json::Value>(std::path::Path::new(
            "/nonexistent/transforms.json",
        ))
        .expect_err("missing file");
        let text = message(&anyhow::Error::new(missing));
        assert_eq!(
            text.matches("No such file or directory").count(),
            1,
            "{text}"
        );
        assert!(text.contains("/nonexistent/transforms.json"), "{text}");

        // A context that does not repeat its cause keeps it.
        let e = anyhow::Error::new(std::io::Error::other("disk on fire")).context("saving");
        assert_eq!(message(&e), "saving: disk on fire");
    }
}
