//! Frames to shareable files: depth colour-mapped with turbo, animated GIFs in pure Rust,
//! and H.264 MP4s through the `ffmpeg` binary when it is installed.

use std::path::Path;
use std::process::Command;

use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};

use crate::error::{NerfError, Result};

/// Google's turbo colour map (a polynomial fit): dark blue at 0, through green and yellow,
/// to dark red at 1.
pub fn turbo(x: f32) -> [f32; 3] {
    let x = x.clamp(0.0, 1.0);
    let poly = |c: [f32; 6]| {
        (c[0] + x * (c[1] + x * (c[2] + x * (c[3] + x * (c[4] + x * c[5]))))).clamp(0.0, 1.0)
    };
    [
        poly([
            0.135_721_4,
            4.615_392_6,
            -42.660_324,
            132.131_08,
            -152.942_4,
            59.286_38,
        ]),
        poly([
            0.091_402_61,
            2.194_188_4,
            4.842_966_6,
            -14.185_033,
            4.277_298_6,
            2.829_566,
        ]),
        poly([
            0.106_673_3,
            12.641_946,
            -60.582_05,
            110.362_77,
            -89.903_11,
            27.348_25,
        ]),
    ]
}

/// Colour-mapped depth: `near` dark blue, `far` dark red, faded to black where the ray
/// hit nothing (by opacity). `depth` is opacity-weighted (as rendered).
pub fn depth_turbo(depth: &[f32], opacity: &[f32], near: f32, far: f32) -> Vec<f32> {
    depth
        .iter()
        .zip(opacity)
        .flat_map(|(&d, &a)| {
            let z = if a > 1e-4 { d / a } else { far };
            let c = turbo((z - near) / (far - near).max(1e-6));
            c.map(|v| v * a.clamp(0.0, 1.0))
        })
        .collect()
}

/// The depth range that covers the 2nd to 98th percentile of the opaque pixels of a view,
/// widened by a fifth so the other frames of a path mostly fit (`None` when nothing is
/// opaque): a fixed range for a whole video without a legend.
pub fn auto_depth_range(depth: &[f32], opacity: &[f32]) -> Option<(f32, f32)> {
    let mut z: Vec<f32> = depth
        .iter()
        .zip(opacity)
        .filter(|(_, &a)| a > 0.5)
        .map(|(&d, &a)| d / a)
        .collect();
    if z.is_empty() {
        return None;
    }
    z.sort_by(f32::total_cmp);
    let at = |q: f32| z[((z.len() - 1) as f32 * q) as usize];
    let (lo, hi) = (at(0.02), at(0.98).max(at(0.02) + 1e-3));
    let pad = 0.1 * (hi - lo);
    Some((lo - pad, hi + pad))
}

/// Writes RGB frames (`width x height`, values in [0, 1]) as a looping animated GIF.
pub fn write_gif(
    path: &Path,
    width: usize,
    height: usize,
    frames: &[Vec<f32>],
    fps: f32,
) -> Result<()> {
    let mut bytes = Vec::new();
    {
        let mut encoder = GifEncoder::new_with_speed(&mut bytes, 10);
        encoder
            .set_repeat(Repeat::Infinite)
            .map_err(|e| NerfError::write(path, std::io::Error::other(e)))?;
        let delay = Delay::from_numer_denom_ms(1000, fps.max(0.1).round().max(1.0) as u32);
        for rgb in frames {
            let rgba: Vec<u8> = rgb
                .chunks_exact(3)
                .flat_map(|p| {
                    [p[0], p[1], p[2], 1.0].map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                })
                .collect();
            let img = RgbaImage::from_raw(width as u32, height as u32, rgba).ok_or_else(|| {
                NerfError::write(path, std::io::Error::other("frame size does not match"))
            })?;
            encoder
                .encode_frame(Frame::from_parts(img, 0, 0, delay))
                .map_err(|e| NerfError::write(path, std::io::Error::other(e)))?;
        }
    }
    crate::io::write_atomic(path, &bytes)
}

/// Whether an `ffmpeg` binary runs (probed once per process: rendering, capture and the
/// MP4 writer all ask).
pub fn ffmpeg_available() -> bool {
    static AVAILABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *AVAILABLE.get_or_init(|| {
        Command::new("ffmpeg")
            .arg("-version")
            .output()
            .is_ok_and(|o| o.status.success())
    })
}

/// Encodes `pattern` (an ffmpeg input pattern such as `dir/frame_%04d.png`) to an H.264
/// MP4 in yuv420p (what players and browsers accept), padding odd sizes to even.
pub fn write_mp4(pattern: &Path, path: &Path, fps: f32) -> Result<()> {
    if !ffmpeg_available() {
        return Err(NerfError::Config(format!(
            "{}: writing MP4 needs ffmpeg on PATH (Debian: apt-get install ffmpeg); write a .gif instead",
            path.display()
        )));
    }
    let tmp = crate::io::tmp_path(path).with_extension("tmp.mp4");
    let out = Command::new("ffmpeg")
        .args(["-y", "-loglevel", "error", "-framerate"])
        .arg(format!("{fps}"))
        .arg("-i")
        .arg(pattern)
        .args([
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
        ])
        .arg(&tmp)
        .output()
        .map_err(|e| NerfError::write(path, e))?;
    if !out.status.success() {
        let _ = std::fs::remove_file(&tmp);
        return Err(NerfError::write(
            path,
            std::io::Error::other(format!(
                "ffmpeg failed: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            )),
        ));
    }
    std::fs::rename(&tmp, path).map_err(|e| NerfError::write(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turbo_runs_blue_to_red_through_green() {
        let (lo, mid, hi) = (turbo(0.1), turbo(0.5), turbo(1.0));
        assert!(lo[2] > lo[0] && lo[2] > lo[1], "{lo:?}");
        assert!(mid[1] > 0.8 && mid[1] > mid[2], "{mid:?}");
        assert!(hi[0] > 0.4 && hi[1] < 0.1 && hi[2] < 0.1, "{hi:?}");
    }

    #[test]
    fn auto_range_ignores_transparent_pixels_and_outliers() {
        let mut depth: Vec<f32> = (0..100).map(|i| 3.0 + i as f32 * 0.01).collect();
        let mut opacity = vec![1.0; 100];
        depth.push(50.0);
        opacity.push(0.01);
        let (lo, hi) = auto_depth_range(&depth, &opacity).expect("range");
        // 2nd..98th percentile (3.02..3.97) widened by a tenth of its width each side.
        assert!(
            (2.91..2.95).contains(&lo) && (4.04..4.08).contains(&hi),
            "{lo} {hi}"
        );
        assert!(auto_depth_range(&[1.0], &[0.0]).is_none());
    }

    #[test]
    fn gif_is_written_with_every_frame() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("a.gif");
        let frames: Vec<Vec<f32>> = (0..3).map(|k| vec![k as f32 / 2.0; 8 * 6 * 3]).collect();
        write_gif(&path, 8, 6, &frames, 10.0).expect("gif");
        let file = std::fs::File::open(&path).expect("open");
        let decoder =
            image::codecs::gif::GifDecoder::new(std::io::BufReader::new(file)).expect("decoder");
        use image::AnimationDecoder;
        let read: Vec<_> = decoder
            .into_frames()
            .collect::<std::result::Result<_, _>>()
            .expect("frames");
        assert_eq!(read.len(), 3);
        assert_eq!(read[0].buffer().dimensions(), (8, 6));
    }
}
