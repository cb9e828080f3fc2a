//! Rendering with every sample on the device: rays march through the occupancy grid in
//! rounds (`march`'s round passes: count, prefix sum, cut at the round's sample budget,
//! packed write), the field evaluates each round's samples, and each ray adds them to its
//! running result and stops once its transmittance falls below `MIN_TRANSMITTANCE`. This
//! is the CPU renderer's early termination (`render::march::render_marched`, the same
//! lattice and the same stopping rule), with the host reading back three numbers per round
//! and the results at the end.

use std::time::{Duration, Instant};

use cubecl::prelude::*;
use cubecl::server::Handle;
use rayon::prelude::*;

use super::antialias::sample_footprints;
use super::codes::SampleCodes;
use super::device::Gpu;
use super::device_field::{DeviceField, DeviceInput, DeviceMoments, FieldNeeds};
use super::launch::grid;
use super::march::{Counted, Cut, GpuMarcher, GpuRays, PendingCut, RoundState, STATE_WORDS};
use super::space_time_grid::per_sample;
use super::trace::tracing;
use crate::error::Result;
use crate::math::length;
use crate::render::march::Marcher;
use crate::render::occupancy::OccupancyGrid;
use crate::stage::{Appearance, RayBatch, RayOutput, MEAN_APPEARANCE};

const GROUP: u32 = 64;

/// Adds each of the first `rays` rays' round samples (CSR `offsets`) to its running result
/// in `state` (`render::volume::Accumulator::add`, depth along the camera direction).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn accumulate(
    offsets: &[u32],
    t: &[f32],
    dt: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    inv_norm: &[f32],
    state: &mut [f32],
    rays: u32,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let b = STATE_WORDS * r;
        let mut trans = state[b];
        let mut c0 = state[b + 1];
        let mut c1 = state[b + 2];
        let mut c2 = state[b + 3];
        let mut depth = state[b + 4];
        let mut opacity = state[b + 5];
        let scale = inv_norm[r];
        for i in offsets[r] as usize..offsets[r + 1] as usize {
            let alpha = 1.0 - f32::exp(-sigma[i] * dt[i]);
            let w = trans * alpha;
            c0 += w * rgb[3 * i];
            c1 += w * rgb[3 * i + 1];
            c2 += w * rgb[3 * i + 2];
            depth += w * (t[i] * scale);
            opacity += w;
            trans *= 1.0 - alpha;
        }
        state[b] = trans;
        state[b + 1] = c0;
        state[b + 2] = c1;
        state[b + 3] = c2;
        state[b + 4] = depth;
        state[b + 5] = opacity;
    }
}

/// Each ray's appearance code on the device.
pub enum RayCodes {
    /// One code for every ray (the mean code, or one photo's).
    All(u32),
    /// A code per ray.
    PerRay(Handle),
}

/// The moments a batch's rays see, for a moving field.
pub enum RayTimes {
    /// One moment for every ray (a view at its time; moment 0 where none is given, as on
    /// the CPU).
    At(f32),
    /// A moment per ray.
    PerRay(Handle),
}

impl RayTimes {
    /// The moments of a host batch's rays (`RayBatch::times`: one per ray, or none).
    pub fn of(gpu: &Gpu, times: &[f32]) -> Self {
        match times.first() {
            None => RayTimes::At(0.0),
            Some(&t) if times.iter().all(|&u| u == t) => RayTimes::At(t),
            Some(_) => RayTimes::PerRay(gpu.upload(times)),
        }
    }
}

/// Rays on the device to render, with what a field may read besides them. Rendering
/// advances the rays (each one's start is where its next round resumes), so a batch
/// renders once.
pub struct DeviceBatch {
    pub rays: GpuRays,
    /// One over the length of each ray's direction in its space: depth's scale.
    pub inv_norm: Handle,
    /// Each ray's cone radius, for footprints; without them every sample takes the
    /// reference footprint, as on the CPU.
    pub radii: Option<Handle>,
    /// Footprints constant along rays (`RayBatch::cylinders`).
    pub cylinders: bool,
    pub codes: RayCodes,
    pub times: RayTimes,
}

impl DeviceBatch {
    /// The host's `rays` on the device, as the renderer's lattice starts them (the first
    /// sample half a step into each span), through `marcher` and `grid` (which give each
    /// ray its span on the host).
    pub fn upload(gpu: &Gpu, marcher: &Marcher, grid: &OccupancyGrid, rays: &RayBatch) -> Self {
        let n = rays.len();
        let codes = match rays.appearance {
            Appearance::Mean => RayCodes::All(MEAN_APPEARANCE),
            Appearance::Of(i) => RayCodes::All(i),
            Appearance::PerView => {
                let per_ray: Vec<u32> = (0..n).map(|r| rays.appearance_of(r)).collect();
                RayCodes::PerRay(gpu.upload_u32(&per_ray))
            }
        };
        let inv_norm: Vec<f32> = rays.dirs.par_iter().map(|&d| 1.0 / length(d)).collect();
        DeviceBatch {
            rays: GpuRays::new(gpu, marcher, grid, rays, &vec![0.5; n]),
            inv_norm: gpu.upload(&inv_norm),
            radii: (!rays.radii.is_empty()).then(|| gpu.upload(&rays.radii)),
            cylinders: rays.cylinders,
            codes,
            times: RayTimes::of(gpu, &rays.times),
        }
    }
}

/// Renders the host's `rays` through `field` at `params`: see [`render_batch`].
#[allow(clippy::too_many_arguments)]
pub fn render_rays<F: DeviceField>(
    gpu: &Gpu,
    device_grid: &GpuMarcher,
    marcher: &Marcher,
    host_grid: &OccupancyGrid,
    (field, params): (&F, &Handle),
    round_samples: usize,
    rays: &RayBatch,
) -> Result<Vec<RayOutput>> {
    if rays.is_empty() {
        return Ok(Vec::new());
    }
    let batch = DeviceBatch::upload(gpu, marcher, host_grid, rays);
    let state = render_batch(
        gpu,
        device_grid,
        marcher,
        (field, params),
        round_samples,
        &batch,
    )?;
    Ok(ray_outputs(&state, |r| rays.backgrounds[r]))
}

/// Each ray's result from its running state (`STATE_WORDS` floats a ray) over its
/// `background`.
pub fn ray_outputs(state: &[f32], background: impl Fn(usize) -> [f32; 3] + Sync) -> Vec<RayOutput> {
    let mut out = vec![RayOutput::default(); state.len() / STATE_WORDS];
    write_ray_outputs(state, background, &mut out);
    out
}

/// [`ray_outputs`] written into `out` (a slot per ray of `state`).
pub fn write_ray_outputs(
    state: &[f32],
    background: impl Fn(usize) -> [f32; 3] + Sync,
    out: &mut [RayOutput],
) {
    out.par_iter_mut()
        .zip(state.par_chunks_exact(STATE_WORDS))
        .enumerate()
        .for_each(|(r, (o, s))| {
            let (opacity, bg) = (s[5], background(r));
            *o = RayOutput {
                rgb: [0, 1, 2].map(|c| s[1 + c] + (1.0 - opacity) * bg[c]),
                depth: s[4],
                opacity,
            };
        });
}

/// Renders `batch` through `field` at `params`: the grid `device_grid` marched as
/// `marcher` marches, at most about `round_samples` samples per round, each round making
/// the inputs the field needs.
/// Returns each ray's running state at the end (`STATE_WORDS` floats a ray: transmittance,
/// rgb, depth, opacity, before any background).
pub fn render_batch<F: DeviceField>(
    gpu: &Gpu,
    device_grid: &GpuMarcher,
    marcher: &Marcher,
    field: (&F, &Handle),
    round_samples: usize,
    batch: &DeviceBatch,
) -> Result<Vec<f32>> {
    let batches = std::slice::from_ref(batch);
    let mut states = render_batches(gpu, device_grid, marcher, field, round_samples, batches)?;
    Ok(states.pop().unwrap_or_default())
}

/// Renders `batches` as [`render_batch`] renders each, their rounds interleaved: while
/// the host waits for one batch's round to be cut, the device works on another's, so
/// the round trips that set a frame's pace on a hardware GPU overlap its work.
pub fn render_batches<F: DeviceField>(
    gpu: &Gpu,
    device_grid: &GpuMarcher,
    marcher: &Marcher,
    (field, params): (&F, &Handle),
    round_samples: usize,
    batches: &[DeviceBatch],
) -> Result<Vec<Vec<f32>>> {
    let rounds = Rounds {
        gpu,
        device_grid,
        marcher,
        field,
        params,
        needs: field.needs(),
        round_samples: round_samples.max(1),
    };
    rounds.render(batches)
}

/// Where the host's time goes in a render, told on stderr when `NERF_GPU_TRACE` is set:
/// the rounds, the time spent waiting for their cuts, and the results' read-back.
struct Trace {
    on: bool,
    start: Instant,
    rounds: usize,
    samples: usize,
    waiting: Duration,
    rounds_done: Duration,
}

impl Trace {
    fn start() -> Self {
        Trace {
            on: tracing(),
            start: Instant::now(),
            rounds: 0,
            samples: 0,
            waiting: Duration::ZERO,
            rounds_done: Duration::ZERO,
        }
    }

    fn wait(&mut self, pending: PendingCut) -> Result<Cut> {
        let t = Instant::now();
        let cut = pending.wait()?;
        self.waiting += t.elapsed();
        self.rounds += usize::from(cut.samples > 0);
        self.samples += cut.samples;
        Ok(cut)
    }

    fn rounds_done(&mut self) {
        self.rounds_done = self.start.elapsed();
    }

    fn report(&self, batches: &[DeviceBatch]) {
        if self.on {
            let ms = |d: Duration| d.as_secs_f64() * 1e3;
            eprintln!(
                "gpu render: {} rays in {} lanes, {} rounds, {} samples; {:.1} ms: rounds {:.1} \
                 (waiting for cuts {:.1}), read-back {:.1}",
                batches.iter().map(|b| b.rays.len).sum::<usize>(),
                batches.len(),
                self.rounds,
                self.samples,
                ms(self.start.elapsed()),
                ms(self.rounds_done),
                ms(self.waiting),
                ms(self.start.elapsed() - self.rounds_done),
            );
        }
    }
}

/// `range` cut into at most `lanes` contiguous parts of nearly equal length (none empty,
/// except one for an empty range).
pub fn lane_ranges(range: std::ops::Range<usize>, lanes: usize) -> Vec<std::ops::Range<usize>> {
    let len = range.len();
    let parts = lanes.clamp(1, len.max(1));
    (0..parts)
        .map(|k| range.start + k * len / parts..range.start + (k + 1) * len / parts)
        .collect()
}

/// What every batch's rounds share.
struct Rounds<'a, F> {
    gpu: &'a Gpu,
    device_grid: &'a GpuMarcher,
    marcher: &'a Marcher,
    field: &'a F,
    params: &'a Handle,
    needs: FieldNeeds,
    round_samples: usize,
}

/// One batch's rendering: its rays' running state, and the round counted whose cut is on
/// its way back (`None` once every ray is done).
struct Lane<'a> {
    batch: &'a DeviceBatch,
    round: RoundState<'a>,
    /// The codes a field reads: each sample its ray's, or one for all (made once).
    all_codes: SampleCodes,
    ray_codes: Option<&'a Handle>,
    radii: Option<&'a Handle>,
    per_ray: usize,
    pending: Option<(Counted, PendingCut<'a>)>,
}

impl<'a, F: DeviceField> Rounds<'a, F> {
    fn render(&self, batches: &'a [DeviceBatch]) -> Result<Vec<Vec<f32>>> {
        let mut trace = Trace::start();
        // A lane per batch with rays.
        let mut lanes: Vec<Option<Lane>> = batches
            .iter()
            .map(|b| (b.rays.len > 0).then(|| self.lane(b)))
            .collect();
        while lanes.iter().flatten().any(|lane| lane.pending.is_some()) {
            for lane in lanes.iter_mut().flatten() {
                self.advance(lane, &mut trace)?;
            }
        }
        trace.rounds_done();
        let states = lanes
            .iter()
            .map(|lane| match lane {
                Some(l) => self
                    .gpu
                    .read(&l.round.state, STATE_WORDS * l.batch.rays.len),
                None => Ok(Vec::new()),
            })
            .collect();
        trace.report(batches);
        states
    }

    /// A batch's rays before their first round, that round counted and its cut on its way.
    fn lane(&self, batch: &'a DeviceBatch) -> Lane<'a> {
        let gpu = self.gpu;
        let all_codes = match (&batch.codes, self.needs.codes) {
            (RayCodes::All(code), true) => SampleCodes::all(gpu, *code),
            _ => SampleCodes::all(gpu, MEAN_APPEARANCE),
        };
        let ray_codes = match (&batch.codes, self.needs.codes) {
            (RayCodes::PerRay(codes), true) => Some(codes),
            _ => None,
        };
        // At first a round's budget is spread over all of the rays.
        let per_ray = self.per_ray(batch.rays.len);
        let mut lane = Lane {
            batch,
            round: RoundState::new(gpu, &batch.rays),
            all_codes,
            ray_codes,
            radii: batch.radii.as_ref().filter(|_| self.needs.footprints),
            per_ray,
            pending: None,
        };
        self.count(&mut lane);
        lane
    }

    /// As many samples per ray as spread a round's budget over `live` rays. After the first
    /// round only the rays that had samples in the round before can have any now, so the
    /// budget cuts no ray short, and no ray is marched in a count pass only to be marched
    /// again in the next one. The budget bounds a round's memory, so unlike the CPU
    /// renderer (64) a ray's share has no cap of its own: the last few rays finish in one
    /// round, not in many round trips.
    fn per_ray(&self, live: usize) -> usize {
        let most = self.marcher.max_samples.max(1);
        (self.round_samples / live.max(1)).clamp(1, most)
    }

    /// Queues `lane`'s next round's count and cut, the cut's numbers sent back.
    fn count(&self, lane: &mut Lane<'a>) {
        let n = lane.batch.rays.len;
        let counted = self
            .device_grid
            .count_round(self.gpu, &lane.round, lane.per_ray);
        let cut = self
            .device_grid
            .cut_later(self.gpu, &counted, n, self.round_samples, n);
        lane.pending = Some((counted, cut));
    }

    /// Waits for `lane`'s cut and queues its round: the samples written, the field, each
    /// ray's sums; then the next round's count. A lane whose cut is empty is done.
    fn advance(&self, lane: &mut Lane<'a>, trace: &mut Trace) -> Result<()> {
        let Some((counted, pending)) = lane.pending.take() else {
            return Ok(());
        };
        let cut = trace.wait(pending)?;
        if cut.samples == 0 {
            return Ok(());
        }
        let gpu = self.gpu;
        let (n, round) = (lane.batch.rays.len, &lane.round);
        let (samples, positions, dirs) =
            self.device_grid
                .write_round(gpu, round, &counted, cut, lane.per_ray);
        let (k, s) = (cut.rays, cut.samples);
        let round_codes = lane
            .ray_codes
            .map(|per_ray| SampleCodes::of_rays(gpu, per_ray, &samples.offsets, k, s));
        // A still field reads no moment: its rays' own are not spread to their samples.
        let each;
        let moments = match (&lane.batch.times, self.needs.moments) {
            (RayTimes::PerRay(per_ray), true) => {
                each = per_sample(gpu, per_ray, &samples.offsets, k, s);
                DeviceMoments::Each(&each)
            }
            (RayTimes::PerRay(_), false) => DeviceMoments::At(0.0),
            (RayTimes::At(t), _) => DeviceMoments::At(*t),
        };
        let footprints = lane.radii.map(|radii| {
            let csr = (&samples.offsets, &samples.t);
            sample_footprints(
                gpu,
                round.rays,
                radii,
                lane.batch.cylinders,
                self.marcher.contract,
                csr,
                k,
                s,
            )
        });
        let input = DeviceInput {
            positions: &positions,
            dirs: &dirs,
            codes: round_codes.as_ref().unwrap_or(&lane.all_codes),
            footprints: footprints.as_ref(),
            variances: None,
            moments,
            n: s,
        };
        let (sigma, rgb) = self.field.infer(gpu, self.params, &input);
        // SAFETY: `offsets` holds `k + 1` slots ending at `s`, the length of every sample
        // buffer (`3s` for colours); `inv_norm` and `state` hold the `n >= k` rays.
        unsafe {
            let (c, d) = grid(k, GROUP);
            accumulate::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(samples.offsets.clone(), k + 1),
                BufferArg::from_raw_parts(samples.t.clone(), s),
                BufferArg::from_raw_parts(samples.dt.clone(), s),
                BufferArg::from_raw_parts(sigma, s),
                BufferArg::from_raw_parts(rgb, 3 * s),
                BufferArg::from_raw_parts(lane.batch.inv_norm.clone(), n),
                BufferArg::from_raw_parts(round.state.clone(), STATE_WORDS * n),
                k as u32,
            );
        }
        lane.per_ray = self.per_ray(cut.live);
        self.count(lane);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::engine::gpu::field::tests::small_field;
    use crate::engine::gpu::field::GpuFastField;
    use crate::render::march::{render_marched, MarchWorkspace};
    use crate::rng::Rng;

    #[test]
    fn lanes_cover_the_range_in_order_without_empty_parts() {
        for (range, lanes) in [(0..10, 3), (5..7, 4), (3..3, 2), (0..1 << 20, 2), (4..9, 1)] {
            let parts = lane_ranges(range.clone(), lanes);
            assert!(parts.len() <= lanes.max(1));
            assert_eq!(parts.first().map(|p| p.start), Some(range.start));
            assert_eq!(parts.last().map(|p| p.end), Some(range.end));
            for pair in parts.windows(2) {
                assert_eq!(pair[0].end, pair[1].start);
            }
            if !range.is_empty() {
                assert!(
                    parts.iter().all(|p| !p.is_empty()),
                    "{range:?} in {lanes}: {parts:?}"
                );
                let (min, max) = (
                    parts.iter().map(|p| p.len()).min().unwrap_or(0),
                    parts.iter().map(|p| p.len()).max().unwrap_or(0),
                );
                assert!(max - min <= 1, "{parts:?}");
            }
        }
        assert_eq!(lane_ranges(5..7, 4), vec![5..6, 6..7]);
    }

    /// A random field over a random half-occupied grid, 300 rays from outside the box (some
    /// missing it): the device's rounds against the CPU renderer, with a round budget of a
    /// few samples (many rounds, most cut short) and a large one. Samples past a ray's early
    /// termination (transmittance below 1e-4) may differ, so results agree within 1e-3.
    #[test]
    fn device_rendering_matches_the_cpu_renderer() {
        let Some(gpu) = test_gpu() else {
            return;
        };
        let field = small_field();
        let mut rng = Rng::new(4);
        // Large weights: densities from none to opaque within a few cells.
        let params: Vec<f32> = (0..field.num_params())
            .map(|_| rng.range(-1.5, 1.5))
            .collect();
        let thickness: Vec<f32> = (0..16 * 16 * 16)
            .map(|_| if rng.uniform() < 0.5 { 1.0 } else { 0.0 })
            .collect();
        let grid = OccupancyGrid::from_thickness(16, 1.5, thickness, 0.5);
        let marcher = Marcher {
            dt: 0.02,
            max_samples: 200,
            near: 0.5,
            far: 8.0,
            contract: None,
        };
        let mut rays = RayBatch::new(marcher.near, marcher.far);
        // The same rays in three lanes (120, 100 and 80 of them), for interleaved rounds.
        let mut lanes: Vec<RayBatch> = (0..3)
            .map(|_| RayBatch::new(marcher.near, marcher.far))
            .collect();
        for k in 0..300 {
            let origin = [rng.range(-4.0, 4.0), -4.0, rng.range(-1.0, 1.0)];
            let target = [rng.range(-2.0, 2.0), 0.0, rng.range(-2.0, 2.0)];
            let dir = [target[0] - origin[0], 4.0, target[2] - origin[2]];
            let ray = crate::camera::Ray { origin, dir };
            let bg = [rng.uniform(), rng.uniform(), rng.uniform()];
            rays.push(ray, dir, bg, k);
            lanes[usize::from(k >= 120) + usize::from(k >= 220)].push(ray, dir, bg, k);
        }
        let mut want = vec![RayOutput::default(); rays.len()];
        let mut ws = MarchWorkspace::default();
        render_marched(
            &field,
            &params,
            &marcher,
            &grid,
            1 << 16,
            0.0,
            &rays,
            &mut ws,
            &mut want,
        );

        let device_field = GpuFastField::new(&gpu, &field);
        let device_params = gpu.upload(&params);
        let field_at = (&device_field, &device_params);
        let device_grid = GpuMarcher::with_grid(&gpu, &marcher, &grid);
        let flat = |o: &[RayOutput]| -> Vec<f32> {
            o.iter()
                .flat_map(|r| [r.rgb[0], r.rgb[1], r.rgb[2], r.depth, r.opacity])
                .collect()
        };
        for round_samples in [40, 1 << 16] {
            let got = render_rays(
                &gpu,
                &device_grid,
                &marcher,
                &grid,
                field_at,
                round_samples,
                &rays,
            )
            .expect("render");
            let err = worst(&flat(&got), &flat(&want));
            eprintln!("round budget {round_samples}: worst difference {err:.1e}");
            assert!(err < 1e-3, "round budget {round_samples}: {err}");
        }
        // Interleaved lanes render each ray as one lane alone does, whatever the budget
        // (rendering advances a batch's rays, so each render takes fresh ones).
        for round_samples in [40, 1 << 16] {
            let batches: Vec<DeviceBatch> = lanes
                .iter()
                .map(|lane| DeviceBatch::upload(&gpu, &marcher, &grid, lane))
                .collect();
            let states = render_batches(
                &gpu,
                &device_grid,
                &marcher,
                field_at,
                round_samples,
                &batches,
            )
            .expect("render lanes");
            assert_eq!(
                states.iter().map(Vec::len).collect::<Vec<_>>(),
                [120, 100, 80].map(|n| n * STATE_WORDS)
            );
            let got = ray_outputs(&states.concat(), |r| rays.backgrounds[r]);
            let err = worst(&flat(&got), &flat(&want));
            eprintln!("3 lanes, round budget {round_samples}: worst difference {err:.1e}");
            assert!(err < 1e-3, "lanes, round budget {round_samples}: {err}");
        }
        // Something to compare: opaque rays, empty rays and ones in between.
        let opacity: Vec<f32> = want.iter().map(|o| o.opacity).collect();
        let opaque = opacity.iter().filter(|&&o| o > 0.99).count();
        eprintln!("{opaque} of {} rays opaque", opacity.len());
        assert!(opacity.iter().any(|&o| o > 0.99), "no opaque ray");
        assert!(opacity.contains(&0.0), "no empty ray");
        assert!(
            opacity.iter().any(|&o| o > 0.05 && o < 0.95),
            "no partly transparent ray"
        );
    }
}
