//! `cargo bench --bench kernels`: our hand-written kernels against the plain versions they
//! replace, measured in the same run (median of repeated runs): the fused ReLU backward on
//! one chunk of the paper's model (64 rays x 192 samples = 12288 rows of 256), the grouped
//! hash-grid encoding (eight samples at a time with AVX2), the dirty-block gradient update of
//! the fast model, Adam's loop in the CPU's widest vectors, the anti-aliased level
//! weights, and the fast field's network products in f32 against bfloat16 inputs.

use std::time::Instant;

use nerf::nn::activation::{relu_bwd_bias, relu_bwd_then_bias};

fn median_seconds(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[reps / 2]
}

fn main() {
    let (rows, cols) = (12288, 256);
    let h: Vec<f32> = (0..rows * cols)
        .map(|i| ((i * 7919) % 13) as f32 - 6.0)
        .map(|v| v.max(0.0))
        .collect();
    let dh: Vec<f32> = (0..rows * cols)
        .map(|i| ((i * 104729) % 17) as f32 * 0.1 - 0.8)
        .collect();
    let mut buf = dh.clone();
    let mut bias = vec![0.0f32; cols];
    let plain = median_seconds(21, || {
        buf.copy_from_slice(&dh);
        relu_bwd_then_bias(&mut buf, &h, cols, &mut bias);
    });
    let fused = median_seconds(21, || {
        buf.copy_from_slice(&dh);
        relu_bwd_bias(&mut buf, &h, cols, &mut bias);
    });
    println!(
        "ReLU backward + bias gradient, {rows}x{cols} (includes a copy of the input each run):"
    );
    println!(
        "  plain (conditional store, then column sums): {:8.3} ms",
        plain * 1e3
    );
    println!(
        "  fused (select and sum in one pass):          {:8.3} ms",
        fused * 1e3
    );
    println!("  speed-up: {:.2}x", plain / fused);
    for log2_table_size in [19, 15] {
        hash_grid_encode(log2_table_size);
    }
    for touched in [0.05, 0.25, 0.5, 1.0] {
        sparse_update(touched);
    }
    adam_widths();
    level_weights();
    network_products();
}

/// The fast field's network products over one chunk of 8192 samples (forward: the density
/// network 32x64, 64x16, the colour network 31x64, 64x64, 64x3; backward: each layer's
/// input and weight gradients), in `f32` against bfloat16 inputs with `f32` sums.
fn network_products() {
    use nerf::nn::linalg::{matmul_in, MatRef, Precision};
    let Some(bf16) = Precision::bf16() else {
        println!("\nnetwork products: this CPU has no AVX-512 BF16");
        return;
    };
    let n = 8192;
    let layers = [(32, 64), (64, 16), (31, 64), (64, 64), (64, 3)];
    let values = |len: usize| -> Vec<f32> {
        (0..len)
            .map(|i| ((i * 7919) % 13) as f32 * 0.1 - 0.6)
            .collect()
    };
    let inputs: Vec<Vec<f32>> = layers.iter().map(|&(k, _)| values(n * k)).collect();
    let outputs: Vec<Vec<f32>> = layers.iter().map(|&(_, m)| values(n * m)).collect();
    let weights: Vec<Vec<f32>> = layers.iter().map(|&(k, m)| values(k * m)).collect();
    let mut out = vec![0.0f32; n * 64];
    let mut grad = vec![0.0f32; 64 * 64];
    let mut time = |precision: Precision| {
        let forward = median_seconds(15, || {
            for (l, &(k, m)) in layers.iter().enumerate() {
                let (x, w) = (
                    MatRef::new(&inputs[l], n, k),
                    MatRef::new(&weights[l], k, m),
                );
                matmul_in(precision, &mut out, x, w, false);
            }
        });
        let backward = median_seconds(15, || {
            for (l, &(k, m)) in layers.iter().enumerate() {
                let (x, w) = (
                    MatRef::new(&inputs[l], n, k),
                    MatRef::new(&weights[l], k, m),
                );
                let dy = MatRef::new(&outputs[l], n, m);
                matmul_in(precision, &mut grad, x.t(), dy, true);
                matmul_in(precision, &mut out, dy, w.t(), false);
            }
        });
        (forward, backward)
    };
    let (f32_fwd, f32_bwd) = time(Precision::F32);
    let (bf_fwd, bf_bwd) = time(bf16);
    println!(
        "\nthe fast field's network products, {n} samples, one thread (f32 / bfloat16 inputs):"
    );
    println!(
        "  forward:  {:8.3} / {:8.3} ms, {:.2}x",
        f32_fwd * 1e3,
        bf_fwd * 1e3,
        f32_fwd / bf_fwd
    );
    println!(
        "  backward: {:8.3} / {:8.3} ms, {:.2}x",
        f32_bwd * 1e3,
        bf_bwd * 1e3,
        f32_bwd / bf_bwd
    );
}

/// Adam's loop in the baseline's vectors against the widest the CPU has, on one segment of
/// the gradient buffer (the unit a thread updates), in cache and out of it.
fn adam_widths() {
    use nerf::nn::adam::{update_slices, update_slices_in, Adam, AdamConfig, Rule, Slices};
    use nerf::simd::Width;
    for n in [1 << 16, 1 << 23] {
        let mut p = vec![0.01f32; n];
        let g: Vec<f32> = (0..n).map(|i| ((i * 7919) % 13) as f32 * 1e-3).collect();
        let (mut m, mut v) = (vec![0.0f32; n], vec![0.0f32; n]);
        let mut adam = Adam::new(AdamConfig::default(), 1);
        let step = adam.begin_step(1e-3);
        let rule = Rule {
            lazy: true,
            ..Rule::default()
        };
        let mut time = |update: fn(&AdamConfig, _, Slices, Rule)| {
            median_seconds(15, || {
                let s = Slices {
                    params: &mut p,
                    grads: &g,
                    m: &mut m,
                    v: &mut v,
                };
                update(&AdamConfig::default(), step, s, rule);
            })
        };
        let baseline = time(|c, st, s, r| update_slices_in(Width::baseline(), c, st, s, r));
        let widest = time(update_slices);
        println!("\nAdam update of {n} parameters, one thread:");
        println!(
            "  baseline vectors (SSE2 on x86-64): {:8.3} ms",
            baseline * 1e3
        );
        println!(
            "  widest the CPU has:                {:8.3} ms",
            widest * 1e3
        );
        println!("  speed-up: {:.2}x", baseline / widest);
    }
}

/// The anti-aliased field's level weights of 8192 samples x 16 levels: the library's erf
/// (a call to `exp` per value) against the branch-free one the field uses, which vectorises.
fn level_weights() {
    use nerf::math::{erf, erf_of_inv_sqrt};
    let (n, levels) = (8192usize, 16usize);
    let sigmas: Vec<f32> = (0..n).map(|i| 1e-4 + (i % 97) as f32 * 5e-5).collect();
    let factors: Vec<f32> = (0..levels)
        .map(|l| 8.0 * (16.0 * 1.38f32.powi(l as i32)).powi(2))
        .collect();
    let mut out = vec![0.0f32; n * levels];
    // Generic, so each weight inlines into its loop as it does in the field.
    fn fill(out: &mut [f32], sigmas: &[f32], factors: &[f32], weight: impl Fn(f32) -> f32) {
        for (row, s) in out.chunks_exact_mut(factors.len()).zip(sigmas) {
            for (w, f) in row.iter_mut().zip(factors) {
                *w = weight(s * s * f);
            }
        }
        std::hint::black_box(out);
    }
    let library = median_seconds(21, || {
        fill(&mut out, &sigmas, &factors, |x| {
            if x <= 0.0 {
                1.0
            } else {
                erf(x.sqrt().recip())
            }
        })
    });
    let branch_free = median_seconds(21, || fill(&mut out, &sigmas, &factors, erf_of_inv_sqrt));
    println!("\nanti-aliasing level weights, {n} samples x {levels} levels:");
    println!("  library erf:     {:8.3} ms", library * 1e3);
    println!("  branch-free erf: {:8.3} ms", branch_free * 1e3);
    println!("  speed-up: {:.2}x", library / branch_free);
}

/// The hash-grid encoding with its gathers grouped and prefetched, against the plain loop,
/// and eight samples at a time (AVX2, where present) against one at a time, on 65536 points spread along rays through the default grid with
/// `2^log2_table_size` entries per level (19: the default, the fine levels far larger than
/// the caches; 15: the tests' and the small scenes', every level in the cache).
fn hash_grid_encode(log2_table_size: u32) {
    use nerf::encoding::{HashGrid, HashGridConfig};
    use nerf::nn::ParamLayout;
    let mut layout = ParamLayout::default();
    let config = HashGridConfig {
        log2_table_size,
        ..HashGridConfig::default()
    };
    let grid = HashGrid::new(config, "hash.", &mut layout);
    let params: Vec<f32> = (0..layout.total)
        .map(|i| ((i * 2654435761usize) % 1000) as f32 * 1e-6)
        .collect();
    // 1024 rays of 64 consecutive samples, as the marcher produces them.
    let mut pts = Vec::with_capacity(65536 * 3);
    for r in 0..1024u32 {
        let o = [
            (r.wrapping_mul(7919) % 1000) as f32 / 1000.0,
            (r.wrapping_mul(104729) % 1000) as f32 / 1000.0,
            0.1,
        ];
        for s in 0..64 {
            let t = s as f32 * 0.0025;
            pts.extend_from_slice(&[o[0] * 0.8 + 0.1, o[1] * 0.8 + 0.1, o[2] + t]);
        }
    }
    // In batches of the fast model's 8192 samples, as training calls it.
    let batch = 8192;
    let mut out = vec![0.0f32; batch * grid.dims()];
    let mut time = |encode: &dyn Fn(&[f32], &mut [f32])| {
        median_seconds(11, || {
            for p in pts.chunks(3 * batch) {
                encode(p, &mut out);
            }
        })
    };
    let plain = time(&|p, o| grid.encode_reference(&params, p, o));
    let scalar = time(&|p, o| grid.encode_scalar(&params, p, o));
    let grouped = time(&|p, o| grid.encode(&params, p, o));
    println!(
        "\nhash-grid encoding, 65536 points in batches of {batch}, 16 levels, 2^{log2_table_size} entries (one thread):"
    );
    println!("  plain loop:                     {:8.3} ms", plain * 1e3);
    println!("  grouped, one sample at a time: {:8.3} ms", scalar * 1e3);
    println!("  grouped, 8 samples at a time:  {:8.3} ms", grouped * 1e3);
    println!(
        "  speed-up: {:.2}x over the plain loop, {:.2}x from the AVX2 loops",
        plain / grouped,
        scalar / grouped
    );
}

/// Reducing two threads' gradients and applying Adam over the dirty blocks only, against
/// the same over the whole parameter vector (both in parallel over segments), for the
/// default fast model's size and a given fraction of blocks touched.
fn sparse_update(touched: f64) {
    use nerf::nn::adam::{update_slices, Adam, AdamConfig, DirtyStep, Rule, Slices};
    use nerf::nn::grads::{GradBuffer, BLOCK, SEGMENT};
    use rayon::prelude::*;
    let n = 12_213_148;
    let mut params = vec![0.01f32; n];
    let mut adam = Adam::new(AdamConfig::default(), n);
    let blocks = n / BLOCK;
    let stride = (1.0 / touched).round().max(1.0) as usize;
    let fill = |g: &mut GradBuffer| {
        for b in (0..blocks).step_by(stride) {
            g.add_pair(b * BLOCK, [1e-3, -1e-3]);
        }
    };
    let mut bufs = [GradBuffer::new(n), GradBuffer::new(n)];
    let sparse = median_seconds(7, || {
        bufs.iter_mut().for_each(fill);
        GradBuffer::reduce_into_first(&mut bufs);
        let how = DirtyStep {
            scale: 1.0,
            lazy_end: n,
            table_decay: 0.0,
            weight_decay: 0.0,
            group: None,
        };
        adam.step_dirty(&mut params, &mut bufs[0], 1e-3, how);
    });
    let mut dense_a = vec![0.0f32; n];
    let mut dense_b = vec![0.0f32; n];
    let dense = median_seconds(7, || {
        for b in (0..blocks).step_by(stride) {
            dense_a[b * BLOCK] += 1e-3;
            dense_b[b * BLOCK] += 1e-3;
        }
        dense_a
            .par_iter_mut()
            .zip(dense_b.par_iter_mut())
            .for_each(|(a, b)| *a += std::mem::take(b));
        let step = adam.begin_step(1e-3);
        let config = adam.config;
        let Adam { m, v, .. } = &mut adam;
        params
            .par_chunks_mut(SEGMENT)
            .zip(m.par_chunks_mut(SEGMENT))
            .zip(v.par_chunks_mut(SEGMENT))
            .zip(dense_a.par_chunks_mut(SEGMENT))
            .for_each(|(((p, m), v), g)| {
                let s = Slices {
                    params: p,
                    grads: g,
                    m,
                    v,
                };
                update_slices(
                    &config,
                    step,
                    s,
                    Rule {
                        lazy: true,
                        ..Rule::default()
                    },
                );
                g.fill(0.0);
            });
    });
    println!(
        "\ngradient reduction (2 threads) + Adam + clearing, {n} parameters, {:.0}% of blocks touched:",
        100.0 * touched
    );
    println!("  whole vector:                   {:8.3} ms", dense * 1e3);
    println!("  dirty blocks only:              {:8.3} ms", sparse * 1e3);
    println!("  speed-up: {:.2}x", dense / sparse);
}
