//! Decoded images, read as premultiplied RGBA `f32`, and compositing over a background.
//!
//! Premultiplied values make area-average downscaling exact (colour is weighted by
//! coverage) and compositing one multiply-add: `c = rgb_pm + bg * (1 - a)`. An 8-bit photo
//! keeps its bytes (a quarter of the floats' memory: a training split is most of a run's
//! memory) and is premultiplied as it is read, to the same bits as a float copy would hold.

use std::path::Path;

use crate::error::{NerfError, Result};

/// A `width x height` image, row-major, 4 premultiplied channels per pixel as read.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbaImage {
    pub width: usize,
    pub height: usize,
    texels: Texels,
}

/// How the pixels are held.
#[derive(Clone, Debug, PartialEq)]
enum Texels {
    /// Straight-alpha RGBA bytes, as 8-bit files store them.
    Bytes(Vec<u8>),
    /// Premultiplied RGBA values (16-bit files, downscaled or made images).
    Floats(Vec<f32>),
}

/// A byte's value in [0, 1], as the `image` crate converts it (`v / 255`).
#[inline]
fn unit(v: u8) -> f32 {
    v as f32 / 255.0
}

/// Each byte value's channel value as [`RgbaImage::pixel`] reads it (`v / 255`), so that
/// another reader of [`RgbaImage::straight_bytes`] (the GPU engine) makes the same floats.
pub fn unit_values() -> [f32; 256] {
    std::array::from_fn(|v| unit(v as u8))
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
        let (w, h) = (img.width() as usize, img.height() as usize);
        // Colour photos of 8 bits a channel (PNG, JPEG) keep their bytes; the crate's gray
        // conversion rounds otherwise than `unit`, so gray ones (and deeper ones) are floats.
        let colour_bytes = matches!(
            img,
            image::DynamicImage::ImageRgb8(_) | image::DynamicImage::ImageRgba8(_)
        );
        Ok(if colour_bytes {
            RgbaImage::from_straight_bytes(w, h, img.into_rgba8().into_raw())
        } else {
            RgbaImage::from_straight_alpha(w, h, img.into_rgba32f().into_raw())
        })
    }

    /// An image from straight-alpha RGBA values (as PNGs store them), premultiplied here.
    pub fn from_straight_alpha(width: usize, height: usize, mut data: Vec<f32>) -> RgbaImage {
        for px in data.chunks_exact_mut(4) {
            let a = px[3];
            px[0] *= a;
            px[1] *= a;
            px[2] *= a;
        }
        RgbaImage::from_premultiplied(width, height, data)
    }

    /// An image from premultiplied RGBA values.
    pub fn from_premultiplied(width: usize, height: usize, data: Vec<f32>) -> RgbaImage {
        debug_assert_eq!(data.len(), width * height * 4);
        RgbaImage {
            width,
            height,
            texels: Texels::Floats(data),
        }
    }

    /// An image from straight-alpha RGBA bytes, kept as bytes.
    pub fn from_straight_bytes(width: usize, height: usize, data: Vec<u8>) -> RgbaImage {
        debug_assert_eq!(data.len(), width * height * 4);
        RgbaImage {
            width,
            height,
            texels: Texels::Bytes(data),
        }
    }

    /// Pixel `index`, premultiplied: for an 8-bit image the same bits as
    /// `from_straight_alpha` of the `image` crate's `f32` conversion.
    #[inline]
    pub fn pixel(&self, index: usize) -> [f32; 4] {
        match &self.texels {
            Texels::Bytes(b) => {
                let p = &b[index * 4..][..4];
                let a = unit(p[3]);
                [unit(p[0]) * a, unit(p[1]) * a, unit(p[2]) * a, a]
            }
            Texels::Floats(f) => {
                let p = &f[index * 4..][..4];
                [p[0], p[1], p[2], p[3]]
            }
        }
    }

    /// The pixels as read from an 8-bit file, straight (not premultiplied) RGBA, 4 bytes a
    /// pixel; `None` for an image held as floats (16-bit files, downscaled or rendered
    /// images). [`pixel`](Self::pixel) turns each byte `v` into `unit_values()[v]`.
    pub fn straight_bytes(&self) -> Option<&[u8]> {
        match &self.texels {
            Texels::Bytes(b) => Some(b),
            Texels::Floats(_) => None,
        }
    }

    /// Every pixel, premultiplied, as packed RGBA.
    pub fn premultiplied(&self) -> Vec<f32> {
        match &self.texels {
            Texels::Bytes(_) => (0..self.width * self.height)
                .flat_map(|i| self.pixel(i))
                .collect(),
            Texels::Floats(f) => f.clone(),
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
                        let p = self.pixel(row + x * factor + sx);
                        for c in 0..4 {
                            o[c] += p[c];
                        }
                    }
                }
                o.iter_mut().for_each(|v| *v *= norm);
            }
        }
        RgbaImage::from_premultiplied(w, h, data)
    }

    /// The colour of pixel `index` composited over `bg`.
    #[inline]
    pub fn composite_pixel(&self, index: usize, bg: [f32; 3]) -> [f32; 3] {
        let p = self.pixel(index);
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
        match &self.texels {
            Texels::Bytes(b) => b.chunks_exact(4).any(|p| p[3] < u8::MAX),
            Texels::Floats(f) => f.chunks_exact(4).any(|p| p[3] < 1.0),
        }
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
        let img = RgbaImage::from_premultiplied(
            2,
            2,
            vec![
                1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
            ],
        );
        let small = img.downscale(2);
        assert_eq!(small.premultiplied(), vec![0.25, 0.0, 0.0, 0.25]);
        // Over white: 0.25 red + 0.75 white.
        assert_eq!(small.composite_pixel(0, [1.0; 3]), [1.0, 0.75, 0.75]);
    }

    /// The floats an 8-bit file reads as before it is kept as bytes: the `image` crate's
    /// conversion, premultiplied.
    fn as_floats(path: &Path) -> RgbaImage {
        let img = image::open(path).expect("open");
        let (w, h) = (img.width() as usize, img.height() as usize);
        RgbaImage::from_straight_alpha(w, h, img.to_rgba32f().into_raw())
    }

    /// Every byte value in every channel, against every alpha, in RGBA, RGB and gray files
    /// (gray ones kept as floats): the kept bytes read as the same bits as the floats, pixel by pixel, composited,
    /// downscaled and as a whole.
    #[test]
    fn eight_bit_images_kept_as_bytes_read_as_their_floats() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (w, h) = (256u32, 256u32);
        let rgba = image::RgbaImage::from_fn(w, h, |x, y| {
            image::Rgba([
                x as u8,
                y as u8,
                (x ^ y) as u8,
                (x.wrapping_mul(7) ^ y) as u8,
            ])
        });
        let rgb = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([y as u8, x as u8, 3]));
        let gray = image::GrayImage::from_fn(w, h, |x, y| image::Luma([(x + y) as u8]));
        let files = [
            ("rgba.png", image::DynamicImage::from(rgba)),
            ("rgb.png", image::DynamicImage::from(rgb)),
            ("gray.png", image::DynamicImage::from(gray)),
        ];
        for (name, img) in files {
            let path = dir.path().join(name);
            img.save(&path).expect("save");
            let (bytes, floats) = (RgbaImage::load(&path).expect("load"), as_floats(&path));
            let kept_as_bytes = matches!(bytes.texels, Texels::Bytes(_));
            assert_eq!(kept_as_bytes, name != "gray.png", "{name}");
            let (a, b) = (bytes.premultiplied(), floats.premultiplied());
            let apart = a
                .iter()
                .zip(&b)
                .position(|(x, y)| x.to_bits() != y.to_bits());
            assert_eq!(apart, None, "{name}: value {apart:?} differs");
            for i in [0, 1, 255, 256 * 128 + 77, 256 * 256 - 1] {
                assert_eq!(
                    bytes.composite_pixel(i, [0.2, 0.6, 1.0]),
                    floats.composite_pixel(i, [0.2, 0.6, 1.0])
                );
            }
            assert!(bytes.downscale(4) == floats.downscale(4), "{name}");
            assert_eq!(
                bytes.has_transparency(),
                floats.has_transparency(),
                "{name}"
            );
            assert_eq!(bytes.has_transparency(), name == "rgba.png");
        }
    }

    /// A 16-bit file keeps its precision (floats, not bytes).
    #[test]
    fn sixteen_bit_images_keep_their_precision() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("deep.png");
        save_gray16_png(&path, 2, 1, vec![1, 65535]).expect("save");
        let img = RgbaImage::load(&path).expect("load");
        assert!(matches!(img.texels, Texels::Floats(_)));
        assert_eq!(
            img.pixel(0),
            [1.0 / 65535.0, 1.0 / 65535.0, 1.0 / 65535.0, 1.0]
        );
        assert_eq!(img.pixel(1), [1.0; 4]);
    }

    #[test]
    fn png_round_trip_and_truncated_file_error() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("a.png");
        let rgba = vec![1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.5];
        save_rgba_png(&path, 2, 1, &rgba).expect("save");
        let back = RgbaImage::load(&path).expect("load");
        assert_eq!((back.width, back.height), (2, 1));
        let green = back.pixel(1);
        assert!(
            (green[1] - 0.502).abs() < 0.01,
            "premultiplied green {green:?}"
        );
        assert!((green[3] - 0.502).abs() < 0.01);
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
