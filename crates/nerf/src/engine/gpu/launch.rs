//! Small helpers every GPU module shares: launch grids past the 65535-workgroup limit of
//! one axis, and moving `f32` buffers to and from the device.

use std::future::Future;
use std::pin::Pin;

use cubecl::bytes::Bytes;
use cubecl::prelude::*;
use cubecl::server::{Handle, ServerError};

use super::device::Gpu;
use crate::error::{NerfError, Result};

/// Workgroups along x before a grid spills into y (Vulkan guarantees 65535 per axis).
const MAX_GROUPS_X: u32 = 32768;

/// Threads per workgroup of the fill kernel.
const FILL_GROUP: u32 = 256;

#[cube(launch_unchecked)]
fn fill_zero(v: &mut [u32]) {
    let i = ABSOLUTE_POS;
    if i < v.len() {
        v[i] = 0;
    }
}

/// `dst[start + i] += src[i]` for `i < n` (`add`), or `dst[i] = src[start + i]` (not).
#[cube(launch_unchecked)]
fn range_copy(src: &[f32], dst: &mut [f32], start: u32, n: u32, #[comptime] add: bool) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        if add {
            dst[start as usize + i] += src[i];
        } else {
            dst[i] = src[start as usize + i];
        }
    }
}

/// A one-dimensional launch of at least `threads` threads in workgroups of `group`.
/// `ABSOLUTE_POS` counts threads linearly across both axes; kernels bounds-check it, since
/// the last workgroup (and, past 32768 workgroups, the last row) runs over.
pub fn grid(threads: usize, group: u32) -> (CubeCount, CubeDim) {
    let groups = (threads as u64).div_ceil(group as u64).max(1);
    let x = groups.min(MAX_GROUPS_X as u64) as u32;
    let y = groups.div_ceil(x as u64) as u32;
    (CubeCount::Static(x, y, 1), CubeDim::new_1d(group))
}

impl Gpu {
    /// A device copy of `values`.
    pub fn upload(&self, values: &[f32]) -> Handle {
        if values.is_empty() {
            return self.client.empty(4);
        }
        self.client.create_from_slice(f32::as_bytes(values))
    }

    /// A device copy of `values`.
    pub fn upload_u32(&self, values: &[u32]) -> Handle {
        if values.is_empty() {
            return self.client.empty(4);
        }
        self.client.create_from_slice(u32::as_bytes(values))
    }

    /// An uninitialised device buffer of `n` floats (at least one, so a handle exists).
    pub fn floats(&self, n: usize) -> Handle {
        self.client.empty(n.max(1) * 4)
    }

    /// A device buffer of `n` zeros (filled on the device: nothing crosses the bus).
    pub fn zeros(&self, n: usize) -> Handle {
        self.zeros_u32(n)
    }

    /// A device buffer of `n` zero `u32`s (the bits of `0.0f32` too).
    pub fn zeros_u32(&self, n: usize) -> Handle {
        let n = n.max(1);
        let h = self.client.empty(n * 4);
        let (count, dim) = grid(n, FILL_GROUP);
        // SAFETY: `h` holds `n` words and the kernel bounds-checks its index against them.
        unsafe {
            fill_zero::launch_unchecked(
                &self.client,
                count,
                dim,
                BufferArg::from_raw_parts(h.clone(), n),
            );
        }
        h
    }

    /// The first `n` floats of `h`, read back (waits for the work that writes them).
    pub fn read(&self, h: &Handle, n: usize) -> Result<Vec<f32>> {
        let bytes = self
            .client
            .read_one(h.clone())
            .map_err(|e| NerfError::Device(format!("reading a buffer back failed: {e:?}")))?;
        let all = f32::from_bytes(&bytes);
        Ok(all[..n.min(all.len())].to_vec())
    }

    /// The first `n` floats of `h` and the `u32` in `count`, read back together (one wait
    /// for the device rather than two).
    pub fn read_with_count(&self, h: &Handle, n: usize, count: &Handle) -> Result<(Vec<f32>, u32)> {
        let buffers = self
            .client
            .read(vec![h.clone(), count.clone()])
            .map_err(|e| NerfError::Device(format!("reading buffers back failed: {e:?}")))?;
        let [values, count] = buffers.as_slice() else {
            return Err(NerfError::Device(
                "a read of two buffers returned another number".into(),
            ));
        };
        let values = f32::from_bytes(values);
        let count = u32::from_bytes(count).first().copied().unwrap_or(u32::MAX);
        Ok((values[..n.min(values.len())].to_vec(), count))
    }

    /// Floats `start..start + n` of `h` (which holds at least `start + n`), read back.
    pub fn read_range(&self, h: &Handle, start: usize, n: usize) -> Result<Vec<f32>> {
        if n == 0 {
            return Ok(Vec::new());
        }
        let part = self.floats(n);
        self.range_copy((h, start + n), (&part, n), start, n, false);
        self.read(&part, n)
    }

    /// Adds `values` into floats `start..start + values.len()` of `h` (which holds them).
    pub fn add_range(&self, h: &Handle, start: usize, values: &[f32]) {
        let n = values.len();
        if n == 0 {
            return;
        }
        let src = self.upload(values);
        self.range_copy((&src, n), (h, start + n), start, n, true);
    }

    /// [`range_copy`]'s launch over `n` values, `src` and `dst` with their lengths.
    fn range_copy(
        &self,
        (src, src_len): (&Handle, usize),
        (dst, dst_len): (&Handle, usize),
        start: usize,
        n: usize,
        add: bool,
    ) {
        let (count, dim) = grid(n, FILL_GROUP);
        // SAFETY: the callers give each buffer's length (the range's end at least), and
        // the kernel bounds-checks `i < n`.
        unsafe {
            range_copy::launch_unchecked(
                &self.client,
                count,
                dim,
                BufferArg::from_raw_parts(src.clone(), src_len),
                BufferArg::from_raw_parts(dst.clone(), dst_len),
                start as u32,
                n as u32,
                add,
            );
        }
    }

    /// The first `n` `u32`s of `h`, read back.
    pub fn read_u32(&self, h: &Handle, n: usize) -> Result<Vec<u32>> {
        self.read_u32_later(h, n).wait()
    }

    /// The first `n` `u32`s of `h`, on their way back: the copy is queued, and the queue
    /// sent to the device, now, so work queued after this call does not delay the copy,
    /// and the host can queue more before it waits ([`PendingRead::wait`]).
    pub fn read_u32_later(&self, h: &Handle, n: usize) -> PendingRead<'_> {
        PendingRead {
            bytes: Box::pin(self.client.read_async(vec![h.clone()])),
            n,
            _source: h.clone(),
        }
    }
}

/// `u32`s on their way back from the device: [`Gpu::read_u32_later`].
pub struct PendingRead<'a> {
    bytes: Pin<Box<dyn Future<Output = std::result::Result<Vec<Bytes>, ServerError>> + Send + 'a>>,
    n: usize,
    /// The buffer read, kept until its values are back (as a blocking read keeps it).
    _source: Handle,
}

impl PendingRead<'_> {
    /// Waits for the copy and returns the values.
    pub fn wait(self) -> Result<Vec<u32>> {
        let buffers = cubecl::future::block_on(self.bytes)
            .map_err(|e| NerfError::Device(format!("reading a buffer back failed: {e:?}")))?;
        let bytes = buffers
            .first()
            .ok_or_else(|| NerfError::Device("a read returned no buffer".into()))?;
        let all = u32::from_bytes(bytes);
        Ok(all[..self.n.min(all.len())].to_vec())
    }
}

#[cfg(test)]
mod tests {
    use crate::engine::gpu::device::test_gpu;

    /// A range read back is that range; a range added to changes that range alone.
    #[test]
    fn ranges_read_and_add_in_place() {
        let Some(gpu) = test_gpu() else { return };
        let values: Vec<f32> = (0..10).map(|i| i as f32).collect();
        let h = gpu.upload(&values);
        assert_eq!(
            gpu.read_range(&h, 3, 4).expect("read"),
            [3.0, 4.0, 5.0, 6.0]
        );
        assert!(gpu.read_range(&h, 9, 0).expect("read").is_empty());
        gpu.add_range(&h, 8, &[0.5, -1.0]);
        let mut want = values;
        want[8] += 0.5;
        want[9] -= 1.0;
        assert_eq!(gpu.read(&h, 10).expect("read"), want);
    }
}
