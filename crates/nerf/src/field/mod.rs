//! Radiance fields: functions from a position and a view direction to density and colour.

pub mod fast;
pub mod vanilla;

pub use fast::{FastField, FastFieldConfig, FastWorkspace};
pub use vanilla::{VanillaConfig, VanillaNet, VanillaWorkspace};
