//! Activations next to their derivatives, over flat row-major buffers.

/// `x = max(x, 0)` in place.
pub fn relu(x: &mut [f32]) {
    x.iter_mut().for_each(|v| *v = v.max(0.0));
}

/// ReLU backward fused with the bias gradient of the same layer: `dz = dh * (h > 0)` in place
/// (`h` is the layer's post-ReLU output, `cols` wide) and `d_bias += column sums of dz`, in
/// one pass over memory. The mask is a select, not a conditional store, so it vectorises;
/// `cargo bench --bench kernels` compares it with [`relu_bwd_then_bias`].
pub fn relu_bwd_bias(dh: &mut [f32], h: &[f32], cols: usize, d_bias: &mut [f32]) {
    for (drow, hrow) in dh.chunks_exact_mut(cols).zip(h.chunks_exact(cols)) {
        for ((d, &y), b) in drow.iter_mut().zip(hrow).zip(d_bias.iter_mut()) {
            *d = if y > 0.0 { *d } else { 0.0 };
            *b += *d;
        }
    }
}

/// The plain two-pass version of [`relu_bwd_bias`], kept as its reference.
pub fn relu_bwd_then_bias(dh: &mut [f32], h: &[f32], cols: usize, d_bias: &mut [f32]) {
    for (d, &y) in dh.iter_mut().zip(h) {
        if y <= 0.0 {
            *d = 0.0;
        }
    }
    col_sum_into(dh, cols, d_bias);
}

/// `out += column sums of m` (`m` is `rows x cols`).
pub fn col_sum_into(m: &[f32], cols: usize, out: &mut [f32]) {
    for row in m.chunks_exact(cols) {
        for (o, v) in out.iter_mut().zip(row) {
            *o += v;
        }
    }
}

/// `1 / (1 + exp(-x))`; its derivative is `y (1 - y)` of the output `y`.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn fused_relu_backward_matches_the_plain_one() {
        let (rows, cols) = (37, 19);
        let mut rng = Rng::new(8);
        let mut h: Vec<f32> = (0..rows * cols).map(|_| rng.range(-1.0, 1.0)).collect();
        relu(&mut h);
        assert!(h.iter().all(|&v| v >= 0.0) && h.contains(&0.0));
        let dh: Vec<f32> = (0..rows * cols).map(|_| rng.range(-1.0, 1.0)).collect();
        let (mut a, mut b) = (dh.clone(), dh);
        let (mut ga, mut gb) = (vec![0.5; cols], vec![0.5; cols]);
        relu_bwd_bias(&mut a, &h, cols, &mut ga);
        relu_bwd_then_bias(&mut b, &h, cols, &mut gb);
        assert_eq!(a, b);
        for (x, y) in ga.iter().zip(&gb) {
            assert!((x - y).abs() < 1e-5);
        }
        assert!(a.iter().zip(&h).all(|(d, y)| *y > 0.0 || *d == 0.0));
    }

    #[test]
    fn sigmoid_derivative_from_output() {
        let x = 0.3f32;
        let y = sigmoid(x);
        let fd = (sigmoid(x + 1e-3) - sigmoid(x - 1e-3)) / 2e-3;
        assert!((fd - y * (1.0 - y)).abs() < 1e-4);
    }
}
