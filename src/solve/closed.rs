//! Closed scenes: the per-channel scales that make a closed scene absorb exactly what it emits,
//! in every solve path, and the exact sums they come from.
//!
//! **Why.** Light cannot leave a closed room, so every ray from its surfaces meets a surface and
//! the power the surfaces receive in a bounce is the power they sent. The discrete lines do not
//! quite keep this: a ray that crosses a wall's plane a few hundredths of a voxel outside its own
//! line at the grid's edge meets nothing, and partner links are not mutual (a receiver takes light
//! from a sender whose own ray along the direction meets someone else), so a closed room gathered
//! 0.2 to 1.8 % more or less than it sent at resolution 32 to 128, depending on where its planes
//! fall on the grid (`docs/accuracy.md`). Classical radiosity normalises the form factors of an
//! enclosure for the same reason. Here one number per channel is enough: each update scales the
//! light every surfel side gathered by `sent / gathered` over the whole scene (the power the lines
//! carried, `sum A R` with `R` the radiosity they read, against the power received, `sum A H /
//! S(n)`), and the direct-light pass's light by `emitted / received` likewise. One number per
//! channel moves no light from one surface to another; a uniform field gives exactly 1, so the
//! furnace stays exact. The sums are taken over the light of the iteration being updated (a pass
//! before the update where the light lives in files), so a checkpoint holds nothing more.
//!
//! **Which scenes.** Those `enclosure` finds closed: no emitting side faces air that reaches the
//! grid's outside. An open scene (the Cornell box, open at the front; a room with a window
//! opening) keeps its light's losses, which are physical there.

/// The per-channel scales an update applies: to the light gathered along the lines and to the
/// direct-light pass's light. 1 in an open scene.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Scales {
    pub gathered: [f64; 3],
    pub direct: [f64; 3],
}

impl Scales {
    pub const ONE: Scales = Scales {
        gathered: [1.0; 3],
        direct: [1.0; 3],
    };
}

impl Default for Scales {
    fn default() -> Self {
        Scales::ONE
    }
}

/// What a closed scene's scales are made of, added over the surfels (area in voxel units; one
/// channel only for a grey scene): `sum A R`, the power the lines carried (`R` as they read it,
/// f32); `sum A H / S(n)`, the power the sides received along them; `sum A E`, the power
/// emitted; `sum A D`, the power the direct-light pass brought.
///
/// The sums are exact: each term is rounded once to a fixed point (2^-64 of the scene's largest
/// emission) and added as an integer, so they do not depend on the order of the surfels or on
/// how they are dealt over threads and ranks, and every solve path finds the same scales to the
/// bit (the out-of-core data mode gives the one-process answer bit for bit).
#[derive(Clone, Copy, Debug)]
pub struct ClosureSums {
    /// One fixed-point step, as a factor.
    unit: f64,
    /// Sent, gathered, emitted, direct; three channels each.
    sums: [i128; 12],
}

/// Bits per part when the sums travel between ranks as `f64`s: 6 parts hold 128 bits, and
/// up to 2^29 ranks' parts add exactly.
const PART_BITS: u32 = 24;
const PARTS: usize = 6;

impl ClosureSums {
    /// Empty sums for a scene whose materials are `materials`.
    pub fn new(materials: &[crate::scene::Material]) -> Self {
        let largest = materials
            .iter()
            .flat_map(|m| m.emission)
            .fold(0.0f64, f64::max);
        // Radiosity stays below `E / (1 - rho)`: with rho up to 0.999 and areas of a few voxels,
        // terms stay below 2^76 steps and the sums of 2^40 surfels below 2^116.
        let exponent = if largest > 0.0 {
            largest.log2().ceil() as i32
        } else {
            0
        };
        ClosureSums {
            unit: 2f64.powi(64 - exponent),
            sums: [0; 12],
        }
    }

    fn step(&self, v: f64) -> i128 {
        (v * self.unit).round() as i128
    }

    /// Adds the light one surfel's sides gathered along the lines.
    pub fn add_gathered(&mut self, h: &[[f64; 3]; 2], channels: usize, norm: f64, area: f64) {
        for side in h {
            for (ch, &light) in side.iter().enumerate().take(channels) {
                self.sums[3 + ch] += self.step(area * light / norm);
            }
        }
    }

    /// Adds one surfel: `carried` is what its sides sent along the lines this iteration (`B - E`
    /// with the direct pass, else `B`), `h` what they gathered, `direct` the pass's light.
    #[allow(clippy::too_many_arguments)]
    pub fn add(
        &mut self,
        emission: &[[f32; 3]; 2],
        carried: &[[f32; 3]; 2],
        h: &[[f64; 3]; 2],
        direct: Option<&[[f64; 3]; 2]>,
        channels: usize,
        norm: f64,
        area: f64,
    ) {
        self.add_gathered(h, channels, norm, area);
        for side in 0..2 {
            for ch in 0..channels {
                self.sums[ch] += self.step(area * carried[side][ch] as f64);
                self.sums[6 + ch] += self.step(area * emission[side][ch] as f64);
                if let Some(d) = direct {
                    self.sums[9 + ch] += self.step(area * d[side][ch]);
                }
            }
        }
    }

    /// Adds the sums of every rank of `comm` (collective), exactly.
    pub fn add_over(&mut self, comm: &dyn crate::comm::Comm) {
        if comm.size() == 1 {
            return;
        }
        let mask = (1u128 << PART_BITS) - 1;
        let mut parts = vec![0f64; self.sums.len() * PARTS];
        for (k, &v) in self.sums.iter().enumerate() {
            for p in 0..PARTS {
                parts[k * PARTS + p] = ((v as u128 >> (p as u32 * PART_BITS)) & mask) as f64;
            }
        }
        comm.sum_in_place(&mut parts);
        for (k, v) in self.sums.iter_mut().enumerate() {
            let mut total = 0u128;
            for p in 0..PARTS {
                let part = parts[k * PARTS + p] as u128;
                total = total.wrapping_add(part.wrapping_shl(p as u32 * PART_BITS));
            }
            *v = total as i128;
        }
    }

    /// The scales these sums call for (`channels` 1: the first channel's, copied).
    pub fn scales(&self, channels: usize) -> Scales {
        let ratio = |num: i128, den: i128| {
            if num > 0 && den > 0 {
                num as f64 / den as f64
            } else {
                1.0
            }
        };
        let mut s = Scales::ONE;
        for ch in 0..3 {
            let c = if channels == 1 { 0 } else { ch };
            s.gathered[ch] = ratio(self.sums[c], self.sums[3 + c]);
            s.direct[ch] = ratio(self.sums[6 + c], self.sums[9 + c]);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scales_are_one_for_balanced_sums_and_copy_a_grey_channel() {
        let lamp = crate::scene::Material::new("lamp", [0.0; 3], [10.0; 3]);
        let mut s = ClosureSums::new(&[lamp]);
        s.add(
            &[[1.0; 3], [0.0; 3]],
            &[[2.0; 3], [0.0; 3]],
            &[[4.0, 0.0, 0.0], [0.0; 3]],
            Some(&[[0.5; 3], [0.0; 3]]),
            1,
            2.0,
            3.0,
        );
        let k = s.scales(1);
        assert_eq!(k.gathered, [1.0; 3]);
        assert_eq!(k.direct, [2.0; 3]);
    }

    #[test]
    fn the_sums_do_not_depend_on_their_order() {
        let lamp = crate::scene::Material::new("lamp", [0.0; 3], [7.0; 3]);
        let values: Vec<f64> = (0..1000)
            .map(|i| 1.0 / (1.0 + i as f64).powf(1.7))
            .collect();
        let total = |order: &mut dyn Iterator<Item = &f64>| {
            let mut s = ClosureSums::new(std::slice::from_ref(&lamp));
            for &v in order {
                s.add_gathered(&[[v, 2.0 * v, 0.1], [0.0; 3]], 3, 0.7, 1.3);
            }
            s.sums
        };
        assert_eq!(total(&mut values.iter()), total(&mut values.iter().rev()));
    }
}
