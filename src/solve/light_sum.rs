//! Where a gather adds the light a surfel side receives: the kernels (`propagate::gather_lines`,
//! `links::DirectionLinks::replay`) are generic over it.
//!
//! In memory every solve sums in f64 (`[[f64; 3]; 2]` a surfel). The out-of-core band passes
//! sum the light of a main axis's directions in f32 (`[[f32; 3]; 2]`), each link's light added
//! in f64 and the sum rounded at once: that is what their files hold, at half the bytes, and
//! since every path adds a surfel's links in the same order, the one-process solver and the
//! data mode, which cut the directions into passes differently, still agree to the bit
//! (`outcore::files`, "The axis light in f32").

/// A surfel's light by side and channel, as a gather adds to it.
pub trait LightSum: Copy + Send + Sync + 'static {
    /// Adds `factor` times the first `channels` channels of `from` to side `side`.
    fn add(&mut self, side: usize, from: &[f32; 3], factor: f64, channels: usize);
}

impl LightSum for [[f64; 3]; 2] {
    #[inline(always)]
    fn add(&mut self, side: usize, from: &[f32; 3], factor: f64, channels: usize) {
        for (t, &b) in self[side].iter_mut().zip(from).take(channels) {
            *t += b as f64 * factor;
        }
    }
}

impl LightSum for [[f32; 3]; 2] {
    #[inline(always)]
    fn add(&mut self, side: usize, from: &[f32; 3], factor: f64, channels: usize) {
        for (t, &b) in self[side].iter_mut().zip(from).take(channels) {
            *t = (*t as f64 + b as f64 * factor) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f32_sums_round_each_addition_of_the_f64_sum() {
        let from = [1.0f32, 0.1, 3.0];
        let factor = 1.0 / 3.0;
        let (mut wide, mut narrow) = ([[0.0f64; 3]; 2], [[0.0f32; 3]; 2]);
        for _ in 0..10 {
            let before = narrow;
            wide.add(1, &from, factor, 2);
            narrow.add(1, &from, factor, 2);
            for c in 0..2 {
                let exact = before[1][c] as f64 + from[c] as f64 * factor;
                assert_eq!(narrow[1][c], exact as f32);
            }
        }
        // The channels beyond `channels` and the other side are not touched.
        assert_eq!((narrow[1][2], narrow[0]), (0.0, [0.0; 3]));
        assert_eq!((wide[1][2], wide[0]), (0.0, [0.0; 3]));
        assert!((narrow[1][0] as f64 - wide[1][0]).abs() < 1e-6 * wide[1][0]);
    }
}
