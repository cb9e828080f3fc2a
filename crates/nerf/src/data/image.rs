//! Decoded images as premultiplied RGBA `f32`, and compositing over a background.
//!
//! Premultiplied storage makes area-average downscaling exact (colour is weighted by
//! coverage) and compositing one multiply-add: `c = rgb_pm + bg * (1 - a)`.

use std::path::Path;

use crate::error::{NerfError, Result};

/// A `width x height` image, row-major, 4 premultiplied channels per pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbaImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl RgbaImage {
    /// Reads an 8- or 16-bit PNG (or any format the `image` crate decodes); images without
    /// alpha are opaque.
    pub fn load(path: &Path) -> Result<RgbaImage> {
        let bytes = std::fs::read(path).map_err(|e| NerfError::io(path, e))?;
        let img = image::load_from_memory(&bytes).map_err(|e| NerfError::Image {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        let rgba = img.to_rgba32f();
        let (w, h) = rgba.dimensions();
        Ok(RgbaImage::from_straight_alpha(
            w as usize,
            h as usize,
            rgba.into_raw(),
        ))
    }

    /// An image from straight-alpha RGBA values (as PNGs store them), premultiplied here.
    pub fn from_straight_alpha(width: usize, height: usize, mut data: Vec<f32>) -> RgbaImage {
        for px in data.chunks_exact_mut(4) {
            let a = px[3];
            px[0] *= a;
            px[1] *= a;
            px[2] *= a;
        }
        RgbaImage {
            width,
            height,
            data,
        }
    }

    /// Area-average downscale by an integer factor (partial blocks at the edges are dropped,
    /// as the output size is `floor(size / factor)`).
    pub fn downscale(&self, factor: usize) -> RgbaImage {
        if factor <= 1 {
            return self.clone();
        }
        let (w, h) = (self.width / factor, self.height / factor);
        let mut data = vec![0.0f32; w * h * 4];
        let norm = 1.0 / (factor * factor) as f32;
        for y in 0..h {
            for x in 0..w {
                let o = &mut data[(y * w + x) * 4..][..4];
                for sy in 0..factor {
                    let row = (y * factor + sy) * self.width;
                    for sx in 0..factor {
                        let p = &self.data[(row + x * factor + sx) * 4..][..4];
                        for c in 0..4 {
                            o[c] += p[c];
                        }
                    }
                }
                o.iter_mut().for_each(|v| *v *= norm);
            }
        }
        RgbaImage {
            width: w,
            height: h,
            data,
        }
    }

    /// The colour of pixel `index` composited over `bg`.
    #[inline]
    pub fn composite_pixel(&self, index: usize, bg: [f32; 3]) -> [f32; 3] {
        let p = &self.data[index * 4..][..4];
        let t = 1.0 - p[3];
        [p[0] + bg[0] * t, p[1] + bg[1] * t, p[2] + bg[2] * t]
    }

    /// The whole image composited over `bg`, as packed RGB.
    pub fn composite(&self, bg: [f32; 3]) -> Vec<f32> {
        (0..self.width * self.height)
            .flat_map(|i| self.composite_pixel(i, bg))
            .collect()
    }

    /// Whether any pixel is not fully opaque (so the background colour matters).
    pub fn has_transparency(&self) -> bool {
        self.data.chunks_exact(4).any(|p| p[3] < 1.0)
    }
}

/// Writes packed RGB in [0, 1] as an 8-bit PNG, through a temporary file renamed into place.
pub fn save_rgb_png(path: &Path, width: usize, height: usize, rgb: &[f32]) -> Result<()> {
    save_png::<image::Rgb<u8>>(path, width, height, rgb.iter().map(|&v| to_u8(v)).collect())
}

/// Writes straight-alpha RGBA in [0, 1] as an 8-bit PNG.
pub fn save_rgba_png(path: &Path, width: usize, height: usize, rgba: &[f32]) -> Result<()> {
    save_png::<image::Rgba<u8>>(
        path,
        width,
        height,
        rgba.iter().map(|&v| to_u8(v)).collect(),
    )
}

/// Writes a 16-bit grayscale PNG.
pub fn save_gray16_png(path: &Path, width: usize, height: usize, values: Vec<u16>) -> Result<()> {
    save_png::<image::Luma<u16>>(path, width, height, values)
}

fn save_png<P>(path: &Path, width: usize, height: usize, values: Vec<P::Subpixel>) -> Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
{
    let img = image::ImageBuffer::<P, _>::from_raw(width as u32, height as u32, values)
        .ok_or_else(|| {
            NerfError::format(
                path,
                format!(
                    "buffer does not hold {width}x{height} pixels of {} channels",
                    P::CHANNEL_COUNT
                ),
            )
        })?;
    // Encode in memory, then write through the one crash-safe path: the image crate's own
    // file writer buffers, and a buffered write that fails at its final flush (a full disk)
    // is dropped silently, leaving a 0-byte PNG reported as written.
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, image::ImageFormat::Png)
        .map_err(|e| NerfError::write(path, std::io::Error::other(e.to_string())))?;
    crate::io::write_atomic(path, &bytes.into_inner())
}

/// A colour value in [0, 1] as an 8-bit one (clamped, rounded), as every PNG we write.
#[inline]
pub fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscale_averages_premultiplied_colour() {
        // One opaque red pixel and three transparent ones: a quarter-covered red pixel.
        let img = RgbaImage {
            width: 2,
            height: 2,
            data: vec![
                1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
            ],
        };
        let small = img.downscale(2);
        assert_eq!(small.data, vec![0.25, 0.0, 0.0, 0.25]);
        // Over white: 0.25 red + 0.75 white.
        assert_eq!(small.composite_pixel(0, [1.0; 3]), [1.0, 0.75, 0.75]);
    }

    #[test]
    fn png_round_trip_and_truncated_file_error() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("a.png");
        let rgba = vec![1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.5];
        save_rgba_png(&path, 2, 1, &rgba).expect("save");
        let back = RgbaImage::load(&path).expect("load");
        assert_eq!((back.width, back.height), (2, 1));
        assert!(
            (back.data[5] - 0.502).abs() < 0.01,
            "premultiplied green {}",
            back.data[5]
        );
        assert!((back.data[7] - 0.502).abs() < 0.01);
        let bytes = std::fs::read(&path).expect("read");
        std::fs::write(&path, &bytes[..bytes.len() / 2]).expect("truncate");
        let err = RgbaImage::load(&path).expect_err("truncated PNG must fail");
        assert!(err.to_string().contains("a.png"), "{err}");
    }

    /// A full disk. The temporary file is made a link to `/dev/full`, where
    /// every write fails with "No space left on device"; the save must fail, naming the
    /// file, and leave nothing in its place.
    #[test]
    #[cfg(unix)]
    fn a_full_disk_is_an_error_not_an_empty_png() {
        if !Path::new("/dev/full").exists() {
            eprintln!("skipping: /dev/full is absent");
            return;
        }
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("frame.png");
        std::os::unix::fs::symlink("/dev/full", crate::io::tmp_path(&path)).expect("symlink");
        let err = save_rgb_png(&path, 2, 2, &[0.5; 12]).expect_err("a full disk must fail");
        assert!(
            err.to_string().contains("frame.png") && err.to_string().contains("space"),
            "{err}"
        );
        assert!(!path.exists(), "nothing may be left in place of frame.png");
    }
}
