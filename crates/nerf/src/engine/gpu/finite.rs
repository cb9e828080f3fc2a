//! Counting non-finite values on the device, so a step that diverged is refused before the
//! optimiser writes it: the count stays on the device, where the optimiser reads it
//! (`adam`), and comes back as one `u32` rather than the whole gradient.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use crate::error::Result;

const GROUP: u32 = 256;
/// Values each thread checks.
const PER_THREAD: usize = 64;

#[cube(launch_unchecked)]
fn count_nonfinite_kernel(values: &[f32], count: &mut [Atomic<u32>], n: u32, per_thread: u32) {
    let first = ABSOLUTE_POS * per_thread as usize;
    // `n`, not the binding's length: a buffer may be longer than the values it holds.
    let end = usize::min(first + per_thread as usize, n as usize);
    let mut bad = 0u32;
    for i in first..end {
        // On the bits, so no fast-math compiler can assume it away: an all-ones exponent
        // is an infinity (zero mantissa) or a NaN.
        let magnitude = u32::reinterpret(values[i]) & 0x7fff_ffffu32;
        bad += select(magnitude >= 0x7f80_0000u32, 1u32, 0u32);
    }
    if bad > 0 {
        count[0].fetch_add(bad);
    }
}

/// How many of the first `n` floats of `values` are NaN or infinite.
pub fn count_nonfinite(gpu: &Gpu, values: &Handle, n: usize) -> Result<u32> {
    let count = gpu.upload_u32(&[0]);
    add_nonfinite(gpu, values, n, &count);
    Ok(gpu.read_u32(&count, 1)?[0])
}

/// Adds how many of the first `n` floats of `values` are NaN or infinite to the `u32` in
/// `count`, on the device.
pub fn add_nonfinite(gpu: &Gpu, values: &Handle, n: usize, count: &Handle) {
    if n > 0 {
        let (c, d) = grid(n.div_ceil(PER_THREAD), GROUP);
        // SAFETY: `values` holds `n` floats and `count` one `u32`; each thread reads only
        // its own range, clipped to `n`.
        unsafe {
            count_nonfinite_kernel::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(values.clone(), n),
                BufferArg::from_raw_parts(count.clone(), 1),
                n as u32,
                PER_THREAD as u32,
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_nan_and_infinities_only() {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        let mut v: Vec<f32> = (0..1000).map(|i| i as f32 * 1e30).collect();
        assert_eq!(
            count_nonfinite(&gpu, &gpu.upload(&v), v.len()).expect("count"),
            0
        );
        v[3] = f32::NAN;
        v[500] = f32::INFINITY;
        v[999] = f32::NEG_INFINITY;
        v[10] = f32::MAX;
        assert_eq!(
            count_nonfinite(&gpu, &gpu.upload(&v), v.len()).expect("count"),
            3
        );
        // Only the first n values count.
        assert_eq!(
            count_nonfinite(&gpu, &gpu.upload(&v), 500).expect("count"),
            1
        );
    }
}
