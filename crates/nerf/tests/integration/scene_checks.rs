//! Scene files as real tools export them, and as they break. Each test names the
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

    // Moving scenes: a frame's optional moment, read alongside its camera.
    let timed = |t: Value| json!({"camera_to_world": pose(1), "fov": 50.0, "time": t});
    write(
        &path,
        &json!({"camera_path": [timed(json!(0.25)), frame(pose(1))]}),
    );
    let times = nerf::camera::path::load_camera_path_times(&path).expect("times");
    assert_eq!(times, [Some(0.25), None]);
    write(&path, &json!({"camera_path": [timed(json!(1.5))]}));
    let err = nerf::camera::path::load_camera_path_times(&path)
        .expect_err("a moment outside [0, 1]")
        .to_string();
    assert!(
        err.contains("camera_path[0].time 1.5") && err.contains("camera_path.json"),
        "{err}"
    );
}

/// A 4x4 row list of a camera at `eye` looking at `target` (+Z up).
fn pose_at(eye: [f32; 3], target: [f32; 3]) -> Value {
    let p = nerf::camera::look_at(eye, target, [0.0, 0.0, 1.0]);
    let mut rows: Vec<Vec<f32>> = p.iter().map(|r| r.to_vec()).collect();
    rows.push(vec![0.0, 0.0, 0.0, 1.0]);
    json!(rows)
}

/// A `transforms.json` whose `n` cameras sit on a circle of `radius` at height 1, each
/// looking at `target(eye)`, with the `top` keys (nerfstudio's `camera_model` and these).
fn ring_scene(
    dir: &Path,
    n: usize,
    radius: f32,
    target: impl Fn([f32; 3]) -> [f32; 3],
    top: Value,
) {
    let frames: Vec<Value> = (0..n)
        .map(|k| {
            let a = k as f32 * std::f32::consts::TAU / n as f32;
            let eye = [radius * a.cos(), radius * a.sin(), 1.0];
            png(&dir.join(format!("images/{k:04}.png")), 16, 16);
            json!({"file_path": format!("images/{k:04}.png"), "transform_matrix": pose_at(eye, target(eye))})
        })
        .collect();
    let mut doc = json!({"camera_model": "OPENCV", "fl_x": 14.0, "fl_y": 14.0, "frames": frames});
    if let (Some(d), Some(e)) = (doc.as_object_mut(), top.as_object()) {
        d.extend(e.clone());
    }
    write(&dir.join("transforms.json"), &doc);
}

fn warns_of_looking_away(scene: &Scene) -> bool {
    scene
        .warnings()
        .iter()
        .any(|w| w.contains("see no part of the scene box") && w.contains("--convention"))
}

/// Cameras that all look away from the scene (a file read in another convention than it
/// was written in) are warned of; an inward capture, a forward-facing one and an inside-out
/// room, whose box is around the cameras, are not.
#[test]
fn cameras_looking_away_from_the_scene_are_warned_of() {
    // instant-ngp's placement (0.33 units a metre, a box of 1) leaves the ring outside.
    let ngp = json!({"aabb_scale": 2, "scale": 0.33});
    let away = tempfile::tempdir().expect("tempdir");
    ring_scene(
        away.path(),
        12,
        4.0,
        |e| [3.0 * e[0], 3.0 * e[1], 1.0],
        ngp.clone(),
    );
    let scene = open(away.path(), 1).expect("open");
    assert!(warns_of_looking_away(&scene), "{:?}", scene.warnings());

    let inward = tempfile::tempdir().expect("tempdir");
    ring_scene(inward.path(), 12, 4.0, |_| [0.0; 3], ngp);
    let scene = open(inward.path(), 1).expect("open");
    assert!(!warns_of_looking_away(&scene), "{:?}", scene.warnings());

    // nerfstudio's placement scales the cameras into the box: a room around them.
    let room = tempfile::tempdir().expect("tempdir");
    ring_scene(
        room.path(),
        12,
        0.2,
        |e| [10.0 * e[0], 10.0 * e[1], 1.0],
        json!({}),
    );
    let scene = open(room.path(), 1).expect("open");
    assert!(!warns_of_looking_away(&scene), "{:?}", scene.warnings());

    // Forward-facing: a row of cameras all looking along +Y at what stands before them.
    let forward = tempfile::tempdir().expect("tempdir");
    ring_scene(forward.path(), 1, 0.0, |_| [0.0; 3], json!({}));
    let frames: Vec<Value> = (0..9)
        .map(|k| {
            let eye = [k as f32 * 0.1 - 0.4, -1.0, 0.2];
            png(&forward.path().join(format!("images/{k:04}.png")), 16, 16);
            json!({"file_path": format!("images/{k:04}.png"),
                   "transform_matrix": pose_at(eye, [eye[0], 3.0, 0.2])})
        })
        .collect();
    write(
        &forward.path().join("transforms.json"),
        &json!({"camera_model": "OPENCV", "fl_x": 14.0, "fl_y": 14.0, "frames": frames}),
    );
    let scene = open(forward.path(), 1).expect("open");
    assert!(!warns_of_looking_away(&scene), "{:?}", scene.warnings());
}

/// Blender-format files with `near` and `far` keys (DS-NeRF's and others'), whose cameras
/// circle a point away from the origin: the keys are read, and the box is moved onto what
/// the cameras look at, and said.
#[test]
fn blender_files_with_near_far_around_another_centre() {
    let dir = tempfile::tempdir().expect("tempdir");
    let centre = [6.0, -3.0, 0.5];
    for (split, n) in [("train", 10), ("test", 3)] {
        let frames: Vec<Value> = (0..n)
            .map(|k| {
                let a = k as f32 * 0.6 + if split == "test" { 0.3 } else { 0.0 };
                let eye = [centre[0] + 3.0 * a.cos(), centre[1] + 3.0 * a.sin(), 1.5];
                png(&dir.path().join(format!("{split}/r_{k}.png")), 8, 8);
                json!({"file_path": format!("./{split}/r_{k}"), "transform_matrix": pose_at(eye, centre)})
            })
            .collect();
        let doc = json!({"camera_angle_x": 0.69, "near": 1.5, "far": 4.5, "frames": frames});
        write(&dir.path().join(format!("transforms_{split}.json")), &doc);
    }
    let scene = open(dir.path(), 1).expect("open");
    assert_eq!((scene.near, scene.far), (1.5, 4.5));
    let said = scene.notes.join("\n");
    assert!(said.contains("near 1.5 and far 4.5"), "{said}");
    assert!(said.contains("look past the box"), "{said}");
    // Every camera's central ray now crosses the box, which is centred on what they see.
    for c in scene.cameras(Split::Train) {
        assert!(
            nerf::data::aim::central_ray_hits_box(&c, scene.bound, scene.far),
            "bound {}: {:?}",
            scene.bound,
            c.origin()
        );
        let distance = nerf::math::length(c.origin());
        assert!((distance - 3.0f32.hypot(1.0)).abs() < 0.05, "{distance}");
    }
    assert!(scene.bound > 0.5 && scene.bound < 3.0, "{}", scene.bound);
}

/// Test images that are training images saved again under other names are counted;
/// a scene whose splits hold different photos is not warned of.
#[test]
fn test_images_copied_from_training_images_are_counted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let picture = |k: usize, noise: f32| -> Vec<f32> {
        (0..16 * 16 * 4)
            .map(|i| {
                let v = ((i / 4) * (k + 3) % 17) as f32 / 17.0;
                if i % 4 == 3 {
                    1.0
                } else {
                    (v + noise * if i % 2 == 0 { 1.0 } else { -1.0 }).clamp(0.0, 1.0)
                }
            })
            .collect()
    };
    for (split, n) in [("train", 4), ("test", 3)] {
        let frames: Vec<Value> = (0..n)
            .map(|k| {
                let path = dir.path().join(format!("{split}/view_{k}.png"));
                std::fs::create_dir_all(path.parent().expect("parent")).expect("mkdir");
                // Test 0 and 1 are training photos 2 and 3 saved again (slightly changed).
                let content = match (split, k) {
                    ("test", 0 | 1) => picture(k + 2, 0.004),
                    ("test", _) => picture(k + 10, 0.0),
                    _ => picture(k, 0.0),
                };
                save_rgba_png(&path, 16, 16, &content).expect("png");
                json!({"file_path": format!("./{split}/view_{k}"), "transform_matrix": pose(k)})
            })
            .collect();
        let doc = json!({"camera_angle_x": 0.69, "frames": frames});
        write(&dir.path().join(format!("transforms_{split}.json")), &doc);
    }
    let scene = open(dir.path(), 1).expect("open");
    let warning = scene
        .copied_held_out_images()
        .expect("read")
        .expect("warned");
    assert!(warning.starts_with("2 of 3 test"), "{warning}");

    std::fs::remove_file(dir.path().join("test/view_0.png")).expect("rm");
    save_rgba_png(
        &dir.path().join("test/view_0.png"),
        16,
        16,
        &picture(9, 0.0),
    )
    .expect("png");
    std::fs::remove_file(dir.path().join("test/view_1.png")).expect("rm");
    save_rgba_png(
        &dir.path().join("test/view_1.png"),
        16,
        16,
        &picture(11, 0.0),
    )
    .expect("png");
    let scene = open(dir.path(), 1).expect("open");
    assert_eq!(scene.copied_held_out_images().expect("read"), None);
}

/// A pose whose 3x3 part is a rotation scaled uniformly (an exporter's `scale_factor`) is
/// normalised with a note; reflections and shears are still refused.
#[test]
fn a_uniformly_scaled_rotation_is_normalised() {
    let dir = tempfile::tempdir().expect("tempdir");
    let doc = transforms(dir.path(), 4, 8, 8, json!({}));
    let scaled = |doc: &Value, f: &dyn Fn(usize, usize, f64) -> f64| {
        let mut doc = doc.clone();
        for frame in doc["frames"].as_array_mut().expect("frames") {
            for r in 0..3 {
                for c in 0..3 {
                    let v = frame["transform_matrix"][r][c].as_f64().expect("number");
                    frame["transform_matrix"][r][c] = json!(f(r, c, v));
                }
            }
        }
        doc
    };
    write(
        &dir.path().join("transforms.json"),
        &scaled(&doc, &|_, _, v| 2.5 * v),
    );
    let scene = open(dir.path(), 1).expect("a scaled rotation loads");
    let said = scene.notes.join("\n");
    assert!(
        said.contains("4 poses have a rotation scaled uniformly") && said.contains("2.5"),
        "{said}"
    );
    let c2w = scene.cameras(Split::Train)[0].c2w;
    let column: [f32; 3] = [c2w[0][0], c2w[1][0], c2w[2][0]];
    assert!((nerf::math::length(column) - 1.0).abs() < 1e-5);

    // A reflection (one column negated) and a shear stay refused.
    write(
        &dir.path().join("transforms.json"),
        &scaled(&doc, &|_, c, v| if c == 0 { -2.0 * v } else { 2.0 * v }),
    );
    assert!(open_err(dir.path(), 1).contains("not a rotation"));
    write(
        &dir.path().join("transforms.json"),
        &scaled(&doc, &|_, c, v| if c == 1 { 3.0 * v } else { v }),
    );
    assert!(open_err(dir.path(), 1).contains("not a rotation"));
}

/// Adds `time(k)` to every frame of the JSON file at `path`.
fn add_times(path: &Path, time: impl Fn(usize) -> Value) {
    let mut doc: Value =
        serde_json::from_str(&std::fs::read_to_string(path).expect("read")).expect("json");
    if let Some(frames) = doc["frames"].as_array_mut() {
        for (k, f) in frames.iter_mut().enumerate() {
            f["time"] = time(k);
        }
    }
    write(path, &doc);
}

/// Dynamic scenes (D-NeRF's `time` key): each frame's moment reaches its view, times
/// outside [0, 1] are mapped onto it with a note, and a frame without one is named.
#[test]
fn dynamic_scenes_carry_each_frames_time() {
    let tmp = tempfile::tempdir().expect("tmp");
    let dir = tmp.path().join("blender");
    blender(&dir, 8, 4, 2, json!({}));
    add_times(&dir.join("transforms_train.json"), |k| {
        json!(10.0 * k as f64)
    });
    add_times(&dir.join("transforms_test.json"), |k| {
        json!(5.0 + 10.0 * k as f64)
    });
    let s = open(&dir, 1).expect("open");
    assert!(s.is_dynamic());
    assert_eq!(
        s.moments(Split::Train),
        vec![0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0]
    );
    assert_eq!(s.moments(Split::Test), vec![1.0 / 6.0, 0.5]);
    assert!(
        s.notes.iter().any(|n| n.contains("mapped onto [0, 1]")),
        "{:?}",
        s.notes
    );
    let test = s.load(Split::Test, 1).expect("load");
    let times: Vec<_> = test.views.iter().map(|v| v.time).collect();
    assert_eq!(times, [Some(1.0 / 6.0), Some(0.5)]);

    // A transforms.json with times in [0, 1]: kept as they are, without a note.
    let tf = tmp.path().join("transforms");
    transforms(&tf, 5, 8, 8, json!({}));
    add_times(&tf.join("transforms.json"), |k| json!(k as f64 / 4.0));
    let s = open(&tf, 1).expect("open");
    let all: Vec<f32> = s.frames.iter().filter_map(|f| f.time).collect();
    assert_eq!(all, [0.0, 0.25, 0.5, 0.75, 1.0]);
    assert!(!s.notes.iter().any(|n| n.contains("mapped onto")));

    // A static scene has no moments; a frame without a time is refused by name.
    let still = tmp.path().join("still");
    blender(&still, 8, 2, 1, json!({}));
    assert!(!open(&still, 1).expect("open").is_dynamic());
    add_times(&still.join("transforms_train.json"), |k| json!(k as f64));
    let err = open_err(&still, 1);
    assert!(
        err.contains("./test/r_0") && err.contains("no time"),
        "{err}"
    );
}
