//! Rendering a camera path to PNG frames (RGB, turbo-coloured depth, opacity) and a video:
//! the test views, an orbit, an LLFF spiral, a loop through the training cameras, or a
//! nerfstudio `camera_path.json`. What `nerf render` and the demo run.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::Instant;

use crate::camera::{Camera, Pose};
use crate::data::image::save_rgb_png;
use crate::data::scene::Scene;
use crate::data::Split;
use crate::error::{NerfError, Result};
use crate::train::folder::LoadedRun;
use crate::views::{render_view, render_views, RenderSettings};

/// Which cameras to render.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PathKind {
    /// The test split's cameras.
    Test,
    /// A circle around the object, like the paper's videos.
    Orbit,
    /// A spiral in front of the average training camera (forward-facing scenes, LLFF style).
    Spiral,
    /// A smooth loop through the training cameras.
    Interpolate,
    /// The cameras of a nerfstudio camera_path.json (--camera-path).
    File,
}

impl PathKind {
    pub fn name(self) -> &'static str {
        match self {
            PathKind::Test => "test",
            PathKind::Orbit => "orbit",
            PathKind::Spiral => "spiral",
            PathKind::Interpolate => "interpolate",
            PathKind::File => "file",
        }
    }
}

/// What to render and how (the options of `nerf render`).
#[derive(Clone, Debug, clap::Args)]
pub struct FramesOptions {
    /// Which cameras to render.
    #[arg(long, value_enum, default_value = "orbit")]
    pub path: PathKind,
    /// Frames of an orbit, spiral or interpolated path.
    #[arg(long, default_value_t = 40)]
    pub frames: usize,
    /// nerfstudio camera_path.json to render with `--path file`.
    #[arg(long)]
    pub camera_path: Option<PathBuf>,
    /// Orbit elevation in degrees.
    #[arg(long, default_value_t = 30.0, value_parser = crate::args::finite, allow_negative_numbers = true)]
    pub elevation: f32,
    /// Orbit radius in scene units (default: the training cameras' mean distance from the
    /// scene centre).
    #[arg(long, value_parser = crate::args::positive, allow_negative_numbers = true)]
    pub radius: Option<f32>,
    /// Output size: the width for generated paths (the height keeps the scene's aspect
    /// ratio), the height for --path file (default: the training resolution, or the
    /// file's).
    #[arg(long)]
    pub size: Option<usize>,
    /// Also write the RGB frames as a video: .gif (built in) or .mp4 (H.264 through
    /// ffmpeg, which must be on PATH).
    #[arg(long)]
    pub video: Option<PathBuf>,
    /// Models trained with --appearance: render with this training photo's look (its
    /// index in the training split or its file name) instead of the mean.
    #[arg(long)]
    pub appearance_of: Option<String>,
    /// Models of a moving scene: the moment to render, from 0 (the first photo's) to 1
    /// (the last's). Default: each frame's own (`--path test`: the test photo's; `--path
    /// file`: the frame's `time` in the file), else 0.
    #[arg(long, value_parser = crate::args::fraction, conflicts_with = "time_sweep")]
    pub time: Option<f32>,
    /// Models of a moving scene: time runs with the frames, from 0 at the first to 1 at
    /// the last (the replay of the capture along the path).
    #[arg(long)]
    pub time_sweep: bool,
    /// Frames per second of the video.
    #[arg(long, default_value_t = 24.0, value_parser = crate::args::positive, allow_negative_numbers = true)]
    pub fps: f32,
    /// Fixed depth range NEAR,FAR for the colour map (default: the first frame's 2nd-98th
    /// percentile of opaque pixels, kept for all frames).
    #[arg(long, value_parser = parse_range)]
    pub depth_range: Option<(f32, f32)>,
}

impl FramesOptions {
    /// An orbit of `frames` frames at `radius`, written as a GIF to `video`.
    pub fn orbit(frames: usize, radius: f32, video: PathBuf) -> Self {
        FramesOptions {
            path: PathKind::Orbit,
            frames,
            camera_path: None,
            elevation: 30.0,
            radius: Some(radius),
            size: None,
            video: Some(video),
            appearance_of: None,
            time: None,
            time_sweep: false,
            fps: 24.0,
            depth_range: None,
        }
    }
}

/// `NEAR,FAR` with NEAR < FAR.
pub fn parse_range(s: &str) -> std::result::Result<(f32, f32), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?}: expected NEAR,FAR such as 2.5,5"))?;
    let (a, b): (f32, f32) = (crate::args::finite(a)?, crate::args::finite(b)?);
    if a >= b {
        return Err(format!("{s:?}: NEAR must be less than FAR"));
    }
    Ok((a, b))
}

/// The cameras of `opts.path` in `scene`.
/// The moments the frames of `opts`' path show by themselves (one per frame, or empty):
/// a camera-path file's per-frame `time`s, the test photos' moments.
fn frame_times(scene: &Scene, opts: &FramesOptions) -> Result<Vec<Option<f32>>> {
    Ok(match (opts.path, &opts.camera_path) {
        (PathKind::File, Some(file)) => crate::camera::path::load_camera_path_times(file)?,
        (PathKind::Test, _) => scene
            .indices(Split::Test)
            .iter()
            .map(|&i| scene.frames.get(i).and_then(|f| f.time))
            .collect(),
        _ => Vec::new(),
    })
}

pub fn cameras(scene: &Scene, opts: &FramesOptions) -> Result<Vec<Camera>> {
    if opts.camera_path.is_some() && opts.path != PathKind::File {
        return Err(NerfError::Config(format!(
            "--camera-path is read only with --path file (the path asked for is {}); add \
             --path file, or drop --camera-path",
            opts.path.name()
        )));
    }
    if opts.path == PathKind::File {
        let file = opts
            .camera_path
            .as_ref()
            .ok_or_else(|| NerfError::Config("--path file needs --camera-path FILE".into()))?;
        return crate::camera::path::load_camera_path(file, opts.size);
    }
    if opts.path == PathKind::Test {
        if scene.test.is_empty() {
            return Err(NerfError::Config(format!(
                "the scene in {} has no test split (no transforms_test.json or no held-out \
                 images); render --path orbit, spiral or interpolate instead",
                scene.dir.display()
            )));
        }
        return Ok(scene.cameras(Split::Test));
    }
    let train = scene.cameras(Split::Train);
    let reference = train
        .first()
        .ok_or_else(|| NerfError::Config("the scene has no training views".into()))?;
    let poses: Vec<Pose> = train.iter().map(|c| c.c2w).collect();
    let frames = opts.frames.max(1);
    let path = match opts.path {
        PathKind::Spiral => crate::camera::path::spiral(&poses, frames, 2.0),
        PathKind::Interpolate => crate::camera::path::interpolate(&poses, 8, frames),
        _ => {
            let mean_distance = poses
                .iter()
                .map(|p| crate::math::length([p[0][3], p[1][3], p[2][3]]))
                .sum::<f32>()
                / poses.len() as f32;
            let radius = opts.radius.unwrap_or(mean_distance);
            crate::camera::orbit(frames, radius, opts.elevation.to_radians())
        }
    };
    let template = match opts.size {
        Some(width) => resized(reference, width),
        None => reference.clone(),
    };
    crate::camera::check_image_size(template.width, template.height)
        .map_err(|m| NerfError::Config(format!("--size {}: {m}", template.width)))?;
    Ok(path
        .into_iter()
        .map(|c2w| Camera {
            c2w,
            ..template.clone()
        })
        .collect())
}

/// `camera`'s pinhole view (no lens distortion: rendered views are ideal) at `width`
/// pixels across, keeping its field of view and aspect ratio.
pub fn resized(camera: &Camera, width: usize) -> Camera {
    let s = width as f32 / camera.width as f32;
    Camera {
        width,
        height: ((camera.height as f32 * s).round() as usize).max(1),
        fx: camera.fx * s,
        fy: camera.fy * s,
        cx: camera.cx * s,
        cy: camera.cy * s,
        c2w: camera.c2w,
        distortion: Default::default(),
    }
}

/// How a video is written.
#[derive(Clone, Debug, PartialEq)]
pub struct VideoTarget {
    pub path: PathBuf,
    /// H.264 through ffmpeg; else a GIF encoded here.
    pub mp4: bool,
    /// Why the file differs from the one asked for (an MP4 without ffmpeg becomes a GIF).
    pub fallback: Option<String>,
}

/// The video for `path`: `.gif`, or `.mp4` when ffmpeg is on PATH (a GIF beside it when
/// it is not).
pub fn video_target(path: &Path) -> Result<VideoTarget> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("gif") => Ok(VideoTarget {
            path: path.to_path_buf(),
            mp4: false,
            fallback: None,
        }),
        Some("mp4") if crate::app::video::ffmpeg_available() => Ok(VideoTarget {
            path: path.to_path_buf(),
            mp4: true,
            fallback: None,
        }),
        Some("mp4") => {
            let gif = path.with_extension("gif");
            Ok(VideoTarget {
                fallback: Some(format!(
                    "ffmpeg is not on PATH (Debian: apt-get install ffmpeg): writing {} instead of {}",
                    gif.display(),
                    path.display()
                )),
                path: gif,
                mp4: false,
            })
        }
        _ => Err(NerfError::Config(format!(
            "{}: choose a .gif or .mp4 video file",
            path.display()
        ))),
    }
}

/// Progress of [`render_frames`].
#[derive(Clone, Copy, Debug)]
pub struct FrameProgress {
    /// The frame being rendered (0-based) of `frames`.
    pub frame: usize,
    pub frames: usize,
    pub rays_done: usize,
    pub rays_total: usize,
    pub frames_per_second: f64,
}

/// What [`render_frames`] wrote.
#[derive(Clone, Debug)]
pub struct FramesReport {
    pub frames: usize,
    /// Wall time of the whole path, writing included.
    pub seconds: f64,
    /// Wall time from the first frame's start until the last is rendered (writing, and
    /// frames in flight, overlap each other inside it).
    pub render_seconds: f64,
    /// The first frame's share of it (which includes compiling a GPU's kernels).
    pub first_frame_seconds: f64,
    pub video: Option<VideoTarget>,
}

/// Renders `opts.path` of `run` into `out` (`frame_NNNN.png`, `_depth.png`,
/// `_opacity.png`) and the video, if asked for.
pub fn render_frames(
    run: &LoadedRun,
    opts: &FramesOptions,
    out: &Path,
    on_progress: &(dyn Fn(FrameProgress) + Sync),
) -> Result<FramesReport> {
    let cfg = &run.config;
    let scene = cfg.open_scene(1)?;
    let mut cameras = cameras(&scene, opts)?;
    // A run that refined its cameras learned the scene in a frame of its own: the path,
    // given in the scene's frame, moves into it (see `refined_cameras`).
    if let Some(run_cameras) = crate::train::refined_cameras::RunCameras::of(run)? {
        let to_model = run_cameras.to_model_frame();
        for c in &mut cameras {
            c.c2w = to_model.apply_pose(&c.c2w);
        }
    }
    let video = opts.video.as_deref().map(video_target).transpose()?;
    crate::io::create_dir(out)?;
    let mut settings = RenderSettings::of_scene(&scene, cfg.background.eval_colour());
    if let Some(which) = &opts.appearance_of {
        settings.appearance = crate::app::looks::appearance_of(cfg, &scene, which)?;
    }
    let path_times = frame_times(&scene, opts)?;
    let frame_count = cameras.len();
    let settings_of = |k: usize| RenderSettings {
        time: match (opts.time_sweep, opts.time) {
            (true, _) => Some(k as f32 / frame_count.saturating_sub(1).max(1) as f32),
            (false, Some(t)) => Some(t),
            (false, None) => path_times.get(k).copied().flatten(),
        },
        ..settings
    };
    let rays_total: usize = cameras.iter().map(|c| c.width * c.height).sum();
    let t0 = Instant::now();
    let frames_done = AtomicUsize::new(0);
    let progress = |rays_done| {
        let done = frames_done.load(Ordering::Relaxed);
        on_progress(FrameProgress {
            frame: done.min(cameras.len().saturating_sub(1)),
            frames: cameras.len(),
            rays_done,
            rays_total,
            frames_per_second: done as f64 / t0.elapsed().as_secs_f64().max(1e-9),
        })
    };
    let gif_frames = Mutex::new(Vec::new());
    let keep_gif = video.as_ref().is_some_and(|v| !v.mp4);
    let (mut render_seconds, mut first_frame_seconds) = (0.0, 0.0);
    // Frames are written by a thread of their own while the next ones render, so the
    // engine never waits on PNG encoding; at most two rendered frames wait to be written.
    let (send, receive) = std::sync::mpsc::sync_channel::<FrameToWrite>(2);
    let written = std::thread::scope(|scope| -> Result<()> {
        let writer = scope.spawn(move || -> Result<()> {
            for frame in receive {
                frame.write(out)?;
            }
            Ok(())
        });
        // A frame on its way to the writer; `Err` once the writer has stopped on an error,
        // which it returns below.
        let emit = |index, view: crate::views::RenderedView, depth_range| {
            if keep_gif {
                lock(&gif_frames).push((index, view.rgb.clone()));
            }
            frames_done.fetch_add(1, Ordering::Relaxed);
            let frame = FrameToWrite {
                index,
                view,
                depth_range,
            };
            send.send(frame).map_err(|_| ())
        };
        if let Some((first, rest)) = cameras.split_first() {
            // The first frame alone: it compiles a GPU's kernels, and sets the depth range.
            let started = Instant::now();
            let r = render_view(run.engine.as_ref(), first, &settings_of(0), &progress);
            first_frame_seconds = started.elapsed().as_secs_f64();
            let depth_range = opts.depth_range.unwrap_or_else(|| {
                crate::app::video::auto_depth_range(&r.depth, &r.opacity)
                    .unwrap_or((settings.near, settings.far))
            });
            let first_rays = first.width * first.height;
            // The rest as many at once as the engine renders best.
            let _stopped = emit(0, r, depth_range).and_then(|()| {
                render_views(
                    run.engine.as_ref(),
                    rest,
                    &|k| settings_of(k + 1),
                    run.engine.views_in_flight(),
                    &|n| progress(first_rays + n),
                    &|k, view| emit(k + 1, view, depth_range),
                )
            });
            render_seconds = started.elapsed().as_secs_f64();
        }
        drop(send);
        writer
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    });
    written?;
    if let Some(v) = &video {
        if v.mp4 {
            crate::app::video::write_mp4(&out.join("frame_%04d.png"), &v.path, opts.fps)?;
        } else if let Some(c) = cameras.first() {
            let mut frames = gif_frames.into_inner().unwrap_or_else(|e| e.into_inner());
            frames.sort_by_key(|&(index, _)| index);
            let frames: Vec<Vec<f32>> = frames.into_iter().map(|(_, rgb)| rgb).collect();
            crate::app::video::write_gif(&v.path, c.width, c.height, &frames, opts.fps)?;
        }
    }
    Ok(FramesReport {
        frames: cameras.len(),
        seconds: t0.elapsed().as_secs_f64(),
        render_seconds,
        first_frame_seconds,
        video,
    })
}

/// `m`'s value, even if a thread panicked holding it (the frames pushed stay whole).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A rendered frame on its way to its three PNGs.
struct FrameToWrite {
    index: usize,
    view: crate::views::RenderedView,
    /// Depths mapped to the turbo colour map's ends.
    depth_range: (f32, f32),
}

impl FrameToWrite {
    /// Writes `frame_NNNN.png`, `_depth.png` and `_opacity.png` into `out`, side by side.
    fn write(self, out: &Path) -> Result<()> {
        let (r, k) = (&self.view, self.index);
        let (near, far) = self.depth_range;
        let rgb = || {
            save_rgb_png(
                &out.join(format!("frame_{k:04}.png")),
                r.width,
                r.height,
                &r.rgb,
            )
        };
        let depth = || {
            let turbo = crate::app::video::depth_turbo(&r.depth, &r.opacity, near, far);
            let path = out.join(format!("frame_{k:04}_depth.png"));
            save_rgb_png(&path, r.width, r.height, &turbo)
        };
        let opacity = || {
            let grey: Vec<f32> = r.opacity.iter().flat_map(|&o| [o; 3]).collect();
            let path = out.join(format!("frame_{k:04}_opacity.png"));
            save_rgb_png(&path, r.width, r.height, &grey)
        };
        let (a, (b, c)) = rayon::join(rgb, || rayon::join(depth, opacity));
        a.and(b).and(c)
    }
}
