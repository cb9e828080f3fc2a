//! Rendering with every sample on the device: rays march through the occupancy grid in
//! rounds (`march`'s round passes: count, prefix sum, cut at the round's sample budget,
//! packed write), the field evaluates each round's samples, and each ray adds them to its
//! running result and stops once its transmittance falls below `MIN_TRANSMITTANCE`. This
//! is the CPU renderer's early termination (`render::march::render_marched`, the same
//! lattice and the same stopping rule), with the host reading back three numbers per round
//! and the results at the end.

use cubecl::prelude::*;
use cubecl::server::Handle;
use rayon::prelude::*;

use super::antialias::sample_footprints;
use super::codes::SampleCodes;
use super::device::Gpu;
use super::field::DeviceInput;
use super::launch::grid;
use super::march::{GpuMarcher, GpuRays, RoundState, STATE_WORDS};
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

/// A field on the device: densities (`n`) and colours (`n x 3`) of a round's samples.
pub type DeviceFieldFn<'a> = dyn Fn(&DeviceInput) -> (Handle, Handle) + 'a;

/// What a field reads besides positions and directions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FieldNeeds {
    /// Each sample's appearance code (`RayBatch::appearance_of` its ray; else the mean).
    pub codes: bool,
    /// Each sample's footprint (from the batch's cone radii; else the reference one).
    pub footprints: bool,
}

/// Each ray's appearance code on the device.
pub enum RayCodes {
    /// One code for every ray (the mean code, or one photo's).
    All(u32),
    /// A code per ray.
    PerRay(Handle),
}

/// Rays on the device to render, with what a field may read besides them.
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
        }
    }
}

/// Renders the host's `rays` through `field`: see [`render_batch`].
#[allow(clippy::too_many_arguments)]
pub fn render_rays(
    gpu: &Gpu,
    device_grid: &GpuMarcher,
    marcher: &Marcher,
    host_grid: &OccupancyGrid,
    field: &DeviceFieldFn,
    needs: FieldNeeds,
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
        field,
        needs,
        round_samples,
        &batch,
    )?;
    Ok(ray_outputs(&state, |r| rays.backgrounds[r]))
}

/// Each ray's result from its running state (`STATE_WORDS` floats a ray) over its
/// `background`.
pub fn ray_outputs(state: &[f32], background: impl Fn(usize) -> [f32; 3] + Sync) -> Vec<RayOutput> {
    state
        .par_chunks_exact(STATE_WORDS)
        .enumerate()
        .map(|(r, s)| {
            let (opacity, bg) = (s[5], background(r));
            RayOutput {
                rgb: [0, 1, 2].map(|c| s[1 + c] + (1.0 - opacity) * bg[c]),
                depth: s[4],
                opacity,
            }
        })
        .collect()
}

/// Renders `batch` through `field`: the grid `device_grid` marched as `marcher` marches,
/// at most about `round_samples` samples per round, the field told what it `needs`.
/// Returns each ray's running state at the end (`STATE_WORDS` floats a ray: transmittance,
/// rgb, depth, opacity, before any background).
pub fn render_batch(
    gpu: &Gpu,
    device_grid: &GpuMarcher,
    marcher: &Marcher,
    field: &DeviceFieldFn,
    needs: FieldNeeds,
    round_samples: usize,
    batch: &DeviceBatch,
) -> Result<Vec<f32>> {
    let n = batch.rays.len;
    if n == 0 {
        return Ok(Vec::new());
    }
    // The codes a field reads: each sample its ray's, or one for all (made once).
    let all_codes = match (&batch.codes, needs.codes) {
        (RayCodes::All(code), true) => SampleCodes::all(gpu, *code),
        _ => SampleCodes::all(gpu, MEAN_APPEARANCE),
    };
    let ray_codes = match (&batch.codes, needs.codes) {
        (RayCodes::PerRay(codes), true) => Some(codes),
        _ => None,
    };
    let radii = batch.radii.as_ref().filter(|_| needs.footprints);
    let round = RoundState::new(gpu, &batch.rays);
    let round_samples = round_samples.max(1);
    // As many samples per ray as spread a round's budget over the rays still marching: all
    // of them at first, then those that had samples in the round before (no more can have
    // any now), so that after the first round the budget cuts no ray short, and no ray
    // is marched in a count pass only to be marched again in the next one. The budget
    // bounds a round's memory, so unlike the CPU renderer (64) a ray's share has no cap
    // of its own: the last few rays finish in one round, not in many round trips.
    let most = marcher.max_samples.max(1);
    let mut per_ray = (round_samples / n).clamp(1, most);
    loop {
        let counted = device_grid.count_round(gpu, &round, per_ray);
        let cut = device_grid.cut(gpu, &counted, n, round_samples, n)?;
        if cut.samples == 0 {
            break;
        }
        let (samples, positions, dirs) =
            device_grid.write_round(gpu, &round, &counted, cut, per_ray);
        let (k, s) = (cut.rays, cut.samples);
        let round_codes =
            ray_codes.map(|per_ray| SampleCodes::of_rays(gpu, per_ray, &samples.offsets, k, s));
        let footprints = radii.map(|radii| {
            let csr = (&samples.offsets, &samples.t);
            sample_footprints(
                gpu,
                round.rays,
                radii,
                batch.cylinders,
                marcher.contract,
                csr,
                k,
                s,
            )
        });
        let (sigma, rgb) = field(&DeviceInput {
            positions: &positions,
            dirs: &dirs,
            codes: round_codes.as_ref().unwrap_or(&all_codes),
            footprints: footprints.as_ref(),
            n: s,
        });
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
                BufferArg::from_raw_parts(batch.inv_norm.clone(), n),
                BufferArg::from_raw_parts(round.state.clone(), STATE_WORDS * n),
                k as u32,
            );
        }
        per_ray = (round_samples / cut.live.max(1)).clamp(1, most);
    }
    gpu.read(&round.state, STATE_WORDS * n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::engine::gpu::field::tests::small_field;
    use crate::engine::gpu::field::GpuFastField;
    use crate::render::march::{render_marched, MarchWorkspace};
    use crate::rng::Rng;

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
        for k in 0..300 {
            let origin = [rng.range(-4.0, 4.0), -4.0, rng.range(-1.0, 1.0)];
            let target = [rng.range(-2.0, 2.0), 0.0, rng.range(-2.0, 2.0)];
            let dir = [target[0] - origin[0], 4.0, target[2] - origin[2]];
            let ray = crate::camera::Ray { origin, dir };
            let bg = [rng.uniform(), rng.uniform(), rng.uniform()];
            rays.push(ray, dir, bg, k);
        }
        let mut want = vec![RayOutput::default(); rays.len()];
        let mut ws = MarchWorkspace::default();
        render_marched(
            &field,
            &params,
            &marcher,
            &grid,
            1 << 16,
            &rays,
            &mut ws,
            &mut want,
        );

        let device_field = GpuFastField::new(&gpu, &field);
        let device_params = gpu.upload(&params);
        let field_fn = |input: &DeviceInput| {
            let acts = device_field.forward(&gpu, &device_params, input);
            (acts.sigma, acts.rgb)
        };
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
                &field_fn,
                FieldNeeds::default(),
                round_samples,
                &rays,
            )
            .expect("render");
            let err = worst(&flat(&got), &flat(&want));
            eprintln!("round budget {round_samples}: worst difference {err:.1e}");
            assert!(err < 1e-3, "round budget {round_samples}: {err}");
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
