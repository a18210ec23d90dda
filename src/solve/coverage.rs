//! Coverage of surfels at the open edges of surfaces.
//!
//! A discrete line that passes through a voxel meets whatever surfel the voxel holds, as if the
//! surface filled the voxel. Inside a surface that is true; at its open edge (the rim of a lamp,
//! a table top's outline seen by a line that only grazes it) the surface covers part of the voxel,
//! and counting a whole hit makes every open surface look about half a voxel wider on each side
//! (+6 % on the form factor of two unit squares at resolution 33). So a surfel alone in its voxel
//! whose piece covers only part of the voxel's slice of its plane gets a coverage below 1. The
//! coverage marks the open edge; how much of a line the edge's plane then blocks is decided per
//! line and direction by propagation, from the projected areas of the plane's pieces on the line
//! (`solve::propagate`, "Open edges"), and the rest of a ray's light comes from what lies behind.
//!
//! A voxel holding one plane twice (a sheet modelled back to back) counts as holding one plane,
//! and a plane parallel to the piece's (a lamp hanging less than a voxel above a floor) cannot
//! bound it, so it does not count either; propagation then lets the rest of a ray go on to the
//! other plane in the same voxel. Where several planes meet in one voxel (edges and corners of closed objects) the pieces bound
//! each other and propagation decides which one a ray crosses, so their coverage stays 1; a
//! voxel that a plane only touches (zero area, no slice) keeps 1 too, because tunnel-freeness
//! depends on such voxels blocking.

use crate::voxel::polygon::{clip_to_unit_cube, polygon_area_centroid};
use crate::voxel::{Surfel, SurfelSet};
use glam::DVec3;

/// `|n . n'|` from which two planes count as parallel (normals are stored in f32).
const PARALLEL: f64 = 1.0 - 1e-6;

/// Smallest slice area (voxel-size squared) for which a coverage is computed at all.
const MIN_SLICE: f64 = 0.05;

/// Area of the plane through `point` (voxel-relative, in `[0, 1]^3`) with unit `normal`, inside
/// the unit cube.
pub fn slice_area(normal: DVec3, point: DVec3) -> f64 {
    let u = normal.any_orthonormal_vector();
    let v = normal.cross(u);
    CLIP_BUFFERS.with_borrow_mut(|(polygon, scratch)| {
        // A square of side 4 around the point covers the cube's slice (its diagonal is below 2).
        polygon.clear();
        polygon.extend([
            point + 2.0 * (u + v),
            point + 2.0 * (v - u),
            point - 2.0 * (u + v),
            point + 2.0 * (u - v),
        ]);
        clip_to_unit_cube(polygon, scratch);
        polygon_area_centroid(polygon).0
    })
}

thread_local! {
    /// The polygon [`slice_area`] clips and the clipper's scratch, kept per thread. It runs for
    /// every surfel alone in its voxel and on every line meeting an open edge; two fresh vectors
    /// per call cost two system calls each where the allocator maps small blocks one by one
    /// (a worker thread's arena under a small address-space limit: the out-of-core solve under
    /// 32 MiB in `tests/memory_limit.rs` spent nine tenths of its time mapping and unmapping).
    static CLIP_BUFFERS: std::cell::RefCell<(Vec<DVec3>, Vec<DVec3>)> =
        std::cell::RefCell::new((Vec::with_capacity(12), Vec::with_capacity(12)));
}

/// Coverage of every surfel of `set` (see the module header).
pub fn coverages(set: &SurfelSet) -> Vec<f32> {
    let s = &set.surfels;
    let mut out = Vec::with_capacity(s.len());
    // Surfels of one voxel are adjacent in the set.
    let mut first = 0;
    while first < s.len() {
        let mut end = first + 1;
        while end < s.len() && s[end].voxel == s[first].voxel {
            end += 1;
        }
        let mates = &s[first..end];
        out.extend((0..mates.len()).map(|k| coverage_in_voxel(mates, k)));
        first = end;
    }
    out
}

/// Coverage of `mates[k]`, where `mates` are all the surfels of one voxel.
pub fn coverage_in_voxel(mates: &[Surfel], k: usize) -> f32 {
    let s = &mates[k];
    let normal = DVec3::new(s.normal[0] as f64, s.normal[1] as f64, s.normal[2] as f64);
    // Alone in its voxel, sharing it only with its own plane (a sheet modelled twice, back to
    // back), or only with planes parallel to its own (a lamp hanging less than a voxel above a
    // floor): no other plane can bound the piece inside the voxel, so its open edge is open.
    let bounded = mates.iter().any(|m| {
        m.group != s.group && {
            let n = DVec3::new(m.normal[0] as f64, m.normal[1] as f64, m.normal[2] as f64);
            n.dot(normal).abs() < PARALLEL
        }
    });
    if bounded {
        return 1.0;
    }
    let point = DVec3::new(s.point[0] as f64, s.point[1] as f64, s.point[2] as f64);
    let slice = slice_area(normal, point);
    let area = s.area as f64;
    if slice < MIN_SLICE || area >= slice * (1.0 - 1e-3) {
        1.0
    } else {
        (area / slice) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slices_of_the_unit_cube() {
        assert!((slice_area(DVec3::Z, DVec3::splat(0.5)) - 1.0).abs() < 1e-12);
        // The diagonal plane x = y through the centre: a 1 x sqrt(2) rectangle.
        let n = DVec3::new(1.0, -1.0, 0.0).normalize();
        assert!((slice_area(n, DVec3::splat(0.5)) - 2f64.sqrt()).abs() < 1e-12);
        // The plane x + y + z = 1.5 through the centre: a regular hexagon of side sqrt(2)/2.
        let n = DVec3::ONE.normalize();
        let hexagon = 3.0 * 3f64.sqrt() / 2.0 * 0.5;
        assert!((slice_area(n, DVec3::splat(0.5)) - hexagon).abs() < 1e-12);
    }
}
