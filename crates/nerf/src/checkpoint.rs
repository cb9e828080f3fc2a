//! Checkpoints: weights, Adam moments, step and random state in one `safetensors` file.
//!
//! Tensors are stored under the model's names (`coarse.pts_0.weight`, ...), Adam's moments
//! under `adam.m.<name>` and `adam.v.<name>`, non-trainable buffers (the fast model's
//! occupancy grid) under their own names. The header metadata holds the step, the Adam
//! step count, the seed and the training time so far. The random state of a run is fully
//! determined by `(seed, step)` (see `rng`), so nothing else is needed to resume exactly.
//! Files are written to a temporary name and renamed, so a crash never leaves a torn file.

use std::collections::HashMap;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use crate::error::{NerfError, Result};
use crate::nn::ParamLayout;

const FORMAT: &str = "nerf-checkpoint-1";

/// Everything needed to continue a run.
#[derive(Clone, Debug, PartialEq)]
pub struct Checkpoint {
    pub step: u64,
    pub seed: u64,
    pub elapsed_seconds: f64,
    pub params: Vec<f32>,
    pub adam_m: Vec<f32>,
    pub adam_v: Vec<f32>,
    pub adam_t: u64,
    /// Non-trainable model state (the occupancy grid), in buffer-layout order.
    pub buffers: Vec<f32>,
}

fn bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Writes `ckpt` (parameters laid out by `layout`, buffers by `buffer_layout`) to `path`
/// atomically.
pub fn save(
    path: &Path,
    layout: &ParamLayout,
    buffer_layout: &ParamLayout,
    ckpt: &Checkpoint,
) -> Result<()> {
    let groups = [
        ("", &ckpt.params, layout),
        ("adam.m.", &ckpt.adam_m, layout),
        ("adam.v.", &ckpt.adam_v, layout),
        ("", &ckpt.buffers, buffer_layout),
    ];
    let mut owned = Vec::new();
    for (prefix, values, layout) in groups {
        for t in &layout.tensors {
            owned.push((
                format!("{prefix}{}", t.name),
                t.shape.clone(),
                bytes(&values[t.range()]),
            ));
        }
    }
    let views = owned
        .iter()
        .map(|(name, shape, data)| {
            TensorView::new(Dtype::F32, shape.clone(), data).map(|v| (name.clone(), v))
        })
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| problem(path, e))?;
    let mut meta = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("step".to_string(), ckpt.step.to_string()),
        ("seed".to_string(), ckpt.seed.to_string()),
        ("adam_t".to_string(), ckpt.adam_t.to_string()),
        (
            "elapsed_seconds".to_string(),
            ckpt.elapsed_seconds.to_string(),
        ),
    ]);
    // A checksum per tensor, so a bit flipped on disk is reported, not trained on.
    for (name, _, data) in &owned {
        meta.insert(checksum_key(name), format!("{:08x}", crc32fast::hash(data)));
    }
    let data = safetensors::serialize(views, Some(meta)).map_err(|e| problem(path, e))?;
    crate::io::write_atomic(path, &data)
}

/// Reads a checkpoint and checks that it has every tensor of `layout` and `buffer_layout`
/// with the same shape.
pub fn load(path: &Path, layout: &ParamLayout, buffer_layout: &ParamLayout) -> Result<Checkpoint> {
    let data = std::fs::read(path).map_err(|e| NerfError::io(path, e))?;
    let st = SafeTensors::deserialize(&data).map_err(|e| problem(path, e))?;
    let (_, header) = SafeTensors::read_metadata(&data).map_err(|e| problem(path, e))?;
    let meta = header.metadata().clone().unwrap_or_default();
    if meta.get("format").map(String::as_str) != Some(FORMAT) {
        return Err(problem(
            path,
            "not a nerf checkpoint (metadata `format` missing or different)",
        ));
    }
    let num = |key: &str| -> Result<f64> {
        meta.get(key)
            .and_then(|v| v.parse::<f64>().ok())
            .ok_or_else(|| problem(path, format!("metadata `{key}` missing or not a number")))
    };
    let read_group = |prefix: &str, layout: &ParamLayout| -> Result<Vec<f32>> {
        let mut out = vec![0.0f32; layout.total];
        for t in &layout.tensors {
            let name = format!("{prefix}{}", t.name);
            let view = st.tensor(&name).map_err(|_| {
                problem(
                    path,
                    format!(
                        "tensor `{name}` is missing; was it saved by another model configuration?"
                    ),
                )
            })?;
            if view.dtype() != Dtype::F32 || view.shape() != t.shape.as_slice() {
                return Err(problem(
                    path,
                    format!(
                        "tensor `{name}` is {:?} {:?}, expected F32 {:?}",
                        view.dtype(),
                        view.shape(),
                        t.shape
                    ),
                ));
            }
            // Checkpoints written before checksums existed have none; they load unchecked.
            if let Some(want) = meta.get(&checksum_key(&name)) {
                let got = format!("{:08x}", crc32fast::hash(view.data()));
                if *want != got {
                    return Err(problem(
                        path,
                        format!(
                            "tensor `{name}` is corrupt (checksum {got}, saved as {want}); \
                             the file was damaged after it was written"
                        ),
                    ));
                }
            }
            let range = t.range();
            for (o, b) in out[range.clone()]
                .iter_mut()
                .zip(view.data().chunks_exact(4))
            {
                *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
            if let Some(i) = out[range].iter().position(|v| !v.is_finite()) {
                return Err(problem(
                    path,
                    format!(
                        "tensor `{name}` holds a non-finite value ({} at index {i}); the \
                         weights are unusable",
                        out[t.range()][i]
                    ),
                ));
            }
        }
        Ok(out)
    };
    Ok(Checkpoint {
        step: num("step")? as u64,
        seed: meta
            .get("seed")
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| problem(path, "metadata `seed` missing"))?,
        elapsed_seconds: num("elapsed_seconds")?,
        adam_t: num("adam_t")? as u64,
        params: read_group("", layout)?,
        adam_m: read_group("adam.m.", layout)?,
        adam_v: read_group("adam.v.", layout)?,
        buffers: read_group("", buffer_layout)?,
    })
}

fn checksum_key(tensor: &str) -> String {
    format!("crc32.{tensor}")
}

/// The step a checkpoint was saved at, from its header alone.
pub fn read_step(path: &Path) -> Result<u64> {
    use std::io::Read;
    // Only the header (an 8-byte length, then JSON): the tensors after it can be hundreds
    // of megabytes, which the resume reads once, afterwards, in `load`.
    let mut file = std::fs::File::open(path).map_err(|e| NerfError::io(path, e))?;
    let mut len = [0u8; 8];
    file.read_exact(&mut len)
        .map_err(|_| problem(path, "too short to be a checkpoint"))?;
    let len = u64::from_le_bytes(len);
    if len > MAX_HEADER_BYTES {
        return Err(problem(
            path,
            format!("header of {len} bytes: not a checkpoint"),
        ));
    }
    let mut header = vec![0u8; len as usize];
    file.read_exact(&mut header)
        .map_err(|_| problem(path, "the header is cut short"))?;
    let header: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| problem(path, e))?;
    header["__metadata__"]["step"]
        .as_str()
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| problem(path, "metadata `step` missing or not a number"))
}

/// The safetensors format's own bound on its JSON header.
const MAX_HEADER_BYTES: u64 = 100_000_000;

fn problem(path: &Path, e: impl std::fmt::Display) -> NerfError {
    NerfError::Checkpoint {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> ParamLayout {
        let mut l = ParamLayout::default();
        l.push("a.weight", &[2, 3]);
        l.push("a.bias", &[3]);
        l
    }

    fn buffers() -> ParamLayout {
        let mut l = ParamLayout::default();
        l.push("grid", &[2, 2]);
        l
    }

    #[test]
    fn round_trip_and_errors() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("ckpt.safetensors");
        let ckpt = Checkpoint {
            step: 42,
            seed: u64::MAX - 3,
            elapsed_seconds: 1.5,
            params: (0..9).map(|i| i as f32 * 0.5).collect(),
            adam_m: vec![0.25; 9],
            adam_v: vec![0.125; 9],
            adam_t: 42,
            buffers: vec![7.0; 4],
        };
        save(&path, &layout(), &buffers(), &ckpt).expect("save");
        assert!(!crate::io::tmp_path(&path).exists());
        assert_eq!(read_step(&path).expect("step"), 42);
        assert_eq!(load(&path, &layout(), &buffers()).expect("load"), ckpt);
        let mut absent = ParamLayout::default();
        absent.push("occupancy", &[2, 2]);
        let missing = load(&path, &layout(), &absent).expect_err("buffer missing");
        assert!(missing.to_string().contains("occupancy"), "{missing}");

        let mut other = ParamLayout::default();
        other.push("a.weight", &[3, 3]);
        let err = load(&path, &other, &buffers()).expect_err("shape mismatch");
        assert!(
            err.to_string().contains("a.weight") && err.to_string().contains("ckpt.safetensors"),
            "{err}"
        );

        std::fs::write(&path, b"garbage").expect("write");
        assert!(load(&path, &layout(), &buffers()).is_err());
        assert!(read_step(&path).is_err());
    }

    /// A flipped bit is found by the tensor's checksum, and non-finite
    /// weights (saved as such) are refused, each naming the tensor and the file.
    #[test]
    fn corrupt_and_non_finite_tensors_are_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("ckpt.safetensors");
        let mut ckpt = Checkpoint {
            step: 1,
            seed: 0,
            elapsed_seconds: 0.0,
            params: vec![0.5; 9],
            adam_m: vec![0.0; 9],
            adam_v: vec![0.0; 9],
            adam_t: 1,
            buffers: vec![1.0; 4],
        };
        save(&path, &layout(), &buffers(), &ckpt).expect("save");
        // 0.5f32 is 00 00 00 3f: flip a bit of the first weight's mantissa.
        let mut bytes = std::fs::read(&path).expect("read");
        let at = bytes
            .windows(4)
            .position(|w| w == 0.5f32.to_le_bytes())
            .expect("a weight");
        bytes[at] ^= 1;
        std::fs::write(&path, &bytes).expect("write");
        let err = load(&path, &layout(), &buffers())
            .expect_err("bit flip")
            .to_string();
        assert!(
            err.contains("corrupt")
                && err.contains("ckpt.safetensors")
                && err.contains("tensor `a."),
            "{err}"
        );

        ckpt.params[4] = f32::NAN;
        save(&path, &layout(), &buffers(), &ckpt).expect("save");
        let err = load(&path, &layout(), &buffers())
            .expect_err("NaN")
            .to_string();
        assert!(
            err.contains("a.weight")
                && err.contains("non-finite")
                && err.contains("ckpt.safetensors"),
            "{err}"
        );
    }
}
