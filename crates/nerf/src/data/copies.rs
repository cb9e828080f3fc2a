//! Images that are copies of each other under other names: a dataset whose test split is
//! its training split renamed (or re-encoded) scores its model on photos it trained on.
//! Images are compared by small thumbnails, so a copy saved again as JPEG still matches.

use std::path::Path;

use rayon::prelude::*;

use super::image::RgbaImage;
use crate::error::Result;

/// Thumbnails are this many pixels a side.
const SIDE: usize = 16;

/// Two thumbnails that differ by less than this in every cell and channel (values in
/// [0, 1]) are one image: re-encoding moves a cell's average by far less, while two photos
/// taken from different places differ by more somewhere (lego's two nearest renders, a
/// test and a training view whose poses differ by 0.02 in their matrices, by 0.019).
const SAME: f32 = 0.008;

/// An image's thumbnail: its premultiplied RGBA averaged over a `SIDE x SIDE` grid of
/// cells, plus its aspect ratio (copies have the same shape).
pub struct Thumbnail {
    cells: Vec<f32>,
    aspect: f32,
}

impl Thumbnail {
    pub fn of(image: &RgbaImage) -> Thumbnail {
        let (w, h) = (image.width.max(1), image.height.max(1));
        let mut cells = vec![0.0f32; SIDE * SIDE * 4];
        let mut counts = vec![0u32; SIDE * SIDE];
        for y in 0..image.height {
            for x in 0..image.width {
                let cell = (y * SIDE / h) * SIDE + x * SIDE / w;
                let px = image.pixel(y * image.width + x);
                for c in 0..4 {
                    cells[cell * 4 + c] += px[c];
                }
                counts[cell] += 1;
            }
        }
        for (cell, &n) in counts.iter().enumerate() {
            for c in 0..4 {
                cells[cell * 4 + c] /= n.max(1) as f32;
            }
        }
        Thumbnail {
            cells,
            aspect: w as f32 / h as f32,
        }
    }

    pub fn load(path: &Path) -> Result<Thumbnail> {
        Ok(Thumbnail::of(&RgbaImage::load(path)?))
    }

    /// Whether the two are one image (see [`SAME`]).
    pub fn same_as(&self, other: &Thumbnail) -> bool {
        if (self.aspect - other.aspect).abs() > 0.01 * self.aspect {
            return false;
        }
        self.cells
            .iter()
            .zip(&other.cells)
            .all(|(a, b)| (a - b).abs() < SAME)
    }
}

/// How many of `held_out` are copies of one of `training` (image files, read in parallel).
pub fn copies_among(held_out: &[&Path], training: &[&Path]) -> Result<usize> {
    let load = |paths: &[&Path]| -> Result<Vec<Thumbnail>> {
        paths.par_iter().map(|p| Thumbnail::load(p)).collect()
    };
    let training = load(training)?;
    let held_out = load(held_out)?;
    Ok(held_out
        .iter()
        .filter(|t| training.iter().any(|u| t.same_as(u)))
        .count())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(seed: u32, w: usize, h: usize) -> RgbaImage {
        let data = (0..w * h * 4)
            .map(|i| {
                let x = (i as u32).wrapping_mul(2654435761).wrapping_add(seed * 97);
                ((x >> 8) % 1000) as f32 / 1000.0
            })
            .collect();
        RgbaImage::from_straight_alpha(w, h, data)
    }

    #[test]
    fn a_reencoded_copy_matches_and_another_image_does_not() {
        let a = image(1, 64, 48);
        let mut values = a.premultiplied();
        for (k, v) in values.iter_mut().enumerate() {
            // What JPEG does to a pixel: a few levels either way, nothing on average.
            *v += if (k / 4) % 2 == 0 { 0.02 } else { -0.02 };
        }
        let noisy = RgbaImage::from_premultiplied(64, 48, values);
        let ta = Thumbnail::of(&a);
        assert!(ta.same_as(&Thumbnail::of(&noisy)));
        assert!(!ta.same_as(&Thumbnail::of(&image(2, 64, 48))));
        // Same content, another shape: not a copy.
        assert!(!ta.same_as(&Thumbnail::of(&image(1, 48, 48))));
    }
}
