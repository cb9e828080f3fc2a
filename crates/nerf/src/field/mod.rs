//! Radiance fields: functions from a position and a view direction to density and colour.

pub mod vanilla;

pub use vanilla::{VanillaConfig, VanillaNet, VanillaWorkspace};
