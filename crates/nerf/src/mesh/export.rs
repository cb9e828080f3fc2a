//! Writing meshes: binary PLY, OBJ and binary glTF (.glb), chosen by file extension, with
//! per-vertex colours. PLY and OBJ keep the scene's axes (Blender's, +Z up); glTF is +Y up
//! by specification, so .glb files are rotated into it (x, y, z) -> (x, z, -y). Files are
//! written to a temporary name and renamed into place.

use std::path::Path;

use super::Mesh;
use crate::error::{NerfError, Result};

/// Writes `mesh` with `colours` (one straight RGB per vertex) in the format of `path`'s
/// extension: `.ply`, `.obj` or `.glb`.
pub fn write_mesh(path: &Path, mesh: &Mesh, colours: &[[f32; 3]]) -> Result<()> {
    assert_eq!(mesh.vertices.len(), colours.len());
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let bytes = match ext.as_str() {
        "ply" => ply(mesh, colours),
        "obj" => obj(mesh, colours).into_bytes(),
        "glb" => {
            if mesh.triangles.is_empty() {
                return Err(NerfError::Config(format!(
                    "{}: the mesh is empty (no surface at this threshold); glTF cannot hold it",
                    path.display()
                )));
            }
            glb(mesh, colours)
        }
        _ => {
            return Err(NerfError::Config(format!(
                "{}: unknown mesh format; use .ply, .obj or .glb",
                path.display()
            )))
        }
    };
    crate::io::write_atomic(path, &bytes)
}

fn byte(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Binary little-endian PLY: float xyz + uchar rgb per vertex, int triangles.
pub fn ply(mesh: &Mesh, colours: &[[f32; 3]]) -> Vec<u8> {
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by nerf\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    );
    let mut out = header.into_bytes();
    for (v, c) in mesh.vertices.iter().zip(colours) {
        for x in v {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend(c.map(byte));
    }
    for t in &mesh.triangles {
        out.push(3);
        for i in t {
            out.extend_from_slice(&(*i as i32).to_le_bytes());
        }
    }
    out
}

/// OBJ with the common `v x y z r g b` colour extension; faces are 1-based.
pub fn obj(mesh: &Mesh, colours: &[[f32; 3]]) -> String {
    use std::fmt::Write;
    let mut s = String::from("# written by nerf\n");
    for (v, c) in mesh.vertices.iter().zip(colours) {
        let _ = writeln!(
            s,
            "v {} {} {} {:.4} {:.4} {:.4}",
            v[0], v[1], v[2], c[0], c[1], c[2]
        );
    }
    for t in &mesh.triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

/// Binary glTF 2.0: one mesh with POSITION, COLOR_0 (float RGB) and u32 indices.
pub fn glb(mesh: &Mesh, colours: &[[f32; 3]]) -> Vec<u8> {
    let y_up = |v: &[f32; 3]| [v[0], v[2], -v[1]];
    let mut bin = Vec::new();
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for v in &mesh.vertices {
        let p = y_up(v);
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
            bin.extend_from_slice(&p[k].to_le_bytes());
        }
    }
    let positions_len = bin.len();
    for c in colours {
        for x in c {
            bin.extend_from_slice(&x.clamp(0.0, 1.0).to_le_bytes());
        }
    }
    let colours_len = bin.len() - positions_len;
    for t in &mesh.triangles {
        for i in t {
            bin.extend_from_slice(&i.to_le_bytes());
        }
    }
    let indices_len = bin.len() - positions_len - colours_len;
    let (n, m) = (mesh.vertices.len(), mesh.triangles.len() * 3);
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "nerf"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "COLOR_0": 1},
            "indices": 2,
            "mode": 4
        }]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": positions_len, "target": 34962},
            {"buffer": 0, "byteOffset": positions_len, "byteLength": colours_len, "target": 34962},
            {"buffer": 0, "byteOffset": positions_len + colours_len, "byteLength": indices_len, "target": 34963}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": n, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5125, "count": m, "type": "SCALAR"}
        ]
    });
    let mut json = json.to_string().into_bytes();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}
