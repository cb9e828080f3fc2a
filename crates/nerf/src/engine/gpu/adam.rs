//! Adam on the GPU: `nn::adam`'s update over the whole parameter vector in one pass, one
//! thread per parameter, clearing the gradient behind it for the next step. The update is
//! queued behind a device-side count of the step's non-finite values (`finite`) and does
//! nothing where it is not zero, so the host need not wait for the count before queuing it. Hash-table
//! entries (before `lazy_end`) update lazily: an exact-zero gradient leaves the entry and
//! its moments alone, as the CPU's dirty-block path does, and a touched one takes the
//! tables' decay; the MLP weights after it take the weight decay. (The CPU skips whole
//! untouched blocks of MLP weights too; every MLP weight gets a gradient in a real step,
//! so the two agree there.)

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use crate::nn::adam::{AdamConfig, AdamStep, DirtyStep};

/// Threads per workgroup.
const GROUP: u32 = 256;

/// The constants of one update, in the order the kernel reads them.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
struct Update {
    scale: f32,
    table_decay: f32,
    weight_decay: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    lr_over_bc1: f32,
    inv_bc2: f32,
    lazy_end: u32,
    /// Parameters from here on (camera corrections) update densely, without weight
    /// decay, at their own rate.
    group_start: u32,
    group_lr_over_bc1: f32,
}

#[cube(launch_unchecked)]
fn adam_step(
    params: &mut [f32],
    m: &mut [f32],
    v: &mut [f32],
    grads: &mut [f32],
    nonfinite: &[u32],
    u: Update,
) {
    let i = ABSOLUTE_POS;
    if i < params.len() && nonfinite[0] == 0 {
        let p = params[i];
        let lazy = (i as u32) < u.lazy_end;
        let grouped = (i as u32) >= u.group_start;
        let raw = grads[i] * u.scale;
        let keep = lazy && raw == 0.0;
        let dense_decay = select(grouped, 0.0, u.weight_decay);
        let g = raw + select(lazy, u.table_decay, dense_decay) * p;
        let m_new = u.beta1 * m[i] + (1.0 - u.beta1) * g;
        let v_new = u.beta2 * v[i] + (1.0 - u.beta2) * g * g;
        let rate = select(grouped, u.group_lr_over_bc1, u.lr_over_bc1);
        let p_new = p - rate * m_new / (f32::sqrt(v_new * u.inv_bc2) + u.eps);
        m[i] = select(keep, m[i], m_new);
        v[i] = select(keep, v[i], v_new);
        params[i] = select(keep, p, p_new);
        grads[i] = 0.0;
    }
}

/// Applies `step` (from `Adam::begin_step`) to `n` parameters and their moments, reading
/// and clearing `grads`, unless the `u32` in `nonfinite` is not zero when the update runs
/// (then nothing is written). The group of `how` (if any) updates with `group_step`'s
/// rate (`Adam::step_at` of its learning rate).
#[allow(clippy::too_many_arguments)]
pub fn step(
    gpu: &Gpu,
    config: &AdamConfig,
    step: AdamStep,
    group_step: AdamStep,
    how: DirtyStep,
    n: usize,
    params: &Handle,
    m: &Handle,
    v: &Handle,
    grads: &Handle,
    nonfinite: &Handle,
) {
    if n == 0 {
        return;
    }
    let (lr_over_bc1, inv_bc2) = step.factors();
    let group_start = how.group.map_or(n, |(start, _)| start.min(n));
    let update = UpdateLaunch::new(
        how.scale,
        how.table_decay,
        how.weight_decay,
        config.beta1,
        config.beta2,
        config.eps,
        lr_over_bc1,
        inv_bc2,
        how.lazy_end.min(n) as u32,
        group_start as u32,
        group_step.factors().0,
    );
    // SAFETY: the four buffers hold `n` floats each; the kernel bounds-checks `i < n`.
    unsafe {
        adam_step::launch_unchecked(
            &gpu.client,
            CubeCount::Static((n as u32).div_ceil(GROUP), 1, 1),
            CubeDim::new_1d(GROUP),
            BufferArg::from_raw_parts(params.clone(), n),
            BufferArg::from_raw_parts(m.clone(), n),
            BufferArg::from_raw_parts(v.clone(), n),
            BufferArg::from_raw_parts(grads.clone(), n),
            BufferArg::from_raw_parts(nonfinite.clone(), 1),
            update,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::worst;
    use crate::nn::adam::Adam;
    use crate::nn::GradBuffer;
    use crate::rng::Rng;

    /// Three steps against the CPU's dirty-block Adam: a lazy region with untouched entries
    /// and whole untouched blocks (different ones each step) and decay on the touched
    /// ones, a dense region with weight decay, a group at its own rate. Parameters and both
    /// moments within 1e-6 relative, and the gradients cleared.
    #[test]
    fn adam_matches_the_cpu_dirty_block_update() {
        let Some(gpu) = crate::engine::gpu::device::test_gpu() else {
            return;
        };
        let (n, lazy_end) = (20_000usize, 12_000usize);
        let config = AdamConfig {
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-15,
        };
        let how = DirtyStep {
            scale: 1.0 / 4096.0,
            lazy_end,
            // Strong enough to move the touched entries as much as their gradients do.
            table_decay: 1e-3,
            weight_decay: 1e-6,
            // Camera corrections at the end: dense, no decay, their own rate.
            group: Some((n - 600, 3e-3)),
        };
        let mut rng = Rng::new(11);
        let mut params: Vec<f32> = (0..n).map(|_| rng.range(-0.5, 0.5)).collect();
        let mut cpu = Adam::new(config, n);
        let mut gpu_adam = Adam::new(config, n);
        let upload = |v: &[f32]| gpu.client.create_from_slice(f32::as_bytes(v));
        let (p, m, v) = (upload(&params), upload(&cpu.m), upload(&cpu.v));
        for round in 0..3 {
            let grads: Vec<f32> = (0..n)
                .map(|i| {
                    // Which entries go untouched changes from step to step, so a lazy
                    // skip (moments kept) differs from a dense update (moments decayed).
                    let block = 4096 * ((round + 1) % 3);
                    let untouched = i < lazy_end
                        && ((i + 3 * round) % 7 == 0 || (block..block + 4096).contains(&i));
                    if untouched {
                        0.0
                    } else {
                        rng.range(-3.0, 3.0) + round as f32
                    }
                })
                .collect();
            let mut buffer = GradBuffer::new(n);
            buffer.values.copy_from_slice(&grads);
            buffer.mark(0..n);
            cpu.step_dirty(&mut params, &mut buffer, 1e-2, how);
            let g = upload(&grads);
            let field_step = gpu_adam.begin_step(1e-2);
            step(
                &gpu,
                &config,
                field_step,
                gpu_adam.step_at(3e-3),
                how,
                n,
                &p,
                &m,
                &v,
                &g,
                &gpu.upload_u32(&[0]),
            );
            let read = |h: &Handle| {
                let bytes = gpu.client.read_one(h.clone()).expect("read back");
                f32::from_bytes(&bytes).to_vec()
            };
            for (name, got, want) in [
                ("params", read(&p), &params),
                ("m", read(&m), &cpu.m),
                ("v", read(&v), &cpu.v),
            ] {
                // Relative to 1 + |b|: Vulkan lets a GPU's division and square root be
                // off by a few ulp (NVIDIA's are), where lavapipe and the CPU round exactly.
                let worst = worst(&got, want);
                assert!(worst < 1e-5, "round {round}: {name} differs by {worst}");
            }
            assert!(read(&g).iter().all(|&x| x == 0.0), "gradients cleared");
        }
        // A step with a non-finite value counted writes nothing: parameters, moments and
        // gradients stay as they were.
        let read = |h: &Handle| {
            let bytes = gpu.client.read_one(h.clone()).expect("read back");
            f32::from_bytes(&bytes).to_vec()
        };
        let before = [read(&p), read(&m), read(&v)];
        let grads: Vec<f32> = (0..n).map(|_| rng.range(-3.0, 3.0)).collect();
        let g = upload(&grads);
        let refused = gpu_adam.begin_step(1e-2);
        step(
            &gpu,
            &config,
            refused,
            refused,
            how,
            n,
            &p,
            &m,
            &v,
            &g,
            &gpu.upload_u32(&[2]),
        );
        assert_eq!(
            [read(&p), read(&m), read(&v)],
            before,
            "a refused step wrote"
        );
        assert_eq!(read(&g), grads, "a refused step cleared the gradients");
    }
}
