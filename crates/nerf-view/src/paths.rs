//! Camera paths from the editor: their frames (the Catmull-Rom / slerp interpolation of
//! `nerf render --path interpolate`, through the keyframes in the order given), saving
//! them as nerfstudio `camera_path.json` files in the run folder, and rendering them with
//! the code of `nerf render --path file`.

use std::path::{Path, PathBuf};

use nerf::app::frames::{render_frames, FrameProgress, FramesOptions, PathKind};
use nerf::camera::path::{path_parameter, through_keyframes};
use nerf::camera::Pose;
use serde_json::json;

use crate::protocol::{check_name, CameraPath};
use crate::state::Viewer;

/// Where saved paths and their renders go, inside the run folder.
pub const PATHS_DIR: &str = "camera_paths";
pub const RENDERS_DIR: &str = "renders";

/// A path's frames.
pub struct Frames {
    pub poses: Vec<Pose>,
    /// Vertical fields of view (degrees).
    pub fov_y: Vec<f32>,
    /// Each frame's moment, where the keyframes carry time.
    pub times: Option<Vec<f32>>,
}

/// Every frame's pose and vertical field of view, and its moment where the keyframes
/// carry time (both run linearly between keyframes).
pub fn frames(path: &CameraPath) -> Frames {
    let keys: Vec<Pose> = path.keyframes.iter().map(|k| k.c2w).collect();
    let n = path.frames();
    let between = |of: &dyn Fn(usize) -> f32| -> Vec<f32> {
        (0..n)
            .map(|f| {
                let (i, t) = path_parameter(f, n, keys.len(), path.looped);
                let (a, b) = (of(i), of((i + 1) % keys.len()));
                a + (b - a) * t
            })
            .collect()
    };
    let timed = path.keyframes.iter().all(|k| k.time.is_some());
    Frames {
        poses: through_keyframes(&keys, n, path.looped),
        fov_y: between(&|k| path.keyframes[k].fov_y),
        times: timed.then(|| between(&|k| path.keyframes[k].time.unwrap_or(0.0))),
    }
}

/// The path as nerfstudio writes `camera_path.json` (what `nerf render --path file`
/// reads), with the editor's keyframes kept beside it.
pub fn nerfstudio_json(path: &CameraPath) -> serde_json::Value {
    let Frames {
        poses,
        fov_y,
        times,
    } = frames(path);
    let aspect = path.width as f32 / path.height as f32;
    let frames: Vec<_> = poses
        .iter()
        .zip(&fov_y)
        .enumerate()
        .map(|(k, (p, f))| {
            let mut m: Vec<f32> = p.iter().flatten().copied().collect();
            m.extend([0.0, 0.0, 0.0, 1.0]);
            let mut frame = json!({"camera_to_world": m, "fov": f, "aspect": aspect});
            if let Some(t) = times.as_ref().map(|t| t[k]) {
                frame["time"] = json!(t);
            }
            frame
        })
        .collect();
    json!({
        "camera_type": "perspective",
        "render_width": path.width,
        "render_height": path.height,
        "seconds": path.seconds,
        "fps": path.fps,
        "camera_path": frames,
        "keyframes": path.keyframes,
        "loop": path.looped,
    })
}

/// Saves `path` as `camera_paths/<name>.json` in the run folder (written whole, then
/// renamed into place); returns the file.
pub fn save(run_dir: &Path, name: &str, path: &CameraPath) -> Result<PathBuf, String> {
    check_name(name).map_err(|e| e.to_string())?;
    let dir = run_dir.join(PATHS_DIR);
    nerf::io::create_dir(&dir).map_err(|e| e.to_string())?;
    let file = dir.join(format!("{name}.json"));
    nerf::io::write_json(&file, &nerfstudio_json(path)).map_err(|e| e.to_string())?;
    Ok(file)
}

/// What rendering a path wrote, relative to the run folder.
pub struct Rendered {
    pub folder: String,
    pub video: Option<String>,
}

/// Saves `path`, then renders it into `renders/<name>/` with a video beside it
/// (`renders/<name>.mp4` through ffmpeg, or `.gif` without it), as `nerf render --path
/// file` does (with `appearance`'s photo look, as `--appearance-of` gives it);
/// `on_frame` hears the frames done of all.
pub fn render(
    viewer: &Viewer,
    name: &str,
    path: &CameraPath,
    appearance: nerf::stage::Appearance,
    on_frame: &(dyn Fn(usize, usize) + Sync),
) -> Result<Rendered, String> {
    let file = save(&viewer.run_dir, name, path)?;
    let ext = if nerf::app::video::ffmpeg_available() {
        "mp4"
    } else {
        "gif"
    };
    let folder = Path::new(RENDERS_DIR).join(name);
    let video = Path::new(RENDERS_DIR).join(format!("{name}.{ext}"));
    let mut opts = FramesOptions::orbit(path.frames(), 1.0, viewer.run_dir.join(&video));
    opts.path = PathKind::File;
    opts.camera_path = Some(file);
    opts.radius = None;
    opts.fps = path.fps;
    if let nerf::stage::Appearance::Of(i) = appearance {
        opts.appearance_of = Some(i.to_string());
    }
    let run = viewer.model.run.read().unwrap_or_else(|e| e.into_inner());
    let progress = |p: FrameProgress| on_frame(p.frame, p.frames);
    render_frames(&run, &opts, &viewer.run_dir.join(&folder), &progress)
        .map_err(|e| e.to_string())?;
    Ok(Rendered {
        folder: folder.display().to_string(),
        video: Some(video.display().to_string()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::Keyframe;

    fn key(eye: [f32; 3], fov_y: f32) -> Keyframe {
        Keyframe {
            c2w: nerf::camera::look_at(eye, [0.0; 3], [0.0, 0.0, 1.0]),
            fov_y,
            time: None,
        }
    }

    fn path() -> CameraPath {
        CameraPath {
            keyframes: vec![key([4.0, 0.0, 1.0], 30.0), key([0.0, 4.0, 2.0], 50.0)],
            seconds: 1.0,
            fps: 5.0,
            width: 40,
            height: 30,
            looped: false,
        }
    }

    /// The saved file is what `nerf render --path file` reads: its frames start and end
    /// on the keyframes, at the path's size, with the field of view between the keys'.
    #[test]
    fn saved_paths_load_as_camera_path_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = path();
        let file = save(dir.path(), "take_1", &p).expect("save");
        assert_eq!(file, dir.path().join("camera_paths/take_1.json"));
        let cams = nerf::camera::path::load_camera_path(&file, None).expect("load");
        assert_eq!(cams.len(), 5);
        assert_eq!((cams[0].width, cams[0].height), (40, 30));
        for (cam, k) in [(&cams[0], &p.keyframes[0]), (&cams[4], &p.keyframes[1])] {
            for r in 0..3 {
                for c in 0..4 {
                    assert!((cam.c2w[r][c] - k.c2w[r][c]).abs() < 1e-4);
                }
            }
            let fov_y = cam.fov_y_degrees();
            assert!((fov_y - k.fov_y).abs() < 1e-2, "{fov_y} vs {}", k.fov_y);
        }
        assert!(save(dir.path(), "../out", &p).is_err());
        assert!(!dir.path().join("out.json").exists());
        // Without keyed times the frames carry none.
        let times = nerf::camera::path::load_camera_path_times(&file).expect("times");
        assert!(times.iter().all(Option::is_none), "{times:?}");
    }

    /// Keyed moments run linearly between the keyframes, in the preview and in the saved
    /// file, which `nerf render --path file` renders frame by frame at its moment.
    #[test]
    fn keyed_times_run_between_the_keyframes() {
        let mut p = path();
        p.keyframes[0].time = Some(0.2);
        p.keyframes[1].time = Some(0.6);
        let times = frames(&p).times.expect("times");
        let expected = [0.2, 0.3, 0.4, 0.5, 0.6];
        assert_eq!(times.len(), expected.len());
        for (t, e) in times.iter().zip(expected) {
            assert!((t - e).abs() < 1e-6, "{times:?}");
        }
        let dir = tempfile::tempdir().expect("tempdir");
        let file = save(dir.path(), "moving", &p).expect("save");
        let read = nerf::camera::path::load_camera_path_times(&file).expect("times");
        assert_eq!(read.len(), 5);
        for (t, e) in read.iter().zip(expected) {
            assert!(t.is_some_and(|t| (t - e).abs() < 1e-6), "{read:?}");
        }
        // A looped path comes back to the first keyframe's moment.
        p.looped = true;
        let looped = frames(&p).times.expect("times");
        assert!(
            (looped[0] - 0.2).abs() < 1e-6 && looped[4] < 0.6,
            "{looped:?}"
        );
    }
}
