//! The stage contract's field on the device: [`DeviceField`] is to the GPU engine what
//! `stage::Field` is to the CPU engine. A field's samples, parameters, activations and
//! gradients stay in device buffers; the renderer and the training steps reach a field only
//! through this trait, so a new field plugs into the GPU engine by implementing it (and its
//! kernels are tested against its CPU `Field` on the same inputs).

use cubecl::server::Handle;

use super::codes::SampleCodes;
use super::device::Gpu;
use super::space_time_grid::Moments;

/// A radiance field on the device: density and colour of a batch of samples, and the
/// backward of that.
pub trait DeviceField {
    /// What [`forward`](Self::forward) keeps for [`backward`](Self::backward).
    type Activations: DeviceOutput;
    /// What the backward hands back besides the parameters' gradients (the inputs'
    /// gradients a field can give, for camera refinement; `()` where none).
    type InputGradients;

    /// The length of the field's parameter vector (the model's, laid out as on the CPU).
    fn num_params(&self) -> usize;

    /// What the field reads besides positions and directions: the renderer makes only
    /// those inputs.
    fn needs(&self) -> FieldNeeds;

    /// Density (`n`, non-negative) and colour (`n x 3`, in [0, 1]) of `input`'s samples,
    /// keeping the activations.
    fn forward(&self, gpu: &Gpu, params: &Handle, input: &DeviceInput) -> Self::Activations;

    /// Backward of the forward that made `acts`: from `d_sigma` (`n`) and `d_rgb`
    /// (`n x 3`), adds every parameter's gradient into `grads`.
    fn backward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        grads: &Handle,
        acts: &Self::Activations,
        d_sigma: &Handle,
        d_rgb: &Handle,
    ) -> Self::InputGradients;

    /// Densities and colours for rendering, no backward to come (a field may take a
    /// faster path that keeps nothing).
    fn infer(&self, gpu: &Gpu, params: &Handle, input: &DeviceInput) -> (Handle, Handle) {
        let acts = self.forward(gpu, params, input);
        (acts.sigma().clone(), acts.rgb().clone())
    }

    /// Densities alone (`n`) at `n` world `positions` (`n x 3`) at `moments`, each with the
    /// reference footprint and the mean appearance: occupancy refreshes and meshes.
    fn density(
        &self,
        gpu: &Gpu,
        params: &Handle,
        positions: &Handle,
        moments: DeviceMoments,
        n: usize,
    ) -> Handle;
}

/// A forward's outputs, as its activations hold them.
pub trait DeviceOutput {
    /// Densities (`n`).
    fn sigma(&self) -> &Handle;
    /// Colours (`n x 3`).
    fn rgb(&self) -> &Handle;
}

/// What a field reads besides positions and directions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FieldNeeds {
    /// Each sample's appearance code (`RayBatch::appearance_of` its ray; else the mean).
    pub codes: bool,
    /// Each sample's footprint (from the batch's cone radii; else the reference one).
    pub footprints: bool,
    /// Each sample's moment (a moving field: the batch's `RayTimes`).
    pub moments: bool,
}

/// One batch of samples for a field, as `stage::FieldInput` on the host: world positions
/// and unit view directions (`n x 3` each), and what fields that need them read.
pub struct DeviceInput<'a> {
    pub positions: &'a Handle,
    pub dirs: &'a Handle,
    /// Each sample's appearance code, or one for all (fields with codes).
    pub codes: &'a SampleCodes,
    /// Each sample's footprint (anti-aliased fields; `None`: the reference footprint).
    pub footprints: Option<&'a Handle>,
    /// The diagonal of each sample's covariance (`n x 3`; fields with an integrated
    /// positional encoding; `None`: points).
    pub variances: Option<&'a Handle>,
    /// When the samples are, for a moving field (others ignore it).
    pub moments: DeviceMoments<'a>,
    pub n: usize,
}

/// When a batch's samples are, for a moving field: as the CPU field's `Moments`.
#[derive(Clone, Copy)]
pub enum DeviceMoments<'a> {
    /// Each its own (`n` floats).
    Each(&'a Handle),
    /// All at one moment.
    At(f32),
    /// Any: a moment drawn from each point (the occupancy grid's refreshes).
    Any,
}

impl<'a> DeviceMoments<'a> {
    /// Each sample's own moment where the step has them (a moving field's training
    /// samples), else one moment, which a still field does not read.
    pub fn each_if_any(times: Option<&'a Handle>) -> Self {
        times.map_or(DeviceMoments::At(0.0), DeviceMoments::Each)
    }

    /// The moments as the space-time kernels read them: a buffer (one a sample, or one
    /// for all; unread for `Any`) and how to read it.
    pub(super) fn times(&self, gpu: &Gpu) -> (Handle, Moments) {
        match *self {
            DeviceMoments::Each(t) => (t.clone(), Moments::Each),
            DeviceMoments::At(t) => (gpu.upload(&[t]), Moments::At),
            DeviceMoments::Any => (gpu.floats(1), Moments::Any),
        }
    }
}
