//! Scene generators: the Cornell box and procedural scenes of any size, for examples and tests.
//!
//! This module owns the small helpers the generators share: a deterministic PRNG (so that a seed
//! fully determines a scene, on every platform, with no extra crate), and box/polygon builders that
//! pick each face's winding from the direction it must face rather than trusting hand-written
//! vertex orders.
//!
//! - [`cornell`]: the measured Cornell box.
//! - [`procedural`]: rooms, buildings of any size, the sealed-rooms leak test, the furnace and the
//!   parallel squares with their analytic form factor.
//! - [`interiors`]: closed realistic interiors (an office, a room lit by a window, a corridor of
//!   rooms) and thin slabs under directional light, each with probe points for the path-traced
//!   reference data.
//! - [`obj_writer`]: writes any [`Scene`](crate::scene::Scene) as OBJ + MTL.

pub mod cornell;
pub mod interiors;
pub mod obj_writer;
pub mod procedural;

pub use cornell::cornell_box;
pub use interiors::{
    corridor, hard_twin, office, thin_slab, window_room, HardTwin, Interior, Probe, SlabLight,
};
pub use obj_writer::write_obj;
pub use procedural::{
    building, furnace, parallel_rectangles_form_factor, parallel_squares,
    parallel_squares_form_factor, parallel_squares_reflecting, room, sealed_rooms,
};

use crate::scene::Scene;
use glam::DVec3;

/// splitmix64 (Steele, Lea and Flood 2014): tiny, fast, passes BigCrush, and its output depends
/// only on the seed, which is what reproducible test scenes need.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }

    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)` from the top 53 bits (exactly representable, never 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[lo, hi)`.
    pub(crate) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform integer in `0..n`; `n == 0` gives 0 rather than a panic.
    pub(crate) fn below(&mut self, n: u64) -> u64 {
        if n == 0 {
            0
        } else {
            // Modulo bias is below 2^-40 for the small n used here; irrelevant for scenes.
            self.next_u64() % n
        }
    }

    /// True with probability `p`.
    pub(crate) fn chance(&mut self, p: f64) -> bool {
        self.unit() < p
    }
}

/// Newell's normal of a polygon: robust for slightly non-planar quads (the Cornell data has some).
pub(crate) fn newell_normal(points: &[DVec3]) -> DVec3 {
    let mut n = DVec3::ZERO;
    for (k, p) in points.iter().enumerate() {
        let q = points[(k + 1) % points.len()];
        n += DVec3::new(
            (p.y - q.y) * (p.z + q.z),
            (p.z - q.z) * (p.x + q.x),
            (p.x - q.x) * (p.y + q.y),
        );
    }
    n
}

/// Adds a convex polygon whose front faces `facing` (roughly): the winding is reversed if needed,
/// so the caller states intent instead of getting vertex order right by hand.
pub(crate) fn add_facing(scene: &mut Scene, points: &[DVec3], facing: DVec3, material: u32) {
    if newell_normal(points).dot(facing) < 0.0 {
        let reversed: Vec<DVec3> = points.iter().rev().copied().collect();
        scene.add_polygon(&reversed, material);
    } else {
        scene.add_polygon(points, material);
    }
}

/// Face order of [`add_solid_box`] materials: -x, +x, -y, +y, -z, +z.
pub(crate) const FACE_NORMALS: [DVec3; 6] = [
    DVec3::NEG_X,
    DVec3::X,
    DVec3::NEG_Y,
    DVec3::Y,
    DVec3::NEG_Z,
    DVec3::Z,
];

/// The four corners of face `f` (in [`FACE_NORMALS`] order) of the box `[min, max]`, in
/// no particular winding.
pub(crate) fn box_face(min: DVec3, max: DVec3, f: usize) -> [DVec3; 4] {
    let axis = f / 2;
    let at = if f % 2 == 0 { min } else { max };
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    let corner = |a: bool, b: bool| {
        let mut p = at;
        p[u] = if a { max[u] } else { min[u] };
        p[v] = if b { max[v] } else { min[v] };
        p
    };
    [
        corner(false, false),
        corner(true, false),
        corner(true, true),
        corner(false, true),
    ]
}

/// Adds an axis-aligned box with one material per face (order of [`FACE_NORMALS`]); fronts face
/// outwards, or inwards if `inward` (a room seen from inside). Per-face materials let a slab's top
/// be a floor and its underside a ceiling while it stays one closed solid.
pub(crate) fn add_solid_box(
    scene: &mut Scene,
    min: DVec3,
    max: DVec3,
    materials: [u32; 6],
    inward: bool,
) {
    for (f, &normal) in FACE_NORMALS.iter().enumerate() {
        let facing = if inward { -normal } else { normal };
        add_facing(scene, &box_face(min, max, f), facing, materials[f]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Material;

    #[test]
    fn rng_is_deterministic_and_in_range() {
        let mut a = Rng::new(7);
        let mut b = Rng::new(7);
        let mut c = Rng::new(8);
        let va: Vec<u64> = (0..16).map(|_| a.next_u64()).collect();
        let vb: Vec<u64> = (0..16).map(|_| b.next_u64()).collect();
        let vc: Vec<u64> = (0..16).map(|_| c.next_u64()).collect();
        assert_eq!(va, vb);
        assert_ne!(va, vc);
        let mut r = Rng::new(1);
        for _ in 0..10_000 {
            let u = r.unit();
            assert!((0.0..1.0).contains(&u));
            assert!(r.below(5) < 5);
        }
        assert_eq!(r.below(0), 0);
    }

    #[test]
    fn solid_box_faces_point_the_requested_way() {
        for inward in [false, true] {
            let mut s = Scene::default();
            let m = s.add_material(Material::new("m", [0.5; 3], [0.0; 3]));
            let (min, max) = (DVec3::new(1.0, 2.0, 3.0), DVec3::new(2.0, 4.0, 7.0));
            add_solid_box(&mut s, min, max, [m; 6], inward);
            assert_eq!(s.triangles.len(), 12);
            let centre = 0.5 * (min + max);
            let area: f64 = s.triangles.iter().map(|t| t.area()).sum();
            assert!((area - 2.0 * (2.0 + 4.0 + 8.0)).abs() < 1e-12);
            for t in &s.triangles {
                let c = (t.vertices[0] + t.vertices[1] + t.vertices[2]) / 3.0;
                let out = t.cross().dot(c - centre) > 0.0;
                assert_eq!(out, !inward);
            }
        }
    }
}
