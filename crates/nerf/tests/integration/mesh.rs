//! Meshes users take away: files other tools can read, and a trained chair whose mesh has
//! the chair's real size.

use nerf::data::synth::{self, SceneKind};
use nerf::mesh::export::write_mesh;
use nerf::mesh::extract::{colour_vertices, extract, ExtractOptions, DEFAULT_THRESHOLD};
use nerf::mesh::marching_cubes::{marching_cubes, Grid};
use nerf::mesh::Mesh;
use nerf::train::run::LoadedRun;

fn sphere_mesh() -> Mesh {
    let n = 24;
    let s = 2.0 / (n - 1) as f32;
    let mut values = Vec::new();
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = [x, y, z].map(|i| -1.0 + i as f32 * s);
                values.push(0.6 - (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt());
            }
        }
    }
    marching_cubes(
        &Grid {
            values: &values,
            dims: [n; 3],
            origin: [-1.0; 3],
            spacing: s,
        },
        0.0,
    )
}

#[test]
fn written_meshes_read_back_with_independent_readers() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mesh = sphere_mesh();
    let colours: Vec<[f32; 3]> = mesh
        .vertices
        .iter()
        .map(|v| v.map(|c| (c + 1.0) / 2.0))
        .collect();
    let (nv, nt) = (mesh.vertices.len(), mesh.triangles.len());

    let glb = dir.path().join("m.glb");
    write_mesh(&glb, &mesh, &colours).expect("glb");
    let (doc, buffers, _) = gltf::import(&glb).expect("the glTF reader accepts the file");
    let prim = doc
        .meshes()
        .next()
        .and_then(|m| m.primitives().next())
        .expect("one primitive");
    let reader = prim.reader(|b| Some(&buffers[b.index()]));
    let pos: Vec<[f32; 3]> = reader.read_positions().expect("positions").collect();
    let idx: Vec<u32> = reader.read_indices().expect("indices").into_u32().collect();
    let col: Vec<[f32; 3]> = reader
        .read_colors(0)
        .expect("colours")
        .into_rgb_f32()
        .collect();
    assert_eq!((pos.len(), idx.len(), col.len()), (nv, 3 * nt, nv));
    // glTF is +Y up: (x, y, z) -> (x, z, -y).
    let v = mesh.vertices[7];
    assert_eq!(pos[7], [v[0], v[2], -v[1]]);
    assert!((col[7][0] - colours[7][0]).abs() < 1e-6);

    let obj = dir.path().join("m.obj");
    write_mesh(&obj, &mesh, &colours).expect("obj");
    let (models, _) = tobj::load_obj(&obj, &tobj::GPU_LOAD_OPTIONS).expect("the OBJ reader");
    let m = &models[0].mesh;
    assert_eq!((m.positions.len(), m.indices.len()), (3 * nv, 3 * nt));
    // The reader may reorder vertices: compare the colour totals.
    let total: f32 = colours.iter().map(|c| c[1]).sum();
    let read: f32 = m.vertex_color.iter().skip(1).step_by(3).sum();
    assert!(m.vertex_color.len() == 3 * nv && (total - read).abs() < 1e-3 * nv as f32);

    // PLY: a structural read of the header and the binary body.
    let ply = dir.path().join("m.ply");
    write_mesh(&ply, &mesh, &colours).expect("ply");
    let bytes = std::fs::read(&ply).expect("read");
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("header")
        + 11;
    let header = std::str::from_utf8(&bytes[..end]).expect("ascii header");
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"));
    assert!(header.contains(&format!("element vertex {nv}\n")));
    assert!(header.contains(&format!("element face {nt}\n")));
    assert_eq!(bytes.len(), end + nv * 15 + nt * 13);
    let f = |o: usize| f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
    assert_eq!(
        [f(end + 7 * 15), f(end + 7 * 15 + 4), f(end + 7 * 15 + 8)],
        mesh.vertices[7]
    );
    let face = end + nv * 15;
    assert_eq!(bytes[face], 3);
    assert_eq!(
        i32::from_le_bytes([
            bytes[face + 1],
            bytes[face + 2],
            bytes[face + 3],
            bytes[face + 4]
        ]),
        mesh.triangles[0][0] as i32
    );

    let err = write_mesh(&dir.path().join("m.stl"), &mesh, &colours).expect_err("unknown format");
    assert!(err.to_string().contains("m.stl"), "{err}");
}

/// The shared trained chair's mesh has the chair's size (within 5% on every axis), its
/// point cloud lies on the chair, and its vertices take the chair's colours.
#[test]
fn mesh_of_a_trained_chair_has_the_chairs_size() {
    let chair = crate::common::trained_chair();
    let data = &chair.data;
    let run = LoadedRun::open(&chair.run).expect("run");
    let options = ExtractOptions {
        resolution: 96,
        threshold: DEFAULT_THRESHOLD,
        bound: 1.5,
        keep_largest: Some(1),
        time: 0.0,
    };
    let mesh = extract(run.engine.as_ref(), &options, &mut |_, _| {});
    assert!(
        mesh.triangles.len() > 1000,
        "{} triangles",
        mesh.triangles.len()
    );
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for v in &mesh.vertices {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    let (tlo, thi) = synth::Scene::new(SceneKind::Chair.parts()).bounds();
    for k in 0..3 {
        let (size, truth) = (hi[k] - lo[k], thi[k] - tlo[k]);
        eprintln!("axis {k}: mesh {lo:?}..{hi:?}, size {size:.3} vs {truth:.3}");
        assert!(
            (size / truth - 1.0).abs() < 0.05,
            "axis {k}: mesh extent {size:.3} vs the chair's {truth:.3}"
        );
    }
    // The point cloud from rendered depth lies on the chair too.
    let data_views =
        nerf::data::scene::load_blender(data, nerf::data::Split::Train, 2, 15).expect("views");
    let cameras: Vec<_> = data_views.views.iter().map(|v| v.camera.clone()).collect();
    let settings = nerf::views::RenderSettings::of_dataset(&data_views, [1.0; 3]);
    let (points, point_colours) =
        nerf::mesh::points::from_views(run.engine.as_ref(), &cameras, &settings, 0.95, &mut |_| {});
    assert!(points.len() > 500 && points.len() == point_colours.len());
    let near_chair = points
        .iter()
        .filter(|p| (0..3).all(|k| p[k] > tlo[k] - 0.05 && p[k] < thi[k] + 0.05))
        .count();
    assert!(
        near_chair * 100 >= points.len() * 98,
        "{near_chair} of {} points within 5 cm of the chair's box",
        points.len()
    );
    let colours = colour_vertices(run.engine.as_ref(), &mesh, 0.05, 0.0);
    // The chair is wood and fabric, not black or white: most vertices get a real colour.
    let coloured = colours
        .iter()
        .filter(|c| c.iter().any(|&x| x > 0.05) && c.iter().any(|&x| x < 0.95))
        .count();
    assert!(
        coloured * 10 > colours.len() * 8,
        "{coloured} of {} coloured",
        colours.len()
    );
}
