//! Which triangles have their back side inside a closed solid, where nothing is ever seen.
//!
//! **Why.** A face of a closed solid (a wall box, a slab, the box of a desk top) has its back
//! side inside the solid: no light reaches it and none leaves it. The solver would still gather
//! light there like on any other side, along every direction, and on a building's walls and
//! slabs these searches are about a third of the first pass (docs/throughput.md). The
//! voxelizer gives such back sides the material [`Material::inside_of_solids`], which gathers
//! nothing and sends nothing (`solve::propagate` skips their searches).
//!
//! **The rule.** A triangle's back side is inside when its triangle belongs to a connected piece
//! of the mesh (triangles joined through shared edges, the same two end points exactly, as in
//! `solids`) that is
//! - *closed and consistently wound*: every edge of each of its triangles is paired with one
//!   other triangle of the piece. Around an edge the triangles that meet there are taken in
//!   turn, and two neighbours pair when the wedge between them lies behind both (`pair_around`),
//!   so boxes stacked on or beside each other, sharing edges, stay separate solids; a triangle
//!   left unpaired (an open edge, a winding that flips) makes its piece open;
//! - *wound outward*: its signed volume is positive. A room modelled as a box seen from inside
//!   is closed but wound inward: its back sides face out of the room and are left alone;
//! - *empty*: no corner of another triangle of the scene lies strictly inside its bounding box.
//!   A room modelled as a box wound outward, with its furniture and lamps inside, is left alone,
//!   and so are two solids that run into each other.
//!
//! Anything in doubt keeps its back side as it was (a side that gathers), which is never wrong,
//! only slower: an open box, a box missing a face (the Cornell box's blocks have no bottom), a
//! mesh whose faces meet at T-junctions instead of shared edges.
//!
//! [`Material::inside_of_solids`]: crate::scene::Material::inside_of_solids

use super::disjoint::DisjointSets;
use super::solids::{edge_hash, edge_points};
use crate::scene::Scene;
use glam::DVec3;

/// Signed volume below which a closed piece counts as flat (relative to the cube of its bounding
/// box's diagonal): far below any modelled thickness, far above rounding.
const FLAT: f64 = 1e-12;

/// Margin, relative to the scene's bounding box diagonal, by which a corner must lie inside a
/// piece's bounding box to count as inside it: corners on its faces (a wall's foot on a slab)
/// do not.
const MARGIN: f64 = 1e-9;

/// Per triangle of `scene`: whether its back side lies inside a closed solid (see the module
/// header).
pub(crate) fn inside_backed(scene: &Scene) -> Vec<bool> {
    let triangles = &scene.triangles;
    let n = triangles.len();
    if n == 0 {
        return Vec::new();
    }
    // Every edge, keyed by its two end points in either order: (hash, triangle, edge).
    let mut edges: Vec<(u64, u32, u8)> = Vec::with_capacity(n * 3);
    for (i, t) in triangles.iter().enumerate() {
        for e in 0..3u8 {
            let (a, b) = edge_points(&t.vertices, e);
            edges.push((edge_hash(a, b), i as u32, e));
        }
    }
    edges.sort_unstable();
    let mut pieces = DisjointSets::new(n);
    // Per triangle: how many of its edges were paired with a neighbour of the same solid (each
    // must be, once), and whether it has area.
    let mut paired = vec![0u8; n];
    let mut open = vec![false; n];
    for (t, flag) in triangles.iter().zip(open.iter_mut()) {
        if t.cross().length_squared() == 0.0 {
            *flag = true;
        }
    }
    let mut around: Vec<(f64, i8, u32)> = Vec::new();
    for run in edges.chunk_by(|x, y| x.0 == y.0) {
        // The triangles of one edge (the same two end points, a hash collision aside).
        let (first, e0) = (run[0].1, run[0].2);
        let (a, b) = edge_points(&triangles[first as usize].vertices, e0);
        around.clear();
        for &(_, i, e) in run {
            let t = &triangles[i as usize];
            let (c, d) = edge_points(&t.vertices, e);
            if !((a == c && b == d) || (a == d && b == c)) {
                open[i as usize] = true;
                continue;
            }
            if let Some((angle, turn)) = wing(a, b, t.vertices[(e as usize + 2) % 3], t.cross()) {
                around.push((angle, turn, i));
            }
        }
        pair_around(&mut around, |i, j| {
            pieces.union(i, j);
            paired[i as usize] += 1;
            paired[j as usize] += 1;
        });
    }
    for (flag, &count) in open.iter_mut().zip(&paired) {
        if count != 3 {
            *flag = true;
        }
    }
    let piece_of: Vec<u32> = (0..n as u32).map(|i| pieces.find(i)).collect();
    // Per piece (by root): open, signed volume, bounding box.
    let mut closed = vec![true; n];
    let mut volume = vec![0.0f64; n];
    let mut lo = vec![DVec3::splat(f64::INFINITY); n];
    let mut hi = vec![DVec3::splat(f64::NEG_INFINITY); n];
    // Volumes are summed about a corner of each piece, for precision far from the origin.
    let mut origin = vec![None::<DVec3>; n];
    for (i, t) in triangles.iter().enumerate() {
        let p = piece_of[i] as usize;
        if open[i] {
            closed[p] = false;
        }
        let o = *origin[p].get_or_insert(t.vertices[0]);
        let [v0, v1, v2] = t.vertices.map(|v| v - o);
        volume[p] += v0.dot(v1.cross(v2)) / 6.0;
        for v in t.vertices {
            lo[p] = lo[p].min(v);
            hi[p] = hi[p].max(v);
        }
    }
    let scene_lo = lo
        .iter()
        .fold(DVec3::splat(f64::INFINITY), |a, &b| a.min(b));
    let scene_hi = hi
        .iter()
        .fold(DVec3::splat(f64::NEG_INFINITY), |a, &b| a.max(b));
    let margin = MARGIN * (scene_hi - scene_lo).length();
    let solid: Vec<bool> = (0..n)
        .map(|p| {
            if piece_of[p] as usize != p || !closed[p] {
                return false;
            }
            let diagonal = (hi[p] - lo[p]).length();
            volume[p] > FLAT * diagonal.powi(3)
        })
        .collect();
    // Empty: no corner of another piece strictly inside the bounding box. Corners sorted along
    // each axis; each piece looks along the axis where its box is thinnest.
    let corners: Vec<(DVec3, u32)> = triangles
        .iter()
        .enumerate()
        .flat_map(|(i, t)| t.vertices.map(|v| (v, piece_of[i])))
        .collect();
    let by_axis: [Vec<u32>; 3] = std::array::from_fn(|axis| {
        let mut order: Vec<u32> = (0..corners.len() as u32).collect();
        order.sort_unstable_by(|&a, &b| {
            corners[a as usize].0[axis].total_cmp(&corners[b as usize].0[axis])
        });
        order
    });
    let empty = |p: usize| {
        let (low, high) = (lo[p] + margin, hi[p] - margin);
        let extent = hi[p] - lo[p];
        let axis = (0..3)
            .min_by(|&a, &b| extent[a].total_cmp(&extent[b]))
            .unwrap_or(0);
        let order = &by_axis[axis];
        let first = order.partition_point(|&k| corners[k as usize].0[axis] <= low[axis]);
        order[first..]
            .iter()
            .map(|&k| &corners[k as usize])
            .take_while(|(v, _)| v[axis] < high[axis])
            .all(|&(v, piece)| piece as usize == p || !(v.cmpgt(low).all() && v.cmplt(high).all()))
    };
    let inside: Vec<bool> = (0..n).map(|p| solid[p] && empty(p)).collect();
    piece_of.iter().map(|&p| inside[p as usize]).collect()
}

/// Where triangle `t` (third corner `c`, unnormalised normal `cross`) lies around its edge
/// `a`-`b`: the angle of its wing (the direction from the edge to `c`) about the axis `a -> b`,
/// and whether its front turns toward increasing angle (+1) or decreasing (-1). `None` for a
/// triangle without area.
fn wing(a: DVec3, b: DVec3, c: DVec3, cross: DVec3) -> Option<(f64, i8)> {
    let axis = (b - a).normalize_or_zero();
    let w = (c - a) - axis * (c - a).dot(axis);
    if axis == DVec3::ZERO || w.length_squared() == 0.0 || cross.length_squared() == 0.0 {
        return None;
    }
    let (e1, e2) = axis.any_orthonormal_pair();
    let angle = w.dot(e2).atan2(w.dot(e1));
    let turn = if cross.dot(axis.cross(w)) > 0.0 {
        1
    } else {
        -1
    };
    Some((angle, turn))
}

/// Angles closer than this (radians) are one: coincident faces (a box standing on another).
const SAME_ANGLE: f64 = 1e-9;

/// Pairs the triangles around one edge (`(angle, turn, triangle)`, any order) into solids: going
/// round by increasing angle, a triangle whose front turns back (-1) followed by one whose
/// front turns on (+1) enclose a solid between their back sides. Faces at one angle are taken
/// with the one turning on first, so that two faces in contact (a box standing on another, its
/// bottom on the other's top) never enclose a solid of no thickness between them.
fn pair_around(around: &mut [(f64, i8, u32)], mut join: impl FnMut(u32, u32)) {
    around.sort_unstable_by(|x, y| x.0.total_cmp(&y.0).then(x.2.cmp(&y.2)));
    // Runs of one angle, turning on first.
    let mut start = 0;
    while start < around.len() {
        let mut end = start + 1;
        while end < around.len() && around[end].0 - around[end - 1].0 < SAME_ANGLE {
            end += 1;
        }
        around[start..end].sort_by(|x, y| y.1.cmp(&x.1).then(x.2.cmp(&y.2)));
        start = end;
    }
    let m = around.len();
    if m < 2 {
        return;
    }
    for k in 0..m {
        let (x, y) = (around[k], around[(k + 1) % m]);
        if x.1 < 0 && y.1 > 0 {
            join(x.2, y.2);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Material;

    fn p(x: f64, y: f64, z: f64) -> DVec3 {
        DVec3::new(x, y, z)
    }

    /// The box `[lo, lo + size]` (`Scene::add_box`: two triangles a face, in the order -x, +x,
    /// -y, +y, -z, +z), wound outward (inward if `inward`); `skip` leaves out that face.
    fn add_box(
        scene: &mut Scene,
        lo: DVec3,
        size: DVec3,
        m: u32,
        inward: bool,
        skip: Option<usize>,
    ) {
        let first = scene.triangles.len();
        scene.add_box(lo, lo + size, m, inward);
        if let Some(k) = skip {
            scene.triangles.drain(first + 2 * k..first + 2 * k + 2);
        }
    }

    fn scene() -> (Scene, u32) {
        let mut scene = Scene::default();
        let m = scene.add_material(Material::new("grey", [0.5; 3], [0.0; 3]));
        (scene, m)
    }

    #[test]
    fn faces_of_a_closed_outward_box_are_inside_backed() {
        let (mut s, m) = scene();
        add_box(&mut s, p(0., 0., 0.), p(0.2, 3., 5.), m, false, None);
        // A second box standing on the first's top face, touching it only.
        add_box(&mut s, p(0., 3., 0.), p(0.2, 0.3, 5.), m, false, None);
        let inside = inside_backed(&s);
        assert_eq!(inside.len(), 24);
        assert!(inside.iter().all(|&x| x), "{inside:?}");
    }

    #[test]
    fn inward_open_or_occupied_boxes_keep_their_back_sides() {
        // A room seen from inside: closed, wound inward.
        let (mut s, m) = scene();
        add_box(&mut s, p(0., 0., 0.), p(4., 3., 5.), m, true, None);
        assert!(inside_backed(&s).iter().all(|&x| !x));
        // A box without its top: its inside is seen.
        let (mut s, m) = scene();
        add_box(&mut s, p(0., 0., 0.), p(1., 1., 1.), m, false, Some(3));
        assert!(inside_backed(&s).iter().all(|&x| !x));
        // A room wound outward by mistake, with a desk inside: the desk is a solid, the room is
        // not (the desk's corners lie inside its box).
        let (mut s, m) = scene();
        add_box(&mut s, p(0., 0., 0.), p(4., 3., 5.), m, false, None);
        add_box(&mut s, p(1., 0., 1.), p(1., 0.8, 0.6), m, false, None);
        let inside = inside_backed(&s);
        assert!(inside[..12].iter().all(|&x| !x), "{inside:?}");
        assert!(inside[12..].iter().all(|&x| x), "{inside:?}");
        // Two boxes running into each other: neither.
        let (mut s, m) = scene();
        add_box(&mut s, p(0., 0., 0.), p(1., 1., 1.), m, false, None);
        add_box(&mut s, p(0.5, 0.5, 0.5), p(1., 1., 1.), m, false, None);
        assert!(inside_backed(&s).iter().all(|&x| !x));
        // A sheet modelled twice back to back: closed over its edges, but flat.
        let (mut s, m) = scene();
        let sheet = [p(0., 0., 0.), p(1., 0., 0.), p(1., 0., 1.), p(0., 0., 1.)];
        s.add_polygon(&sheet, m);
        let mut back = sheet;
        back.reverse();
        s.add_polygon(&back, m);
        assert!(inside_backed(&s).iter().all(|&x| !x));
    }

    #[test]
    fn boxes_sharing_edges_or_a_face_are_each_a_solid() {
        // Two boxes sharing one edge exactly (the same end points): four triangles meet there,
        // paired by the side their solid lies on.
        let (mut s, m) = scene();
        add_box(&mut s, p(0., 0., 0.), p(1., 1., 1.), m, false, None);
        add_box(&mut s, p(1., 1., 0.), p(1., 1., 1.), m, false, None);
        assert!(inside_backed(&s).iter().all(|&x| x));
        // A stack of two boxes of one footprint, and the same stack turned so that the faces in
        // contact meet at angles near the wrap of the angle's range.
        for turn in [0.0, std::f64::consts::PI - 1e-12, 1.234] {
            let (mut s, m) = scene();
            add_box(&mut s, p(0., 0., 0.), p(1., 1., 1.), m, false, None);
            add_box(&mut s, p(0., 1., 0.), p(1., 1., 1.), m, false, None);
            let (sin, cos) = turn.sin_cos();
            for t in &mut s.triangles {
                for v in &mut t.vertices {
                    *v = p(cos * v.x - sin * v.y, sin * v.x + cos * v.y, v.z);
                }
            }
            let inside = inside_backed(&s);
            assert!(inside.iter().all(|&x| x), "turned by {turn}: {inside:?}");
        }
    }
}
