//! Issue 10: scene files as real tools export them, and as they break. Each test names the
//! defect of the issue it covers (#N).

use std::path::Path;

use nerf::camera::path::load_camera_path;
use nerf::data::image::save_rgba_png;
use nerf::data::scene::{Convention, Scene, SceneOptions};
use nerf::data::Split;
use serde_json::{json, Value};

fn png(path: &Path, w: usize, h: usize) {
    std::fs::create_dir_all(path.parent().expect("parent")).expect("mkdir");
    save_rgba_png(path, w, h, &vec![0.5; w * h * 4]).expect("png");
}

/// A camera on a circle of radius 4 looking at the origin, as a 4x4 row list.
fn pose(k: usize) -> Value {
    let a = k as f32 * 0.7;
    let p = nerf::camera::look_at(
        [4.0 * a.cos(), 4.0 * a.sin(), 1.0],
        [0.0; 3],
        [0.0, 0.0, 1.0],
    );
    let mut rows: Vec<Vec<f32>> = p.iter().map(|r| r.to_vec()).collect();
    rows.push(vec![0.0, 0.0, 0.0, 1.0]);
    json!(rows)
}

fn write(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_string_pretty(v).expect("json")).expect("write");
}

/// A Blender scene: `train` frames of `size`, plus `test` frames, each split a JSON file.
fn blender(dir: &Path, size: usize, train: usize, test: usize, extra: Value) {
    for (split, n) in [("train", train), ("test", test)] {
        let frames: Vec<Value> = (0..n)
            .map(|k| {
                png(&dir.join(format!("{split}/r_{k}.png")), size, size);
                json!({"file_path": format!("./{split}/r_{k}"), "transform_matrix": pose(k)})
            })
            .collect();
        let mut doc = json!({"camera_angle_x": 0.69, "frames": frames});
        if let (Some(d), Some(e)) = (doc.as_object_mut(), extra.as_object()) {
            d.extend(e.clone());
        }
        write(&dir.join(format!("transforms_{split}.json")), &doc);
    }
}

/// A `transforms.json` with `n` frames of `w x h` images under `images/`.
fn transforms(dir: &Path, n: usize, w: usize, h: usize, top: Value) -> Value {
    let frames: Vec<Value> = (0..n)
        .map(|k| {
            png(&dir.join(format!("images/{k:04}.png")), w, h);
            json!({"file_path": format!("images/{k:04}.png"), "transform_matrix": pose(k)})
        })
        .collect();
    let mut doc = json!({"fl_x": 20.0, "fl_y": 20.0, "frames": frames});
    if let (Some(d), Some(e)) = (doc.as_object_mut(), top.as_object()) {
        d.extend(e.clone());
    }
    write(&dir.join("transforms.json"), &doc);
    doc
}

fn open(dir: &Path, downscale: usize) -> nerf::Result<Scene> {
    Scene::open(dir, &SceneOptions::default(), downscale)
}

fn open_err(dir: &Path, downscale: usize) -> String {
    open(dir, downscale)
        .expect_err("must be refused")
        .to_string()
}

/// #1: a 1x1 image among 32x32 ones, with and without a downscale that leaves no pixels.
#[test]
fn a_tiny_image_among_others_is_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    blender(dir.path(), 32, 3, 1, json!({}));
    png(&dir.path().join("train/r_1.png"), 1, 1);
    for downscale in [1, 4] {
        let err = open_err(dir.path(), downscale);
        assert!(
            err.contains("r_1.png") && err.contains("1x1") && err.contains("32x32"),
            "--downscale {downscale}: {err}"
        );
    }
}

/// #9: rotations that are not rotations, and absurd positions, name the frame.
#[test]
fn poses_are_checked() {
    let dir = tempfile::tempdir().expect("tempdir");
    blender(dir.path(), 8, 2, 1, json!({}));
    let path = dir.path().join("transforms_train.json");
    let mut doc: Value =
        serde_json::from_str(&std::fs::read_to_string(&path).expect("read")).expect("json");
    doc["frames"][1]["transform_matrix"] =
        json!([[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1]]);
    write(&path, &doc);
    let err = open_err(dir.path(), 1);
    assert!(
        err.contains("frame 1") && err.contains("not a rotation"),
        "{err}"
    );

    doc["frames"][1]["transform_matrix"] = pose(1);
    doc["frames"][1]["transform_matrix"][0][3] = json!(1e30);
    write(&path, &doc);
    let err = open_err(dir.path(), 1);
    assert!(
        err.contains("frame 1") && err.contains("from the origin"),
        "{err}"
    );
}

/// #10 and #18: a missing or wrongly sized image of the test split is found when the
/// scene opens, also when the file gives the size (`w`, `h`) and no image is needed for it.
#[test]
fn every_split_and_image_is_checked_on_open() {
    let dir = tempfile::tempdir().expect("tempdir");
    blender(dir.path(), 8, 2, 2, json!({}));
    std::fs::remove_file(dir.path().join("test/r_1.png")).expect("rm");
    let err = open_err(dir.path(), 1);
    assert!(err.contains("test/r_1.png"), "{err}");
    png(&dir.path().join("test/r_1.png"), 8, 6);
    let err = open_err(dir.path(), 1);
    assert!(err.contains("test/r_1.png") && err.contains("8x6"), "{err}");

    let dir = tempfile::tempdir().expect("tempdir");
    transforms(dir.path(), 4, 8, 8, json!({"w": 8, "h": 8}));
    std::fs::remove_file(dir.path().join("images/0002.png")).expect("rm");
    let err = open_err(dir.path(), 1);
    assert!(err.contains("0002.png"), "{err}");
}

/// #12: metadata claiming another size is said out loud; another shape is refused.
#[test]
fn metadata_that_disagrees_with_the_images() {
    let dir = tempfile::tempdir().expect("tempdir");
    transforms(dir.path(), 4, 32, 32, json!({"w": 100000, "h": 100000}));
    let scene = open(dir.path(), 1).expect("same shape: scaled");
    assert!(
        scene
            .warnings()
            .iter()
            .any(|w| w.contains("100000x100000") && w.contains("32x32")),
        "{:?}",
        scene.warnings()
    );
    assert_eq!(scene.cameras(Split::Train)[0].width, 32);

    transforms(dir.path(), 4, 32, 32, json!({"w": 64, "h": 16}));
    let err = open_err(dir.path(), 1);
    assert!(err.contains("different shape"), "{err}");
}

/// #15: instant-ngp keys in a Blender-layout file are read, and said.
#[test]
fn blender_files_with_instant_ngp_keys() {
    let dir = tempfile::tempdir().expect("tempdir");
    blender(
        dir.path(),
        16,
        2,
        1,
        json!({"fl_x": 30.0, "fl_y": 31.0, "cx": 7.0, "cy": 9.0, "k1": 0.01, "aabb_scale": 2}),
    );
    let scene = open(dir.path(), 1).expect("open");
    let c = &scene.cameras(Split::Train)[0];
    assert_eq!((c.fx, c.fy, c.cx, c.cy), (30.0, 31.0, 7.0, 9.0));
    assert_eq!(c.distortion.k[0], 0.01);
    assert!(
        (scene.bound - 1.0 / 0.33).abs() < 1e-4,
        "box {}",
        scene.bound
    );
    assert!(
        scene
            .notes
            .iter()
            .any(|w| w.contains("fl_x") && w.contains("aabb_scale")),
        "{:?}",
        scene.notes
    );
}

/// #16: per-frame `K` matrices and `fx`/`fy`/`cx`/`cy`.
#[test]
fn per_frame_intrinsics_as_k_or_fx() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut doc = transforms(dir.path(), 4, 16, 16, json!({}));
    let d = doc.as_object_mut().expect("object");
    d.remove("fl_x");
    d.remove("fl_y");
    for (k, f) in doc["frames"]
        .as_array_mut()
        .expect("frames")
        .iter_mut()
        .enumerate()
    {
        if k % 2 == 0 {
            f["K"] = json!([[40.0, 0.0, 8.5], [0.0, 41.0, 7.5], [0.0, 0.0, 1.0]]);
        } else {
            f["fx"] = json!(42.0);
            f["fy"] = json!(43.0);
            f["cx"] = json!(8.0);
            f["cy"] = json!(8.0);
        }
    }
    write(&dir.path().join("transforms.json"), &doc);
    let scene = open(dir.path(), 1).expect("open");
    let by_name = |n: &str| {
        let f = scene
            .frames
            .iter()
            .find(|f| f.name.contains(n))
            .expect("frame");
        (f.camera.fx, f.camera.fy, f.camera.cx, f.camera.cy)
    };
    assert_eq!(by_name("0000"), (40.0, 41.0, 8.5, 7.5));
    assert_eq!(by_name("0001"), (42.0, 43.0, 8.0, 8.0));
}

/// #17: Windows paths and absolute paths from another machine.
#[test]
fn windows_and_foreign_absolute_paths() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut doc = transforms(dir.path(), 4, 8, 8, json!({}));
    for (k, f) in doc["frames"]
        .as_array_mut()
        .expect("frames")
        .iter_mut()
        .enumerate()
    {
        f["file_path"] = json!(if k % 2 == 0 {
            format!("images\\{k:04}.png")
        } else {
            format!("/home/someone/capture/images/{k:04}.png")
        });
    }
    write(&dir.path().join("transforms.json"), &doc);
    let scene = open(dir.path(), 1).expect("open");
    scene.load(Split::Train, 1).expect("images load");
    assert!(
        scene
            .warnings()
            .iter()
            .any(|w| w.contains("last") && w.contains("/home/someone")),
        "{:?}",
        scene.warnings()
    );
}

/// #19: a file listing an image several times keeps it once: no test image is trained on.
#[test]
fn duplicate_frames_are_dropped() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut doc = transforms(dir.path(), 8, 8, 8, json!({}));
    let frames = doc["frames"].as_array().expect("frames").clone();
    doc["frames"] = json!(frames
        .iter()
        .chain(&frames)
        .chain(&frames)
        .collect::<Vec<_>>());
    write(&dir.path().join("transforms.json"), &doc);
    let scene = open(dir.path(), 1).expect("open");
    assert_eq!(scene.frames.len(), 8);
    let image = |i: &usize| scene.frames[*i].image.clone();
    assert!(scene
        .test
        .iter()
        .all(|t| !scene.train.iter().any(|r| image(r) == image(t))));
    assert!(
        scene
            .warnings()
            .iter()
            .any(|w| w.contains("16 images more than once")),
        "{:?}",
        scene.warnings()
    );
}

/// #20: a nerfstudio file that also has `aabb_scale` is placed by nerfstudio's rules, and
/// the choice is said with its reason and the override.
#[test]
fn the_convention_weighs_the_evidence() {
    let dir = tempfile::tempdir().expect("tempdir");
    transforms(
        dir.path(),
        4,
        8,
        8,
        json!({"aabb_scale": 16, "camera_model": "OPENCV", "applied_transform": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}),
    );
    let scene = open(dir.path(), 1).expect("open");
    assert_eq!(scene.bound, 1.0, "nerfstudio's box");
    let said = scene.notes.join("\n");
    assert!(
        said.contains("nerfstudio's rules")
            && said.contains("applied_transform")
            && said.contains("--convention ngp"),
        "{said}"
    );
    let ngp = SceneOptions {
        convention: Convention::Ngp,
        ..SceneOptions::default()
    };
    assert_eq!(Scene::open(dir.path(), &ngp, 1).expect("open").bound, 8.0);

    // instant-ngp's own placement puts these cameras far outside a tiny box: said.
    transforms(dir.path(), 4, 8, 8, json!({"aabb_scale": 1, "scale": 2.0}));
    let scene = open(dir.path(), 1).expect("open");
    assert!(
        scene
            .warnings()
            .iter()
            .any(|w| w.contains("cameras sit more than")),
        "{:?}",
        scene.warnings()
    );
}

/// #22: equirectangular scenes are refused up front, with the reason and a way out.
#[test]
fn equirectangular_scenes_are_refused_with_a_reason() {
    let dir = tempfile::tempdir().expect("tempdir");
    transforms(
        dir.path(),
        4,
        16,
        8,
        json!({"camera_model": "EQUIRECTANGULAR"}),
    );
    let err = open_err(dir.path(), 1);
    assert!(
        err.contains("EQUIRECTANGULAR") && err.contains("perspective"),
        "{err}"
    );
}

/// #21 and #11: camera paths: nested matrices, the file's size over a frame's aspect,
/// other camera types, empty lists, broken aspects and poses.
#[test]
fn camera_paths() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("camera_path.json");
    let flat: Vec<f32> = {
        let rows: Vec<Vec<f32>> = serde_json::from_value(pose(1)).expect("rows");
        rows.concat()
    };
    let frame = |m: Value| json!({"camera_to_world": m, "fov": 50.0, "aspect": 1.0});
    write(
        &path,
        &json!({"render_width": 32, "render_height": 18,
                "camera_path": [frame(json!(flat)), frame(pose(1))]}),
    );
    let cams = load_camera_path(&path, None).expect("nested and flat");
    assert_eq!(cams.len(), 2);
    assert_eq!(cams[0], cams[1]);
    assert_eq!(
        (cams[0].width, cams[0].height),
        (32, 18),
        "the file's size wins"
    );

    let refused = |doc: Value, want: &str| {
        write(&path, &doc);
        let err = load_camera_path(&path, None).expect_err(want).to_string();
        assert!(
            err.contains(want) && err.contains("camera_path.json"),
            "{err}"
        );
    };
    refused(
        json!({"camera_type": "fisheye", "camera_path": [frame(pose(1))]}),
        "only perspective",
    );
    refused(
        json!({"camera_type": "equirectangular", "camera_path": [frame(pose(1))]}),
        "only perspective",
    );
    refused(json!({"camera_path": []}), "empty");
    for aspect in [0.0, -1.0] {
        refused(
            json!({"camera_path": [{"camera_to_world": pose(1), "fov": 50.0, "aspect": aspect}]}),
            "aspect",
        );
    }
    let mut far = pose(1);
    far[0][3] = json!(1e38);
    refused(json!({"camera_path": [frame(far)]}), "from the origin");
    // #7: sizes that would not fit in memory.
    refused(
        json!({"camera_path": [{"camera_to_world": pose(1), "fov": 50.0, "aspect": 1e7}]}),
        "larger than the limit",
    );
    refused(
        json!({"render_height": 200000, "render_width": 200000, "camera_path": [frame(pose(1))]}),
        "larger than the limit",
    );
}
