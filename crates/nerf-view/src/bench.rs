//! `nerf view --bench`: how the viewer performs on this machine for a run, through the
//! code that serves pages (render, colour, JPEG): frames per second at several sizes, the
//! preview size the pacer picks for a moving camera, the time from a resting camera to
//! its full-resolution frame, the input-to-frame latency of a preview, and the frames a
//! second of full-size frames streamed as the session streams them (the next frame
//! rendering while the last is encoded).

use std::time::Instant;

use crate::protocol::{Mode, ViewCamera};
use crate::render::{encode_levels, level_sizes, render_level, Model, Pacer, ViewRequest};

/// Frames rendered per size (the median is reported).
const REPEATS: usize = 5;
/// Full-size frames streamed for the streaming figure, unless [`STREAM_SECONDS`] pass
/// first (a CPU takes seconds a frame).
const STREAMED: usize = 24;
const STREAM_SECONDS: f64 = 5.0;

/// One row of the report.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SizeFigure {
    pub width: usize,
    pub height: usize,
    pub median_seconds: f64,
    pub frames_per_second: f64,
}

/// What `nerf view --bench` measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ViewBench {
    pub sizes: Vec<SizeFigure>,
    /// The full size the refinement figures are for.
    pub full: (usize, usize),
    /// The preview size for a moving camera at `full`, and its frame time.
    pub preview: (usize, usize),
    pub preview_seconds: f64,
    /// From a resting camera's request to its full-resolution frame (every level).
    pub refine_seconds: f64,
    /// Full-size frames a second, rendered and encoded as a session streams them.
    pub streamed_frames_per_second: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Benchmarks `model` seen from `c2w` with vertical field of view `fov_y` (degrees), at
/// heights `heights` (4:3), refinement at `full`.
pub fn run(
    model: &Model,
    c2w: [[f32; 4]; 3],
    fov_y: f32,
    heights: &[usize],
    full: (usize, usize),
) -> ViewBench {
    let never = || false;
    let mut pacer = Pacer::default();
    let view = |width, height| ViewRequest {
        seq: 0,
        camera: ViewCamera {
            c2w,
            fov_y,
            width,
            height,
        },
        mode: Mode::Rgb,
        moving: false,
        appearance: Default::default(),
        time: None,
    };
    let mut sizes = Vec::new();
    for &h in heights {
        let w = h * 4 / 3;
        let v = view(w, h);
        let times: Vec<f64> = (0..REPEATS)
            .map(|_| {
                let t0 = Instant::now();
                render_level(model, &mut pacer, &v, (w, h), &never).map(|l| l.encode());
                t0.elapsed().as_secs_f64()
            })
            .collect();
        let t = median(times);
        sizes.push(SizeFigure {
            width: w,
            height: h,
            median_seconds: t,
            frames_per_second: 1.0 / t,
        });
    }
    let v = view(full.0, full.1);
    let preview_scale = pacer.preview_scale(full.0, full.1);
    let preview = level_sizes(&v.camera, preview_scale, true)[0];
    let preview_seconds = median(
        (0..REPEATS)
            .map(|_| {
                let t0 = Instant::now();
                render_level(model, &mut pacer, &v, preview, &never).map(|l| l.encode());
                t0.elapsed().as_secs_f64()
            })
            .collect(),
    );
    let t0 = Instant::now();
    for size in level_sizes(&v.camera, preview_scale, false) {
        render_level(model, &mut pacer, &v, size, &never).map(|l| l.encode());
    }
    let refine_seconds = t0.elapsed().as_secs_f64();
    ViewBench {
        sizes,
        full,
        preview,
        preview_seconds,
        refine_seconds,
        streamed_frames_per_second: streamed(model, &mut pacer, &v, full),
    }
}

/// Full-size frames a second of `view` rendered on this thread while the one before is
/// encoded on another, as a session streams them.
fn streamed(model: &Model, pacer: &mut Pacer, view: &ViewRequest, full: (usize, usize)) -> f64 {
    let (to_encoder, levels) = std::sync::mpsc::sync_channel(1);
    let t0 = Instant::now();
    let frames = std::thread::scope(|scope| {
        scope.spawn(|| encode_levels(model, levels, |_| true));
        let mut frames = 0;
        while frames < STREAMED && (frames < 2 || t0.elapsed().as_secs_f64() < STREAM_SECONDS) {
            if let Some(level) = render_level(model, pacer, view, full, &|| false) {
                let _ = to_encoder.send(level);
            }
            frames += 1;
        }
        drop(to_encoder);
        frames
    });
    // The last frame's encoding counts: the scope waited for it.
    frames as f64 / t0.elapsed().as_secs_f64().max(1e-9)
}

impl ViewBench {
    pub fn print(&self) {
        println!("| frame | median time | frames/s |");
        println!("|---|---|---|");
        for s in &self.sizes {
            println!(
                "| {}x{} | {:.3} s | {:.1} |",
                s.width, s.height, s.median_seconds, s.frames_per_second
            );
        }
        println!(
            "moving camera at {}x{}: preview {}x{} in {:.3} s ({:.1} frames/s; the \
             input-to-frame latency, less the page's own few milliseconds)",
            self.full.0,
            self.full.1,
            self.preview.0,
            self.preview.1,
            self.preview_seconds,
            1.0 / self.preview_seconds
        );
        println!(
            "camera at rest: full {}x{} frame after {:.2} s (every refinement level)",
            self.full.0, self.full.1, self.refine_seconds
        );
        println!(
            "full {}x{} frames streamed (each encoded while the next renders): {:.1} frames/s",
            self.full.0, self.full.1, self.streamed_frames_per_second
        );
    }
}
