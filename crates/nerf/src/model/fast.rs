//! The fast model: one hash-grid field, its occupancy grid, and its training pass and
//! renderer built from the marcher (`render::march`), compositing and the loss.
//!
//! Work mapping of a training step (the same rays and samples for any thread count):
//! 1. Rays are drawn in blocks of [`BLOCK_RAYS`] (block `b` holds rays `b * BLOCK_RAYS..` of
//!    the step) and marched, in waves of blocks run in parallel (first as many blocks as the
//!    previous step used, then 4, 8, ... 64 more) until the rays marched so far hold
//!    `samples_per_step` samples. The step's rays are those up to the first ray at which the
//!    running sample count reaches the budget, whatever the waves were. With RegNeRF's
//!    depth smoothness (`depth_smoothness`), the photo rays are instead the whole blocks
//!    up to that one, and the step's patches from unseen poses follow, one block each.
//! 2. The kept rays are shared among the `W` workers in contiguous runs holding about as
//!    many samples each; a worker runs forward, loss and backward over its run in chunks of
//!    about `batch_samples` samples (never splitting a patch), into its own gradient
//!    buffer. Squared errors are kept per ray and summed in ray order, so losses are the
//!    same for any thread count; gradients differ only by the order in which they are
//!    summed.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera_refine::{self, CameraRefinement, CameraStep};
use super::few_view::{self, FewView};
use super::unseen_patches::{self, DepthSmoothness, PatchDraw};
use super::{Model, PassTotals, StepInput, UpdateRule, Worker};
use crate::camera::ray_space::RaySpace;
use crate::data::pixels::{PixelSampling, TrainingRays};
use crate::data::Dataset;
use crate::field::{FastField, FastFieldConfig, FastWorkspace as FieldContext};
use crate::nn::linalg::Precision;
use crate::nn::{GradBuffer, ParamLayout};
use crate::render::depth_smoothness::{PatchBackward, PATCH_RAYS};
use crate::render::loss::{squared_error, LossBackward};
use crate::render::march::{render_marched, MarchWorkspace, Marcher, MIN_WEIGHT};
use crate::render::occupancy::{OccupancyConfig, OccupancyGrid};
use crate::render::volume::composite_packed;
use crate::stage::finite::{check_outputs, FiniteCheck};
use crate::stage::{Field, FieldOutput, PackedSamples, RayBatch, RayOutput};
use crate::step_clock::{self, Stage};

/// Rays per marching block of a training step.
pub const BLOCK_RAYS: usize = 16;
// A block of patch rays is one patch (see `ChunkInput::patch_from`).
const _: () = assert!(BLOCK_RAYS == PATCH_RAYS);

/// Name of the occupancy grid in checkpoints.
const OCCUPANCY: &str = "occupancy.thickness";
/// Few-view training's hidden cells (1) in a checkpoint, beside the thickness.
const HIDDEN: &str = "occupancy.hidden";

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FastModelConfig {
    pub field: FastFieldConfig,
    pub occupancy: OccupancyConfig,
    /// Field samples per training step; the number of rays follows from it.
    pub samples_per_step: usize,
    /// Samples evaluated per network call (bounds a thread's activation memory).
    pub batch_samples: usize,
    /// Marching steps along the scene box's diagonal (1024: step `sqrt(3) * 2 bound / 1024`).
    pub steps_per_diagonal: f32,
    /// Samples per ray at most.
    pub max_samples_per_ray: usize,
    /// L2 penalty on the MLP weights.
    pub weight_decay: f32,
    /// L2 penalty on the hash tables' entries, on those a step touches (Adam updates the
    /// tables lazily); 0: none, as in runs saved before it existed.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub table_decay: f32,
    /// Unbounded scenes: the field's box `[-B, B]^3` holds the world cube of half-extent
    /// `B / 2` as it is and all space beyond, contracted (see `render::contraction`).
    #[serde(default)]
    pub contract: bool,
    /// Learn a correction of every training camera's pose (see `camera_refine`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine_cameras: Option<CameraRefinement>,
    /// Weight of mip-NeRF 360's distortion loss (`render::distortion`), which gathers each
    /// ray's weight into a short stretch and so clears thin fog; 0: none. Runs saved
    /// before it existed had none.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub distortion: f32,
    /// Few-view training: the space too few photos see kept empty (see `few_view`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub few_view: Option<FewView>,
    /// Moving scenes: weight of the prior that the space-time grid's features change
    /// smoothly in time (`FastField::time_smoothness_bwd`), per ray: its mean over the
    /// step's rays of the squared change over one finest time cell of every
    /// `field::fast::SMOOTH_STRIDE`-th sample's features; 0: none (the default).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub time_smoothness: f32,
    /// RegNeRF's depth smoothness on patches from poses between the training cameras
    /// (see `unseen_patches`, `render::depth_smoothness`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_smoothness: Option<DepthSmoothness>,
    /// Train the networks with their products' inputs rounded to bfloat16 and their sums in
    /// `f32` (CPU engine, on CPUs with AVX-512 BF16: twice the multiply-adds per
    /// instruction). Runs saved before it existed trained in `f32`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub bf16_products: bool,
}

fn is_zero(x: &f32) -> bool {
    *x == 0.0
}

impl Default for FastModelConfig {
    fn default() -> Self {
        FastModelConfig {
            field: FastFieldConfig::default(),
            occupancy: OccupancyConfig::default(),
            samples_per_step: 1 << 16,
            batch_samples: 1 << 13,
            steps_per_diagonal: 1024.0,
            max_samples_per_ray: 1024,
            weight_decay: 1e-6,
            table_decay: 0.0,
            contract: false,
            refine_cameras: None,
            distortion: 0.0,
            few_view: None,
            time_smoothness: 0.0,
            depth_smoothness: None,
            bf16_products: false,
        }
    }
}

impl FastModelConfig {
    /// Few-view training from `photos` training photos: the space too few of them see
    /// kept empty, colour that changes only slowly with the view
    /// ([`few_view::VIEW_HARMONICS`]) and the hash tables' entries pulled towards zero
    /// ([`few_view::TABLE_DECAY`]).
    pub fn train_from_few_views(&mut self, photos: usize) {
        self.few_view = Some(FewView::new(photos));
        self.field.view_harmonics = few_view::VIEW_HARMONICS;
        self.table_decay = few_view::TABLE_DECAY;
    }

    /// Turns anti-aliasing on for a scene seen by `cameras` in `space`, with their typical
    /// footprint as the reference (see [`crate::field::fast::Antialias`]).
    pub fn antialias_for(&mut self, cameras: &[crate::camera::Camera], space: &RaySpace) {
        let reference =
            crate::camera::footprint::reference_footprint(cameras, space, 0.5 * self.field.bound);
        self.field.antialias = Some(crate::field::fast::Antialias {
            reference_footprint: reference,
        });
    }

    /// The diagonal of the scene box `[-B, B]^3`.
    pub fn box_diagonal(&self) -> f32 {
        2.0 * 3f32.sqrt() * self.field.bound
    }

    /// The marching step (metric).
    pub fn step_length(&self) -> f32 {
        self.box_diagonal() / self.steps_per_diagonal
    }
}

#[derive(Clone, Debug)]
pub struct FastModel {
    pub config: FastModelConfig,
    pub field: FastField,
    /// Which cells of the scene box hold anything; refreshed during training and saved
    /// with the checkpoint (rendering needs it).
    pub grid: OccupancyGrid,
    /// The field's parameters, then the camera corrections when cameras are refined.
    layout: ParamLayout,
    cameras_at: Option<usize>,
    /// The precision of the networks' products in training: `config.bf16_products` where
    /// the CPU has the kernels (`nerf train` refuses the setting where it does not).
    products: Precision,
    /// Few-view training: which cells the training cameras frame and which the scene
    /// hides from them.
    visibility: few_view::Visibility,
}

/// What every training chunk of a step reads.
#[derive(Clone, Copy)]
struct ChunkInput<'a> {
    params: &'a [f32],
    /// The step's marched blocks; a chunk takes a range of their rays.
    blocks: &'a [MarchedBlock],
    check: &'a FiniteCheck,
    /// The training cameras' corrections this step (empty: cameras are not refined).
    cameras: &'a [CameraStep],
    /// The step's rays from here on are patches from unseen poses (no photo's pixels),
    /// a whole block each, and their loss's gradient scale.
    patch_from: usize,
    patch_scale: f32,
}

impl FastModel {
    pub fn new(config: FastModelConfig) -> Self {
        let field = FastField::new(config.field.clone());
        let grid = OccupancyGrid::new(config.occupancy.resolution, config.field.bound);
        let mut layout = field.layout.clone();
        let cameras_at = config.refine_cameras.map(|r| {
            layout.push(
                camera_refine::TENSOR,
                &[r.cameras, camera_refine::PER_CAMERA],
            )
        });
        let products = match config.bf16_products {
            true => Precision::bf16().unwrap_or(Precision::F32),
            false => Precision::F32,
        };
        FastModel {
            config,
            field,
            grid,
            layout,
            cameras_at,
            products,
            visibility: few_view::Visibility::default(),
        }
    }

    /// Whether this run looks for the space the scene hides from its training cameras
    /// (`model::hidden_space`); its answer is saved with the checkpoint.
    pub fn keeps_hidden_space(&self) -> bool {
        self.config.few_view.is_some_and(|f| f.hidden_every > 0)
    }

    /// Whether that pass runs after `steps_done` steps (on a scene few-view training
    /// applies to: the cameras are known).
    pub fn hidden_pass_due(&self, steps_done: u64) -> bool {
        self.config
            .few_view
            .is_some_and(|f| f.hidden_pass_after(steps_done))
            && !self.visibility.cameras.is_empty()
    }

    /// The pass on `grid` (the host's, or one an engine read back from its device):
    /// returns the cells that may hold anything from now on.
    pub fn find_hidden(&mut self, grid: &OccupancyGrid) -> Vec<bool> {
        let dt = self.config.step_length();
        self.visibility.find_hidden(grid, dt)
    }

    /// The model's buffers (`Model::buffers`) with the grid's thickness given: an engine
    /// that keeps the grid on a device reads it back and the rest comes from here.
    pub fn buffers_with(&self, mut thickness: Vec<f32>) -> Vec<f32> {
        if self.keeps_hidden_space() {
            let cells = self.grid.resolution.pow(3);
            let hidden = |i: usize| self.visibility.hidden.get(i).copied().unwrap_or(false);
            thickness.extend((0..cells).map(|i| f32::from(u8::from(hidden(i)))));
        }
        thickness
    }

    /// This step's correction of every training camera of `data` (none without refinement).
    fn camera_steps(&self, params: &[f32], data: &Dataset) -> Vec<CameraStep> {
        match self.cameras_at {
            Some(at) => self.camera_steps_of(&params[at..], data),
            None => Vec::new(),
        }
    }

    /// Where the camera corrections begin in the parameter vector (`None`: cameras are
    /// not refined).
    pub fn cameras_at(&self) -> Option<usize> {
        self.cameras_at
    }

    /// Every training camera's step for `corrections` (6 values a camera, from
    /// [`cameras_at`](Self::cameras_at) on; none without refinement).
    pub fn camera_steps_of(&self, corrections: &[f32], data: &Dataset) -> Vec<CameraStep> {
        let Some(refinement) = self.config.refine_cameras else {
            return Vec::new();
        };
        data.views
            .iter()
            .zip(corrections.chunks_exact(camera_refine::PER_CAMERA))
            .map(|(v, c)| CameraStep::new(&v.camera.c2w, c, refinement.frame).in_space(data.space))
            .collect()
    }

    /// How rays between `near` and `far` are marched.
    pub fn marcher(&self, near: f32, far: f32) -> Marcher {
        Marcher {
            dt: self.config.step_length(),
            max_samples: self.config.max_samples_per_ray,
            near,
            far,
            contract: self
                .config
                .contract
                .then_some(0.5 * self.config.field.bound),
        }
    }
}

/// What marching a step's rays reads.
#[derive(Clone, Copy)]
struct MarchInput<'a> {
    data: &'a Dataset,
    sampling: PixelSampling,
    /// The training cameras' corrections this step (empty: none).
    cameras: &'a [CameraStep],
}

/// One block of a step's rays: drawn, marched and packed.
#[derive(Default, Debug)]
pub struct MarchedBlock {
    rays: TrainingRays,
    samples: PackedSamples,
}

/// Buffers of one thread: a training chunk (samples, activations, gradients) and rendering.
#[derive(Default, Debug)]
pub struct FastWorkspace {
    field: FieldContext,
    samples: PackedSamples,
    backgrounds: Vec<[f32; 3]>,
    targets: Vec<[f32; 3]>,
    weights: Vec<f32>,
    outputs: Vec<RayOutput>,
    loss: LossBackward,
    march: MarchWorkspace<FieldContext>,
    /// `dL/d sample position` and `dL/d view direction` (camera refinement).
    d_positions: Vec<f32>,
    d_dirs: Vec<f32>,
    patch: PatchBackward,
}

/// Buffers a whole step shares: the marched blocks.
#[derive(Default, Debug)]
pub struct StepBlocks {
    blocks: Vec<MarchedBlock>,
    /// The step's patches from unseen poses, marched before the photo rays.
    patches: Vec<MarchedBlock>,
    /// Blocks the previous step used: the size of the first wave. Wave sizes decide only
    /// how many rays are marched past the cut, never which rays are kept.
    last_used: usize,
}

impl FastModel {
    /// Draws and marches the rays of block `b` of the step.
    fn march_block(
        &self,
        input: &MarchInput,
        marcher: &Marcher,
        b: usize,
        block: &mut MarchedBlock,
    ) {
        let first = (b * BLOCK_RAYS) as u64;
        block.rays.draw(
            input.data,
            &input.sampling,
            first..first + BLOCK_RAYS as u64,
        );
        camera_refine::correct_drawn_rays(&mut block.rays.rays, input.cameras);
        self.pack_block(marcher, block);
    }

    /// Marches a block's drawn rays into its samples.
    fn pack_block(&self, marcher: &Marcher, block: &mut MarchedBlock) {
        block.samples.clear();
        for r in 0..block.rays.len() {
            let jitter = block.rays.rngs[r].uniform();
            marcher.pack_ray(&self.grid, &block.rays.rays, r, jitter, &mut block.samples);
        }
    }

    /// Draws and marches the step's patches from unseen poses into `patches`, one block
    /// each.
    fn march_patches(
        &self,
        input: &MarchInput,
        smoothness: &DepthSmoothness,
        patches: &mut Vec<MarchedBlock>,
    ) {
        let marcher = self.marcher(input.data.near, input.data.far);
        patches.resize_with(smoothness.patches, MarchedBlock::default);
        patches.par_iter_mut().enumerate().for_each(|(k, block)| {
            let draw = PatchDraw {
                seed: input.sampling.seed,
                step: input.sampling.step,
                k: k as u64,
            };
            unseen_patches::draw_patch(input.data, draw, smoothness.stride, &mut block.rays);
            self.pack_block(&marcher, block);
        });
    }

    /// Phase 1 of a step: marches blocks until the budget is reached. Returns the number of
    /// blocks used and the rays kept of the last one.
    fn march_step(&self, input: &MarchInput, shared: &mut StepBlocks) -> (usize, usize) {
        let (used, last) = self.march_waves(input, &mut shared.blocks, shared.last_used.max(4));
        shared.last_used = used;
        (used, last)
    }

    /// Marches waves of blocks, `first` blocks then 4, 8, ... 64 more, until the budget is
    /// reached.
    fn march_waves(
        &self,
        input: &MarchInput,
        blocks: &mut Vec<MarchedBlock>,
        first: usize,
    ) -> (usize, usize) {
        let marcher = self.marcher(input.data.near, input.data.far);
        let budget = self.config.samples_per_step;
        // Rays that find no occupied cell add no samples: this bound ends the step when the
        // grid is (nearly) empty instead of drawing rays forever.
        let max_rays = budget.max(64);
        let (mut marched, mut wave, mut next) = (0, first, 4);
        let (mut samples, mut rays) = (0, 0);
        loop {
            if blocks.len() < marched + wave {
                blocks.resize_with(marched + wave, MarchedBlock::default);
            }
            blocks[marched..marched + wave]
                .par_iter_mut()
                .enumerate()
                .for_each(|(i, block)| self.march_block(input, &marcher, marched + i, block));
            for (b, block) in blocks[marched..marched + wave].iter().enumerate() {
                for r in 0..block.samples.rays() {
                    samples += block.samples.ray(r).len();
                    rays += 1;
                    if samples >= budget || rays >= max_rays {
                        return (marched + b + 1, r + 1);
                    }
                }
            }
            marched += wave;
            wave = next;
            next = (next * 2).min(64);
        }
    }

    /// Phase 2, one chunk: the step's rays `rays` (indices over all blocks) copied into
    /// `ws`, then forward, loss and backward. Writes each ray's squared error into `sse`.
    fn train_chunk(
        &self,
        input: &ChunkInput,
        rays: std::ops::Range<usize>,
        ws: &mut FastWorkspace,
        grads: &mut GradBuffer,
        sse: &mut [f64],
    ) {
        let ChunkInput {
            params,
            blocks,
            check,
            cameras,
            patch_from,
            patch_scale,
        } = *input;
        let first_ray = rays.start;
        ws.samples.clear();
        ws.backgrounds.clear();
        ws.targets.clear();
        for g in rays {
            let block = &blocks[g / BLOCK_RAYS];
            let (s, r) = (&block.samples, g % BLOCK_RAYS);
            let range = s.ray(r);
            ws.samples.t.extend_from_slice(&s.t[range.clone()]);
            ws.samples.dt.extend_from_slice(&s.dt[range.clone()]);
            ws.samples
                .positions
                .extend_from_slice(&s.positions[range.clone()]);
            ws.samples.dirs.extend_from_slice(&s.dirs[range.clone()]);
            ws.samples
                .appearance
                .extend_from_slice(&s.appearance[range.clone()]);
            if !s.footprints.is_empty() {
                ws.samples
                    .footprints
                    .extend_from_slice(&s.footprints[range.clone()]);
            }
            if !s.times.is_empty() {
                ws.samples.times.extend_from_slice(&s.times[range]);
            }
            ws.samples.end_ray();
            ws.backgrounds.push(block.rays.rays.backgrounds[r]);
            ws.targets.push(block.rays.targets[r]);
        }
        let (r, n) = (ws.samples.rays(), ws.samples.len());
        ws.weights.resize(n, 0.0);
        ws.outputs.resize(r, RayOutput::default());
        let field = if n > 0 {
            self.field
                .forward(params, ws.samples.field_input(), &mut ws.field)
        } else {
            FieldOutput {
                sigma: &[],
                rgb: &[],
            }
        };
        check.check("field.forward", "sigma", field.sigma);
        check.check("field.forward", "rgb", field.rgb);
        let clock = step_clock::start(Stage::Compositing);
        composite_packed(
            &ws.samples,
            field,
            &ws.backgrounds,
            &mut ws.weights,
            &mut ws.outputs,
        );
        check_outputs(check, &ws.weights, &ws.outputs);
        // A patch ray has no photo: compared with what it renders, it adds no colour loss.
        let first_patch = patch_from.saturating_sub(first_ray).min(r);
        for (target, out) in ws.targets[first_patch..]
            .iter_mut()
            .zip(&ws.outputs[first_patch..])
        {
            *target = out.rgb;
        }
        ws.loss.run(
            &ws.samples,
            field,
            &ws.backgrounds,
            &ws.outputs,
            &ws.targets,
        );
        if self.config.distortion > 0.0 {
            ws.loss.add_distortion(
                &ws.samples,
                &ws.weights,
                self.config.step_length(),
                self.config.box_diagonal(),
                self.config.distortion,
            );
        }
        if first_patch < r {
            self.add_depth_smoothness(first_patch, patch_scale, ws);
        }
        clock.stop();
        check.check("loss.backward", "d_sigma", ws.loss.field_grad().d_sigma);
        check.check("loss.backward", "d_rgb", ws.loss.field_grad().d_rgb);
        if n > 0 && !cameras.is_empty() {
            self.field.backward_with_positions(
                params,
                &mut ws.field,
                ws.loss.field_grad(),
                &mut grads.all(),
                ws.samples.dirs.as_flattened(),
                &mut ws.d_positions,
                &mut ws.d_dirs,
            );
            self.camera_gradients(
                blocks,
                first_ray..first_ray + first_patch,
                cameras,
                ws,
                grads,
            );
        } else if n > 0 {
            self.field.backward(
                params,
                &mut ws.field,
                ws.loss.field_grad(),
                &mut grads.all(),
            );
        }
        if n > 0 && self.config.time_smoothness > 0.0 {
            // The step's gradient is scaled by 1 / (3 rays) (see `render::loss`): 3 times
            // the weight makes the prior the weight times its mean over the step's rays.
            self.field.time_smoothness_bwd(
                params,
                &mut ws.field,
                n,
                3.0 * self.config.time_smoothness,
                &mut grads.all(),
            );
        }
        // Per ray, so the step's total is summed in ray order whatever the chunking.
        for ((e, out), target) in sse.iter_mut().zip(&ws.outputs).zip(&ws.targets) {
            *e = squared_error(
                std::slice::from_ref(out),
                std::slice::from_ref(target),
                &mut [[0.0; 3]],
            );
        }
    }
}

impl FastModel {
    /// RegNeRF's depth smoothness of the chunk's patches (its rays from `first` on, in
    /// whole patches), its gradient times `scale` into the loss's density gradient.
    fn add_depth_smoothness(&self, first: usize, scale: f32, ws: &mut FastWorkspace) {
        let FastWorkspace {
            samples,
            weights,
            loss,
            patch,
            ..
        } = ws;
        let unit = self.config.box_diagonal();
        loss.add_penalty(|d_sigma| {
            patch.add_patches(samples, first, (&samples.dt, weights), unit, scale, d_sigma);
        });
    }

    /// Carries the position gradients of the chunk's photo rays `photo_rays` (step
    /// indices; in `ws.d_positions`, packed in `ws.samples` from the chunk's first ray)
    /// back through contraction to each ray's origin and direction, and from there
    /// (through the NDC warp for forward-facing scenes) into its camera's correction in
    /// `grads`.
    fn camera_gradients(
        &self,
        blocks: &[MarchedBlock],
        photo_rays: std::ops::Range<usize>,
        cameras: &[CameraStep],
        ws: &FastWorkspace,
        grads: &mut GradBuffer,
    ) {
        let Some(at) = self.cameras_at else { return };
        let contract = self
            .config
            .contract
            .then_some(0.5 * self.config.field.bound);
        let per = camera_refine::PER_CAMERA;
        let mut touched = (usize::MAX, 0);
        let values = &mut grads.values;
        let first_ray = photo_rays.start;
        for i in 0..photo_rays.len() {
            let g = first_ray + i;
            let block = &blocks[g / BLOCK_RAYS];
            let r = g % BLOCK_RAYS;
            let rays = &block.rays.rays;
            let view = (rays.pixels[r] >> 32) as usize;
            let (o, dir) = (rays.origins[r], rays.dirs[r]);
            let d = crate::math::scale(dir, 1.0 / crate::math::length(dir));
            let (mut d_o, mut d_d, mut d_view) = ([0.0f32; 3], [0.0f32; 3], [0.0f32; 3]);
            for s in ws.samples.ray(i) {
                let t = ws.samples.t[s];
                let q = &ws.d_positions[s * 3..][..3];
                let mut d_p = [q[0], q[1], q[2]];
                if let Some(radius) = contract {
                    let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
                    d_p = crate::render::contraction::contract_bwd(p, radius, d_p);
                }
                let g_view = &ws.d_dirs[s * 3..][..3];
                for a in 0..3 {
                    d_o[a] += d_p[a];
                    // The ray's unit direction places the sample.
                    d_d[a] += t * d_p[a];
                    d_view[a] += g_view[a];
                }
            }
            let slot = &mut values[at + view * per..][..per];
            cameras[view].accumulate_drawn(dir, rays.view_dirs[r], d_o, d_d, d_view, slot);
            touched = (touched.0.min(view), touched.1.max(view + 1));
        }
        if touched.0 < touched.1 {
            grads.all().mark(at + touched.0 * per..at + touched.1 * per);
        }
    }
}

impl Model for FastModel {
    type Workspace = FastWorkspace;
    type StepBuffers = StepBlocks;

    fn layout(&self) -> &ParamLayout {
        &self.layout
    }

    /// The field's initial weights; camera corrections start at zero (the given poses).
    fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut p = self.field.init_params(seed);
        p.resize(self.layout.total, 0.0);
        p
    }

    fn buffer_layout(&self) -> ParamLayout {
        let mut l = ParamLayout::default();
        let r = self.grid.resolution;
        l.push(OCCUPANCY, &[r, r, r]);
        if self.keeps_hidden_space() {
            l.push(HIDDEN, &[r, r, r]);
        }
        l
    }

    fn buffers(&self) -> Vec<f32> {
        self.buffers_with(self.grid.thickness.clone())
    }

    fn load_buffers(&mut self, mut values: Vec<f32>) {
        let (r, b) = (self.grid.resolution, self.grid.bound);
        let hidden = values.split_off(values.len().min(r.pow(3)));
        if self.keeps_hidden_space() {
            self.visibility.hidden = hidden.iter().map(|&h| h != 0.0).collect();
        }
        self.grid = OccupancyGrid::from_thickness(r, b, values, self.config.occupancy.threshold);
    }

    /// Instant-NGP's step: a fixed number of field samples (see the module docs).
    fn train_pass(
        &self,
        input: &StepInput,
        shared: &mut StepBlocks,
        workers: &mut [Worker<FastWorkspace>],
    ) -> PassTotals {
        let cameras = self.camera_steps(input.params, input.data);
        let march = MarchInput {
            data: input.data,
            sampling: input.sampling,
            cameras: &cameras,
        };
        let clock = step_clock::start(Stage::Marching);
        // Patches from unseen poses come on top of the photo rays' budget: taking their
        // samples out of it measured worse at equal time (docs/benchmarks.md).
        if let Some(smoothness) = &self.config.depth_smoothness {
            self.march_patches(&march, smoothness, &mut shared.patches);
        }
        let (used, last_rays) = self.march_step(&march, shared);
        // With patches, the photo rays end with their last whole block and each patch is
        // a block of its own after them.
        let (photo_rays, patches) = match &self.config.depth_smoothness {
            Some(smoothness) => {
                let end = used + smoothness.patches;
                if shared.blocks.len() < end {
                    shared.blocks.resize_with(end, MarchedBlock::default);
                }
                for (block, patch) in shared.blocks[used..end].iter_mut().zip(&mut shared.patches) {
                    std::mem::swap(block, patch);
                }
                (used * BLOCK_RAYS, smoothness.patches)
            }
            None => ((used - 1) * BLOCK_RAYS + last_rays, 0),
        };
        clock.stop();
        let blocks = &shared.blocks[..used + patches];
        let n_rays = photo_rays + patches * PATCH_RAYS;
        // Where a worker's share or a chunk may end: never inside a patch.
        let can_end_after =
            |g: usize| g < photo_rays || (g + 1 - photo_rays).is_multiple_of(PATCH_RAYS);
        // The step's gradient is scaled by 1 / (3 photo rays) (see `render::loss`): this
        // makes the loss the weight times its mean over the step's patches.
        let patch_scale = self.config.depth_smoothness.map_or(0.0, |d| {
            d.weight * (3 * photo_rays) as f32 / d.patches.max(1) as f32
        });
        let samples_of = |g: usize| blocks[g / BLOCK_RAYS].samples.ray(g % BLOCK_RAYS).len();
        // Each worker takes a contiguous share of the rays holding about as many samples as
        // the others' (the threads finish together), in chunks of `batch_samples`.
        let n_workers = workers.len();
        let total: usize = (0..n_rays).map(samples_of).sum();
        let mut shares = Vec::with_capacity(n_workers + 1);
        shares.push(0);
        let mut held = 0;
        for g in 0..n_rays {
            held += samples_of(g);
            while shares.len() < n_workers
                && held * n_workers >= total * shares.len()
                && can_end_after(g)
            {
                shares.push(g + 1);
            }
        }
        shares.resize(n_workers + 1, n_rays);
        let mut sse = vec![0.0f64; n_rays];
        let mut parts = Vec::with_capacity(n_workers);
        let mut rest = sse.as_mut_slice();
        for w in 0..n_workers {
            let (part, tail) = rest.split_at_mut(shares[w + 1] - shares[w]);
            parts.push(part);
            rest = tail;
        }
        let batch = self.config.batch_samples;
        workers
            .par_iter_mut()
            .zip(parts)
            .enumerate()
            .for_each(|(w, (worker, sse))| {
                let first = shares[w];
                let (mut start, mut held) = (first, 0);
                let share: usize = (first..shares[w + 1]).map(samples_of).sum();
                worker.ws.field.defer_grid = Some(share);
                worker.ws.field.products = self.products;
                let mut positions = Vec::with_capacity(share * 3);
                for g in first..shares[w + 1] {
                    let s = &blocks[g / BLOCK_RAYS].samples;
                    positions.extend_from_slice(s.positions[s.ray(g % BLOCK_RAYS)].as_flattened());
                }
                self.field
                    .pre_encode(input.params, &positions, &mut worker.ws.field);
                for g in first..shares[w + 1] {
                    held += samples_of(g);
                    if (held >= batch && can_end_after(g)) || g + 1 == shares[w + 1] {
                        let chunk = ChunkInput {
                            params: input.params,
                            blocks,
                            check: input.check,
                            cameras: &cameras,
                            patch_from: photo_rays,
                            patch_scale,
                        };
                        self.train_chunk(
                            &chunk,
                            start..g + 1,
                            &mut worker.ws,
                            &mut worker.grads,
                            &mut sse[start - first..g + 1 - first],
                        );
                        start = g + 1;
                        held = 0;
                    }
                }
                self.field
                    .scatter_deferred(&mut worker.ws.field, &mut worker.grads.all());
                worker.ws.field.defer_grid = None;
                self.field.end_pre_encoded(&mut worker.ws.field);
            });
        let sse: f64 = sse.iter().sum();
        PassTotals {
            sse,
            final_sse: sse,
            rays: photo_rays,
            samples: total,
        }
    }

    /// Hash-table entries update lazily, MLP weights densely with weight decay.
    fn update_rule(&self) -> UpdateRule {
        UpdateRule {
            lazy_end: self.field.mlp_range().start,
            table_decay: self.config.table_decay,
            weight_decay: self.config.weight_decay,
            group_start: self.cameras_at,
        }
    }

    /// Camera refinement's coarse-to-fine weighting of the hash-grid levels.
    fn set_progress(&mut self, progress: f32) {
        if let Some(r) = &self.config.refine_cameras {
            let weights = r.level_weights(self.field.grid.levels.len(), progress);
            if r.pose_gradient_only {
                self.field.position_level_weights = weights;
            } else {
                self.field.level_weights = weights;
            }
        }
    }

    /// Few-view training of a bounded scene in world space: the space too few training
    /// cameras frame stays empty (`model::few_view`), marked once, and so does the space
    /// the last pass found hidden (`model::hidden_space`).
    fn prepare(&mut self, data: &Dataset) {
        let Some(few) = self.config.few_view else {
            return;
        };
        if !super::few_view::applies(data.space, self.config.contract)
            || self.grid.possible.is_some()
        {
            return;
        }
        // The photos themselves: a multi-scale split repeats them, smaller, after them.
        let photos = data.views.len().min(few.photos.max(1));
        let cameras: Vec<crate::camera::Camera> = data.views[..photos]
            .iter()
            .map(|v| v.camera.clone())
            .collect();
        let (res, bound) = (self.grid.resolution, self.grid.bound);
        self.visibility.framed = super::few_view::seen_by(&cameras, res, bound, few.min_views());
        self.visibility.cameras = cameras;
        self.grid.possible = Some(self.visibility.possible());
        self.grid.refresh(self.config.occupancy.threshold);
    }

    /// Re-evaluates the occupancy grid every `update_every` steps with the current weights,
    /// and runs few-view training's hidden-space pass when it is due.
    fn after_step(&mut self, params: &[f32], steps_done: u64, seed: u64) {
        let dt = self.config.step_length();
        let every = self.config.occupancy.update_every.max(1);
        if steps_done.is_multiple_of(every) {
            // Training's precision: a refresh only compares densities with a threshold.
            let products = self.products;
            let FastModel {
                config,
                field,
                grid,
                ..
            } = self;
            let density =
                |points: &[f32], out: &mut [f32]| field.density_into(params, points, products, out);
            grid.update(&config.occupancy, steps_done, seed, dt, &density);
        }
        if self.hidden_pass_due(steps_done) {
            let possible = self.visibility.find_hidden(&self.grid, dt);
            self.grid.possible = Some(possible);
            self.grid.refresh(self.config.occupancy.threshold);
        }
    }

    fn render_chunk(
        &self,
        params: &[f32],
        rays: &RayBatch,
        ws: &mut FastWorkspace,
        out: &mut [RayOutput],
    ) {
        let marcher = self.marcher(rays.near, rays.far);
        render_marched(
            &self.field,
            params,
            &marcher,
            &self.grid,
            self.config.batch_samples,
            MIN_WEIGHT,
            rays,
            &mut ws.march,
            out,
        );
    }

    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        time: Option<f32>,
        ws: &mut FastWorkspace,
        out: &mut [f32],
    ) {
        self.field
            .density_at(params, positions, time, &mut ws.field, out);
    }

    fn occupancy(&self) -> Option<f64> {
        Some(self.grid.occupancy())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::HashGridConfig;
    use crate::rng::Rng;

    fn dense_model() -> (FastModel, Vec<f32>) {
        let config = FastModelConfig {
            field: FastFieldConfig {
                grid: HashGridConfig {
                    levels: 4,
                    log2_table_size: 10,
                    base_resolution: 4,
                    max_resolution: 32,
                },
                ..FastFieldConfig::default()
            },
            ..FastModelConfig::default()
        };
        let model = FastModel::new(config);
        let mut params = model.field.init_params(5);
        // Positive, varying table values and a positive log-density weight: an opaque,
        // textured fog filling the box.
        let mut rng = Rng::new(8);
        for v in &mut params[model.field.grid.param_range()] {
            *v = rng.range(0.5, 1.5);
        }
        for t in &model.field.layout.tensors {
            if t.name == "density.0.weight" {
                params[t.range()].iter_mut().for_each(|w| *w = w.abs());
            }
            if t.name == "density.1.weight" {
                for row in params[t.range()].chunks_exact_mut(t.shape[1]) {
                    row[0] = 0.5;
                }
            }
        }
        (model, params)
    }

    fn ray_batch(
        origins: &[[f32; 3]],
        dirs: &[[f32; 3]],
        bgs: &[[f32; 3]],
        (near, far): (f32, f32),
    ) -> RayBatch {
        let mut rays = RayBatch::new(near, far);
        for k in 0..origins.len() {
            let ray = crate::camera::Ray {
                origin: origins[k],
                dir: dirs[k],
            };
            rays.push(ray, dirs[k], bgs[k], k as u64);
        }
        rays
    }

    /// Renders the rays, then packs them for training on the renderer's lattice (jitter
    /// 0.5) with the rendered colours as targets and runs the training chunk.
    struct RenderThenTrain {
        out: Vec<RayOutput>,
        /// Samples the renderer evaluated per ray.
        taken: Vec<usize>,
        marcher: Marcher,
        block: MarchedBlock,
        /// Training loss against the rendered colours.
        sse: f64,
    }

    /// What [`FastModel::render_chunk`] renders, with every sample coloured (training
    /// colours every sample).
    fn render_every_colour(
        model: &FastModel,
        params: &[f32],
        rays: &RayBatch,
        ws: &mut FastWorkspace,
    ) -> Vec<RayOutput> {
        let mut out = vec![RayOutput::default(); rays.len()];
        render_marched(
            &model.field,
            params,
            &model.marcher(rays.near, rays.far),
            &model.grid,
            model.config.batch_samples,
            0.0,
            rays,
            &mut ws.march,
            &mut out,
        );
        out
    }

    fn render_then_train(model: &FastModel, params: &[f32], rays: RayBatch) -> RenderThenTrain {
        let n = rays.len();
        let mut ws = FastWorkspace::default();
        let out = render_every_colour(model, params, &rays, &mut ws);
        let taken = ws.march.taken.clone();
        let marcher = model.marcher(rays.near, rays.far);
        let mut block = MarchedBlock::default();
        block.samples.clear();
        for r in 0..n {
            marcher.pack_ray(&model.grid, &rays, r, 0.5, &mut block.samples);
        }
        block.rays.targets = out.iter().map(|o| o.rgb).collect();
        block.rays.rays = rays;
        let mut grads = GradBuffer::new(model.field.num_params());
        let mut per_ray = vec![0.0; n];
        let input = ChunkInput {
            params,
            blocks: std::slice::from_ref(&block),
            check: &FiniteCheck::default(),
            cameras: &[],
            patch_from: n,
            patch_scale: 0.0,
        };
        model.train_chunk(&input, 0..n, &mut ws, &mut grads, &mut per_ray);
        let sse: f64 = per_ray.iter().sum();
        RenderThenTrain {
            out,
            taken,
            marcher,
            block,
            sse,
        }
    }

    /// BARF's coarse-to-fine schedule weighs the field's levels; the straight-through
    /// one weighs only the cameras' gradient, and the field renders every level.
    #[test]
    fn the_schedule_weighs_the_field_or_only_the_pose_gradient() {
        for straight_through in [false, true] {
            let mut refinement = CameraRefinement::new(2);
            refinement.pose_gradient_only = straight_through;
            let mut model = FastModel::new(FastModelConfig {
                refine_cameras: Some(refinement),
                ..FastModelConfig::default()
            });
            model.set_progress(0.1);
            let field = &model.field;
            let (weighted, untouched) = match straight_through {
                true => (&field.position_level_weights, &field.level_weights),
                false => (&field.level_weights, &field.position_level_weights),
            };
            assert!(untouched.is_empty(), "{untouched:?}");
            assert_eq!(weighted.len(), field.grid.levels.len());
            assert_eq!(weighted[0], 1.0);
            assert_eq!(weighted.last(), Some(&0.0));
        }
    }

    /// Rendering (in rounds, stopping opaque rays) and training (all samples, composited at
    /// once) see the same colour for the same lattice, and rendering stops early.
    #[test]
    fn rendering_agrees_with_training_and_terminates_early() {
        let (model, params) = dense_model();
        let origins: Vec<[f32; 3]> = (0..6).map(|_| [0.0, -4.0, 0.3]).collect();
        let dirs: Vec<[f32; 3]> = (0..6)
            .map(|k| [0.05 * k as f32 - 0.1, 1.0, 0.02 * k as f32])
            .collect();
        let bgs: Vec<[f32; 3]> = (0..6).map(|k| [0.1 * k as f32, 0.5, 1.0]).collect();
        let r = render_then_train(
            &model,
            &params,
            ray_batch(&origins, &dirs, &bgs, (2.0, 6.0)),
        );
        assert!(r.out.iter().all(|o| o.opacity > 0.999), "{:?}", r.out);
        // The box is about 590 steps deep; an opaque fog ends each ray within a few rounds.
        assert!(r.taken.iter().all(|&n| n > 0 && n <= 128), "{:?}", r.taken);
        assert!(
            r.block.samples.len() > 6 * 500,
            "training marches whole rays"
        );
        assert!(r.sse < 1e-9, "render and training disagree: sse {}", r.sse);
    }

    /// A model whose rays run through a thin fog into contracted space (light reaches the
    /// far shell), and those rays.
    fn thin_fog() -> (FastModel, Vec<f32>, RayBatch) {
        let (mut model, mut params) = dense_model();
        model.config.contract = true;
        // A thin fog (sigma about 1): light reaches the contracted shell.
        for t in &model.field.layout.tensors {
            if t.name == "density.1.weight" {
                for row in params[t.range()].chunks_exact_mut(t.shape[1]) {
                    row[0] = 0.0;
                }
            }
        }
        let origins: Vec<[f32; 3]> = (0..4).map(|_| [0.0, -1.0, 0.2]).collect();
        let dirs: Vec<[f32; 3]> = (0..4).map(|k| [0.1 * k as f32 - 0.15, 1.0, 0.05]).collect();
        let bgs: Vec<[f32; 3]> = (0..4).map(|_| [0.2, 0.4, 0.6]).collect();
        let rays = ray_batch(&origins, &dirs, &bgs, (0.05, 1e4));
        (model, params, rays)
    }

    /// With contraction, rays run on past the box with growing steps, and rendering and
    /// training still see the same colour.
    #[test]
    fn contracted_rays_march_beyond_the_box_and_agree() {
        let (model, params, rays) = thin_fog();
        let r = render_then_train(&model, &params, rays);
        let inner = r.marcher.contract.expect("contracted");
        // Samples reach far past the inner cube, with steps that grow with distance.
        let far_t = r.block.samples.t.iter().copied().fold(0.0f32, f32::max);
        let max_dt = r.block.samples.dt.iter().copied().fold(0.0f32, f32::max);
        assert!(
            far_t > 20.0 * inner,
            "last sample at {far_t}, inner cube {inner}"
        );
        assert!(
            max_dt > 100.0 * r.marcher.dt,
            "{max_dt} vs {}",
            r.marcher.dt
        );
        assert!(r.block.samples.len() < 4 * r.marcher.max_samples);
        assert!(r.sse < 1e-9, "render and training disagree: sse {}", r.sse);
        assert!(r.out.iter().all(|o| o.opacity > 0.5), "{:?}", r.out);
    }

    /// Rendering leaves out the colour of samples that weigh less than `MIN_WEIGHT` in
    /// their pixel, and nothing else: in a thin fog, whose far samples weigh little each,
    /// opacity and depth are those of colouring every sample, and colour moves by less
    /// than the left-out weights could carry.
    #[test]
    fn rendering_leaves_out_only_the_colour_that_cannot_show() {
        let (model, params, rays) = thin_fog();
        let mut ws = FastWorkspace::default();
        let every = render_every_colour(&model, &params, &rays, &mut ws);
        let mut out = vec![RayOutput::default(); rays.len()];
        model.render_chunk(&params, &rays, &mut ws, &mut out);
        let mut moved = 0.0f32;
        for (a, b) in out.iter().zip(&every) {
            assert_eq!((a.opacity, a.depth), (b.opacity, b.depth));
            for c in 0..3 {
                moved = moved.max((a.rgb[c] - b.rgb[c]).abs());
            }
        }
        assert!(moved > 0.0, "no colour left out: the test shows nothing");
        assert!(moved < 1e-3, "colour moved by {moved}");
    }
}

#[cfg(test)]
mod step_tests {
    use super::*;
    use crate::data::pixels::PixelSampling;
    use crate::data::synth::{self, SynthOptions};
    use crate::data::{Background, Split};

    /// The waves only decide how far past the cut rays are marched: any first wave keeps
    /// the same rays with the same samples.
    #[test]
    fn the_kept_rays_do_not_depend_on_the_waves() {
        let opts = SynthOptions {
            size: 16,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Train, 4);
        let config = FastModelConfig {
            samples_per_step: 5000,
            ..FastModelConfig::default()
        };
        let model = FastModel::new(config);
        let input = MarchInput {
            data: &data,
            sampling: PixelSampling {
                seed: 7,
                step: 2,
                crop: 1.0,
                background: Background::Random,
                appearance: crate::stage::Appearance::PerView,
            },
            cameras: &[],
        };
        let kept = |first: usize| {
            let mut blocks = Vec::new();
            let (used, last) = model.march_waves(&input, &mut blocks, first);
            let t: Vec<f32> = (0..used)
                .flat_map(|b| {
                    let rays = if b + 1 == used { last } else { BLOCK_RAYS };
                    let s = &blocks[b].samples;
                    s.t[..s.offsets[rays]].to_vec()
                })
                .collect();
            (used, last, t)
        };
        let reference = kept(1);
        assert!(reference.2.len() >= 5000, "{} samples", reference.2.len());
        for first in [4, 13, 64] {
            assert_eq!(kept(first), reference, "first wave of {first} blocks");
        }
    }

    /// `dL/d camera correction` through a whole training step (rays, field,
    /// compositing, loss) against central differences of the step's loss: through the
    /// sample positions and the view directions. The box is large enough that every
    /// sample stays in the uncontracted cube, so their depths are fixed.
    #[test]
    fn camera_gradient_matches_finite_differences() {
        use crate::model::{StepInput, Worker};
        use crate::nn::GradBuffer;
        let opts = SynthOptions {
            size: 10,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Train, 2);
        let config = FastModelConfig {
            field: FastFieldConfig {
                grid: crate::encoding::HashGridConfig {
                    levels: 4,
                    log2_table_size: 12,
                    base_resolution: 4,
                    max_resolution: 24,
                },
                bound: 16.0,
                ..FastFieldConfig::default()
            },
            samples_per_step: 3000,
            steps_per_diagonal: 600.0,
            contract: true,
            refine_cameras: Some(CameraRefinement::new(2)),
            ..FastModelConfig::default()
        };
        let model = FastModel::new(config);
        let mut rng = crate::rng::Rng::new(2);
        let mut params = model.init_params(3);
        for v in &mut params[model.field.grid.param_range()] {
            *v = rng.range(-1.0, 1.0);
        }
        let at = model.cameras_at.expect("cameras");
        for v in &mut params[at..] {
            *v = rng.range(-0.05, 0.05);
        }
        let check = FiniteCheck::new(false);
        let step = |p: &[f32]| {
            let input = StepInput {
                data: &data,
                params: p,
                sampling: PixelSampling {
                    seed: 1,
                    step: 0,
                    crop: 1.0,
                    background: Background::White,
                    appearance: crate::stage::Appearance::PerView,
                },
                batch_rays: 0,
                chunk_rays: 64,
                check: &check,
            };
            let mut workers = vec![Worker {
                ws: FastWorkspace::default(),
                grads: GradBuffer::new(p.len()),
            }];
            let totals = model.train_pass(&input, &mut StepBlocks::default(), &mut workers);
            let grads = workers.pop().expect("worker").grads.values;
            (totals.sse, totals.rays, grads)
        };
        let (_, rays, grads) = step(&params);
        assert!(rays > 20, "{rays} rays");
        for k in 0..12 {
            let h = 1e-3;
            let (mut lo, mut hi) = (params.clone(), params.clone());
            lo[at + k] -= h;
            hi[at + k] += h;
            let (a, ra, _) = step(&hi);
            let (b, rb, _) = step(&lo);
            assert_eq!((ra, rb), (rays, rays), "the step kept other rays");
            let fd = (a - b) / (2.0 * h as f64);
            let g = grads[at + k] as f64;
            assert!(
                (fd - g).abs() < 0.05 * fd.abs().max(g.abs()) + 1e-3,
                "camera {} parameter {}: finite difference {fd}, gradient {g}",
                k / 6,
                k % 6
            );
        }
    }
}
