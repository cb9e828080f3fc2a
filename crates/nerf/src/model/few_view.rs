//! Training from few photos (at most [`FEW_VIEWS`]). With few photos, space that few of
//! them see can explain their pixels with anything at any depth, and a field fills it
//! with floaters that every other view then shows. Few-view training keeps the space that
//! fewer than half of the training photos see empty: the occupancy grid never marks it,
//! so no sample is taken there in training or rendering (`render::visibility`).

use serde::{Deserialize, Serialize};

/// Runs on at most this many training views get few-view training by default.
pub const FEW_VIEWS: usize = 16;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FewView {
    /// The training photos.
    pub photos: usize,
}

impl FewView {
    /// How many photos must see a cell for it to hold anything: half of them, at least 2.
    pub fn min_views(&self) -> usize {
        self.photos.div_ceil(2).max(2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_of_the_photos_and_at_least_two_must_see_a_cell() {
        let min = |photos| FewView { photos }.min_views();
        assert_eq!(
            [min(1), min(3), min(4), min(8), min(9), min(16)],
            [2, 2, 2, 4, 5, 8]
        );
    }
}
