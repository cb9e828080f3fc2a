//! Radiance fields: functions from a position and a view direction to density and colour.

pub mod deformation;
pub mod fast;
mod level_weights;
pub mod vanilla;

pub use deformation::DeformationConfig;
pub use fast::{FastField, FastFieldConfig, FastWorkspace};
pub use vanilla::{VanillaConfig, VanillaNet, VanillaWorkspace};
