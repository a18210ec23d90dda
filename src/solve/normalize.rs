//! Per-normal energy normalisation.
//!
//! With a finite direction set, `S(n) = sum over s with n.s > 0 of (n.s) W(s) / pi` is not exactly
//! 1, so a closed furnace would gain or lose energy each bounce (and diverge for reflectance near
//! 1). The gathered sum of a surfel side is divided by `S` of its normal. Both sides of a surfel
//! share `S`, because the direction set is symmetric (`s` and `-s` have equal weights). `S` is
//! computed once per distinct normal with exactly the cosine the propagation uses
//! ([`cosine`]), so a uniform field is reproduced to rounding.

use crate::geometry::directions::DirectionSet;
use glam::DVec3;
use rayon::prelude::*;

/// The cosine factor between a stored (f32) normal and a unit direction, as propagation uses it.
#[inline]
pub fn cosine(normal: [f32; 3], unit: DVec3) -> f64 {
    (normal[0] as f64 * unit.x + normal[1] as f64 * unit.y + normal[2] as f64 * unit.z).abs()
}

/// `S(n)` for every normal of the table, in table order.
pub fn cosine_sums(normals: &[[f32; 3]], directions: &DirectionSet) -> Vec<f64> {
    normals
        .par_iter()
        .map(|&n| {
            directions
                .directions
                .iter()
                .map(|d| cosine(n, d.unit) * d.solid_angle)
                .sum::<f64>()
                / std::f64::consts::PI
        })
        .collect()
}
