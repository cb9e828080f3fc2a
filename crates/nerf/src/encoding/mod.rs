//! Input encodings of positions and directions.

pub mod frequency;

pub use frequency::FrequencyEncoding;
