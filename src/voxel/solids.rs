//! Which triangles are faces of a solid lying behind them, found from the mesh alone.
//!
//! Faces of one plane that face each other (a wall box's foot on the floor, the back of a sofa
//! against its seat) are in contact where they overlap, and the voxelizer takes the overlap out
//! of both (`voxelize::merge_voxel`). A thin sheet modelled twice back to back is the same
//! picture locally, two coincident faces facing opposite ways, but both of its faces are seen.
//! What tells them apart is the solid: the foot of a wall box is joined along its edges to the
//! box's side faces, which rise behind it; a free sheet's edges join nothing behind it.
//!
//! A triangle is taken as a solid's face when some triangle sharing one of its edges (the same
//! two end points, exactly, as meshes that share vertices have them) has its third corner behind
//! the triangle's plane. Boxes, extrusions and closed meshes qualify; a sheet, and the shell of a
//! room seen from inside (its walls rise in front of its floor), do not.

use crate::scene::Scene;
use glam::DVec3;
use std::hash::{Hash, Hasher};

/// Least distance behind a triangle's plane, relative to the triangle's size, at which a
/// neighbour's corner counts as behind it (far below any modelled thickness, far above rounding).
const BEHIND: f64 = 1e-9;

/// Per triangle of `scene`: whether it is a face of a solid lying behind it (see the module
/// header).
pub(crate) fn solid_backed(scene: &Scene) -> Vec<bool> {
    let triangles = &scene.triangles;
    // Every edge, keyed by its two end points in either order: (hash, triangle, edge).
    let mut edges: Vec<(u64, u32, u8)> = Vec::with_capacity(triangles.len() * 3);
    for (i, t) in triangles.iter().enumerate() {
        for e in 0..3u8 {
            let (a, b) = edge_points(&t.vertices, e);
            edges.push((edge_hash(a, b), i as u32, e));
        }
    }
    edges.sort_unstable();
    let mut backed = vec![false; triangles.len()];
    for run in edges.chunk_by(|x, y| x.0 == y.0).filter(|r| r.len() > 1) {
        for &(_, i, e) in run {
            let t = &triangles[i as usize];
            let (a, b) = edge_points(&t.vertices, e);
            let normal = t.cross();
            let size = normal.length();
            if size == 0.0 {
                continue;
            }
            for &(_, j, f) in run {
                if j == i {
                    continue;
                }
                let u = &triangles[j as usize];
                let (c, d) = edge_points(&u.vertices, f);
                // The same edge (a hash collision would join two others).
                if !((a == c && b == d) || (a == d && b == c)) {
                    continue;
                }
                let third = u.vertices[(f as usize + 2) % 3];
                if (third - a).dot(normal) < -BEHIND * size {
                    backed[i as usize] = true;
                }
            }
        }
    }
    backed
}

/// The end points of edge `e` of a triangle: corners `e` and `e + 1`.
pub(super) fn edge_points(v: &[DVec3; 3], e: u8) -> (DVec3, DVec3) {
    (v[e as usize], v[(e as usize + 1) % 3])
}

/// A hash of an edge's end points that does not depend on their order.
pub(super) fn edge_hash(a: DVec3, b: DVec3) -> u64 {
    let bits = |p: DVec3| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
    let (lo, hi) = if bits(a) <= bits(b) {
        (bits(a), bits(b))
    } else {
        (bits(b), bits(a))
    };
    let mut h = std::collections::hash_map::DefaultHasher::new();
    (lo, hi).hash(&mut h);
    h.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Material;

    fn quad(scene: &mut Scene, c: [DVec3; 4], m: u32) {
        scene.add_polygon(&c, m);
    }

    #[test]
    fn a_box_is_a_solid_and_a_sheet_twice_back_to_back_is_not() {
        let mut scene = Scene::default();
        let m = scene.add_material(Material::new("grey", [0.5; 3], [0.0; 3]));
        let p = |x: f64, y: f64, z: f64| DVec3::new(x, y, z);
        // A sheet modelled twice, back to back (its corners shared).
        let sheet = [p(0., 0., 0.), p(1., 0., 0.), p(1., 0., 1.), p(0., 0., 1.)];
        quad(&mut scene, sheet, m);
        let mut back = sheet;
        back.reverse();
        quad(&mut scene, back, m);
        let sheet_triangles = scene.triangles.len();
        // A unit box at x = 5, faces outwards.
        let b = |x: f64, y: f64, z: f64| p(5. + x, y, z);
        let faces = [
            [b(0., 0., 0.), b(1., 0., 0.), b(1., 0., 1.), b(0., 0., 1.)], // bottom, -y
            [b(0., 1., 0.), b(0., 1., 1.), b(1., 1., 1.), b(1., 1., 0.)], // top, +y
            [b(0., 0., 0.), b(0., 1., 0.), b(1., 1., 0.), b(1., 0., 0.)], // -z
            [b(0., 0., 1.), b(1., 0., 1.), b(1., 1., 1.), b(0., 1., 1.)], // +z
            [b(0., 0., 0.), b(0., 0., 1.), b(0., 1., 1.), b(0., 1., 0.)], // -x
            [b(1., 0., 0.), b(1., 1., 0.), b(1., 1., 1.), b(1., 0., 1.)], // +x
        ];
        for f in faces {
            quad(&mut scene, f, m);
        }
        for t in &scene.triangles[sheet_triangles..] {
            // Outward faces: the box lies behind each.
            let centre = b(0.5, 0.5, 0.5);
            assert!((centre - t.vertices[0]).dot(t.cross()) < 0.0);
        }
        let backed = solid_backed(&scene);
        assert!(backed[..sheet_triangles].iter().all(|&x| !x), "{backed:?}");
        assert!(backed[sheet_triangles..].iter().all(|&x| x), "{backed:?}");
    }
}
