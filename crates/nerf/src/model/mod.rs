//! The two models a run can train, on the CPU: the paper's coarse + fine MLPs
//! ([`VanillaModel`]) and the hash-grid field with an occupancy grid ([`FastModel`]).
//!
//! A model strings the pure stages of `render` and a `Field` into its own training pass
//! and renderer, and implements [`Model`], which the CPU engine (`engine::cpu`) drives. Both
//! keep every trainable value in one flat vector described by a [`ParamLayout`], so the
//! optimiser, checkpoints, evaluation and rendering treat them alike.

pub mod camera_refine;
pub mod fast;
pub mod few_view;
pub mod free_nerf;
pub mod hidden_space;
pub mod reg_nerf;
pub mod unseen_patches;
pub mod vanilla;

use serde::{Deserialize, Serialize};

pub use fast::{FastModel, FastModelConfig};
pub use vanilla::{VanillaModel, VanillaModelConfig};

use crate::data::pixels::PixelSampling;
use crate::data::Dataset;
use crate::nn::{GradBuffer, ParamLayout};
use crate::stage::{RayBatch, RayOutput};

/// Which model, by name (the command line's `--model`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// Hash grid + occupancy grid (after Instant-NGP): minutes on a CPU.
    Fast,
    /// The paper's MLPs: days on a CPU.
    Vanilla,
}

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

    /// The model as a trained run is used (rendering, evaluation, meshes, fitting test
    /// cameras): without training's speed settings. The networks' products in bfloat16
    /// speed up the CPU's training steps only (every engine renders in `f32`), so a run
    /// trained with them opens on every engine.
    pub fn for_inference(&self) -> ModelConfig {
        match self {
            ModelConfig::Fast(m) => ModelConfig::Fast(fast::FastModelConfig {
                bf16_products: false,
                ..m.clone()
            }),
            ModelConfig::Vanilla(_) => self.clone(),
        }
    }

    /// Whether the model is a field of space and time (a moving scene: `--dynamic`, or
    /// `--preset dnerf`).
    pub fn is_dynamic(&self) -> bool {
        match self {
            ModelConfig::Fast(m) => m.field.motion.is_some(),
            ModelConfig::Vanilla(m) => m.net.deformation.is_some(),
        }
    }

    /// Training photos with a per-photo appearance code (`--appearance`); 0 without codes.
    pub fn appearance_photos(&self) -> usize {
        match self {
            ModelConfig::Fast(m) if m.field.appearance_dims > 0 => m.field.appearance_images,
            _ => 0,
        }
    }

    /// The density grid `nerf mesh` samples by default: points per axis, and the half-extent
    /// of the box (a contracted model's inner cube, the part of its box that is undistorted).
    pub fn mesh_defaults(&self) -> (usize, f32) {
        match self {
            ModelConfig::Fast(m) if m.contract => (256, 0.5 * m.field.bound),
            ModelConfig::Fast(m) => (256, m.field.bound),
            ModelConfig::Vanilla(_) => (128, 1.5),
        }
    }

    /// One line for logs: the model's shape.
    pub fn describe(&self) -> String {
        match self {
            ModelConfig::Vanilla(m) => format!(
                "{}x{} MLP, PE L={}/{}, {} coarse + {} fine samples{}{}{}",
                m.net.depth,
                m.net.width,
                m.net.position_encoding.frequencies,
                m.net
                    .direction_encoding
                    .map_or("off".to_string(), |d| d.frequencies.to_string()),
                m.n_coarse,
                m.n_fine,
                m.net
                    .deformation
                    .as_ref()
                    .map_or(String::new(), |d| format!(
                        ", deformation {}x{} MLP (time PE L={})",
                        d.depth, d.width, d.time_frequencies
                    )),
                m.free_nerf.map_or(String::new(), |f| format!(
                    ", FreeNeRF (bands revealed over {:.0}% of training, density of the first {} samples penalised x {})",
                    100.0 * f.reveal_until,
                    f.occlusion_samples,
                    f.occlusion_weight
                )),
                m.reg_nerf.map_or(String::new(), |r| {
                    let weight = match r.smoothness_start == r.smoothness_end {
                        true => format!("{}", r.smoothness_end),
                        false => format!(
                            "{} -> {} over {} steps",
                            r.smoothness_start, r.smoothness_end, r.smoothness_steps
                        ),
                    };
                    format!(
                        ", RegNeRF (depth smoothness on patches from unseen poses, weight {weight}; sampled range widened from {:.0}% over {} steps)",
                        100.0 * r.anneal_start,
                        r.anneal_steps
                    )
                }),
            ),
            ModelConfig::Fast(m) => {
                let g = &m.field.grid;
                let motion = m.field.motion.map_or(String::new(), |t| {
                    let smooth = match m.time_smoothness {
                        w if w > 0.0 => format!(", smooth in time x {w}"),
                        _ => String::new(),
                    };
                    format!(
                        ", space-time grid {} levels x 2^{} entries ({}..{} cells, {}..{} along \
                         time{smooth})",
                        t.levels,
                        t.log2_table_size,
                        t.base_resolution,
                        t.max_resolution,
                        t.base_time_resolution,
                        t.max_time_resolution
                    )
                });
                let patches = m.depth_smoothness.map_or(String::new(), |d| {
                    format!(
                        ", depth smoothness x {} on {} patches of {side}x{side} rays {} px apart \
                         from unseen poses per step",
                        d.weight,
                        d.patches,
                        d.stride,
                        side = crate::render::depth_smoothness::PATCH_SIDE
                    )
                });
                format!(
                    "hash grid {} levels x 2^{} entries ({}..{} cells){motion}, {}-wide MLPs, {}^3 occupancy grid, {} samples/step{patches}",
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

/// A model on the CPU engine: how it initialises, trains a step, renders and answers
/// density queries. Engines other than the CPU one implement the same models with their own
/// kernels; this trait is the CPU side of the engine seam.
pub trait Model: Send + Sync + 'static {
    /// One thread's reusable buffers (training and rendering).
    type Workspace: Default + Send + Sync;
    /// Reusable buffers a whole training step shares.
    type StepBuffers: Default + Send + Sync;

    fn layout(&self) -> &ParamLayout;

    /// Fresh weights, deterministic in `seed`.
    fn init_params(&self, seed: u64) -> Vec<f32>;

    /// Names and shapes of the non-trainable state kept in checkpoints.
    fn buffer_layout(&self) -> ParamLayout {
        ParamLayout::default()
    }
    /// That state, laid out by [`buffer_layout`](Self::buffer_layout).
    fn buffers(&self) -> Vec<f32> {
        Vec::new()
    }
    /// Restores state saved by [`buffers`](Self::buffers).
    fn load_buffers(&mut self, _values: Vec<f32>) {}

    /// The forward and backward passes of one step, spread over `workers` (one per
    /// thread): gradients of the summed squared error go into each worker's buffer.
    fn train_pass(
        &self,
        input: &StepInput,
        shared: &mut Self::StepBuffers,
        workers: &mut [Worker<Self::Workspace>],
    ) -> PassTotals;

    /// How Adam treats the parameters.
    fn update_rule(&self) -> UpdateRule {
        UpdateRule::default()
    }

    /// Called after each optimiser step, with the steps completed (occupancy refreshes).
    fn after_step(&mut self, _params: &[f32], _steps_done: u64, _seed: u64) {}

    /// Called before each step with the training data (few-view training marks, once,
    /// the space its cameras see).
    fn prepare(&mut self, _data: &Dataset) {}

    /// Called before each step with how far through its schedule the run is, in [0, 1]
    /// (coarse-to-fine weighting of camera refinement).
    fn set_progress(&mut self, _progress: f32) {}

    /// Renders a chunk of rays into `out` (one per ray).
    fn render_chunk(
        &self,
        params: &[f32],
        rays: &RayBatch,
        ws: &mut Self::Workspace,
        out: &mut [RayOutput],
    );

    /// Densities at world `positions` (`n x 3`) into `out` (`n`), at moment `time` of a
    /// moving scene (`None`: any moment; still models ignore it).
    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        time: Option<f32>,
        ws: &mut Self::Workspace,
        out: &mut [f32],
    );

    /// Fraction of the scene box marked occupied, for models that skip empty space.
    fn occupancy(&self) -> Option<f64> {
        None
    }
}

/// What every worker of a training step reads.
#[derive(Clone, Copy)]
pub struct StepInput<'a> {
    pub data: &'a Dataset,
    pub params: &'a [f32],
    /// Which rays the step draws.
    pub sampling: PixelSampling,
    /// Vanilla model: rays per step.
    pub batch_rays: usize,
    /// Rays per work unit.
    pub chunk_rays: usize,
    /// The debug checks of every stage's outputs and gradients (`NERF_CHECK_FINITE`).
    pub check: &'a crate::stage::finite::FiniteCheck,
}

/// One thread's share of a training step.
pub struct Worker<W> {
    pub ws: W,
    pub grads: GradBuffer,
}

/// What the workers of one step produced, before the optimiser runs.
#[derive(Clone, Copy, Debug, Default)]
pub struct PassTotals {
    /// Summed squared errors of every pass (coarse + fine for the vanilla model).
    pub sse: f64,
    /// Summed squared errors of the final rendering (fine pass, else the only one).
    pub final_sse: f64,
    pub rays: usize,
    pub samples: usize,
}

/// How Adam updates a model's parameters.
#[derive(Clone, Copy, Debug, Default)]
pub struct UpdateRule {
    /// Parameters before this index update lazily (hash tables: only entries with a
    /// gradient), the rest densely.
    pub lazy_end: usize,
    /// L2 penalty on the lazily updated parameters, on the entries a step touches.
    pub table_decay: f32,
    /// L2 penalty on the densely updated parameters.
    pub weight_decay: f32,
    /// Parameters from this index on form their own group (camera corrections): dense,
    /// no weight decay, at the step's `camera_lr`.
    pub group_start: Option<usize>,
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
