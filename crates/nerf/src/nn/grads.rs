//! A gradient buffer that remembers which blocks a step wrote.
//!
//! A hash-grid step touches a part of its tables (a few hundred thousand of 16 million
//! values at the default sizes), yet a dense buffer would have to be summed across threads,
//! fed to Adam and zeroed in full every step. Writes mark their 64-value block dirty, and
//! reduction, the optimiser and clearing visit only dirty blocks.

use rayon::prelude::*;

/// Values per dirty flag.
pub const BLOCK: usize = 64;

/// Values per unit of parallel work in [`GradBuffer::reduce_into_first`].
pub const SEGMENT: usize = 1 << 16;

/// A piece of a gradient buffer: its values and the dirty flags of their blocks.
pub struct Segment<'a> {
    pub values: &'a mut [f32],
    pub dirty: &'a mut [bool],
}

/// 1 for NaN and infinities (exponent all ones), else 0: an OR-reduction of it vectorises,
/// where a running `all(is_finite)` or a float sum would not.
#[inline(always)]
fn not_finite(x: f32) -> u32 {
    ((x.to_bits() & 0x7f80_0000) == 0x7f80_0000) as u32
}

impl Segment<'_> {
    /// Whether more than an eighth of the blocks are dirty. Then one sweep over the whole
    /// segment is cheaper than visiting blocks one by one (`cargo bench --bench kernels`
    /// measures both), and gives the same result: clean values are zero.
    fn mostly_dirty(&self) -> bool {
        8 * self.dirty.iter().filter(|&&d| d).count() > self.dirty.len()
    }

    fn block(&self, b: usize) -> std::ops::Range<usize> {
        b * BLOCK..((b + 1) * BLOCK).min(self.values.len())
    }

    /// `self += other` over `other`'s dirty blocks; zeroes and forgets them in `other`.
    /// When it sweeps the whole segment it also returns whether every sum is finite,
    /// saving a pass.
    fn take_from(&mut self, other: &mut Segment) -> Option<bool> {
        if other.mostly_dirty() {
            let mut bad = 0u32;
            for (a, o) in self.values.iter_mut().zip(other.values.iter_mut()) {
                *a += *o;
                *o = 0.0;
                bad |= not_finite(*a);
            }
            for (d, o) in self.dirty.iter_mut().zip(other.dirty.iter_mut()) {
                *d |= std::mem::take(o);
            }
            return Some(bad == 0);
        }
        for b in 0..self.dirty.len() {
            if std::mem::take(&mut other.dirty[b]) {
                let r = self.block(b);
                for (a, o) in self.values[r.clone()].iter_mut().zip(&mut other.values[r]) {
                    *a += *o;
                    *o = 0.0;
                }
                self.dirty[b] = true;
            }
        }
        None
    }

    fn all_finite(&self) -> bool {
        let bad = |v: &[f32]| v.iter().fold(0, |acc, &g| acc | not_finite(g));
        if self.mostly_dirty() {
            return bad(self.values) == 0;
        }
        (0..self.dirty.len())
            .filter(|&b| self.dirty[b])
            .all(|b| bad(&self.values[self.block(b)]) == 0)
    }

    /// Calls `f` with each run of consecutive dirty blocks (its in-segment range and its
    /// values, which `f` may scale in place), then zeroes and forgets them. A mostly dirty
    /// segment is passed whole, clean blocks (all zeros) included.
    pub fn drain_dirty(&mut self, mut f: impl FnMut(std::ops::Range<usize>, &mut [f32])) {
        if self.mostly_dirty() {
            f(0..self.values.len(), self.values);
            self.values.fill(0.0);
            self.dirty.fill(false);
            return;
        }
        let mut b = 0;
        while b < self.dirty.len() {
            if !self.dirty[b] {
                b += 1;
                continue;
            }
            let first = b;
            while b < self.dirty.len() && self.dirty[b] {
                self.dirty[b] = false;
                b += 1;
            }
            let r = first * BLOCK..(b * BLOCK).min(self.values.len());
            f(r.clone(), &mut self.values[r.clone()]);
            self.values[r].fill(0.0);
        }
    }
}

/// A stage's view of a [`GradBuffer`]: the values of one parameter range (indices are
/// relative to its start) with the dirty flags of the whole buffer, so a stage accumulates
/// into its own parameters wherever they sit in the model's vector.
pub struct Grads<'a> {
    values: &'a mut [f32],
    dirty: &'a mut [bool],
    base: usize,
}

impl Grads<'_> {
    pub fn len(&self) -> usize {
        self.values.len()
    }
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// `values[at] += g[0]; values[at + 1] += g[1]`, marking the block, for an even
    /// `base + at` (a pair never straddles a block).
    #[inline(always)]
    pub fn add_pair(&mut self, at: usize, g: [f32; 2]) {
        debug_assert!((self.base + at).is_multiple_of(2));
        self.values[at] += g[0];
        self.values[at + 1] += g[1];
        self.dirty[(self.base + at) / BLOCK] = true;
    }

    /// Marks `range` (relative) written.
    pub fn mark(&mut self, range: std::ops::Range<usize>) {
        if range.is_empty() {
            return;
        }
        let last = (self.base + range.end - 1) / BLOCK;
        self.dirty[(self.base + range.start) / BLOCK..=last].fill(true);
    }

    /// The values, for a stage that writes a part it marks with [`mark`](Self::mark).
    pub fn values_mut(&mut self) -> &mut [f32] {
        self.values
    }

    /// All values, marked written (for stages whose every parameter gets a gradient).
    pub fn dense(&mut self) -> &mut [f32] {
        self.mark(0..self.values.len());
        self.values
    }
}

#[derive(Clone, Debug)]
pub struct GradBuffer {
    pub values: Vec<f32>,
    dirty: Vec<bool>,
}

impl GradBuffer {
    pub fn new(len: usize) -> Self {
        GradBuffer {
            values: vec![0.0; len],
            dirty: vec![false; len.div_ceil(BLOCK)],
        }
    }

    pub fn len(&self) -> usize {
        self.values.len()
    }
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// `values[at] += g[0]; values[at + 1] += g[1]` for an even `at` (see [`Grads::add_pair`]).
    #[inline(always)]
    pub fn add_pair(&mut self, at: usize, g: [f32; 2]) {
        self.all().add_pair(at, g);
    }

    /// The whole buffer as a stage's gradient view.
    pub fn all(&mut self) -> Grads<'_> {
        self.window(0..self.values.len())
    }

    /// The gradients of the parameters in `range`.
    pub fn window(&mut self, range: std::ops::Range<usize>) -> Grads<'_> {
        Grads {
            base: range.start,
            values: &mut self.values[range],
            dirty: &mut self.dirty,
        }
    }

    /// Marks `range` written (for dense parts such as MLP weights).
    pub fn mark(&mut self, range: std::ops::Range<usize>) {
        self.all().mark(range);
    }

    #[cfg(test)]
    pub fn is_dirty(&self, i: usize) -> bool {
        self.dirty[i / BLOCK]
    }

    /// Value ranges of the dirty blocks, in order.
    #[cfg(test)]
    pub fn dirty_ranges(&self) -> impl Iterator<Item = std::ops::Range<usize>> + '_ {
        let n = self.values.len();
        self.dirty
            .iter()
            .enumerate()
            .filter(|(_, &d)| d)
            .map(move |(b, _)| b * BLOCK..((b + 1) * BLOCK).min(n))
    }

    /// Fraction of blocks written since the last clear.
    pub fn dirty_fraction(&self) -> f64 {
        let d = self.dirty.iter().filter(|&&d| d).count();
        d as f64 / self.dirty.len().max(1) as f64
    }

    /// Consecutive pieces of `seg` values (a multiple of [`BLOCK`]) with their dirty flags.
    pub fn segments_mut(&mut self, seg: usize) -> impl Iterator<Item = Segment<'_>> {
        assert!(seg.is_multiple_of(BLOCK) && seg > 0);
        self.values
            .chunks_mut(seg)
            .zip(self.dirty.chunks_mut(seg / BLOCK))
            .map(|(values, dirty)| Segment { values, dirty })
    }

    /// Sums all buffers into the first over the union of their dirty blocks, zeroing and
    /// forgetting the others', in parallel over segments. Returns whether every summed
    /// value is finite.
    pub fn reduce_into_first(buffers: &mut [GradBuffer]) -> bool {
        let Some(n) = buffers.first().map(|b| b.len()) else {
            return true;
        };
        let segments = n.div_ceil(SEGMENT);
        let mut by_segment: Vec<Vec<Segment>> = (0..segments).map(|_| Vec::new()).collect();
        for b in buffers.iter_mut() {
            assert_eq!(b.len(), n, "gradient buffers differ in size");
            for (k, s) in b.segments_mut(SEGMENT).enumerate() {
                by_segment[k].push(s);
            }
        }
        by_segment.into_par_iter().all(|mut parts| {
            let (first, rest) = parts.split_at_mut(1);
            let mut swept = None;
            for other in rest.iter_mut() {
                swept = first[0].take_from(other);
            }
            swept.unwrap_or_else(|| first[0].all_finite())
        })
    }

    /// Zeroes the dirty blocks and forgets them.
    pub fn clear(&mut self) {
        for b in 0..self.dirty.len() {
            if std::mem::take(&mut self.dirty[b]) {
                let end = ((b + 1) * BLOCK).min(self.values.len());
                self.values[b * BLOCK..end].fill(0.0);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reduction_and_clearing_visit_exactly_the_written_blocks() {
        let mut a = GradBuffer::new(300);
        let mut b = GradBuffer::new(300);
        a.add_pair(2, [1.0, 2.0]);
        b.add_pair(130, [3.0, 4.0]);
        b.mark(250..300);
        b.values[299] = 5.0;
        a.add_pair(4, [0.5, 0.5]);
        let mut both = [a, b];
        assert!(GradBuffer::reduce_into_first(&mut both));
        let [mut a, b] = both;
        assert!(b.values.iter().all(|&v| v == 0.0) && b.dirty_fraction() == 0.0);
        assert_eq!(
            a.dirty_ranges().collect::<Vec<_>>(),
            vec![0..64, 128..192, 192..256, 256..300]
        );
        assert_eq!(
            (a.values[2], a.values[3], a.values[130], a.values[299]),
            (1.0, 2.0, 3.0, 5.0)
        );
        let mut seen = Vec::new();
        for mut s in a.segments_mut(128) {
            s.drain_dirty(|r, v| seen.push((r, v.iter().sum::<f32>())));
        }
        // Half-dirty segments of two blocks are swept whole.
        assert_eq!(seen, vec![(0..128, 4.0), (0..128, 7.0), (0..44, 5.0)]);
        assert!(a.values.iter().all(|&v| v == 0.0) && a.dirty_fraction() == 0.0);
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut pair = [GradBuffer::new(10), GradBuffer::new(10)];
            pair[0].add_pair(2, [1.0, 1.0]);
            pair[1].add_pair(0, [bad, 0.0]);
            assert!(
                !GradBuffer::reduce_into_first(&mut pair),
                "{bad} not caught"
            );
        }
        let mut one = [GradBuffer::new(4096)];
        one[0].add_pair(640, [f32::NAN, 0.0]);
        assert!(
            !GradBuffer::reduce_into_first(&mut one),
            "sparse NaN not caught"
        );
    }

    #[test]
    fn sparse_segments_are_visited_block_by_block_in_runs() {
        // 64 blocks in one segment, 3 dirty: below the sweep threshold.
        let mut bufs = [GradBuffer::new(64 * BLOCK), GradBuffer::new(64 * BLOCK)];
        bufs[0].add_pair(BLOCK, [1.0, 0.0]);
        bufs[1].add_pair(2 * BLOCK + 6, [2.0, 0.0]);
        bufs[1].add_pair(10 * BLOCK, [4.0, 0.0]);
        assert!(GradBuffer::reduce_into_first(&mut bufs));
        let [mut a, b] = bufs;
        assert!(b.values.iter().all(|&v| v == 0.0) && b.dirty_fraction() == 0.0);
        let mut seen = Vec::new();
        for mut s in a.segments_mut(64 * BLOCK) {
            s.drain_dirty(|r, v| seen.push((r, v.iter().sum::<f32>())));
        }
        assert_eq!(
            seen,
            vec![(BLOCK..3 * BLOCK, 3.0), (10 * BLOCK..11 * BLOCK, 4.0)]
        );
        assert!(a.values.iter().all(|&v| v == 0.0) && a.dirty_fraction() == 0.0);
    }
}
