//! Anti-aliasing on the GPU (`field::fast::Antialias`, whose docs give the maths): each
//! marched sample's footprint (its ray's cone radius at its depth, shrunk as contraction
//! shrinks space; `render::march::Marcher::footprint`), and the hash-grid level weights
//! `erf(1 / sqrt(8 sigma^2 N_l^2))` that scale each level's features forward and their
//! gradients backward. The weights depend on no parameter, so the backward is the same
//! scaling.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::hash_grid::GpuHashGrid;
use super::launch::grid;
use super::march::GpuRays;
use crate::encoding::hash_grid::FEATURES;

/// Threads per workgroup.
const GROUP: u32 = 64;

/// `crate::math::erf` for `x >= 0`: the same polynomial, so both engines weigh alike.
#[cube]
fn erf_positive(x: f32) -> f32 {
    let t = 1.0f32 / (1.0f32 + 0.327_591_1f32 * x);
    let poly = t
        * (0.254_829_6f32
            + t * (-0.284_496_74f32
                + t * (1.421_413_7f32 + t * (-1.453_152f32 + t * 1.061_405_4f32))));
    1.0f32 - poly * f32::exp(-x * x)
}

/// The weight of hash-grid level `l` (of the table `levels`) for a footprint of `sigma`
/// (in the unit cube's units).
#[cube]
pub(super) fn level_weight(levels: &[u32], l: usize, sigma: f32) -> f32 {
    let x = sigma * f32::cast_from(levels[4 * l]);
    let x = 8.0f32 * x * x;
    select(x <= 0.0, 1.0f32, erf_positive(1.0f32 / f32::sqrt(x)))
}

/// Footprints of the samples of rays `r < rays` (CSR `offsets`, depths `t` along the unit
/// `dirs` from `origins`): `radius` times the depth (cones) or not (`cylinders`), times
/// contraction's scale at the world point where `contract` is set.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn footprints(
    offsets: &[u32],
    t: &[f32],
    origins: &[f32],
    dirs: &[f32],
    radii: &[f32],
    out: &mut [f32],
    rays: u32,
    cylinders: u32,
    contract: u32,
    inner: f32,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let radius = radii[r];
        for i in offsets[r] as usize..offsets[r + 1] as usize {
            let ti = t[i];
            let mut f = select(cylinders == 1, radius, radius * ti);
            if contract == 1 {
                let x = origins[3 * r] + ti * dirs[3 * r];
                let y = origins[3 * r + 1] + ti * dirs[3 * r + 1];
                let z = origins[3 * r + 2] + ti * dirs[3 * r + 2];
                let n = f32::max(f32::max(f32::abs(x), f32::abs(y)), f32::abs(z)) / inner;
                if n > 1.0 {
                    let s = (2.0f32 - 1.0f32 / n) / n;
                    f *= f32::exp(f32::ln(s * s / (n * n)) / 3.0f32);
                }
            }
            out[i] = f;
        }
    }
}

/// Each sample's level weights (`weights`: `n x levels`) from its footprint (or the
/// reference footprint where `has_footprints` is 0), and the encoding (`enc`: `n x levels x
/// 2`) scaled by them.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn weigh_levels(
    levels: &[u32],
    footprints: &[f32],
    weights: &mut [f32],
    enc: &mut [f32],
    n: u32,
    n_levels: u32,
    has_footprints: u32,
    reference: f32,
    to_unit: f32,
) {
    let idx = ABSOLUTE_POS;
    let nl = n_levels as usize;
    if idx < n as usize * nl {
        let s = idx / nl;
        let l = idx % nl;
        let sigma = select(
            has_footprints == 1,
            footprints[s % footprints.len()],
            reference,
        ) * to_unit;
        let w = level_weight(levels, l, sigma);
        weights[idx] = w;
        enc[2 * idx] *= w;
        enc[2 * idx + 1] *= w;
    }
}

/// `d_enc` (`n x levels x 2`) scaled by the level weights, in place: the backward of
/// [`weigh_levels`].
#[cube(launch_unchecked)]
fn scale_by_levels(weights: &[f32], d_enc: &mut [f32], count: u32) {
    let idx = ABSOLUTE_POS;
    if idx < count as usize {
        let w = weights[idx];
        d_enc[2 * idx] *= w;
        d_enc[2 * idx + 1] *= w;
    }
}

/// The footprints of a marched batch's samples: `rays` (the first `kept` of them kept,
/// their samples at CSR `offsets` with depths `t`, `n` in all), each ray's cone radius in
/// `radii`.
#[allow(clippy::too_many_arguments)]
pub fn sample_footprints(
    gpu: &Gpu,
    rays: &GpuRays,
    radii: &Handle,
    cylinders: bool,
    contract: Option<f32>,
    (offsets, t): (&Handle, &Handle),
    kept: usize,
    n: usize,
) -> Handle {
    let out = gpu.floats(n);
    if kept == 0 || n == 0 {
        return out;
    }
    let (count, dim) = grid(kept, GROUP);
    // SAFETY: `offsets` holds `kept + 1` slots ending at `n`, the length of `t` and `out`;
    // the rays' buffers hold `rays.len >= kept` rays; the kernel reads rays below `kept`.
    unsafe {
        footprints::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(offsets.clone(), kept + 1),
            BufferArg::from_raw_parts(t.clone(), n),
            BufferArg::from_raw_parts(rays.origins.clone(), 3 * rays.len),
            BufferArg::from_raw_parts(rays.dirs.clone(), 3 * rays.len),
            BufferArg::from_raw_parts(radii.clone(), rays.len),
            BufferArg::from_raw_parts(out.clone(), n),
            kept as u32,
            u32::from(cylinders),
            u32::from(contract.is_some()),
            contract.unwrap_or(1.0),
        );
    }
    out
}

/// An anti-aliased field's level weighting on the device.
pub struct LevelWeights {
    /// The footprint of samples that carry none (`Antialias::reference_footprint`).
    pub reference: f32,
    /// Half the side of the field's box: footprints in field units become unit-cube ones.
    pub bound: f32,
}

impl LevelWeights {
    /// Scales `enc` (`n` samples' encodings) by each sample's level weights, from
    /// `footprints` (`n`) or the reference footprint; returns the weights (`n x levels`)
    /// for the backward.
    pub fn forward(
        &self,
        gpu: &Gpu,
        grid_levels: &GpuHashGrid,
        footprints: Option<&Handle>,
        enc: &Handle,
        n: usize,
    ) -> Handle {
        let nl = grid_levels.n_levels;
        let weights = gpu.floats(n * nl);
        if n == 0 {
            return weights;
        }
        let none = gpu.floats(1);
        let (fp, fp_len) = footprints.map_or((&none, 1), |f| (f, n));
        let (count, dim) = grid(n * nl, GROUP);
        // SAFETY: `footprints` holds `n` floats (or one, unread), `weights` `n x levels`,
        // `enc` `n x levels x 2`, the level table four words a level; the kernel
        // bounds-checks its index against `n x levels`.
        unsafe {
            weigh_levels::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(grid_levels.levels.clone(), nl * 4),
                BufferArg::from_raw_parts(fp.clone(), fp_len),
                BufferArg::from_raw_parts(weights.clone(), n * nl),
                BufferArg::from_raw_parts(enc.clone(), n * nl * FEATURES),
                n as u32,
                nl as u32,
                u32::from(footprints.is_some()),
                self.reference,
                0.5 / self.bound,
            );
        }
        weights
    }

    /// The backward of [`forward`](Self::forward): `d_enc` scaled by `weights`, in place.
    pub fn backward(gpu: &Gpu, weights: &Handle, d_enc: &Handle, n: usize, levels: usize) {
        if n == 0 {
            return;
        }
        let (count, dim) = grid(n * levels, GROUP);
        // SAFETY: `weights` holds `n x levels` floats, `d_enc` twice as many.
        unsafe {
            scale_by_levels::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(weights.clone(), n * levels),
                BufferArg::from_raw_parts(d_enc.clone(), n * levels * FEATURES),
                (n * levels) as u32,
            );
        }
    }
}
