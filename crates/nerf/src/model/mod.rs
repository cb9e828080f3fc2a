//! The two models a run can train: the paper's coarse + fine MLPs ([`VanillaModel`]) and the
//! hash-grid field with an occupancy grid ([`FastModel`]). Both keep every trainable value in
//! one flat vector described by a [`ParamLayout`], so the optimiser, checkpoints, evaluation
//! and rendering treat them alike; only how a batch of rays is sampled and differentiated
//! differs.

pub mod fast;
pub mod query;
pub mod vanilla;

use serde::{Deserialize, Serialize};

pub use fast::{FastModel, FastModelConfig};
pub use vanilla::{VanillaModel, VanillaModelConfig};

use crate::nn::ParamLayout;

/// Which model, with its shape; saved in a run's `config.json` under `"kind"`. Configs
/// written before there were two models have no `"kind"` and read as vanilla.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum ModelConfig {
    Vanilla(VanillaModelConfig),
    Fast(FastModelConfig),
}

/// The tagged form, for reading.
#[derive(Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
enum Tagged {
    Vanilla(VanillaModelConfig),
    Fast(FastModelConfig),
}

impl<'de> Deserialize<'de> for ModelConfig {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let value = serde_json::Value::deserialize(d)?;
        if value.get("kind").is_none() {
            return VanillaModelConfig::deserialize(value)
                .map(ModelConfig::Vanilla)
                .map_err(D::Error::custom);
        }
        Ok(
            match Tagged::deserialize(value).map_err(D::Error::custom)? {
                Tagged::Vanilla(m) => ModelConfig::Vanilla(m),
                Tagged::Fast(m) => ModelConfig::Fast(m),
            },
        )
    }
}

impl ModelConfig {
    pub fn kind(&self) -> &'static str {
        match self {
            ModelConfig::Vanilla(_) => "vanilla",
            ModelConfig::Fast(_) => "fast",
        }
    }

    /// One line for logs: the model's shape.
    pub fn describe(&self) -> String {
        match self {
            ModelConfig::Vanilla(m) => format!(
                "{}x{} MLP, PE L={}/{}, {} coarse + {} fine samples",
                m.net.depth,
                m.net.width,
                m.net.position_encoding.frequencies,
                m.net
                    .direction_encoding
                    .map_or("off".to_string(), |d| d.frequencies.to_string()),
                m.n_coarse,
                m.n_fine,
            ),
            ModelConfig::Fast(m) => {
                let g = &m.field.grid;
                format!(
                    "hash grid {} levels x 2^{} entries ({}..{} cells), {}-wide MLPs, {}^3 occupancy grid, {} samples/step",
                    g.levels,
                    g.log2_table_size,
                    g.base_resolution,
                    g.max_resolution,
                    m.field.hidden,
                    m.occupancy.resolution,
                    m.samples_per_step
                )
            }
        }
    }
}

/// One per run, long-lived: the size difference of the variants costs nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Model {
    Vanilla(VanillaModel),
    Fast(FastModel),
}

/// A non-trainable tensor a model keeps in its checkpoint (the occupancy grid).
#[derive(Clone, Debug, PartialEq)]
pub struct Buffer {
    pub name: String,
    pub shape: Vec<usize>,
    pub values: Vec<f32>,
}

const OCCUPANCY: &str = "occupancy.thickness";

impl Model {
    pub fn new(config: ModelConfig) -> Self {
        match config {
            ModelConfig::Vanilla(c) => Model::Vanilla(VanillaModel::new(c)),
            ModelConfig::Fast(c) => Model::Fast(FastModel::new(c)),
        }
    }

    pub fn layout(&self) -> &ParamLayout {
        match self {
            Model::Vanilla(m) => &m.layout,
            Model::Fast(m) => &m.field.layout,
        }
    }

    /// Fresh weights, deterministic in `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        match self {
            Model::Vanilla(m) => m.init_params(seed),
            Model::Fast(m) => m.field.init_params(seed),
        }
    }

    /// Names and shapes of the non-trainable state, in checkpoint order.
    pub fn buffer_layout(&self) -> ParamLayout {
        let mut l = ParamLayout::default();
        if let Model::Fast(m) = self {
            let r = m.grid.resolution;
            l.push(OCCUPANCY, &[r, r, r]);
        }
        l
    }

    /// Non-trainable state to checkpoint, laid out by [`buffer_layout`](Self::buffer_layout).
    pub fn buffers(&self) -> Vec<Buffer> {
        self.buffer_layout()
            .tensors
            .into_iter()
            .map(|t| Buffer {
                values: match self {
                    Model::Fast(m) => m.grid.thickness.clone(),
                    Model::Vanilla(_) => Vec::new(),
                },
                name: t.name,
                shape: t.shape,
            })
            .collect()
    }

    /// Restores state saved by [`buffers`](Self::buffers) (values in layout order).
    pub fn load_buffers(&mut self, values: Vec<f32>) {
        if let Model::Fast(m) = self {
            let (r, b) = (m.grid.resolution, m.grid.bound);
            m.grid = crate::render::occupancy::OccupancyGrid::from_thickness(
                r,
                b,
                values,
                m.config.occupancy.threshold,
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configs_round_trip_and_untagged_ones_read_as_vanilla() {
        let fast = ModelConfig::Fast(FastModelConfig::default());
        let (vanilla, _) = crate::presets::build("demo").expect("preset");
        for c in [fast, ModelConfig::Vanilla(vanilla.clone())] {
            let text = serde_json::to_string(&c).expect("json");
            assert!(
                text.contains(&format!("\"kind\":\"{}\"", c.kind())),
                "{text}"
            );
            assert_eq!(serde_json::from_str::<ModelConfig>(&text).expect("read"), c);
        }
        let old = serde_json::to_string(&vanilla).expect("json");
        assert_eq!(
            serde_json::from_str::<ModelConfig>(&old).expect("old config"),
            ModelConfig::Vanilla(vanilla)
        );
        let err = serde_json::from_str::<ModelConfig>(r#"{"kind":"huge"}"#).expect_err("bad kind");
        assert!(err.to_string().contains("huge"), "{err}");
    }
}
