//! Which look (per-photo appearance code, `--appearance`) a held-out view is evaluated
//! with.
//!
//! A model with codes renders a photo's look only for photos it trained on; a held-out
//! photo has none. The mean code is the model's canonical look (what `render` and the
//! viewer use), but a phone's auto-exposure follows what the camera sees, so a held-out
//! photo looks like the training photos taken next to it: with the mean code, held-out
//! views can score lower than a model without codes, which bakes the look of each place
//! into its colours. By default `nerf eval` gives each view the look of the
//! training photo whose camera is nearest; this reads no pixel of the held-out photo.

use serde::{Deserialize, Serialize};

use crate::camera::Pose;
use crate::data::scene::Scene;
use crate::error::{NerfError, Result};
use crate::math::{length, sub};
use crate::stage::Appearance;
use crate::train::TrainConfig;

/// How `nerf eval` picks the look of each view of a model with appearance codes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum EvalLook {
    /// The look of the training photo whose camera centre is nearest.
    #[default]
    Nearest,
    /// The mean of the training photos' codes (the look of `render` and the viewer).
    Mean,
}

/// The look a view is rendered with, and the training photo it is (if it is one's).
#[derive(Clone, Debug, PartialEq)]
pub struct ViewLook {
    pub appearance: Appearance,
    pub photo: Option<String>,
}

/// The look of each of `poses` (in the frame of `scene`, the run's, before any
/// alignment) for a run with appearance codes under `how`, with the training photo's name
/// where it is one; `None` for a run without codes.
pub fn looks_of(
    config: &TrainConfig,
    scene: &Scene,
    poses: &[Pose],
    how: EvalLook,
) -> Option<Vec<ViewLook>> {
    if config.model.appearance_photos() == 0 {
        return None;
    }
    if how == EvalLook::Mean {
        let mean = ViewLook {
            appearance: Appearance::Mean,
            photo: None,
        };
        return Some(vec![mean; poses.len()]);
    }
    let kept = trained_photos(config, scene);
    let centres: Vec<_> = kept
        .iter()
        .map(|&f| centre(&scene.frames[f].camera.c2w))
        .collect();
    Some(
        poses
            .iter()
            .map(|pose| match nearest(&centres, centre(pose)) {
                Some(k) => ViewLook {
                    appearance: Appearance::Of(k as u32),
                    photo: Some(scene.frames[kept[k]].name.clone()),
                },
                None => ViewLook {
                    appearance: Appearance::Mean,
                    photo: None,
                },
            })
            .collect(),
    )
}

/// The frames of `scene` the run trained on, in the order of their codes: the training
/// split, or the views `--train-views` kept of it.
fn trained_photos(config: &TrainConfig, scene: &Scene) -> Vec<usize> {
    let train = scene.indices(crate::data::Split::Train);
    // A trained run's list was checked against this split when it trained.
    let kept = config
        .kept_train_views(train.len())
        .unwrap_or_else(|_| (0..train.len()).collect());
    kept.into_iter().map(|i| train[i]).collect()
}

/// The look of one training photo (`--appearance-of`): `which` is its index among the
/// photos the run trained on, or its file name.
pub fn appearance_of(config: &TrainConfig, scene: &Scene, which: &str) -> Result<Appearance> {
    let names = |frames: &[usize]| -> Vec<String> {
        frames
            .iter()
            .map(|&f| scene.frames[f].name.clone())
            .collect()
    };
    let trained = names(&trained_photos(config, scene));
    match photo_index(&trained, which) {
        Some(i) => Ok(Appearance::Of(i as u32)),
        None => {
            let split = names(scene.indices(crate::data::Split::Train));
            let why = if photo_index(&split, which).is_some() {
                "that photo is in the training split, but --train-views left it out of training"
                    .to_string()
            } else {
                format!(
                    "no training photo has that index (0..{}) or name",
                    trained.len()
                )
            };
            Err(NerfError::Config(format!("--appearance-of {which}: {why}")))
        }
    }
}

/// Where `which` (an index, a name, or a name's last component) is in `names`.
fn photo_index(names: &[String], which: &str) -> Option<usize> {
    let named = |name: &String| {
        name == which || std::path::Path::new(name).file_name() == Some(which.as_ref())
    };
    which
        .parse::<usize>()
        .ok()
        .filter(|&i| i < names.len())
        .or_else(|| names.iter().position(named))
}

fn centre(pose: &Pose) -> [f32; 3] {
    [pose[0][3], pose[1][3], pose[2][3]]
}

/// Index of the point of `points` nearest to `p` (the first of equals), if any.
fn nearest(points: &[[f32; 3]], p: [f32; 3]) -> Option<usize> {
    points
        .iter()
        .map(|q| length(sub(*q, p)))
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(k, _)| k)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_nearest_centre_wins() {
        let points = [[0.0, 0.0, 4.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0]];
        assert_eq!(nearest(&points, [3.0, 1.0, 0.5]), Some(1));
        assert_eq!(nearest(&points, [0.2, 0.1, 3.0]), Some(0));
        assert_eq!(nearest(&points, [0.0, 4.0, 0.0]), Some(2));
        assert_eq!(nearest(&[], [0.0; 3]), None);
    }

    #[test]
    fn a_photo_is_found_by_index_name_or_file_name() {
        let names = ["train/r_0.png", "train/r_5.png", "train/r_9.png"].map(String::from);
        assert_eq!(photo_index(&names, "1"), Some(1));
        assert_eq!(photo_index(&names, "train/r_9.png"), Some(2));
        assert_eq!(photo_index(&names, "r_5.png"), Some(1));
        assert_eq!(photo_index(&names, "3"), None, "past the end");
        assert_eq!(photo_index(&names, "r_4.png"), None);
    }
}
