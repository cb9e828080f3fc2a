//! The stage contract: the typed values that flow between the stages of a radiance field,
//! and the shape every differentiable stage shares.
//!
//! ```text
//! camera / data ──RayBatch──▶ sampler / marcher ──PackedSamples──▶ Field ──FieldOutput──▶
//!   compositing (render::volume) ──RayOutput──▶ loss (render::loss) ──▶ value, d_rgb
//!   gradients flow back the same way: d_rgb ▶ (d_sigma, d_rgb per sample) ▶ Grads
//! ```
//!
//! Every differentiable stage has the same three operations, after tiny-cuda-nn's object
//! model:
//!
//! - `forward(params, input, ctx) -> output`: the output, with everything the backward
//!   needs kept in the explicit context `ctx`;
//! - `backward(params, ctx, d_output, grads)`: from that context and `dL/d output`, writes
//!   `dL/d input` (where the input is differentiable) and accumulates parameter gradients
//!   into `grads` (a [`Grads`] view of the model's gradient buffer);
//! - `infer(params, input, ctx) -> output`: the same output, keeping no context for a
//!   backward.
//!
//! Fields, the stage that varies, implement them as the [`Field`] trait. The fixed stages
//! are functions of the same shape, side by side in one file each: compositing
//! (`render::volume::composite_packed`, its context the field's output, and
//! `composite_packed_bwd`), the loss (`render::loss::squared_error`, value and gradient;
//! `LossBackward` carries the gradient on through compositing), and the encodings inside
//! the fields (`encode` / `encode_bwd`). Backward functions end in `_bwd`.
//!
//! The context is owned by the caller and reused from call to call (a thread's workspace),
//! so a training step allocates nothing once it has warmed up; outputs are borrowed from
//! it. A backward reads only the context it is handed, never "the last forward" of a
//! shared object. Sampling and marching are not differentiable (as in the paper and in
//! nerfacc): their outputs are inputs, never `d_input`s.
//!
//! Fields plug into the renderers through [`Field`]; the renderers and the marcher take a
//! field, never a concrete model. Engines (see `engine`) run whole steps over these stages.

pub mod finite;
pub mod values;

pub use values::{
    Appearance, FieldGrad, FieldInput, FieldOutput, PackedSamples, RayBatch, RayOutput,
    MEAN_APPEARANCE,
};

pub use crate::nn::Grads;

/// A radiance field: density and colour of samples at positions seen from directions.
///
/// Positions are in the field's own space (contracted for unbounded scenes); directions
/// are unit vectors. `params` is the field's own slice of the model's parameter vector.
pub trait Field: Sync {
    /// Activations kept by [`forward`](Self::forward) for [`backward`](Self::backward),
    /// plus scratch; one per thread, reused.
    type Context: Default + Send;

    fn num_params(&self) -> usize;

    /// Density (`n`, non-negative) and colour (`n x 3`, in [0, 1]) of the samples, keeping
    /// the activations in `ctx`.
    fn forward<'c>(
        &self,
        params: &[f32],
        input: FieldInput,
        ctx: &'c mut Self::Context,
    ) -> FieldOutput<'c>;

    /// Backward of the forward that filled `ctx`: accumulates parameter gradients into
    /// `grads`. Sample positions are not differentiated (sampling is not differentiable).
    fn backward(
        &self,
        params: &[f32],
        ctx: &mut Self::Context,
        d_output: FieldGrad,
        grads: &mut Grads,
    );

    /// The forward's output without a backward to come.
    fn infer<'c>(
        &self,
        params: &[f32],
        input: FieldInput,
        ctx: &'c mut Self::Context,
    ) -> FieldOutput<'c> {
        self.forward(params, input, ctx)
    }

    /// Inference for a renderer that needs colour only where a sample shows: the densities
    /// of every sample first, then `pick`, handed them, pushes onto its list (in increasing
    /// order) the samples that need a colour. The other samples' colour rows are zero, or
    /// their colours where a field has no cheaper way (this default colours every sample
    /// and never asks).
    fn infer_picked<'c>(
        &self,
        params: &[f32],
        input: FieldInput,
        ctx: &'c mut Self::Context,
        pick: &mut dyn FnMut(&[f32], &mut Vec<u32>),
    ) -> FieldOutput<'c> {
        let _ = pick;
        self.infer(params, input, ctx)
    }

    /// Densities alone at `positions` (`n x 3`) into `out` (`n`): occupancy refreshes and
    /// mesh grids need no colour.
    fn density(&self, params: &[f32], positions: &[f32], ctx: &mut Self::Context, out: &mut [f32]);
}
