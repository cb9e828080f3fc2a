//! Crash-safe file output: write beside the target, then rename into place, so a killed
//! process or a full disk never leaves a half-written checkpoint or result behind.

use std::path::{Path, PathBuf};

use crate::error::{NerfError, Result};

/// The temporary sibling of `path` used while writing it.
pub fn tmp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    let tmp = tmp_path(path);
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    result.map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        NerfError::write(path, e)
    })
}

/// Serialises `value` as pretty JSON and writes it atomically.
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| NerfError::write(path, std::io::Error::other(e)))?;
    write_atomic(path, text.as_bytes())
}

/// Reads and parses a JSON file, naming the file in any error.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| NerfError::io(path, e))?;
    serde_json::from_str(&text).map_err(|source| json_error(path, source))
}

/// A JSON error named by its kind: text that is not JSON is "malformed"; valid JSON with
/// a field missing or of the wrong type says which field (serde's message names it).
pub(crate) fn json_error(path: &Path, source: serde_json::Error) -> NerfError {
    match source.classify() {
        serde_json::error::Category::Data => NerfError::format(path, source.to_string()),
        _ => NerfError::Json {
            path: path.to_path_buf(),
            source,
        },
    }
}

/// Creates a directory and its parents, naming it on failure.
pub fn create_dir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(|e| NerfError::write(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Valid JSON with a missing field says which field; broken text is
    /// called malformed.
    #[test]
    fn json_errors_say_what_is_wrong() {
        #[derive(serde::Deserialize, Debug)]
        #[allow(dead_code)]
        struct Doc {
            frames: Vec<u32>,
        }
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.json");
        std::fs::write(&path, r#"{"camera_angle_x": 0.7}"#).expect("write");
        let err = read_json::<Doc>(&path)
            .expect_err("missing field")
            .to_string();
        assert!(
            err.contains("t.json")
                && err.contains("missing field `frames`")
                && !err.contains("malformed"),
            "{err}"
        );
        std::fs::write(&path, r#"{"frames": [1, 2"#).expect("write");
        let err = read_json::<Doc>(&path).expect_err("truncated").to_string();
        assert!(
            err.contains("t.json") && err.contains("malformed JSON"),
            "{err}"
        );
    }
}
