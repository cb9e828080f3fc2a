//! The GPU engine for the fast model: parameters, gradients and Adam's moments live on the
//! device, and a training step runs the field, compositing, the loss, the backward and the
//! optimiser there, reading back one float per ray (the loss) and one count (non-finite
//! gradients).
//!
//! Work mapping of a step: the host draws which pixels the step's rays see exactly as the
//! CPU engine does (`data::pixels`: same pixels, backgrounds and lattice jitters), and the
//! device makes the rays from those indices (`rays`: the training images and cameras are
//! on the device), marches them through the occupancy grid (`march`: the same samples as
//! the CPU marcher while the grids agree), cuts them at the sample budget (two numbers read
//! back), and runs the field, compositing, the loss, the backward and Adam. Every
//! `update_every` steps it refreshes the occupancy grid (`occupancy`), which stays on the
//! device (read back for a checkpoint or when its occupied share is asked for). Rendering
//! (`render`) marches, evaluates and composites on the device in rounds, with early
//! termination.

use cubecl::server::Handle;
use rayon::prelude::*;

use super::camera_poses::DevicePoses;
use super::codes::SampleCodes;
use super::depth_smoothness::LastStep;
use super::device::Gpu;
use super::device_field::{DeviceField, DeviceInput, DeviceMoments};
use super::field::{Activations, GpuFastField, InputGradients};
use super::march::{Cut, GpuMarcher, GpuRays};
use super::occupancy::GpuOccupancy;
use super::params::{
    check_device, density_in_chunks, fail_rays, report_device_failure, DeviceParams,
};
use super::rays::GpuViews;
use super::space_time_grid::per_sample;
use super::trace::{self, Phase, StepTrace};
use super::{antialias, depth_smoothness, distortion, loss, pose_grad, rays, render, volume};
use crate::data::pixels::{PixelChoice, TrainingRays};
use crate::data::Dataset;
use crate::engine::{
    render_in_chunks, Engine, EngineOptions, EngineState, PixelRays, StepSpec, StepStats,
};
use crate::error::Result;
use crate::model::camera_refine::{correct_drawn_rays, CameraStep, PER_CAMERA};
use crate::model::fast::BLOCK_RAYS;
use crate::model::unseen_patches::{self, DepthSmoothness};
use crate::model::{FastModel, FastModelConfig, Model, ModelConfig};
use crate::nn::ParamLayout;
use crate::render::loss::mean_scale;
use crate::render::march::Marcher;
use crate::render::occupancy::OccupancyGrid;
use crate::stage::finite::FiniteCheck;
use crate::stage::{Appearance, RayBatch, RayOutput, MEAN_APPEARANCE};
use crate::step_clock::{self, Stage};

/// The most samples one device call takes, in a training step or a rendering round: at
/// 2^20 a 64-wide activation (256 MiB) overflows the largest storage binding of common
/// adapters and fails wgpu's validation. `gpu::open` refuses larger steps.
pub const MAX_DEVICE_SAMPLES: usize = 1 << 19;

/// Samples per rendering round when the field runs fused: it keeps no activations, so a
/// round holds only the samples' positions, directions, depths and results (44 bytes each).
pub const MAX_FUSED_ROUND: usize = 1 << 22;

/// How the GPU renderer cuts its work.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct RenderSizes {
    /// Rays per rendering call (a pinhole view's slab).
    chunk: usize,
    /// Samples per round.
    round: usize,
    /// Parts of a call whose rounds interleave (`render::render_batches`).
    lanes: usize,
    /// Views rendered at once (`Engine::views_in_flight`).
    views: usize,
}

/// How the renderer cuts its work on `gpu`. A software adapter takes small calls (2^14
/// rays, 2^16 samples: 70 MB of activations per chunk in flight), where a round trip
/// costs little beside the field. On a hardware GPU a camera's rays are cast on the
/// device and every round waits for the host once, so a frame renders fastest in large
/// calls with full rounds, split into lanes whose rounds interleave so that the device
/// works on one lane's round while the host waits for another's (docs/benchmarks.md has
/// the sizes measured): 2^20 rays a call in 2 lanes, rounds of 2^19 samples layer by
/// layer (whose activations cap a round at [`MAX_DEVICE_SAMPLES`]), 2^22 fused; and three
/// views at once, so that one view's rounds run while the host waits on or lays out the
/// others'. `NERF_GPU_RENDER=CHUNK_LOG2,ROUND_LOG2[,LANES[,VIEWS]]` overrides them, for
/// tuning, up to 2^20 rays, the round cap, 8 lanes and 4 views.
fn render_sizes(gpu: &Gpu, fused: bool) -> RenderSizes {
    let max_round = if fused {
        MAX_FUSED_ROUND
    } else {
        MAX_DEVICE_SAMPLES
    };
    let from_env = std::env::var("NERF_GPU_RENDER")
        .ok()
        .and_then(|v| parse_render_sizes(&v, max_round));
    let (chunk, round, lanes, views) = match from_env {
        Some(sizes) => return sizes,
        None if gpu.software => (1 << 14, 1 << 16, 1, 1),
        None if fused => (1 << 20, 1 << 22, 2, 3),
        None => (1 << 20, 1 << 19, 2, 3),
    };
    RenderSizes {
        chunk,
        round,
        lanes,
        views,
    }
}

/// `CHUNK_LOG2,ROUND_LOG2[,LANES[,VIEWS]]` (base-2 logarithms of rays per call and
/// samples per round, a lane count and a count of views in flight), each within its cap;
/// `None` if malformed.
fn parse_render_sizes(spec: &str, max_round: usize) -> Option<RenderSizes> {
    let mut parts = spec.split(',').map(str::trim);
    let log2 = |s: Option<&str>, max: u32| {
        s?.parse::<u32>()
            .ok()
            .filter(|&l| l <= max)
            .map(|l| 1usize << l)
    };
    let chunk = log2(parts.next(), 20)?;
    let round = log2(parts.next(), max_round.trailing_zeros())?;
    let mut count = |most: usize| match parts.next() {
        None => Some(1),
        Some(c) => c.parse::<usize>().ok().filter(|c| (1..=most).contains(c)),
    };
    let lanes = count(8)?;
    let views = count(4)?;
    parts.next().is_none().then_some(RenderSizes {
        chunk,
        round,
        lanes,
        views,
    })
}

/// Points per device call of density queries.
const DENSITY_CHUNK: usize = 1 << 16;

/// A step's rays on the device, cut at the sample budget: their packed samples with
/// positions and view directions, and the targets and backgrounds of the rays marched
/// (`cut.rays` of them count).
struct StepRays {
    cut: Cut,
    samples: volume::GpuSamples,
    positions: Handle,
    dirs: Handle,
    /// Each sample's appearance code: its photo's.
    codes: SampleCodes,
    /// Each sample's footprint, for an anti-aliased field.
    footprints: Option<Handle>,
    targets: Handle,
    backgrounds: Handle,
    /// The rays' world origins and unit directions, where cameras are refined.
    frame: Option<(Handle, Handle)>,
    /// The rays' unit world directions and views, where cameras are corrected on the
    /// device.
    pose_rays: Option<(Handle, Handle)>,
    /// Each sample's moment, for a moving field.
    times: Option<Handle>,
}

/// A step's rays on the device before marching (`GpuEngine::draw_rays`), with what the
/// field reads of each besides its samples.
struct DrawnRays {
    rays: GpuRays,
    /// The index of each one's view (its appearance code): for a field with codes, and
    /// wherever the rays are made on the device.
    of_view: Option<Handle>,
    /// Cone radii, for an anti-aliased field.
    radii: Option<Handle>,
    /// Each one's moment, for a moving field.
    times: Option<Handle>,
    targets: Handle,
    backgrounds: Handle,
}

/// Where a training step's cameras come from.
enum StepCameras {
    /// As given: the run does not refine them.
    Given,
    /// Each corrected by its step on the host, which draws the rays (the views are not on
    /// the device).
    Host(Vec<CameraStep>),
    /// Corrected on the device (`camera_poses`): the corrected cameras, as
    /// `GpuViews::cameras` lays them out.
    Device(Handle),
}

/// The fast model on one GPU.
pub struct GpuEngine {
    gpu: Gpu,
    config: ModelConfig,
    /// The host side: layout, occupancy grid and marching.
    model: FastModel,
    field: GpuFastField,
    /// Parameters, gradients and Adam's moments.
    state: DeviceParams,
    check_finite: bool,
    chunk_rays: usize,
    /// The occupancy grid on the device, and the marcher that reads it.
    occupancy: GpuOccupancy,
    marcher: GpuMarcher,
    /// The training views on the device, with the dataset they came from (`None` inside:
    /// too large for the device, so the host draws whole rays into `rays`).
    views: Option<((usize, usize), Option<GpuViews>)>,
    /// The training rays drawn on the host (buffers reused), and how many the last step
    /// kept.
    rays: TrainingRays,
    last_rays: usize,
    /// Where the host's time goes in training steps (`NERF_GPU_TRACE`).
    trace: StepTrace,
}

impl GpuEngine {
    /// Samples per rendering round: the renderer's size, or a training step's when larger
    /// (each within what a round holds: `open` refuses larger steps, `render_sizes` larger
    /// rounds).
    fn round_samples(&self) -> usize {
        let round = render_sizes(&self.gpu, self.field.is_fused()).round;
        self.model.config.batch_samples.max(round)
    }

    pub fn new(gpu: Gpu, config: FastModelConfig, options: EngineOptions, seed: u64) -> Self {
        let model = FastModel::new(config.clone());
        let field = GpuFastField::new(&gpu, &model.field);
        let (occupancy, marcher) = GpuEngine::upload_occupancy(&gpu, &model);
        GpuEngine {
            state: DeviceParams::new(&gpu, &model.init_params(seed), options.adam),
            check_finite: options.check_finite,
            chunk_rays: options.chunk_rays.max(1),
            config: ModelConfig::Fast(config),
            model,
            field,
            gpu,
            occupancy,
            marcher,
            views: None,
            rays: TrainingRays::default(),
            last_rays: 0,
            trace: StepTrace::default(),
        }
    }

    /// Densities of `positions` (`n x 3`, at most `DENSITY_CHUNK` points) at moment `time`
    /// (a moving field; `None`: any, as the CPU field) into `out`.
    fn density_chunk(&self, positions: &[f32], time: Option<f32>, out: &mut [f32]) -> Result<()> {
        let n = out.len();
        let sigma = self.field.density(
            &self.gpu,
            &self.state.values,
            &self.gpu.upload(positions),
            time.map_or(DeviceMoments::Any, DeviceMoments::At),
            n,
        );
        out.copy_from_slice(&self.gpu.read(&sigma, n)?);
        Ok(())
    }

    /// Draws the step's rays (the same rays as the CPU engine: `data::pixels`) and marches
    /// them on the device until the sample budget is reached.
    fn march_step(
        &mut self,
        data: &Dataset,
        spec: &StepSpec,
        cameras: &StepCameras,
    ) -> Result<StepRays> {
        let marcher = self.model.marcher(data.near, data.far);
        let budget = self.model.config.samples_per_step;
        // As the CPU engine: rays that find no occupied cell add no samples, and this
        // bound ends a step whose grid is (nearly) empty.
        let max_rays = budget.max(64);
        // With patches from unseen poses, the photo rays end with a whole block, as the
        // CPU engine's do (`FastModel::train_pass`).
        let block = match self.model.config.depth_smoothness {
            Some(_) => BLOCK_RAYS,
            None => 1,
        };
        let mut want = (self.last_rays + self.last_rays / 4 + 16).clamp(64, max_rays);
        loop {
            let DrawnRays {
                rays: on_device,
                of_view,
                radii,
                times,
                targets,
                backgrounds,
            } = self.draw_rays(data, spec, &marcher, want, cameras);
            let counted = self.marcher.count(&self.gpu, &on_device);
            self.trace.mark(Phase::Drawing);
            let cut =
                self.marcher
                    .cut_in_blocks(&self.gpu, &counted, want, (budget, max_rays), block)?;
            self.trace.mark(Phase::Cut);
            if cut.found || want >= max_rays {
                self.last_rays = cut.rays;
                let (samples, positions, dirs) =
                    self.marcher.write(&self.gpu, &on_device, &counted, cut);
                let codes = match of_view.as_ref().filter(|_| self.field.needs().codes) {
                    Some(of_view) => SampleCodes::of_rays(
                        &self.gpu,
                        of_view,
                        &samples.offsets,
                        cut.rays,
                        cut.samples,
                    ),
                    None => SampleCodes::all(&self.gpu, crate::stage::MEAN_APPEARANCE),
                };
                let footprints = radii.map(|radii| {
                    antialias::sample_footprints(
                        &self.gpu,
                        &on_device,
                        &radii,
                        data.space.cylinders(),
                        marcher.contract,
                        (&samples.offsets, &samples.t),
                        cut.rays,
                        cut.samples,
                    )
                });
                let refined = !matches!(cameras, StepCameras::Given);
                let frame = refined.then(|| (on_device.origins.clone(), on_device.dirs.clone()));
                let pose_rays = match (cameras, of_view) {
                    (StepCameras::Device(_), Some(of_view)) => {
                        Some((on_device.views.clone(), of_view))
                    }
                    _ => None,
                };
                let times = times.map(|per_ray| {
                    per_sample(&self.gpu, &per_ray, &samples.offsets, cut.rays, cut.samples)
                });
                return Ok(StepRays {
                    cut,
                    samples,
                    positions,
                    dirs,
                    codes,
                    footprints,
                    targets,
                    backgrounds,
                    frame,
                    pose_rays,
                    times,
                });
            }
            want = (want * 2).min(max_rays);
        }
    }

    /// Rays `0..want` of the step on the device, with what the field reads of each, their
    /// targets and backgrounds: made there from the pixels the host picks (`rays`), from
    /// the cameras corrected there where they are refined, or drawn whole on the host
    /// where the views are not on the device (each ray corrected by its camera's step in
    /// `cameras`, as the CPU engine corrects it).
    fn draw_rays(
        &mut self,
        data: &Dataset,
        spec: &StepSpec,
        marcher: &Marcher,
        want: usize,
        cameras: &StepCameras,
    ) -> DrawnRays {
        let footprints = self.model.config.field.antialias.is_some();
        let codes = self.field.needs().codes;
        let moving = self.field.needs().moments;
        let gpu = &self.gpu;
        let host_steps = match cameras {
            StepCameras::Host(steps) => Some(steps),
            _ => None,
        };
        if let (Some(views), None) = (self.device_views(), host_steps) {
            let mut choices: Vec<PixelChoice> = (0..want as u64)
                .into_par_iter()
                .map(|k| PixelChoice::draw(data, &spec.sampling, k))
                .collect();
            // Each ray's first draw after its pixel is its lattice jitter, as in
            // `FastModel::march_block`.
            let jitter: Vec<f32> = choices.iter_mut().map(|c| c.rng.uniform()).collect();
            let bound = self.model.grid.bound;
            // A moving scene's photos each have a moment (`Scene::is_dynamic`).
            let times = moving.then(|| {
                let times: Vec<f32> = choices
                    .iter()
                    .map(|c| data.views[c.view].time.unwrap_or(0.0))
                    .collect();
                gpu.upload(&times)
            });
            let corrected = match cameras {
                StepCameras::Device(cams) => Some(cams),
                _ => None,
            };
            let rays::GeneratedRays {
                rays,
                targets,
                backgrounds,
                of_ray,
                radii,
            } = views.generate(
                gpu,
                &data.space,
                marcher,
                bound,
                &choices,
                &jitter,
                corrected,
                footprints,
            );
            return DrawnRays {
                rays,
                of_view: Some(of_ray),
                radii,
                times,
                targets,
                backgrounds,
            };
        }
        let rays = &mut self.rays;
        rays.draw_parallel(data, &spec.sampling, 0..want as u64);
        if let Some(steps) = host_steps {
            correct_drawn_rays(&mut rays.rays, steps);
        }
        let jitter: Vec<f32> = rays.rngs.iter_mut().map(|r| r.uniform()).collect();
        let on_device = GpuRays::new(gpu, marcher, &self.model.grid, &rays.rays, &jitter);
        let targets = gpu.upload(rays.targets.as_flattened());
        let backgrounds = gpu.upload(rays.rays.backgrounds.as_flattened());
        let of_view = codes.then(|| {
            let of_view: Vec<u32> = rays.rays.pixels.iter().map(|&p| (p >> 32) as u32).collect();
            gpu.upload_u32(&of_view)
        });
        let radii = footprints.then(|| gpu.upload(&rays.rays.radii));
        // Rays carry moments where their views have them, as on the CPU; none is moment 0.
        let times = moving.then(|| match rays.rays.times.len() {
            0 => gpu.upload(&vec![0.0; rays.rays.len()]),
            _ => gpu.upload(&rays.rays.times),
        });
        DrawnRays {
            rays: on_device,
            of_view,
            radii,
            times,
            targets,
            backgrounds,
        }
    }

    /// The step's patches from poses between the training cameras (the CPU engine's:
    /// `model::unseen_patches`), marched and run through the field apart from the photo
    /// rays: they have no colour to match, only RegNeRF's depth smoothness, whose gradient
    /// (with the distortion loss's and the prior of smooth change's, which the CPU engine
    /// adds for every ray) joins the step's. `photo_rays`: the rays the step's loss is a
    /// mean over.
    fn train_patches(
        &self,
        data: &Dataset,
        spec: &StepSpec,
        smoothness: &DepthSmoothness,
        photo_rays: usize,
        check: &FiniteCheck,
    ) -> Result<()> {
        let draw = (spec.sampling.seed, spec.sampling.step);
        let mut patches =
            unseen_patches::draw_patches(data, draw, smoothness.patches, smoothness.stride);
        // Each ray's first draw is its lattice jitter, as in `FastModel::pack_block`.
        let jitter: Vec<f32> = patches.rngs.iter_mut().map(|r| r.uniform()).collect();
        let gpu = &self.gpu;
        let marcher = self.model.marcher(data.near, data.far);
        let on_device = GpuRays::new(gpu, &marcher, &self.model.grid, &patches.rays, &jitter);
        let counted = self.marcher.count(gpu, &on_device);
        let rays = patches.len();
        let all = self.marcher.cut(gpu, &counted, rays, usize::MAX, rays)?;
        let n = all.samples;
        if n == 0 {
            return Ok(());
        }
        let (samples, positions, dirs) = self.marcher.write(gpu, &on_device, &counted, all);
        let codes = SampleCodes::all(gpu, MEAN_APPEARANCE);
        let footprints = (self.model.config.field.antialias.is_some()).then(|| {
            antialias::sample_footprints(
                gpu,
                &on_device,
                &gpu.upload(&patches.rays.radii),
                data.space.cylinders(),
                marcher.contract,
                (&samples.offsets, &samples.t),
                rays,
                n,
            )
        });
        let times = self.field.needs().moments.then(|| {
            let per_ray = match patches.rays.times.len() {
                0 => vec![0.0; rays],
                _ => std::mem::take(&mut patches.rays.times),
            };
            per_sample(gpu, &gpu.upload(&per_ray), &samples.offsets, rays, n)
        });
        let input = DeviceInput {
            positions: &positions,
            dirs: &dirs,
            codes: &codes,
            footprints: footprints.as_ref(),
            variances: None,
            moments: DeviceMoments::each_if_any(times.as_ref()),
            n,
        };
        let acts = self.field.forward(gpu, &self.state.values, &input);
        check_device(gpu, check, "field.forward", "sigma", &acts.sigma, n)?;
        let weights = gpu.floats(n);
        let out = gpu.floats(rays * volume::OUT_WORDS);
        let black = gpu.zeros(3 * rays);
        volume::composite(
            gpu,
            &samples,
            &acts.sigma,
            &acts.rgb,
            &black,
            &weights,
            &out,
        );
        let (d_sigma, d_rgb) = (gpu.zeros(n), gpu.zeros(3 * n));
        let config = &self.model.config;
        // The step's gradient is scaled by 1 / (3 photo rays) (see `render::loss`): this
        // makes the loss the weight times its mean over the step's patches, as on the CPU.
        let scale = smoothness.weight * (3 * photo_rays) as f32 / smoothness.patches.max(1) as f32;
        depth_smoothness::add_depth_smoothness(
            gpu,
            &samples,
            (&weights, &d_sigma),
            config.box_diagonal(),
            scale,
            LastStep::Own,
        );
        if config.distortion > 0.0 {
            distortion::add_distortion(
                gpu,
                &samples,
                &positions,
                &weights,
                &d_sigma,
                config.step_length(),
                config.box_diagonal(),
                config.distortion,
            );
        }
        check_device(gpu, check, "loss.backward", "d_sigma", &d_sigma, n)?;
        let state = (&self.state.values, &self.state.grads);
        self.field
            .backward(gpu, state.0, state.1, &acts, &d_sigma, &d_rgb);
        if config.time_smoothness > 0.0 {
            let weight = 3.0 * config.time_smoothness;
            self.field.time_smoothness_bwd(gpu, state, &acts, weight);
        }
        Ok(())
    }

    /// Uploads `data`'s training views unless they are on the device already.
    fn upload_views(&mut self, data: &Dataset) {
        let uploaded = matches!(&self.views, Some((key, _)) if *key == GpuViews::key_of(data));
        if !uploaded {
            self.views = Some((GpuViews::key_of(data), GpuViews::upload(&self.gpu, data)));
        }
    }

    /// The training views on the device (`None` where they do not fit: the host draws the
    /// rays then).
    fn device_views(&self) -> Option<&GpuViews> {
        self.views.as_ref().and_then(|(_, views)| views.as_ref())
    }

    /// How the run's corrections act on the device (`None` where cameras are not refined).
    fn device_poses(&self) -> Option<DevicePoses> {
        let at = self.model.cameras_at()?;
        let refinement = self.model.config.refine_cameras?;
        Some(DevicePoses {
            at,
            cameras: refinement.cameras,
            frame: refinement.frame,
        })
    }

    /// This step's cameras: as given, corrected on the device from the corrections there,
    /// or, where the views are not on the device, each camera's step read back for the
    /// host to draw its rays with.
    fn step_cameras(&self, data: &Dataset) -> Result<StepCameras> {
        let Some(poses) = self.device_poses() else {
            return Ok(StepCameras::Given);
        };
        if let Some(views) = self.device_views() {
            let (cams, count) = views.cameras();
            let corrected = poses.correct(&self.gpu, cams, &self.state.values, count);
            return Ok(StepCameras::Device(corrected));
        }
        let corrections =
            self.gpu
                .read_range(&self.state.values, poses.at, poses.cameras * PER_CAMERA)?;
        Ok(StepCameras::Host(
            self.model.camera_steps_of(&corrections, data),
        ))
    }

    /// Camera refinement's share of the step's backward, as the CPU engine's
    /// (`FastModel::camera_gradients`): the samples' position and direction gradients on
    /// the device, summed per ray there, and carried through each ray's correction into
    /// its camera's gradient, added to the device's gradients: on the device where it
    /// corrected the cameras (`pose_rays`: the rays' unit world directions and views), else
    /// by the host.
    #[allow(clippy::too_many_arguments)]
    fn add_camera_gradients(
        &self,
        data: &Dataset,
        cameras: &StepCameras,
        acts: &Activations,
        inputs: &InputGradients,
        samples: &volume::GpuSamples,
        dirs: &Handle,
        (origins, units): &(Handle, Handle),
        pose_rays: Option<&(Handle, Handle)>,
    ) -> Result<()> {
        let Some(at) = self.model.cameras_at() else {
            return Ok(());
        };
        let (gpu, field) = (&self.gpu, &self.model.field);
        let levels = field.grid.levels.len();
        let scale = match field.position_level_weights.len() {
            0 => vec![1.0; levels],
            _ => field.position_level_weights.clone(),
        };
        let d_points = pose_grad::position_gradients(
            gpu,
            self.field.hash_grid(),
            &self.state.values,
            self.state.n,
            acts.unit(),
            &inputs.d_enc,
            &scale,
            samples.len,
            field.config.bound,
        );
        let d_dirs = pose_grad::direction_gradients(
            gpu,
            dirs,
            &inputs.d_colour_in,
            inputs.colour_columns,
            samples.len,
        );
        let contract = self.model.marcher(0.0, 1.0).contract;
        let per_ray =
            pose_grad::ray_gradients(gpu, samples, &d_points, &d_dirs, origins, units, contract);
        let cameras = match (cameras, pose_rays, self.device_poses(), self.device_views()) {
            (StepCameras::Host(steps), ..) => steps,
            (
                StepCameras::Device(corrected),
                Some((views, of_ray)),
                Some(poses),
                Some(on_device),
            ) => {
                let (cams, count) = on_device.cameras();
                poses.add_gradients(
                    gpu,
                    (&self.state.values, &self.state.grads),
                    &data.space,
                    (&per_ray, views, of_ray),
                    samples.rays,
                    (cams, corrected),
                    count,
                );
                return Ok(());
            }
            _ => return Ok(()),
        };
        let g = gpu.read(&per_ray, samples.rays * pose_grad::RAY_WORDS)?;
        let rays = &self.rays.rays;
        let mut grad = vec![0.0f32; cameras.len() * PER_CAMERA];
        for (r, w) in g.chunks_exact(pose_grad::RAY_WORDS).enumerate() {
            let view = (rays.pixels[r] >> 32) as usize;
            let Some(camera) = cameras.get(view) else {
                continue;
            };
            camera.accumulate_drawn(
                rays.dirs[r],
                rays.view_dirs[r],
                [w[0], w[1], w[2]],
                [w[3], w[4], w[5]],
                [w[6], w[7], w[8]],
                &mut grad[view * PER_CAMERA..][..PER_CAMERA],
            );
        }
        gpu.add_range(&self.state.grads, at, &grad);
        Ok(())
    }

    /// Re-evaluates the occupancy grid on the device when the schedule says so. The grid
    /// stays there: the marchers read it in place, and a checkpoint or the occupied share
    /// is read back when asked for ([`Engine::state`], [`Engine::occupancy`]); the host's
    /// copy keeps only what the device's refresh does not change (the box, the cells
    /// few-view training leaves empty). Few-view training's hidden-space pass follows
    /// when due.
    fn refresh_occupancy(&mut self, steps_done: u64, seed: u64) {
        let config = self.model.config.occupancy;
        if steps_done.is_multiple_of(config.update_every.max(1)) {
            let dt = self.model.config.step_length();
            let (gpu, field, params) = (&self.gpu, &self.field, &self.state.values);
            let density = |points: &Handle, n: usize| {
                field.density(gpu, params, points, DeviceMoments::Any, n)
            };
            self.occupancy
                .update(gpu, &config, steps_done, seed, dt, &density);
        }
        if self.model.hidden_pass_due(steps_done) {
            if let Err(e) = self.find_hidden() {
                report_device_failure(&e);
            }
        }
    }

    /// Few-view training's pass that finds the space the scene hides from the training
    /// cameras (`model::hidden_space`): the device grid is read back, judged and
    /// refreshed on the host as the CPU engine does, and put back on the device.
    fn find_hidden(&mut self) -> Result<()> {
        let cells = self.occupancy.cells();
        let thickness = self.gpu.read(&self.occupancy.thickness, cells)?;
        let occupied = self.gpu.read_u32(&self.occupancy.occupied, cells)?;
        let occupied = occupied.iter().map(|&o| o == 1).collect();
        let (res, bound) = (self.occupancy.resolution, self.occupancy.bound);
        let mut grid = OccupancyGrid::from_parts(res, bound, thickness, occupied);
        grid.possible = Some(self.model.find_hidden(&grid));
        grid.refresh(self.model.config.occupancy.threshold);
        self.model.grid = grid;
        (self.occupancy, self.marcher) = GpuEngine::upload_occupancy(&self.gpu, &self.model);
        Ok(())
    }

    /// Puts the host grid's state on the device.
    fn upload_occupancy(gpu: &Gpu, model: &FastModel) -> (GpuOccupancy, GpuMarcher) {
        let g = &model.grid;
        let occupancy = GpuOccupancy::new(gpu, g);
        // Near and far only clip each ray's span, which the host computes.
        let marcher = GpuMarcher::new(
            &model.marcher(0.0, 1.0),
            occupancy.occupied.clone(),
            g.resolution,
            g.bound,
        );
        (occupancy, marcher)
    }
}

impl Engine for GpuEngine {
    fn kind(&self) -> crate::engine::caps::EngineKind {
        crate::engine::caps::EngineKind::Gpu
    }

    fn describe(&self) -> String {
        format!(
            "{}{}",
            self.gpu.name,
            if self.gpu.float_atomics {
                ""
            } else {
                " (no float atomics: compare-and-swap)"
            }
        )
    }

    fn model_config(&self) -> &ModelConfig {
        &self.config
    }

    fn param_layout(&self) -> &ParamLayout {
        self.model.layout()
    }

    fn buffer_layout(&self) -> ParamLayout {
        self.model.buffer_layout()
    }

    fn train_step(&mut self, data: &Dataset, spec: &StepSpec) -> Result<StepStats> {
        let step = spec.sampling.step;
        self.trace.begin();
        // Few-view training marks the space its cameras see once, on the host grid; the
        // device's grid follows it from then on.
        let marked = self.model.grid.possible.is_some();
        self.model.prepare(data);
        if !marked && self.model.grid.possible.is_some() {
            (self.occupancy, self.marcher) = GpuEngine::upload_occupancy(&self.gpu, &self.model);
        }
        // Camera refinement's coarse-to-fine weights, as the CPU engine sets them.
        self.model.set_progress(spec.progress);
        self.field
            .set_level_scale(&self.gpu, &self.model.field.level_weights);
        self.upload_views(data);
        let cameras = self.step_cameras(data)?;
        self.trace.mark(Phase::Prepare);
        let clock = step_clock::start(Stage::Marching);
        let StepRays {
            cut,
            samples,
            positions,
            dirs,
            codes,
            footprints,
            targets,
            backgrounds,
            frame,
            pose_rays,
            times,
        } = self.march_step(data, spec, &cameras)?;
        let (rays, n) = (cut.rays, cut.samples);
        let gpu = &self.gpu;
        gpu.stage_done(clock);
        let check = FiniteCheck::new(self.check_finite);

        let input = DeviceInput {
            positions: &positions,
            dirs: &dirs,
            codes: &codes,
            footprints: footprints.as_ref(),
            variances: None,
            moments: DeviceMoments::each_if_any(times.as_ref()),
            n,
        };
        let acts = self.field.forward(gpu, &self.state.values, &input);
        check_device(gpu, &check, "field.forward", "sigma", &acts.sigma, n)?;
        check_device(gpu, &check, "field.forward", "rgb", &acts.rgb, n * 3)?;
        let clock = step_clock::start(Stage::Compositing);
        let weights = gpu.floats(n);
        let out = gpu.floats(rays * volume::OUT_WORDS);
        volume::composite(
            gpu,
            &samples,
            &acts.sigma,
            &acts.rgb,
            &backgrounds,
            &weights,
            &out,
        );
        check_device(
            gpu,
            &check,
            "composite",
            "ray outputs",
            &out,
            rays * volume::OUT_WORDS,
        )?;
        let (sse, d_out) = (gpu.floats(rays), gpu.floats(rays * 3));
        loss::squared_error_per_ray(gpu, rays, &out, &targets, &sse, &d_out);
        let (d_sigma, d_rgb) = (gpu.floats(n), gpu.floats(n * 3));
        volume::composite_backward(
            gpu,
            &samples,
            &acts.sigma,
            &acts.rgb,
            &backgrounds,
            &out,
            &d_out,
            &d_sigma,
            &d_rgb,
        );
        let config = &self.model.config;
        if config.distortion > 0.0 {
            distortion::add_distortion(
                gpu,
                &samples,
                &positions,
                &weights,
                &d_sigma,
                config.step_length(),
                config.box_diagonal(),
                config.distortion,
            );
        }
        gpu.stage_done(clock);
        check_device(gpu, &check, "loss.backward", "d_sigma", &d_sigma, n)?;
        check_device(gpu, &check, "loss.backward", "d_rgb", &d_rgb, n * 3)?;
        let inputs = self.field.backward(
            gpu,
            &self.state.values,
            &self.state.grads,
            &acts,
            &d_sigma,
            &d_rgb,
        );
        if let Some(frame) = &frame {
            self.trace.mark(Phase::Queueing);
            self.add_camera_gradients(
                data,
                &cameras,
                &acts,
                &inputs,
                &samples,
                &dirs,
                frame,
                pose_rays.as_ref(),
            )?;
            self.trace.mark(Phase::Cameras);
        }
        if config.time_smoothness > 0.0 {
            // The step's gradient is scaled by 1 / (3 rays) (see `render::loss`): 3 times
            // the weight makes the prior the weight times its mean over the step's rays, as
            // on the CPU engine.
            let state = (&self.state.values, &self.state.grads);
            let weight = 3.0 * config.time_smoothness;
            self.field.time_smoothness_bwd(gpu, state, &acts, weight);
        }
        if let Some(smoothness) = config.depth_smoothness {
            self.train_patches(data, spec, &smoothness, rays, &check)?;
        }
        check_device(
            gpu,
            &check,
            "field.backward",
            "parameter gradients",
            &self.state.grads,
            self.state.n,
        )?;
        if let Some(e) = check.take(step + 1) {
            self.state.clear_grads(gpu);
            return Err(e);
        }
        let scale = mean_scale(rays);
        let rule = self.model.update_rule();
        // A frozen field is a learning rate of zero, as on the CPU engine.
        let field_lr = if spec.frozen_field { 0.0 } else { spec.lr };
        self.trace.mark(Phase::Queueing);
        let clock = step_clock::start(Stage::Adam);
        // The per-ray errors summed in ray order in f64: the CPU engine's loss to rounding.
        let sse = self.state.finish_step(
            gpu,
            step,
            &sse,
            rays,
            (field_lr, spec.camera_lr),
            scale as f32,
            rule,
        )?;
        let loss = (sse * scale) as f32;
        gpu.stage_done(clock);
        self.trace.mark(Phase::End);
        check_device(
            gpu,
            &check,
            "adam",
            "parameters",
            &self.state.values,
            self.state.n,
        )?;
        if let Some(e) = check.take(step + 1) {
            return Err(e);
        }
        if !spec.frozen_field {
            self.refresh_occupancy(step + 1, spec.sampling.seed);
        }
        self.trace.mark(Phase::Refresh);
        self.trace.step_done();
        Ok(StepStats {
            step: step + 1,
            loss,
            psnr: crate::metrics::psnr_from_mse(sse * scale),
            lr: spec.lr,
            rays,
            samples: n,
        })
    }

    fn render_rays(
        &self,
        rays: &RayBatch,
        out: &mut [RayOutput],
        on_progress: &(dyn Fn(usize) + Sync),
    ) {
        // Few, large device calls: every round of the renderer is a round trip.
        let chunk_rays = render_sizes(&self.gpu, self.field.is_fused()).chunk;
        let chunk = self.chunk_rays.max(chunk_rays);
        let marcher = self.model.marcher(rays.near, rays.far);
        let (gpu, params) = (&self.gpu, &self.state.values);
        render_in_chunks(rays, out, chunk, on_progress, |part, out| {
            let rendered = render::render_rays(
                gpu,
                &self.marcher,
                &marcher,
                &self.model.grid,
                (&self.field, params),
                self.round_samples(),
                part,
            );
            match rendered {
                Ok(r) => out.copy_from_slice(&r),
                Err(e) => fail_rays(&e, out),
            }
        });
    }

    /// A pinhole camera's pixels: rays cast on the device, the slab's rows rendered in
    /// lanes whose rounds interleave.
    fn render_pixels(&self, pixels: &PixelRays, out: &mut [RayOutput]) -> bool {
        let started = std::time::Instant::now();
        let marcher = self.model.marcher(pixels.near, pixels.far);
        let bound = self.model.grid.bound;
        let lanes = render_sizes(&self.gpu, self.field.is_fused()).lanes;
        let code = match pixels.appearance {
            Appearance::Of(i) => i,
            Appearance::Mean | Appearance::PerView => MEAN_APPEARANCE,
        };
        let mut batches = Vec::with_capacity(lanes);
        let parts = render::lane_ranges(pixels.pixels.clone(), lanes);
        for part in &parts {
            let Some(cast) = rays::camera_rays(
                &self.gpu,
                pixels.camera,
                &pixels.space,
                &marcher,
                bound,
                part.clone(),
            ) else {
                return false;
            };
            batches.push(render::DeviceBatch {
                rays: cast.rays,
                inv_norm: cast.inv_norm,
                radii: Some(cast.radii),
                cylinders: pixels.space.cylinders(),
                codes: render::RayCodes::All(code),
                times: render::RayTimes::At(pixels.time.unwrap_or(0.0)),
            });
        }
        let (gpu, params) = (&self.gpu, &self.state.values);
        let cast = started.elapsed();
        let rendered = render::render_batches(
            gpu,
            &self.marcher,
            &marcher,
            (&self.field, params),
            self.round_samples(),
            &batches,
        );
        match rendered {
            Ok(states) => {
                // Each lane's results straight into its pixels of `out`.
                let start = pixels.pixels.start;
                for (part, state) in parts.iter().zip(&states) {
                    let slots = &mut out[part.start - start..part.end - start];
                    render::write_ray_outputs(state, |_| pixels.background, slots);
                }
            }
            Err(e) => fail_rays(&e, out),
        }
        if trace::tracing() {
            let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
            eprintln!(
                "gpu view: {} pixels in {:.1} ms: casting {:.1}, rendering and writing {:.1}",
                out.len(),
                ms(started.elapsed()),
                ms(cast),
                ms(started.elapsed() - cast)
            );
        }
        true
    }

    /// A view goes to the device in chunks as large as its rendering takes (fewer calls,
    /// each with its rays' spans made and uploaded at once).
    fn render_slab(&self) -> usize {
        render_sizes(&self.gpu, self.field.is_fused())
            .chunk
            .max(crate::engine::RENDER_SLAB)
    }

    /// Moving scenes do not run on this engine (`engine::caps`): `time` has no use here.
    fn density(&self, positions: &[f32], time: Option<f32>, out: &mut [f32]) {
        density_in_chunks(positions, out, DENSITY_CHUNK, |p, o| {
            self.density_chunk(p, time, o)
        });
    }

    /// The weights, Adam's moments and the device grid's thickness (the model's buffer).
    fn state(&self) -> EngineState {
        let cells = self.occupancy.cells();
        let thickness = self
            .gpu
            .read(&self.occupancy.thickness, cells)
            .unwrap_or_else(|e| {
                report_device_failure(&e);
                vec![f32::NAN; cells]
            });
        self.state
            .state(&self.gpu, self.model.buffers_with(thickness))
    }

    fn set_state(&mut self, state: EngineState) -> Result<()> {
        let buffers = self.model.buffer_layout().total;
        self.state.set_state(&self.gpu, &state, buffers)?;
        self.model.load_buffers(state.buffers);
        (self.occupancy, self.marcher) = GpuEngine::upload_occupancy(&self.gpu, &self.model);
        Ok(())
    }

    /// The device grid's occupied share.
    fn occupancy(&self) -> Option<f64> {
        let cells = self.occupancy.cells();
        let flags = self.gpu.read_u32(&self.occupancy.occupied, cells).ok()?;
        Some(flags.iter().filter(|&&o| o == 1).count() as f64 / cells.max(1) as f64)
    }

    /// A hardware GPU's whole rendering chunk; a software adapter runs a call as slowly as
    /// a CPU, so it takes a CPU's few thousand rays and stops as soon.
    fn interactive_slab(&self) -> usize {
        if self.gpu.software {
            crate::engine::INTERACTIVE_SLAB
        } else {
            render_sizes(&self.gpu, self.field.is_fused()).chunk
        }
    }

    fn views_in_flight(&self) -> usize {
        render_sizes(&self.gpu, self.field.is_fused()).views
    }

    /// Every parameter goes through the device's Adam pass (hash entries without a
    /// gradient are skipped inside it); there are no untouched blocks to report.
    fn touched_fraction(&self) -> f64 {
        1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn render_sizes_parse_from_logarithms_with_optional_lanes_and_views() {
        let sizes = |chunk, round, lanes, views| RenderSizes {
            chunk,
            round,
            lanes,
            views,
        };
        let max = MAX_DEVICE_SAMPLES;
        assert_eq!(
            parse_render_sizes("19,18", max),
            Some(sizes(1 << 19, 1 << 18, 1, 1))
        );
        assert_eq!(
            parse_render_sizes(" 20, 19 ,3", max),
            Some(sizes(1 << 20, 1 << 19, 3, 1))
        );
        assert_eq!(
            parse_render_sizes("20,19,2,2", max),
            Some(sizes(1 << 20, 1 << 19, 2, 2))
        );
        for bad in [
            "21,18",
            "19,20",
            "19",
            "19,18,0",
            "19,18,9",
            "a,b",
            "19,18,2,0",
            "19,18,2,5",
            "19,18,2,1,1",
            "",
        ] {
            assert_eq!(parse_render_sizes(bad, max), None, "{bad}");
        }
        assert_eq!(
            parse_render_sizes("20,22,2", MAX_FUSED_ROUND),
            Some(sizes(1 << 20, 1 << 22, 2, 1))
        );
    }
}
