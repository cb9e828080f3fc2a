//! The values passed between stages, struct-of-arrays, with their shapes. `[f32; 3]`
//! vectors are laid out exactly as flat `n x 3` buffers (`as_flattened`), the form a GPU
//! kernel reads.

use crate::camera::Ray;

/// A batch of `n` rays: what a camera (or the training-pixel sampler) hands the sampler.
///
/// Example: one ray from `(0, -4, 0)` looking along `+y` over a white background,
/// between depths 2 and 6: `origins = [[0, -4, 0]]`, `dirs = [[0, 1, 0]]`,
/// `view_dirs = [[0, 1, 0]]`, `backgrounds = [[1, 1, 1]]`, `near = 2`, `far = 6`.
#[derive(Clone, Debug, Default)]
pub struct RayBatch {
    /// `n x 3`: origins in ray space (NDC for forward-facing LLFF scenes, else world).
    pub origins: Vec<[f32; 3]>,
    /// `n x 3`: directions in ray space, unnormalised (depth `t` runs along them: for a
    /// pinhole camera, `t` is the depth along the optical axis).
    pub dirs: Vec<[f32; 3]>,
    /// `n x 3`: the world directions colour is conditioned on (unnormalised). Equal to
    /// `dirs` in world space; NDC rays march along warped directions but are seen from
    /// their world ones, as in the paper's code.
    pub view_dirs: Vec<[f32; 3]>,
    /// `n x 3`: the colour behind each ray.
    pub backgrounds: Vec<[f32; 3]>,
    /// `n`: where each ray came from: `view << 32 | pixel` for training rays, the ray's
    /// index in its image (or list) when rendering.
    pub pixels: Vec<u64>,
    /// `n`, or empty (point rays: no footprint known): the pixel's footprint radius, the
    /// standard deviation of a disc as wide as the pixel (mip-NeRF's `2 / sqrt(12)` of
    /// its width). Per unit of metric distance along the ray for world rays (cones), or
    /// the same at every depth where [`cylinders`](Self::cylinders) is set (NDC rays: a
    /// pixel covers the same NDC `x, y` at any depth). See [`crate::camera::footprint`].
    pub radii: Vec<f32>,
    /// `radii` are absolute (NDC), not per unit distance.
    pub cylinders: bool,
    /// Bounds of `t` along `dirs`, shared by the batch (see `Dataset::near`).
    pub near: f32,
    pub far: f32,
    /// Which learned per-photo appearance colours the batch (fields with appearance
    /// codes, `--appearance`; others ignore it).
    pub appearance: Appearance,
    /// `n`, or empty (a still scene, or its field's own moment): the moment in [0, 1] each
    /// ray sees in a moving scene. Fields of space and time read it; others ignore it.
    pub times: Vec<f32>,
}

/// Which per-photo appearance code (exposure, white balance: `--appearance`) a batch of
/// rays is coloured with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Appearance {
    /// The mean of the training photos' codes: what eval and render use by default.
    #[default]
    Mean,
    /// Each ray its own photo's, from `pixels` (`view << 32 | pixel`): training rays.
    PerView,
    /// Training photo `i`'s (`--appearance-of`).
    Of(u32),
}

/// A sample's appearance index meaning "the mean code".
pub const MEAN_APPEARANCE: u32 = u32::MAX;

impl RayBatch {
    /// The appearance index of ray `r`'s samples (a training photo, or [`MEAN_APPEARANCE`]).
    pub fn appearance_of(&self, r: usize) -> u32 {
        match self.appearance {
            Appearance::Mean => MEAN_APPEARANCE,
            Appearance::PerView => (self.pixels[r] >> 32) as u32,
            Appearance::Of(i) => i,
        }
    }
}

impl RayBatch {
    /// An empty batch between `near` and `far`.
    pub fn new(near: f32, far: f32) -> Self {
        RayBatch {
            near,
            far,
            ..RayBatch::default()
        }
    }

    pub fn len(&self) -> usize {
        self.origins.len()
    }
    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    /// Empties the batch, keeping its buffers and bounds.
    pub fn clear(&mut self) {
        self.origins.clear();
        self.dirs.clear();
        self.view_dirs.clear();
        self.backgrounds.clear();
        self.pixels.clear();
        self.radii.clear();
        self.times.clear();
    }

    /// Appends a ray already in ray space, seen from `view_dir`.
    pub fn push(&mut self, ray: Ray, view_dir: [f32; 3], background: [f32; 3], pixel: u64) {
        self.origins.push(ray.origin);
        self.dirs.push(ray.dir);
        self.view_dirs.push(view_dir);
        self.backgrounds.push(background);
        self.pixels.push(pixel);
    }

    /// [`push`](Self::push) with the pixel's footprint radius (see [`radii`](Self::radii)):
    /// a batch holds footprints for all its rays or for none.
    pub fn push_with_radius(
        &mut self,
        ray: Ray,
        view_dir: [f32; 3],
        background: [f32; 3],
        pixel: u64,
        radius: f32,
    ) {
        debug_assert_eq!(self.radii.len(), self.origins.len());
        self.push(ray, view_dir, background, pixel);
        self.radii.push(radius);
    }

    /// Ray `r`'s footprint radius at metric distance `s` along it (0: no footprints).
    #[inline]
    pub fn radius_at(&self, r: usize, s: f32) -> f32 {
        match self.radii.get(r) {
            None => 0.0,
            Some(&radius) if self.cylinders => radius,
            Some(&radius) => radius * s,
        }
    }

    /// Appends `other`'s rays (with their footprints and moments, which both batches
    /// hold or neither); the bounds and appearance stay this batch's.
    pub fn extend(&mut self, other: &RayBatch) {
        self.origins.extend_from_slice(&other.origins);
        self.dirs.extend_from_slice(&other.dirs);
        self.view_dirs.extend_from_slice(&other.view_dirs);
        self.backgrounds.extend_from_slice(&other.backgrounds);
        self.pixels.extend_from_slice(&other.pixels);
        self.radii.extend_from_slice(&other.radii);
        self.times.extend_from_slice(&other.times);
    }

    /// Rays `range` of this batch as a new batch (for tests and chunked callers).
    pub fn slice(&self, range: std::ops::Range<usize>) -> RayBatch {
        RayBatch {
            origins: self.origins[range.clone()].to_vec(),
            dirs: self.dirs[range.clone()].to_vec(),
            view_dirs: self.view_dirs[range.clone()].to_vec(),
            backgrounds: self.backgrounds[range.clone()].to_vec(),
            pixels: self.pixels[range.clone()].to_vec(),
            radii: self
                .radii
                .get(range.clone())
                .map(<[f32]>::to_vec)
                .unwrap_or_default(),
            cylinders: self.cylinders,
            near: self.near,
            far: self.far,
            appearance: self.appearance,
            times: self
                .times
                .get(range)
                .map(<[f32]>::to_vec)
                .unwrap_or_default(),
        }
    }
}

/// Samples of many rays packed one after another (CSR, as nerfacc packs them): the samples
/// of ray `r` are `offsets[r]..offsets[r + 1]`. Rays may hold any number of samples,
/// including none.
#[derive(Clone, Debug, Default)]
pub struct PackedSamples {
    /// `rays + 1` offsets into the per-sample arrays, starting at 0.
    pub offsets: Vec<usize>,
    /// `n`: depth of each sample along its ray's (unit, for marched rays) direction.
    pub t: Vec<f32>,
    /// `n`: length of the ray segment each sample stands for (compositing's `delta`).
    pub dt: Vec<f32>,
    /// `n x 3`: where the field is evaluated (field space: contracted where the scene is).
    pub positions: Vec<[f32; 3]>,
    /// `n / samples_per_dir x 3`: unit view directions, each shared by `samples_per_dir`
    /// consecutive samples (1: one per sample; the paper's sampler gives every sample of a
    /// ray one direction).
    pub dirs: Vec<[f32; 3]>,
    pub samples_per_dir: usize,
    /// `n` appearance indices (see [`RayBatch::appearance_of`]), or empty: the mean code
    /// for every sample. Only fields with appearance codes read them.
    pub appearance: Vec<u32>,
    /// `n` footprints, or empty (see [`FieldInput::footprints`]).
    pub footprints: Vec<f32>,
    /// `n x 3` covariance diagonals, or empty (see [`FieldInput::variances`]).
    pub variances: Vec<f32>,
    /// `n` moments, or empty (see [`FieldInput::times`]).
    pub times: Vec<f32>,
}

impl PackedSamples {
    pub fn rays(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }
    pub fn len(&self) -> usize {
        self.t.len()
    }
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }
    /// The samples of ray `r`.
    pub fn ray(&self, r: usize) -> std::ops::Range<usize> {
        self.offsets[r]..self.offsets[r + 1]
    }

    /// Empties the batch (keeping its buffers) for samples with one direction each.
    pub fn clear(&mut self) {
        self.offsets.clear();
        self.offsets.push(0);
        self.t.clear();
        self.dt.clear();
        self.positions.clear();
        self.dirs.clear();
        self.samples_per_dir = 1;
        self.appearance.clear();
        self.footprints.clear();
        self.variances.clear();
        self.times.clear();
    }

    /// Closes the current ray (its samples are those pushed since the last close).
    pub fn end_ray(&mut self) {
        self.offsets.push(self.t.len());
    }

    /// What the field reads.
    pub fn field_input(&self) -> FieldInput<'_> {
        FieldInput {
            positions: self.positions.as_flattened(),
            dirs: self.dirs.as_flattened(),
            samples_per_dir: self.samples_per_dir.max(1),
            appearance: &self.appearance,
            footprints: &self.footprints,
            variances: &self.variances,
            times: &self.times,
        }
    }
}

/// A field's input: `n` sample positions and their view directions.
#[derive(Clone, Copy, Debug)]
pub struct FieldInput<'a> {
    /// `n x 3`, in the field's space.
    pub positions: &'a [f32],
    /// `n / samples_per_dir x 3`, unit length.
    pub dirs: &'a [f32],
    /// Consecutive samples that share one direction (`n` must be a multiple of it).
    pub samples_per_dir: usize,
    /// `n` appearance indices, or empty (the mean code); see [`PackedSamples::appearance`].
    pub appearance: &'a [u32],
    /// `n` footprints, or empty: the radius (standard deviation, in field units) of the
    /// region of space each sample stands for, the pixel's cone at its depth. Anti-aliased
    /// fields read no detail finer than it; others ignore it. Empty: the field's own
    /// reference footprint (occupancy refreshes, meshes).
    pub footprints: &'a [f32],
    /// `n x 3`, or empty: the diagonal of the covariance of the conical frustum each sample
    /// stands for (mip-NeRF; the positions are its means). Fields with an integrated
    /// positional encoding read them; others ignore them.
    pub variances: &'a [f32],
    /// `n` moments in [0, 1], or empty: when in a moving scene each sample is seen. Fields
    /// of space and time read them (empty: the field's own moment); others ignore them.
    pub times: &'a [f32],
}

impl FieldInput<'_> {
    pub fn len(&self) -> usize {
        self.positions.len() / 3
    }
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// A field's output, borrowed from its context.
#[derive(Clone, Copy, Debug)]
pub struct FieldOutput<'a> {
    /// `n`: volume density, non-negative.
    pub sigma: &'a [f32],
    /// `n x 3`: colour in [0, 1].
    pub rgb: &'a [f32],
}

/// `dL/d output` of a field.
#[derive(Clone, Copy, Debug)]
pub struct FieldGrad<'a> {
    /// `n`
    pub d_sigma: &'a [f32],
    /// `n x 3`
    pub d_rgb: &'a [f32],
}

/// What one ray renders to.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayOutput {
    /// Colour composited over the ray's background.
    pub rgb: [f32; 3],
    /// Expected depth `sum w_i t_i` along the ray's camera direction (0 where empty).
    pub depth: f32,
    /// `sum w_i`.
    pub opacity: f32,
}
