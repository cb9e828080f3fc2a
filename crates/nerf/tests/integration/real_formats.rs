//! Real-capture formats on fixtures the tests write from the built-in scenes, whose true
//! cameras are known: LLFF (`poses_bounds.npy`), COLMAP text models and `transforms.json`
//! must give back the true cameras up to the similarity each format's placement applies.

use std::path::Path;

use nerf::camera::ray_space::RaySpace;
use nerf::camera::{look_at, Camera, Pose};
use nerf::data::colmap::{self, CameraModel, Model};
use nerf::data::image::save_rgb_png;
use nerf::data::poses::{column, fit_similarity, origin, rotation_error_degrees, Similarity};
use nerf::data::scene::{Format, Scene, SceneOptions};
use nerf::data::synth::{self, SceneKind};
use nerf::data::{llff, npy, Split};
use nerf::math::{length, normalize_or_zero, sub};

/// A rendered view: camera, opaque RGB over grey, per-pixel depth (0 = background).
struct Shot {
    camera: Camera,
    rgb: Vec<f32>,
    depth: Vec<f32>,
}

fn shoot(kind: SceneKind, cameras: Vec<Camera>) -> Vec<Shot> {
    let scene = synth::Scene::new(kind.parts());
    cameras
        .into_iter()
        .map(|camera| {
            let img = synth::render(&scene, &camera, 1);
            let rgb = img
                .rgba
                .chunks_exact(4)
                .flat_map(|p| [0, 1, 2].map(|c| p[c] * p[3] + 0.5 * (1.0 - p[3])))
                .collect();
            Shot {
                camera,
                rgb,
                depth: img.depth,
            }
        })
        .collect()
}

/// Asserts `loaded` = `sim(truth)` for one similarity (positions and rotations), and
/// returns it.
fn assert_same_up_to_similarity(truth: &[Pose], loaded: &[Pose], what: &str) -> Similarity {
    let a: Vec<_> = truth.iter().map(origin).collect();
    let b: Vec<_> = loaded.iter().map(origin).collect();
    let (sim, rms) = fit_similarity(&a, &b);
    let spread = b
        .iter()
        .map(|p| length(*p))
        .fold(0.0f32, f32::max)
        .max(1e-3);
    assert!(
        rms < 1e-4 * spread,
        "{what}: camera centres off by {rms} (spread {spread})"
    );
    for (t, l) in truth.iter().zip(loaded) {
        let err = rotation_error_degrees(&sim.apply_pose(t), l);
        assert!(err < 0.05, "{what}: rotation off by {err} degrees");
    }
    sim
}

fn write_llff(dir: &Path, cameras: &[Camera], world: &Similarity) {
    synth::llff::write(SceneKind::Rug, cameras, 1, world, dir, &mut |_, _| {}).expect("write llff");
}

#[test]
fn llff_forward_facing_round_trips_and_trains_in_ndc() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cameras = synth::llff::forward_facing_cameras(96, 72, 5, 6);
    let shots = shoot(SceneKind::Rug, cameras.clone());
    let world = Similarity {
        rotation: [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [10.0, -3.0, 2.0],
        scale: 7.0,
    };
    write_llff(dir.path(), &cameras, &world);

    let scene = Scene::open(dir.path(), &SceneOptions::default(), 1).expect("open llff");
    assert_eq!(scene.format, Format::Llff);
    assert_eq!(scene.frames.len(), 30);
    assert_eq!(
        scene.test,
        vec![0, 8, 16, 24],
        "every 8th image is held out"
    );
    assert!(matches!(scene.space, RaySpace::Ndc(_)), "{:?}", scene.space);
    assert_eq!(scene.ray_bounds(), (0.0, 1.0));
    assert!(
        scene.warnings().is_empty(),
        "a forward-facing capture: {:?}",
        scene.warnings()
    );
    assert!(!scene.contract, "NDC already reaches infinity");
    let truth: Vec<Pose> = shots.iter().map(|s| s.camera.c2w).collect();
    let loaded: Vec<Pose> = scene.frames.iter().map(|f| f.camera.c2w).collect();
    let sim = assert_same_up_to_similarity(&truth, &loaded, "LLFF");
    // Recentred on the average pose: it looks down -Z from the origin.
    let mean_z = loaded.iter().map(|p| column(p, 2)[2]).sum::<f32>() / 30.0;
    let mean_o = loaded
        .iter()
        .fold([0.0f32; 3], |s, p| nerf::math::add(s, origin(p)));
    assert!(
        mean_z > 0.99 && length(mean_o) / 20.0 < 1e-4,
        "{mean_z} {mean_o:?}"
    );
    // Scaled so the nearest scene point is 1 / 0.75 away: beyond the NDC near plane (1).
    let nearest = shots
        .iter()
        .flat_map(|s| s.depth.iter().copied().filter(|d| *d > 0.0))
        .fold(f32::INFINITY, f32::min);
    assert!(
        (nearest * sim.scale - 1.0 / 0.75).abs() < 1e-3,
        "{}",
        nearest * sim.scale
    );
    let f = &scene.frames[3].camera;
    assert_eq!((f.width, f.height), (96, 72));
    assert!((f.fx - shots[3].camera.fx).abs() < 1e-3);

    // --downscale 2 reads images_2/ with the focal length halved.
    let half = Scene::open(dir.path(), &SceneOptions::default(), 2).expect("open half");
    let cams = half.cameras(Split::Train);
    assert_eq!((cams[0].width, cams[0].height), (48, 36));
    assert!((cams[0].fx - 0.5 * shots[1].camera.fx).abs() < 1e-3);
    assert_eq!(half.load(Split::Test, 1).expect("load").views.len(), 4);
    // A run's record of the scene, taken at full resolution, gives the same cameras at
    // --downscale 2 as images_2/ does.
    let full = Scene::open(dir.path(), &SceneOptions::default(), 1).expect("open full");
    let kept = nerf::data::snapshot::SceneSnapshot::of(&full).scene(2, String::new());
    for (a, b) in kept.cameras(Split::Train).iter().zip(&cams) {
        assert_eq!((a.width, a.height), (b.width, b.height));
        assert!((a.fx - b.fx).abs() < 1e-3 && (a.cx - b.cx).abs() < 1e-3);
    }

    // The fast model learns the scene in NDC space: held-out PSNR well above a blank guess.
    let mut config = crate::common::fast_config(dir.path(), 600);
    if let nerf::model::ModelConfig::Fast(m) = &mut config.model {
        m.field.bound = scene.bound;
        m.samples_per_step = 1 << 14;
    }
    let out = dir.path().join("run");
    nerf::train::run::train(&crate::common::cpu_run(&out, config), &mut |_| {}).expect("train");
    let run = nerf::train::run::LoadedRun::open(&out).expect("open run");
    let report = crate::common::eval_test(&run, 1, &out.join("eval"));
    // The best constant image (each view's own mean colour) scores far lower (measured:
    // 26.3 dB against 17.7 dB).
    let test = scene.load(Split::Test, 1).expect("test views");
    let constant = test
        .views
        .iter()
        .map(|v| {
            let rgb = v.image.composite([0.0; 3]);
            let n = (rgb.len() / 3) as f32;
            let mean: Vec<f32> = (0..3)
                .map(|c| rgb.iter().skip(c).step_by(3).sum::<f32>() / n)
                .collect();
            let flat: Vec<f32> = (0..rgb.len()).map(|i| mean[i % 3]).collect();
            nerf::metrics::psnr(&flat, &rgb)
        })
        .sum::<f32>()
        / test.views.len() as f32;
    eprintln!(
        "LLFF fixture, NDC, 600 steps: held-out PSNR {:.2} dB (best constant image {constant:.2} dB)",
        report.mean_psnr
    );
    assert!(
        report.mean_psnr > constant + 7.0,
        "PSNR {} vs constant {constant}",
        report.mean_psnr
    );
}

#[test]
fn llff_errors_name_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cameras = synth::llff::forward_facing_cameras(8, 6, 1, 3);
    write_llff(dir.path(), &cameras, &Similarity::IDENTITY);
    std::fs::remove_file(dir.path().join("images/001.png")).expect("rm");
    let err = Scene::open(dir.path(), &SceneOptions::default(), 1).expect_err("2 images, 3 poses");
    assert!(
        err.to_string().contains("holds 2 images") && err.to_string().contains("3 poses"),
        "{err}"
    );
    let bad = npy::Array2 {
        rows: 2,
        cols: 15,
        data: vec![0.0; 30],
    };
    npy::write(&dir.path().join(llff::POSES_FILE), &bad).expect("npy");
    let err = Scene::open(dir.path(), &SceneOptions::default(), 1).expect_err("2x15");
    assert!(
        err.to_string().contains("poses_bounds.npy") && err.to_string().contains("N x 17"),
        "{err}"
    );
}

/// Cameras around the object, as a handheld capture would be.
fn around(n: usize, size: usize) -> Vec<Camera> {
    (0..n)
        .map(|k| {
            let az = k as f32 / n as f32 * std::f32::consts::TAU;
            let el = 0.35 + 0.25 * (k % 3) as f32;
            let eye = nerf::camera::spherical(4.0, az, el);
            Camera::from_fov_x(
                size,
                size,
                0.8,
                look_at(eye, [0.1, -0.05, 0.0], [0.0, 0.0, 1.0]),
            )
        })
        .collect()
}

#[test]
fn colmap_text_model_round_trips_with_bounds_from_its_points() {
    let dir = tempfile::tempdir().expect("tempdir");
    let shots = shoot(SceneKind::Chair, around(12, 40));
    // COLMAP's world: ours under an arbitrary similarity.
    let world = Similarity {
        rotation: [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        translation: [3.0, 1.0, -2.0],
        scale: 2.0,
    };
    let mut model = Model::default();
    model.cameras.insert(
        1,
        colmap::Camera {
            id: 1,
            model: CameraModel::Pinhole,
            width: 40,
            height: 40,
            params: vec![
                shots[0].camera.fx as f64,
                shots[0].camera.fy as f64,
                20.0,
                20.0,
            ],
        },
    );
    model.cameras.insert(
        2,
        colmap::Camera {
            id: 2,
            model: CameraModel::Opencv,
            width: 40,
            height: 40,
            params: vec![
                shots[0].camera.fx as f64,
                shots[0].camera.fy as f64,
                20.0,
                20.0,
                0.02,
                -0.01,
                0.001,
                0.0,
            ],
        },
    );
    std::fs::create_dir_all(dir.path().join("images")).expect("mkdir");
    // Scene points: every 7th hit pixel of every view, seen by that view.
    let mut point_id = 0u64;
    for (k, s) in shots.iter().enumerate() {
        let name = format!("view_{k:02}.png");
        save_rgb_png(&dir.path().join("images").join(&name), 40, 40, &s.rgb).expect("png");
        let pose = world.apply_pose(&s.camera.c2w);
        let mut image =
            colmap::Image::from_camera_to_world(k as u32 + 1, 1 + (k % 2) as u32, &name, &pose);
        for (p, &d) in s
            .depth
            .iter()
            .enumerate()
            .filter(|(_, d)| **d > 0.0)
            .step_by(7)
        {
            let ray = s.camera.ray(p % 40, p / 40);
            let x = world.apply_point(std::array::from_fn(|c| ray.origin[c] + d * ray.dir[c]));
            point_id += 1;
            model.points.push(colmap::Point {
                id: point_id,
                xyz: x.map(f64::from),
                rgb: [0; 3],
                error: 0.1,
            });
            image.point_ids.push(point_id);
        }
        model.images.push(image);
    }
    colmap::write_text_model(&dir.path().join("sparse/0"), &model).expect("write");

    let scene = Scene::open(dir.path(), &SceneOptions::default(), 1).expect("open colmap");
    assert_eq!(scene.format, Format::Colmap);
    let truth: Vec<Pose> = shots.iter().map(|s| s.camera.c2w).collect();
    let loaded: Vec<Pose> = scene.frames.iter().map(|f| f.camera.c2w).collect();
    let sim = assert_same_up_to_similarity(&truth, &loaded, "COLMAP");
    // Placed: cameras at RMS radius 1 around what they look at, +Z up.
    let rms = (loaded
        .iter()
        .map(|p| nerf::math::dot(origin(p), origin(p)))
        .sum::<f32>()
        / 12.0)
        .sqrt();
    assert!((rms - 1.0).abs() < 1e-4, "radius {rms}");
    let centre = sim.apply_point([0.1, -0.05, 0.0]);
    assert!(length(centre) < 1e-3, "focus point at {centre:?}");
    let up = sim.rotation[2];
    assert!(
        normalize_or_zero(up)[2] > 0.999,
        "our +Z is the scene's up: {:?}",
        sim.rotation
    );
    // Near and far bracket every true depth; the box holds the chair.
    let depths: Vec<f32> = shots
        .iter()
        .flat_map(|s| s.depth.iter().copied().filter(|d| *d > 0.0))
        .collect();
    let (lo, hi) = depths
        .iter()
        .fold((f32::INFINITY, 0.0f32), |(l, h), &d| (l.min(d), h.max(d)));
    assert!(
        scene.near <= lo * sim.scale && scene.far >= hi * sim.scale,
        "{} {} vs {lo} {hi}",
        scene.near,
        scene.far
    );
    let (cmin, cmax) = synth::Scene::new(SceneKind::Chair.parts()).bounds();
    for corner in [cmin, cmax] {
        let p = sim.apply_point(corner);
        assert!(
            p.iter().all(|v| v.abs() <= scene.bound * 1.05),
            "{p:?} outside box {}",
            scene.bound
        );
    }
    // Per-image camera models: the OPENCV camera's distortion is carried.
    assert!(scene.frames[0].camera.distortion.is_pinhole());
    assert_eq!(scene.frames[1].camera.distortion.k[0], 0.02);
    assert_eq!(scene.load(Split::Train, 1).expect("load").views.len(), 10);

    // The transforms.json `nerf capture` writes from this model reads exactly
    // as the model does: the same cameras, box, contraction and bounds, as any reader of
    // the folder must agree; the box is the cameras' (as LLFF --spherify's), not the
    // points'.
    let file = dir.path().join("transforms.json");
    nerf::app::capture::transforms_from_colmap(dir.path(), &file).expect("write transforms.json");
    let text = std::fs::read_to_string(&file).expect("read");
    assert!(
        text.contains("\"images/"),
        "relative image paths beside the images"
    );
    let written = Scene::open(dir.path(), &SceneOptions::default(), 1).expect("open transforms");
    assert_eq!(written.format, Format::Transforms);
    assert_eq!(
        (written.bound, written.contract, written.near, written.far),
        (scene.bound, scene.contract, scene.near, scene.far)
    );
    assert_eq!(scene.bound, nerf::data::poses::INWARD_BOX);
    for (a, b) in written.frames.iter().zip(&scene.frames) {
        assert!(length(sub(a.camera.origin(), b.camera.origin())) < 1e-5);
        assert!(rotation_error_degrees(&a.camera.c2w, &b.camera.c2w) < 0.01);
        assert_eq!(a.camera.distortion, b.camera.distortion);
    }
    // A broken record is refused, naming the file and the field.
    let broken = text.replacen("\"bound\": 3.0", "\"bound\": -1.0", 1);
    assert_ne!(broken, text);
    std::fs::write(&file, broken).expect("write");
    let err = Scene::open(dir.path(), &SceneOptions::default(), 1).expect_err("refused");
    assert!(
        err.to_string().contains("transforms.json") && err.to_string().contains("nerf_box"),
        "{err}"
    );
}

#[test]
fn transforms_json_intrinsics_distortion_masks_and_conventions() {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::create_dir_all(dir.path().join("images")).expect("mkdir");
    let cams = around(4, 16);
    let mut frames = Vec::new();
    for (k, c) in cams.iter().enumerate() {
        let name = format!("images/{k}.png");
        save_rgb_png(&dir.path().join(&name), 16, 12, &vec![0.5; 16 * 12 * 3]).expect("png");
        let mut f = serde_json::json!({
            "file_path": name,
            "transform_matrix": nerf::data::reader::pose_to_matrix(&c.c2w),
        });
        if k == 1 {
            f["fl_x"] = serde_json::json!(30.0);
            f["mask_path"] = serde_json::json!("mask1.png");
        }
        frames.push(f);
    }
    // Mask: the left half is kept.
    let mask: Vec<f32> = (0..16 * 12)
        .flat_map(|p| [if p % 16 < 8 { 1.0 } else { 0.0 }; 3])
        .collect();
    save_rgb_png(&dir.path().join("mask1.png"), 16, 12, &mask).expect("png");
    let mut doc = serde_json::json!({
        "fl_x": 20.0, "fl_y": 21.0, "cx": 7.5, "cy": 6.5, "w": 16, "h": 12,
        "k1": 0.05, "k2": -0.02, "p1": 0.001, "p2": -0.001,
        "aabb_scale": 4, "scale": 0.5, "offset": [0.5, 0.6, 0.5],
        "frames": frames,
    });
    let write = |doc: &serde_json::Value| {
        nerf::io::write_json(&dir.path().join("transforms.json"), doc).expect("json")
    };
    write(&doc);

    let holdout2 = SceneOptions {
        holdout: 2,
        ..SceneOptions::default()
    };
    let scene = Scene::open(dir.path(), &holdout2, 1).expect("open ngp");
    assert_eq!(scene.format, Format::Transforms);
    assert_eq!(scene.bound, 2.0, "aabb_scale / 2");
    for (f, c) in scene.frames.iter().zip(&cams) {
        // instant-ngp: p * scale + offset - 0.5.
        let want = [
            c.c2w[0][3] * 0.5,
            c.c2w[1][3] * 0.5 + 0.1,
            c.c2w[2][3] * 0.5,
        ];
        assert!(
            length(sub(f.camera.origin(), want)) < 1e-5,
            "{:?} vs {want:?}",
            f.camera.origin()
        );
    }
    let c0 = &scene.frames[0].camera;
    assert_eq!(
        (c0.fx, c0.fy, c0.cx, c0.cy, c0.width, c0.height),
        (20.0, 21.0, 7.5, 6.5, 16, 12)
    );
    assert_eq!(c0.distortion.k[..2], [0.05, -0.02]);
    assert_eq!(
        scene.frames[1].camera.fx, 30.0,
        "per-frame fl_x overrides the file's"
    );
    // Rays are undistorted: the ray through a point's distorted projection hits it.
    let world_point = [0.2f32, 0.1, 0.3];
    let m = &c0.c2w;
    let rel = sub(world_point, c0.origin());
    let cam: [f32; 3] = std::array::from_fn(|a| (0..3).map(|r| m[r][a] * rel[r]).sum());
    let (x, y) = (cam[0] / -cam[2], -cam[1] / -cam[2]);
    let (xd, yd) = c0.distortion.distort(x, y);
    let ray = c0.ray_at(xd * c0.fx + c0.cx, yd * c0.fy + c0.cy);
    let hit = normalize_or_zero(ray.dir);
    assert!(nerf::math::dot(hit, normalize_or_zero(rel)) > 1.0 - 1e-6);
    // The mask keeps the left half of frame 1 (a training frame with --holdout 2).
    let train = scene.load(Split::Train, 1).expect("load");
    let masked = train
        .views
        .iter()
        .find(|v| v.name == "images/1.png")
        .expect("frame 1");
    let kept = masked.kept_pixels.as_ref().expect("mask");
    assert_eq!(kept.len(), 8 * 12);
    assert!(kept.iter().all(|&p| p % 16 < 8));

    // nerfstudio: no aabb_scale / scale / offset -> cameras centred and inside [-1, 1]^3.
    for key in ["aabb_scale", "scale", "offset"] {
        doc.as_object_mut().expect("object").remove(key);
    }
    write(&doc);
    let ns = Scene::open(dir.path(), &holdout2, 1).expect("open nerfstudio");
    assert_eq!(ns.bound, 1.0);
    let origins: Vec<_> = ns.frames.iter().map(|f| f.camera.origin()).collect();
    let max = origins.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
    let mean = origins
        .iter()
        .fold([0.0f32; 3], |s, p| nerf::math::add(s, *p));
    assert!(
        (max - 1.0).abs() < 1e-5 && length(mean) < 1e-4,
        "{max} {mean:?}"
    );
    assert_same_up_to_similarity(
        &cams.iter().map(|c| c.c2w).collect::<Vec<_>>(),
        &ns.frames.iter().map(|f| f.camera.c2w).collect::<Vec<_>>(),
        "nerfstudio",
    );

    doc["frames"][2]["transform_matrix"] = serde_json::json!([[1, 0, 0], [0, 1, 0]]);
    write(&doc);
    let err = Scene::open(dir.path(), &holdout2, 1)
        .expect_err("bad matrix")
        .to_string();
    assert!(
        err.contains("transforms.json") && err.contains("frame 2") && err.contains("4x4"),
        "{err}"
    );
}

fn shared(name: &str) -> Option<std::path::PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(name);
    if dir.exists() {
        Some(dir)
    } else {
        eprintln!("skipping: {} is absent", dir.display());
        None
    }
}

#[test]
fn real_beer_llff_and_its_colmap_model_agree() {
    let Some(dir) = shared("llff_beer") else {
        return;
    };
    let spherify = SceneOptions {
        spherify: true,
        ..SceneOptions::default()
    };
    let llff = Scene::open(&dir, &spherify, 4).expect("llff");
    let colmap_opts = SceneOptions {
        format: Some(Format::Colmap),
        ..SceneOptions::default()
    };
    let colmap = Scene::open(&dir, &colmap_opts, 4).expect("colmap");
    assert_eq!(llff.frames.len(), 71);
    assert_eq!(colmap.frames.len(), 71);
    assert_eq!(llff.test.len(), 9);
    // poses_bounds.npy was made from this COLMAP model: both readers, placing the cameras
    // the same way, must agree.
    for (a, b) in llff.frames.iter().zip(&colmap.frames) {
        assert!(
            length(sub(a.camera.origin(), b.camera.origin())) < 1e-3,
            "{}",
            a.name
        );
        assert!(
            rotation_error_degrees(&a.camera.c2w, &b.camera.c2w) < 0.05,
            "{}",
            a.name
        );
    }
    assert!(
        colmap.near < 0.5 && colmap.far > 3.0,
        "{} {}",
        colmap.near,
        colmap.far
    );
    assert!(llff.warnings().is_empty(), "{:?}", llff.warnings());
    assert!(
        llff.contract && colmap.contract,
        "360-degree captures are unbounded"
    );
    // Read as forward-facing, the half circle of cameras is flagged.
    let ndc = Scene::open(&dir, &SceneOptions::default(), 4).expect("llff as forward-facing");
    assert!(ndc.warnings().iter().any(|w| w.contains("--spherify")));
    let cam = &llff.cameras(Split::Train)[0];
    assert_eq!((cam.width, cam.height), (180, 320));
}

#[test]
fn real_fox_transforms_if_present() {
    let Some(dir) = shared("ngp_fox") else { return };
    let scene = Scene::open(&dir, &SceneOptions::default(), 4).expect("fox");
    assert_eq!(scene.frames.len(), 50);
    assert_eq!(scene.bound, 2.0);
    let c = &scene.cameras(Split::Train)[0];
    assert_eq!((c.width, c.height), (270, 480));
    assert!(!c.distortion.is_pinhole());
    assert!((c.fx - 1375.52 / 4.0).abs() < 1e-2);
}
