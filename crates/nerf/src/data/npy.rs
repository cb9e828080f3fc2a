//! Minimal reader and writer of NumPy `.npy` files holding one 2-D float array (what LLFF's
//! `poses_bounds.npy` is). Format: magic `\x93NUMPY`, version, header length, a Python dict
//! literal `{'descr': '<f8', 'fortran_order': False, 'shape': (N, M), }` padded with spaces,
//! then the raw little-endian values.

use std::path::Path;

use crate::error::{NerfError, Result};

/// A row-major 2-D array.
#[derive(Clone, Debug, PartialEq)]
pub struct Array2 {
    pub rows: usize,
    pub cols: usize,
    pub data: Vec<f64>,
}

impl Array2 {
    pub fn row(&self, r: usize) -> &[f64] {
        &self.data[r * self.cols..(r + 1) * self.cols]
    }
}

pub fn read(path: &Path) -> Result<Array2> {
    let bytes = std::fs::read(path).map_err(|e| NerfError::io(path, e))?;
    parse(&bytes).map_err(|m| NerfError::format(path, m))
}

fn parse(bytes: &[u8]) -> std::result::Result<Array2, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a NumPy .npy file (bad magic)".into());
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(format!("unsupported .npy version {v}")),
    };
    let header = bytes
        .get(start..start + header_len)
        .ok_or("truncated .npy header")?;
    let header = std::str::from_utf8(header).map_err(|_| "the .npy header is not text")?;
    let field = |key: &str| -> std::result::Result<&str, String> {
        let at = header
            .find(&format!("'{key}'"))
            .ok_or(format!("the .npy header has no '{key}'"))?;
        let rest = &header[at + key.len() + 2..];
        Ok(rest.trim_start().trim_start_matches(':').trim_start())
    };
    let descr = field("descr")?;
    let width = if descr.starts_with("'<f8'") {
        8
    } else if descr.starts_with("'<f4'") {
        4
    } else {
        return Err(format!(
            "holds {}, expected little-endian float64 or float32",
            descr.split(',').next().unwrap_or(descr)
        ));
    };
    if field("fortran_order")?.starts_with("True") {
        return Err("Fortran-ordered arrays are not supported".into());
    }
    let shape = field("shape")?;
    let inner = shape
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or("cannot read the array's shape")?;
    let dims: Vec<usize> = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| format!("bad shape entry {s:?}"))
        })
        .collect::<std::result::Result<_, _>>()?;
    let (rows, cols) = match dims[..] {
        [r, c] => (r, c),
        [n] => (1, n),
        _ => return Err(format!("expected a 2-D array, got shape {dims:?}")),
    };
    let body = &bytes[start + header_len..];
    if body.len() < rows * cols * width {
        return Err(format!(
            "truncated: a {rows}x{cols} array needs {} bytes, the file has {}",
            rows * cols * width,
            body.len()
        ));
    }
    let data = body
        .chunks_exact(width)
        .take(rows * cols)
        .map(|c| match *c {
            [a, b, c, d, e, f, g, h] => f64::from_le_bytes([a, b, c, d, e, f, g, h]),
            [a, b, c, d] => f32::from_le_bytes([a, b, c, d]) as f64,
            _ => f64::NAN,
        })
        .collect();
    Ok(Array2 { rows, cols, data })
}

/// Writes a float64 `.npy` file (atomically).
pub fn write(path: &Path, a: &Array2) -> Result<()> {
    let mut header = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, {}), }}",
        a.rows, a.cols
    );
    // Magic (6) + version (2) + length (2) + header + '\n' is a multiple of 64.
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in &a.data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    crate::io::write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_rejects_bad_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("a.npy");
        let a = Array2 {
            rows: 2,
            cols: 3,
            data: vec![1.0, -2.5, 3.0, 4.0, 5.0, 1e-9],
        };
        write(&path, &a).expect("write");
        assert_eq!(read(&path).expect("read"), a);
        assert_eq!(read(&path).expect("read").row(1), &[4.0, 5.0, 1e-9]);

        std::fs::write(&path, b"hello").expect("write");
        assert!(read(&path)
            .expect_err("magic")
            .to_string()
            .contains("a.npy"));
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        let h = "{'descr': '<i8', 'fortran_order': False, 'shape': (2, 3), }\n";
        bytes.extend_from_slice(&(h.len() as u16).to_le_bytes());
        bytes.extend_from_slice(h.as_bytes());
        std::fs::write(&path, &bytes).expect("write");
        let err = read(&path).expect_err("ints").to_string();
        assert!(err.contains("float64"), "{err}");
    }
}
