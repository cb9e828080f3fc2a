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

impl Segment<'_> {
    /// Calls `f` with the in-segment range of each dirty block, then zeroes and forgets it.
    pub fn drain_dirty(&mut self, mut f: impl FnMut(std::ops::Range<usize>, &[f32])) {
        for b in 0..self.dirty.len() {
            if std::mem::take(&mut self.dirty[b]) {
                let r = b * BLOCK..((b + 1) * BLOCK).min(self.values.len());
                f(r.clone(), &self.values[r.clone()]);
                self.values[r].fill(0.0);
            }
        }
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

    /// `values[at] += g[0]; values[at + 1] += g[1]` for an even `at` (a pair never straddles
    /// a block).
    #[inline(always)]
    pub fn add_pair(&mut self, at: usize, g: [f32; 2]) {
        self.values[at] += g[0];
        self.values[at + 1] += g[1];
        self.dirty[at / BLOCK] = true;
    }

    /// Marks `range` written (for dense parts such as MLP weights).
    pub fn mark(&mut self, range: std::ops::Range<usize>) {
        if range.is_empty() {
            return;
        }
        let last = (range.end - 1) / BLOCK;
        self.dirty[range.start / BLOCK..=last].fill(true);
    }

    pub fn is_dirty(&self, i: usize) -> bool {
        self.dirty[i / BLOCK]
    }

    /// Value ranges of the dirty blocks, in order.
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
        assert!(seg % BLOCK == 0 && seg > 0);
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
            let first = &mut first[0];
            let mut finite = true;
            for b in 0..first.dirty.len() {
                let r = b * BLOCK..((b + 1) * BLOCK).min(first.values.len());
                for other in rest.iter_mut() {
                    if std::mem::take(&mut other.dirty[b]) {
                        for (a, o) in first.values[r.clone()]
                            .iter_mut()
                            .zip(&mut other.values[r.clone()])
                        {
                            *a += std::mem::take(o);
                        }
                        first.dirty[b] = true;
                    }
                }
                if first.dirty[b] {
                    finite &= first.values[r].iter().all(|g| g.is_finite());
                }
            }
            finite
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
        assert_eq!(
            seen,
            vec![(0..64, 4.0), (0..64, 7.0), (64..128, 0.0), (0..44, 5.0)]
        );
        assert!(a.values.iter().all(|&v| v == 0.0) && a.dirty_fraction() == 0.0);
        let mut nan = [GradBuffer::new(10), GradBuffer::new(10)];
        nan[1].add_pair(0, [f32::NAN, 0.0]);
        assert!(!GradBuffer::reduce_into_first(&mut nan));
    }
}
