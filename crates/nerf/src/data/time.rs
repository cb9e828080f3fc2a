//! The moments of a dynamic scene: each photo's `time` (D-NeRF's key), checked and brought
//! into [0, 1] when a scene opens, and what a split's moments are.

use std::path::Path;

use super::reader::Frame;
use crate::error::{NerfError, Result};

/// Two times closer than this are one moment.
const SAME_MOMENT: f32 = 1e-6;

/// Checks `frames`' times (of the scene in `dir`) and brings them into [0, 1]. A scene has
/// a time on every frame (a dynamic scene) or on none (a static one); every time must be
/// finite. Times outside [0, 1] are mapped linearly onto it, the first moment to 0 and the
/// last to 1, and the returned note says so.
pub(crate) fn normalise(dir: &Path, frames: &mut [Frame]) -> Result<Option<String>> {
    let timed = frames.iter().filter(|f| f.time.is_some()).count();
    if timed == 0 {
        return Ok(None);
    }
    if let Some(untimed) = frames.iter().find(|f| f.time.is_none()) {
        return Err(NerfError::format(
            dir,
            format!(
                "frame {} has no time while {timed} of the scene's {} frames have one: a \
                 dynamic scene needs a `time` on every frame",
                untimed.name,
                frames.len()
            ),
        ));
    }
    if let Some(bad) = frames
        .iter()
        .find(|f| f.time.is_some_and(|t| !t.is_finite()))
    {
        return Err(NerfError::format(
            dir,
            format!("frame {}: its time is not a finite number", bad.name),
        ));
    }
    let (first, last) = frames
        .iter()
        .filter_map(|f| f.time)
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), t| {
            (lo.min(t), hi.max(t))
        });
    if first >= 0.0 && last <= 1.0 {
        return Ok(None);
    }
    let span = last - first;
    for f in frames.iter_mut() {
        f.time = f
            .time
            .map(|t| if span > 0.0 { (t - first) / span } else { 0.0 });
    }
    Ok(Some(format!(
        "the frames' times run from {first} to {last}, outside [0, 1]: mapped onto [0, 1] \
         (the first moment 0, the last 1)"
    )))
}

/// The distinct moments among `times`, in order.
pub fn moments(times: impl IntoIterator<Item = f32>) -> Vec<f32> {
    let mut sorted: Vec<f32> = times.into_iter().filter(|t| t.is_finite()).collect();
    sorted.sort_by(f32::total_cmp);
    sorted.dedup_by(|later, kept| *later - *kept < SAME_MOMENT);
    sorted
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;

    fn frames(times: &[Option<f32>]) -> Vec<Frame> {
        times
            .iter()
            .enumerate()
            .map(|(k, &time)| Frame {
                camera: Camera::from_fov_x(
                    4,
                    4,
                    0.7,
                    [
                        [1.0, 0.0, 0.0, 0.0],
                        [0.0, 1.0, 0.0, 0.0],
                        [0.0, 0.0, 1.0, 4.0],
                    ],
                ),
                image: format!("r_{k}.png").into(),
                mask: None,
                name: format!("r_{k}"),
                time,
            })
            .collect()
    }

    #[test]
    fn a_static_scene_and_times_within_zero_to_one_are_kept() {
        let dir = Path::new("scene");
        let mut none = frames(&[None, None]);
        assert_eq!(normalise(dir, &mut none).ok(), Some(None));
        let mut within = frames(&[Some(0.0), Some(0.25), Some(1.0)]);
        assert_eq!(normalise(dir, &mut within).ok(), Some(None));
        let kept: Vec<_> = within.iter().map(|f| f.time).collect();
        assert_eq!(kept, [Some(0.0), Some(0.25), Some(1.0)]);
    }

    #[test]
    fn times_outside_zero_to_one_are_mapped_onto_it_with_a_note() {
        let mut f = frames(&[Some(10.0), Some(30.0), Some(20.0)]);
        let note = normalise(Path::new("scene"), &mut f).expect("normalised");
        let note = note.expect("a note");
        assert!(note.contains("10") && note.contains("30"), "{note}");
        let got: Vec<_> = f.iter().map(|f| f.time).collect();
        assert_eq!(got, [Some(0.0), Some(1.0), Some(0.5)]);
        // One moment outside [0, 1]: every frame at 0.
        let mut one = frames(&[Some(5.0), Some(5.0)]);
        assert!(normalise(Path::new("scene"), &mut one)
            .expect("ok")
            .is_some());
        assert!(one.iter().all(|f| f.time == Some(0.0)));
    }

    #[test]
    fn a_frame_without_a_time_or_with_a_non_finite_one_is_refused_by_name() {
        let mut partly = frames(&[Some(0.0), None, Some(1.0)]);
        let err = normalise(Path::new("scene"), &mut partly).expect_err("refused");
        let msg = err.to_string();
        assert!(
            msg.contains("r_1") && msg.contains("2 of the scene's 3"),
            "{msg}"
        );
        let mut nan = frames(&[Some(0.0), Some(f32::NAN)]);
        let msg = normalise(Path::new("scene"), &mut nan)
            .expect_err("refused")
            .to_string();
        assert!(msg.contains("r_1") && msg.contains("finite"), "{msg}");
    }

    #[test]
    fn moments_are_the_distinct_times_in_order() {
        assert_eq!(
            moments([0.5, 0.0, 0.5, 1.0, 0.5 + 1e-8]),
            vec![0.0, 0.5, 1.0]
        );
        assert!(moments([]).is_empty());
    }
}
