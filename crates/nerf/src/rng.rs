//! Counter-based random numbers.
//!
//! Every random draw of a training step is a pure function of `(seed, step, stream)`, so a
//! run resumed from a checkpoint draws exactly what the uninterrupted run would have, and
//! the result does not depend on how rays are split among threads. The checkpoint therefore
//! only needs the seed and the step to restore the random state.

/// SplitMix64 finaliser: a bijective 64-bit mixer with good avalanche.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// A small, fast generator (SplitMix64) whose whole state is one `u64`.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
}

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng {
            state: mix64(seed ^ 0x9e37_79b9_7f4a_7c15),
        }
    }

    /// The generator for one independent stream of a step (e.g. one ray of one step).
    pub fn for_stream(seed: u64, step: u64, stream: u64) -> Self {
        Rng::new(mix64(
            seed ^ mix64(step.wrapping_add(0x1234_5678)) ^ mix64(!stream),
        ))
    }

    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        mix64(self.state)
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn uniform(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    /// Uniform integer in [0, n); n must be positive.
    #[inline]
    pub fn below(&mut self, n: usize) -> usize {
        (((self.next_u64() >> 32) * n as u64) >> 32) as usize
    }

    /// Uniform in [lo, hi).
    #[inline]
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform()
    }
}

#[cfg(test)]
impl Rng {
    /// `n` unit directions (`n x 3`), each a point uniform in the cube `[-1, 1)^3`
    /// normalised: what the field tests look along.
    pub(crate) fn unit_directions(&mut self, n: usize) -> Vec<f32> {
        (0..n)
            .flat_map(|_| {
                let d = [
                    self.range(-1.0, 1.0),
                    self.range(-1.0, 1.0),
                    self.range(-1.0, 1.0),
                ];
                crate::math::scale(d, 1.0 / crate::math::length(d))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_is_in_range_and_roughly_uniform() {
        let mut rng = Rng::new(7);
        let n = 100_000;
        let mut mean = 0.0f64;
        for _ in 0..n {
            let u = rng.uniform();
            assert!((0.0..1.0).contains(&u));
            mean += u as f64;
        }
        mean /= n as f64;
        assert!((mean - 0.5).abs() < 0.01, "mean {mean}");
    }

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let a = Rng::for_stream(1, 5, 9).next_u64();
        assert_eq!(a, Rng::for_stream(1, 5, 9).next_u64());
        assert_ne!(a, Rng::for_stream(1, 6, 9).next_u64());
        assert_ne!(a, Rng::for_stream(1, 5, 10).next_u64());
        assert_ne!(a, Rng::for_stream(2, 5, 9).next_u64());
    }

    #[test]
    fn below_covers_its_range() {
        let mut rng = Rng::new(3);
        let mut seen = [false; 7];
        for _ in 0..1000 {
            seen[rng.below(7)] = true;
        }
        assert!(seen.iter().all(|&s| s));
    }
}
