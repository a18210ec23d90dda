//! The update of one surfel's radiosity after an iteration's gather, written once for every
//! iteration loop (in memory, the data and hybrid modes, out of core, the data mode out of
//! core): `B = E + rho (k H / S(n) + k_direct H_direct)` by side and channel (`k`, `k_direct`:
//! a closed scene's scales, `closed`; 1 in an open one), with the sums the stopping rule and the
//! tail extrapolation read; and the power a surfel emits and absorbs, for the loops that add it
//! up as they update.

use super::closed::Scales;
use super::direct::DirectLight;
/// Light by side and channel as gathered (f64), radiosity as stored (f32).
pub use crate::checkpoint::{Gathered, Radiosity};

/// What an update of `B` adds up over the surfels it updates: the change and the total (for the
/// stopping rule) and, where a loop adds them here, the power emitted and absorbed, by channel.
#[derive(Clone, Copy, Debug, Default)]
pub struct UpdateSums {
    pub change: f64,
    /// The change a plain iteration would have made (`|G(B) - B|`, area-weighted): the
    /// residual the stopping rule reads while the Chebyshev semi-iteration runs
    /// (`solve::accelerate`); `change` itself otherwise.
    pub residual: f64,
    /// Area times the decrease, where a value fell (see `solve::accelerate`).
    pub falling: f64,
    pub total: f64,
    pub emitted: [f64; 3],
    pub absorbed: [f64; 3],
    /// The part of `absorbed` the direct light deposits, kept apart (added last, as in memory).
    pub absorbed_direct: [f64; 3],
}

/// What the lines of the iterations carry with the direct-light pass: the reflected part
/// `B - E` (f32, as radiosity is stored), the same arithmetic in every loop.
pub fn reflected_part(b: &Radiosity, emission: &Radiosity) -> Radiosity {
    let mut r = [[0f32; 3]; 2];
    for side in 0..2 {
        for ch in 0..3 {
            r[side][ch] = (b[side][ch] as f64 - emission[side][ch] as f64) as f32;
        }
    }
    r
}

/// What the lines carried from a surfel this iteration: `B - E` where the direct-light pass
/// ran (`direct`), else `B`.
pub fn carried(previous: &Radiosity, emission: &Radiosity, direct: bool) -> Radiosity {
    if direct {
        reflected_part(previous, emission)
    } else {
        *previous
    }
}

/// One surfel's new radiosity `B = E + rho H / S(n)` (`norm` is `S(n)`) from the light `h` it
/// gathered (only the first channel when `channels` is 1: a grey scene), plus `rho` times its
/// `direct` light where the direct-light pass ran, each scaled by `scales` (a closed scene's,
/// `closed`; else 1); adds its change, falling part and total (area-weighted) to `sums`.
/// `emission` is `E` as stored (f32), `reflectance` `rho`. With `older` (the radiosity before
/// `previous`, and a weight `w`) the new value is the Chebyshev semi-iteration's,
/// `older + w (B - older)` (`accelerate::chebyshev_value`).
#[allow(clippy::too_many_arguments)]
pub fn update_surfel(
    emission: &Radiosity,
    reflectance: &Gathered,
    mut h: Gathered,
    direct: Option<&Gathered>,
    channels: usize,
    previous: &Radiosity,
    older: Option<(&Radiosity, f64)>,
    norm: f64,
    area: f64,
    scales: &Scales,
    sums: &mut UpdateSums,
) -> Radiosity {
    if channels == 1 {
        for side in &mut h {
            *side = [side[0]; 3];
        }
    }
    let mut b_new: Radiosity = [[0.0; 3]; 2];
    for side in 0..2 {
        for ch in 0..3 {
            let rho = reflectance[side][ch];
            let mut b =
                emission[side][ch] as f64 + rho * (h[side][ch] * scales.gathered[ch]) / norm;
            if let Some(d) = direct {
                b += rho * (d[side][ch] * scales.direct[ch]);
            }
            let plain = b - previous[side][ch] as f64;
            sums.residual += area * plain.abs();
            if let Some((older, w)) = older {
                let e = emission[side][ch] as f64;
                b = super::accelerate::chebyshev_value(b, older[side][ch] as f64, w, e);
            }
            let d = b - previous[side][ch] as f64;
            sums.change += area * d.abs();
            sums.falling += area * (-d).max(0.0);
            sums.total += area * b;
            b_new[side][ch] = b as f32;
        }
    }
    b_new
}

/// The light of surfel `k` the direct pass gathered, if it ran.
pub fn direct_of(direct: Option<&DirectLight>, k: usize) -> Option<&Gathered> {
    direct.map(|d| &d.irradiance[k])
}

/// Adds to `sums` the power a surfel whose sides have the materials `sides` emits and absorbs
/// (world units: `area` in voxel units times `area_unit`), from the light `h` it gathered (the
/// first channel only when `channels` is 1) over `norm` and its `direct` light, scaled as the
/// update scaled them. The loops that stream their surfels add it as they update; the in-memory
/// ones from their last gather.
#[allow(clippy::too_many_arguments)]
pub fn add_power(
    sides: [&crate::scene::Material; 2],
    mut h: Gathered,
    direct: Option<&Gathered>,
    channels: usize,
    norm: f64,
    area: f64,
    area_unit: f64,
    scales: &Scales,
    sums: &mut UpdateSums,
) {
    if channels == 1 {
        for side in &mut h {
            *side = [side[0]; 3];
        }
    }
    for (side, m) in sides.iter().enumerate() {
        for ch in 0..3 {
            if let Some(d) = direct {
                sums.absorbed_direct[ch] += (1.0 - m.reflectance[ch])
                    * (d[side][ch] * scales.direct[ch])
                    * (area * area_unit);
            }
            sums.emitted[ch] += m.emission[ch] * area * area_unit;
            sums.absorbed[ch] += (1.0 - m.reflectance[ch]) * (h[side][ch] * scales.gathered[ch])
                / norm
                * area
                * area_unit;
        }
    }
}
