//! `cargo bench --bench kernels`: our fused kernels against the plain versions they replace,
//! measured in the same run (median of repeated runs) on one chunk of the paper's model
//! (64 rays x 192 samples = 12288 rows of 256).

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
}
