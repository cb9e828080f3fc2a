//! A gradient buffer that remembers which blocks a step wrote.
//!
//! A hash-grid step touches a part of its tables (a few hundred thousand of 16 million
//! values at the default sizes), yet a dense buffer would have to be summed across threads,
//! fed to Adam and zeroed in full every step. Writes mark their 64-value block dirty, and
//! reduction, the optimiser and clearing visit only dirty blocks.

/// Values per dirty flag.
pub const BLOCK: usize = 64;

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

    /// `self += other` over `other`'s dirty blocks.
    pub fn add_from(&mut self, other: &GradBuffer) {
        assert_eq!(self.values.len(), other.values.len());
        for r in other.dirty_ranges() {
            for (a, b) in self.values[r.clone()].iter_mut().zip(&other.values[r.clone()]) {
                *a += b;
            }
            self.dirty[r.start / BLOCK] = true;
        }
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

    /// Whether every value in a dirty block is finite.
    pub fn all_finite(&self) -> bool {
        self.dirty_ranges()
            .all(|r| self.values[r].iter().all(|g| g.is_finite()))
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
        a.add_from(&b);
        assert_eq!(
            a.dirty_ranges().collect::<Vec<_>>(),
            vec![0..64, 128..192, 192..256, 256..300]
        );
        assert_eq!((a.values[2], a.values[3], a.values[130], a.values[299]), (1.0, 2.0, 3.0, 5.0));
        assert!(a.all_finite());
        a.values[131] = f32::NAN;
        assert!(!a.all_finite());
        a.clear();
        assert!(a.values.iter().all(|&v| v == 0.0) && a.dirty_fraction() == 0.0);
    }
}
