//! Convex polygons in 3D, as the voxelizer cuts triangles: clipping to a voxel's cube, area and
//! centroid, and the parts of one polygon outside another in the same plane (what two faces
//! pressed together leave visible of each other, `voxelize::merge_voxel`).

use glam::DVec3;

/// Area below which a part is dropped (voxel units squared): well under what a ray can tell.
pub(crate) const NEGLIGIBLE_AREA: f64 = 1e-9;

/// Sutherland-Hodgman clipping of a convex polygon to the closed cube `[0, 1]^3`. Points on the
/// cube's boundary are kept, so contacts along faces, edges and corners survive as degenerate
/// polygons. Intersection points get the bound's exact coordinate.
pub(crate) fn clip_to_unit_cube(polygon: &mut Vec<DVec3>, scratch: &mut Vec<DVec3>) {
    for axis in 0..3 {
        for (bound, keep_below) in [(0.0, false), (1.0, true)] {
            if polygon.is_empty() {
                return;
            }
            scratch.clear();
            let inside = |p: &DVec3| {
                if keep_below {
                    p[axis] <= bound
                } else {
                    p[axis] >= bound
                }
            };
            for k in 0..polygon.len() {
                let a = polygon[k];
                let b = polygon[(k + 1) % polygon.len()];
                let (ia, ib) = (inside(&a), inside(&b));
                if ia {
                    scratch.push(a);
                }
                if ia != ib {
                    let t = (bound - a[axis]) / (b[axis] - a[axis]);
                    let mut p = a + (b - a) * t;
                    p[axis] = bound;
                    scratch.push(p);
                }
            }
            std::mem::swap(polygon, scratch);
        }
    }
}

/// Area and area-weighted centroid sum of a planar convex polygon (fan triangulation).
pub(crate) fn polygon_area_centroid(polygon: &[DVec3]) -> (f64, DVec3) {
    let mut area = 0.0;
    let mut sum = DVec3::ZERO;
    for k in 1..polygon.len().saturating_sub(1) {
        let (a, b, c) = (polygon[0], polygon[k], polygon[k + 1]);
        let t = 0.5 * (b - a).cross(c - a).length();
        area += t;
        sum += (a + b + c) / 3.0 * t;
    }
    (area, sum)
}

/// The convex parts of `polygon` outside the convex `cover` (both in one plane): the part
/// outside `cover`'s first edge, then the part inside it and outside the second, and so on. What
/// is inside every edge is covered.
pub(crate) fn outside_of(polygon: &[DVec3], cover: &[DVec3]) -> Vec<Vec<DVec3>> {
    let (cover_area, cover_sum) = polygon_area_centroid(cover);
    if cover_area <= NEGLIGIBLE_AREA {
        return vec![polygon.to_vec()];
    }
    let centre = cover_sum / cover_area;
    let normal = plane_normal(cover);
    let mut parts = Vec::new();
    let mut rest = polygon.to_vec();
    for k in 0..cover.len() {
        let (a, b) = (cover[k], cover[(k + 1) % cover.len()]);
        let mut across = (b - a).cross(normal);
        if (b - a).length_squared() < 1e-24 {
            continue;
        }
        // Orient the edge's normal in the plane away from the cover.
        if across.dot(centre - a) > 0.0 {
            across = -across;
        }
        let outside = clip(&rest, a, across);
        if polygon_area_centroid(&outside).0 > NEGLIGIBLE_AREA {
            parts.push(outside);
        }
        rest = clip(&rest, a, -across);
        if rest.len() < 3 {
            return parts;
        }
    }
    parts
}

/// Whether `point` (in the polygon's plane, to rounding) lies in the convex `polygon`, its
/// boundary included to 1e-9 voxel.
pub(crate) fn contains(polygon: &[DVec3], point: DVec3) -> bool {
    let normal = plane_normal(polygon);
    if normal == DVec3::ZERO {
        return false;
    }
    // Inside every edge: on the same side of each as the polygon's other corners, so the
    // winding does not matter.
    let (area, sum) = polygon_area_centroid(polygon);
    let centre = sum / area;
    (0..polygon.len()).all(|k| {
        let (a, b) = (polygon[k], polygon[(k + 1) % polygon.len()]);
        let across = (b - a).cross(normal);
        let inward = if across.dot(centre - a) >= 0.0 {
            across
        } else {
            -across
        };
        (point - a).dot(inward.normalize_or_zero()) >= -1e-9
    })
}

/// A unit normal of the convex polygon `polygon` (its largest corner cross product).
fn plane_normal(polygon: &[DVec3]) -> DVec3 {
    let mut best = DVec3::ZERO;
    for k in 1..polygon.len().saturating_sub(1) {
        let c = (polygon[k] - polygon[0]).cross(polygon[k + 1] - polygon[0]);
        if c.length_squared() > best.length_squared() {
            best = c;
        }
    }
    best.normalize_or_zero()
}

/// The part of the convex `polygon` where `(p - at) . towards >= 0` (Sutherland-Hodgman).
pub(crate) fn clip(polygon: &[DVec3], at: DVec3, towards: DVec3) -> Vec<DVec3> {
    let mut out = Vec::with_capacity(polygon.len() + 1);
    let side = |p: &DVec3| (*p - at).dot(towards);
    for k in 0..polygon.len() {
        let (a, b) = (polygon[k], polygon[(k + 1) % polygon.len()]);
        let (sa, sb) = (side(&a), side(&b));
        if sa >= 0.0 {
            out.push(a);
        }
        if (sa >= 0.0) != (sb >= 0.0) {
            out.push(a + (b - a) * (sa / (sa - sb)));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(lo: [f64; 2], hi: [f64; 2]) -> Vec<DVec3> {
        vec![
            DVec3::new(lo[0], 0.5, lo[1]),
            DVec3::new(hi[0], 0.5, lo[1]),
            DVec3::new(hi[0], 0.5, hi[1]),
            DVec3::new(lo[0], 0.5, hi[1]),
        ]
    }

    fn area(parts: &[Vec<DVec3>]) -> f64 {
        parts.iter().map(|p| polygon_area_centroid(p).0).sum()
    }

    #[test]
    fn a_strip_across_a_square_leaves_the_two_sides() {
        // A wall's foot 0.15 wide across a floor's voxel: what is left is the two strips.
        let floor = square([0.0, 0.0], [1.0, 1.0]);
        let foot = square([0.0, 0.45], [1.0, 0.6]);
        let parts = outside_of(&floor, &foot);
        assert!((area(&parts) - 0.85).abs() < 1e-12, "{}", area(&parts));
        for part in &parts {
            assert!(part
                .iter()
                .all(|p| p.z <= 0.45 + 1e-12 || p.z >= 0.6 - 1e-12));
        }
    }

    #[test]
    fn a_covered_polygon_leaves_nothing_and_a_distant_one_is_whole() {
        let foot = square([0.0, 0.0], [1.0, 1.0]);
        assert!(area(&outside_of(&square([0.2, 0.2], [0.4, 0.9]), &foot)) < 1e-12);
        let far = square([0.0, 0.0], [0.3, 0.3]);
        let other = square([0.5, 0.5], [1.0, 1.0]);
        assert!((area(&outside_of(&far, &other)) - 0.09).abs() < 1e-12);
    }

    #[test]
    fn containment_holds_inside_and_on_the_boundary_only() {
        let mut sq = square([0.0, 0.0], [1.0, 1.0]);
        for _ in 0..2 {
            assert!(contains(&sq, DVec3::new(0.5, 0.5, 0.5)));
            assert!(contains(&sq, DVec3::new(1.0, 0.5, 0.3)));
            assert!(!contains(&sq, DVec3::new(1.01, 0.5, 0.3)));
            assert!(!contains(&sq, DVec3::new(0.5, 0.5, -0.2)));
            sq.reverse();
        }
    }

    #[test]
    fn a_triangle_cover_works_whatever_its_winding() {
        let floor = square([0.0, 0.0], [1.0, 1.0]);
        let t = vec![
            DVec3::new(0.0, 0.5, 0.0),
            DVec3::new(1.0, 0.5, 0.0),
            DVec3::new(0.0, 0.5, 1.0),
        ];
        let mut reversed = t.clone();
        reversed.reverse();
        for cover in [t, reversed] {
            assert!((area(&outside_of(&floor, &cover)) - 0.5).abs() < 1e-12);
        }
    }
}
