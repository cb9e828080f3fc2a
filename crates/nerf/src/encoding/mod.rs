//! Input encodings of positions and directions.

pub mod frequency;
#[cfg(target_arch = "x86_64")]
mod grid_simd;
pub mod hash_grid;
pub mod integrated;
pub mod space_time_grid;
pub mod spherical_harmonics;

pub use frequency::FrequencyEncoding;
pub use hash_grid::{HashGrid, HashGridConfig};
