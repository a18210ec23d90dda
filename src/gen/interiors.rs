//! Closed, realistic interiors and thin-feature boxes, each with its own probe points: the scenes
//! the path-traced reference (`tools/reference/mitsuba_reference.py`, data under
//! `tests/data/reference/`) is computed for.
//!
//! - [`office`]: a 12 x 3 x 8 m open-plan office with 12 suspended luminaires (6 cm housings, a
//!   one-sided emitting quad 1 mm below each housing's underside), 16 desks on legs, 5 cm thick
//!   partitions and a row of cabinets along the back wall.
//! - [`window_room`]: a 5 x 2.8 x 4 m furnished room lit only by a 2 x 1.4 m emitting quad set
//!   flush into an opening of one wall (a window), with a sofa, a table, a shelf and a 1 cm rug.
//! - [`corridor`]: a 12 m corridor, 2 m wide and 3 m tall, with six rooms opening onto it through
//!   door openings in 15 cm walls, lit by 0.2 x 0.2 m lamps (one per room, three in the corridor).
//! - [`thin_slab`]: a closed 1 m box with a 0.6 x 0.6 m slab of a given thickness in voxels (at
//!   resolution 128) floating in the middle, axis-aligned or tilted, lit from one side wall or
//!   at grazing angles from a strip of the ceiling beside the slab.
//! - [`hard_twin`]: the furnace hard cases of `tests/hard_cases.rs` (a box of reflectance 0.999,
//!   a black box, a slab thinner than a voxel and a cube on voxel corners) lit by one lamp.
//!
//! Every scene is closed: an inward-facing shell (a box seen from inside, possibly with an opening
//! that an emitter fills exactly) holds everything else, so no light leaves and a solve must
//! absorb exactly what the emitters emit. Solids are closed boxes with their fronts facing out;
//! solids may touch (a desk's legs stand on the floor, cabinets stand against a wall and each
//! other) but never overlap. Units are metres, y is up.
//!
//! Probes ([`Probe`]) are placed per kind of surface (their `surface` label), uniformly at random
//! (a fixed seed) inside rectangles of the faces, at least a margin from the rectangle's edges
//! (0.1 m; less on faces too small for it, such as a housing's 6 cm sides) and at least a
//! clearance from every other solid or emitter in front of the face, so that no probe sits in a
//! corner, under a desk leg or on a lamp. The thin slabs get a regular 5 x 5 grid on each face
//! inside 10 % margins. Everything is deterministic; the tilted slab's rotation uses `sin` and
//! `cos`, which can differ in the last bit between platforms' maths libraries.

use super::{add_facing, box_face, Rng, FACE_NORMALS};
use crate::scene::{Material, Scene};
use glam::{DMat3, DVec3};
use std::fmt::Write as _;

/// A point on a surface where the reference radiosity is known: `B` of the side `normal` faces.
#[derive(Clone, Debug, PartialEq)]
pub struct Probe {
    pub point: DVec3,
    /// Unit normal of the side the probe looks at.
    pub normal: DVec3,
    /// Kind of surface (`floor`, `partition`, `slab -x`, ...): tests average per kind or face.
    pub surface: String,
}

/// A generated scene and its probes.
#[derive(Clone, Debug)]
pub struct Interior {
    pub scene: Scene,
    pub probes: Vec<Probe>,
}

/// Rows `x,y,z,nx,ny,nz` with a header, as `voxrad probe --points` reads them.
pub fn probes_csv(probes: &[Probe]) -> String {
    let mut s = String::from("x,y,z,nx,ny,nz\n");
    for p in probes {
        let (q, n) = (p.point, p.normal);
        let _ = writeln!(s, "{},{},{},{},{},{}", q.x, q.y, q.z, n.x, n.y, n.z);
    }
    s
}

/// Rows `probe,surface` (probe index from 0, in the order of [`probes_csv`]).
pub fn surfaces_csv(probes: &[Probe]) -> String {
    let mut s = String::from("probe,surface\n");
    for (i, p) in probes.iter().enumerate() {
        let _ = writeln!(s, "{i},{}", p.surface);
    }
    s
}

// ---------------------------------------------------------------------------------------------
// Building blocks: solids (boxes, optionally rotated about their centre), the shell, emitters,
// and probe regions.

#[derive(Clone, Debug)]
struct Solid {
    min: DVec3,
    max: DVec3,
    /// Rotation about the box centre; `None` keeps the exact axis-aligned coordinates.
    rotation: Option<DMat3>,
}

impl Solid {
    fn centre(&self) -> DVec3 {
        0.5 * (self.min + self.max)
    }

    fn to_world(&self, p: DVec3) -> DVec3 {
        match self.rotation {
            Some(r) => self.centre() + r * (p - self.centre()),
            None => p,
        }
    }

    /// World-space axis-aligned bounds (of the rotated box if rotated).
    fn bounds(&self) -> (DVec3, DVec3) {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for f in 0..6 {
            for c in box_face(self.min, self.max, f) {
                let w = self.to_world(c);
                lo = lo.min(w);
                hi = hi.max(w);
            }
        }
        (lo, hi)
    }
}

/// A rectangle where probes of one label may go: `origin + a u + b v`, `a, b` in `[0, 1]`.
#[derive(Clone, Debug)]
struct Region {
    label: &'static str,
    origin: DVec3,
    u: DVec3,
    v: DVec3,
    normal: DVec3,
    /// Obstacle owner to ignore (the surface the region lies on).
    owner: usize,
}

/// An axis-aligned obstacle box for the clearance test, and who it belongs to.
#[derive(Clone, Copy, Debug)]
struct Obstacle {
    min: DVec3,
    max: DVec3,
    owner: usize,
}

#[derive(Default)]
struct Builder {
    scene: Scene,
    /// Interior bounds of the shell.
    shell: Option<(DVec3, DVec3)>,
    regions: Vec<Region>,
    obstacles: Vec<Obstacle>,
    /// Owner ids: 0 is the shell, solids and emitters count up from 1.
    owners: usize,
    /// Emitting quads as (corners, facing), for the tests.
    emitters: Vec<([DVec3; 4], DVec3)>,
}

/// Corner `k` of the rectangle `[lo, hi]` lying in the plane `axis = lo[axis]`, counter-clockwise
/// in (u, v) = the next two axes.
fn rect_corners(lo: DVec3, hi: DVec3, axis: usize) -> [DVec3; 4] {
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    let c = |a: bool, b: bool| {
        let mut p = lo;
        p[u] = if a { hi[u] } else { lo[u] };
        p[v] = if b { hi[v] } else { lo[v] };
        p
    };
    [
        c(false, false),
        c(true, false),
        c(true, true),
        c(false, true),
    ]
}

fn axis_of(normal: DVec3) -> usize {
    let a = normal.abs();
    if a.x >= a.y && a.x >= a.z {
        0
    } else if a.y >= a.z {
        1
    } else {
        2
    }
}

impl Builder {
    fn new(source: &str) -> Self {
        Builder {
            scene: Scene {
                source: source.into(),
                ..Scene::default()
            },
            owners: 1,
            ..Builder::default()
        }
    }

    fn material(&mut self, name: &str, kd: [f64; 3], ke: [f64; 3]) -> u32 {
        self.scene.add_material(Material::new(name, kd, ke))
    }

    fn next_owner(&mut self) -> usize {
        self.owners += 1;
        self.owners - 1
    }

    /// The room's shell `[min, max]`, fronts facing in. `materials` and `labels` per face in
    /// [`FACE_NORMALS`] order. `opening`: a face index and the world rectangle (zero extent along
    /// the face's axis) left open in it, for an emitter to fill; that face is built from the
    /// eight rectangles around the opening (no T-junctions).
    fn shell(
        &mut self,
        min: DVec3,
        max: DVec3,
        materials: [u32; 6],
        labels: [Option<&'static str>; 6],
        opening: Option<(usize, DVec3, DVec3)>,
    ) {
        self.shell = Some((min, max));
        for (f, &outward) in FACE_NORMALS.iter().enumerate() {
            let facing = -outward;
            let axis = f / 2;
            let at = if f % 2 == 0 { min[axis] } else { max[axis] };
            let mut lo = min;
            let mut hi = max;
            lo[axis] = at;
            hi[axis] = at;
            // Obstacle for clearance tests of other surfaces' probes: the face as a flat box.
            self.obstacles.push(Obstacle {
                min: lo,
                max: hi,
                owner: 0,
            });
            let pieces: Vec<(DVec3, DVec3)> = match opening {
                Some((of, olo, ohi)) if of == f => {
                    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                    let us = [lo[u], olo[u], ohi[u], hi[u]];
                    let vs = [lo[v], olo[v], ohi[v], hi[v]];
                    let mut out = Vec::new();
                    for i in 0..3 {
                        for j in 0..3 {
                            if i == 1 && j == 1 {
                                continue;
                            }
                            let mut a = lo;
                            let mut b = lo;
                            a[u] = us[i];
                            b[u] = us[i + 1];
                            a[v] = vs[j];
                            b[v] = vs[j + 1];
                            out.push((a, b));
                        }
                    }
                    out
                }
                _ => vec![(lo, hi)],
            };
            for (a, b) in pieces {
                add_facing(
                    &mut self.scene,
                    &rect_corners(a, b, axis),
                    facing,
                    materials[f],
                );
                if let Some(label) = labels[f] {
                    self.region(label, a, b, facing, 0);
                }
            }
        }
    }

    /// A probe region on the axis-aligned rectangle `[lo, hi]` (flat along the normal's axis).
    fn region(&mut self, label: &'static str, lo: DVec3, hi: DVec3, normal: DVec3, owner: usize) {
        let axis = axis_of(normal);
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        let mut du = DVec3::ZERO;
        let mut dv = DVec3::ZERO;
        du[u] = hi[u] - lo[u];
        dv[v] = hi[v] - lo[v];
        self.regions.push(Region {
            label,
            origin: lo,
            u: du,
            v: dv,
            normal,
            owner,
        });
    }

    /// A closed solid box, fronts facing out; faces with a label get probe regions.
    fn solid(
        &mut self,
        min: DVec3,
        max: DVec3,
        material: u32,
        labels: [Option<&'static str>; 6],
    ) -> usize {
        self.solid_rotated(min, max, None, [material; 6], labels)
    }

    fn solid_rotated(
        &mut self,
        min: DVec3,
        max: DVec3,
        rotation: Option<DMat3>,
        materials: [u32; 6],
        labels: [Option<&'static str>; 6],
    ) -> usize {
        let owner = self.next_owner();
        let s = Solid { min, max, rotation };
        let (lo, hi) = s.bounds();
        self.obstacles.push(Obstacle {
            min: lo,
            max: hi,
            owner,
        });
        for (f, &n) in FACE_NORMALS.iter().enumerate() {
            let corners = box_face(min, max, f).map(|c| s.to_world(c));
            let facing = match rotation {
                Some(r) => r * n,
                None => n,
            };
            add_facing(&mut self.scene, &corners, facing, materials[f]);
            if let (Some(label), None) = (labels[f], rotation) {
                let axis = f / 2;
                let mut a = min;
                let mut b = max;
                let at = if f % 2 == 0 { min[axis] } else { max[axis] };
                a[axis] = at;
                b[axis] = at;
                self.region(label, a, b, n, owner);
            }
        }
        owner
    }

    /// A one-sided emitting rectangle `[lo, hi]` (flat along one axis) whose front faces `facing`.
    fn emitter(&mut self, lo: DVec3, hi: DVec3, facing: DVec3, material: u32) {
        let axis = axis_of(facing);
        let corners = rect_corners(lo, hi, axis);
        add_facing(&mut self.scene, &corners, facing, material);
        let owner = self.next_owner();
        self.obstacles.push(Obstacle {
            min: lo,
            max: hi,
            owner,
        });
        self.emitters.push((corners, facing));
    }

    /// Distance from `p` to the part of obstacle `o` in the closed half-space in front of the
    /// plane through `p` with normal `n` (axis-aligned normals), or infinity if none of it is.
    fn clearance(p: DVec3, n: DVec3, o: &Obstacle) -> f64 {
        let (mut lo, mut hi) = (o.min, o.max);
        let axis = axis_of(n);
        if n[axis] > 0.0 {
            lo[axis] = lo[axis].max(p[axis]);
        } else {
            hi[axis] = hi[axis].min(p[axis]);
        }
        if lo[axis] > hi[axis] {
            return f64::INFINITY;
        }
        let d = (lo - p).max(p - hi).max(DVec3::ZERO);
        d.length()
    }

    /// Places `count` probes on the regions labelled `label`: region by area, uniform inside
    /// margins of `margin` (at most 40 % of a side), at least `clearance` from other obstacles
    /// in front. Gives up on a probe after many misses (the tests check the counts).
    fn probes(
        &self,
        rng: &mut Rng,
        label: &'static str,
        count: usize,
        margin: f64,
        clearance: f64,
        out: &mut Vec<Probe>,
    ) {
        let regions: Vec<&Region> = self.regions.iter().filter(|r| r.label == label).collect();
        let areas: Vec<f64> = regions
            .iter()
            .map(|r| r.u.length() * r.v.length())
            .collect();
        let total: f64 = areas.iter().sum();
        if regions.is_empty() || total <= 0.0 {
            return;
        }
        let mut placed = 0;
        let mut misses = 0;
        while placed < count && misses < 10_000 {
            let mut pick = rng.unit() * total;
            let mut r = regions[regions.len() - 1];
            for (k, &a) in areas.iter().enumerate() {
                if pick < a {
                    r = regions[k];
                    break;
                }
                pick -= a;
            }
            let (lu, lv) = (r.u.length(), r.v.length());
            let mu = margin.min(0.4 * lu) / lu;
            let mv = margin.min(0.4 * lv) / lv;
            let a = rng.range(mu, 1.0 - mu);
            let b = rng.range(mv, 1.0 - mv);
            let p = r.origin + a * r.u + b * r.v;
            let clear = self
                .obstacles
                .iter()
                .filter(|o| o.owner != r.owner)
                .all(|o| Self::clearance(p, r.normal, o) >= clearance);
            if clear {
                out.push(Probe {
                    point: p,
                    normal: r.normal,
                    surface: label.to_string(),
                });
                placed += 1;
                misses = 0;
            } else {
                misses += 1;
            }
        }
    }
}

fn v(x: f64, y: f64, z: f64) -> DVec3 {
    DVec3::new(x, y, z)
}

const NONE6: [Option<&str>; 6] = [None; 6];

// ---------------------------------------------------------------------------------------------
// The office.

/// Material indices of [`office`].
pub mod office_materials {
    pub const WALL: u32 = 0;
    pub const CEILING: u32 = 1;
    pub const FLOOR: u32 = 2;
    pub const DESK: u32 = 3;
    pub const PARTITION: u32 = 4;
    pub const CABINET: u32 = 5;
    pub const HOUSING: u32 = 6;
    /// The luminaires' emitting undersides.
    pub const LAMP: u32 = 7;
    /// Emitted radiosity of every lamp quad.
    pub const LAMP_EMISSION: [f64; 3] = [3000.0, 3000.0, 3000.0];
}

/// A table of `w` x `d` (x, z) with its top (3 cm) at `top` metres, on four 5 cm legs.
fn desk(b: &mut Builder, x0: f64, z0: f64, w: f64, d: f64, top: f64, m: u32) {
    let t = 0.03;
    let leg = 0.05;
    let inset = 0.03;
    b.solid(
        v(x0, top - t, z0),
        v(x0 + w, top, z0 + d),
        m,
        [None, None, None, Some("desk top"), None, None],
    );
    for (lx, lz) in [
        (x0 + inset, z0 + inset),
        (x0 + w - inset - leg, z0 + inset),
        (x0 + inset, z0 + d - inset - leg),
        (x0 + w - inset - leg, z0 + d - inset - leg),
    ] {
        b.solid(v(lx, 0.0, lz), v(lx + leg, top - t, lz + leg), m, NONE6);
    }
}

/// The open-plan office (see the module header). Luminaire housings are 1.2 x 0.06 x 0.3 m with
/// their tops 0.5 m below the 3 m ceiling; each emitting quad (`E` = 3000 per channel, facing
/// down) is the size of the housing's underside and hangs 1 mm below it (not flush: two
/// coincident faces would make the side that is seen ambiguous). Four groups of 2 x 2 desks
/// (1.6 x 0.8 m, top 0.75 m) have a 1.2 m partition down their middle, a 5.4 m partition
/// separates the left and right groups, and eight 1 m cabinets (1.1 m tall) stand against the
/// back wall. 108 probes on floor, ceiling, walls, desk tops, both faces of the partitions,
/// cabinet tops and fronts, and the housings' tops and long sides.
pub fn office() -> Interior {
    use office_materials::*;
    let mut b = Builder::new("generator:office");
    let table = [
        ("wall", [0.66, 0.65, 0.62], [0.0; 3]),
        ("ceiling", [0.8, 0.8, 0.8], [0.0; 3]),
        ("floor", [0.32, 0.3, 0.27], [0.0; 3]),
        ("desk", [0.55, 0.5, 0.42], [0.0; 3]),
        ("partition", [0.38, 0.5, 0.62], [0.0; 3]),
        ("cabinet", [0.6, 0.6, 0.6], [0.0; 3]),
        ("housing", [0.7, 0.7, 0.7], [0.0; 3]),
        ("lamp", [0.7, 0.7, 0.7], LAMP_EMISSION),
    ];
    for (name, kd, ke) in table {
        b.material(name, kd, ke);
    }
    let (w, h, d) = (12.0, 3.0, 8.0);
    b.shell(
        DVec3::ZERO,
        v(w, h, d),
        [WALL, WALL, FLOOR, CEILING, WALL, WALL],
        [
            Some("wall"),
            Some("wall"),
            Some("floor"),
            Some("ceiling"),
            Some("wall"),
            Some("wall"),
        ],
        None,
    );
    // Desk groups: two desks along x, two rows facing each other across a spine partition.
    let (dw, dd, top) = (1.6, 0.8, 0.75);
    let half = 0.025;
    for cx in [3.0, 9.0] {
        for cz in [2.2, 5.2] {
            for (x0, z0) in [
                (cx - 1.62, cz - half - dd),
                (cx + 0.02, cz - half - dd),
                (cx - 1.62, cz + half),
                (cx + 0.02, cz + half),
            ] {
                desk(&mut b, x0, z0, dw, dd, top, DESK);
            }
            b.solid(
                v(cx - 1.65, 0.0, cz - half),
                v(cx + 1.65, 1.2, cz + half),
                PARTITION,
                [None, None, None, None, Some("partition"), Some("partition")],
            );
        }
    }
    b.solid(
        v(6.0 - half, 0.0, 1.2),
        v(6.0 + half, 1.2, 6.2),
        PARTITION,
        [Some("partition"), Some("partition"), None, None, None, None],
    );
    // Cabinets against the back wall (z = 8), pressed against each other.
    for k in 0..8 {
        let x0 = 2.0 + k as f64;
        b.solid(
            v(x0, 0.0, d - 0.45),
            v(x0 + 1.0, 1.1, d),
            CABINET,
            [
                None,
                None,
                None,
                Some("cabinet top"),
                Some("cabinet front"),
                None,
            ],
        );
    }
    // Luminaires: housings and their emitting undersides.
    for cx in [1.5, 4.5, 7.5, 10.5] {
        for cz in [1.5, 4.0, 6.5] {
            let (lo, hi) = (v(cx - 0.6, 2.44, cz - 0.15), v(cx + 0.6, 2.5, cz + 0.15));
            b.solid(
                lo,
                hi,
                HOUSING,
                [
                    None,
                    None,
                    None,
                    Some("housing top"),
                    Some("housing side"),
                    Some("housing side"),
                ],
            );
            let y = lo.y - 0.001;
            b.emitter(v(lo.x, y, lo.z), v(hi.x, y, hi.z), DVec3::NEG_Y, LAMP);
        }
    }
    let mut rng = Rng::new(0x0ff1ce);
    let mut probes = Vec::new();
    for (label, count, margin, clearance) in [
        ("floor", 16, 0.1, 0.1),
        ("ceiling", 12, 0.1, 0.1),
        ("wall", 16, 0.1, 0.1),
        ("desk top", 16, 0.1, 0.1),
        ("partition", 20, 0.1, 0.1),
        ("cabinet top", 6, 0.1, 0.1),
        ("cabinet front", 6, 0.1, 0.1),
        ("housing top", 8, 0.1, 0.1),
        ("housing side", 8, 0.1, 0.02),
    ] {
        b.probes(&mut rng, label, count, margin, clearance, &mut probes);
    }
    Interior {
        scene: b.scene,
        probes,
    }
}

// ---------------------------------------------------------------------------------------------
// The room lit by a window.

/// Material indices of [`window_room`].
pub mod window_room_materials {
    pub const WALL: u32 = 0;
    pub const CEILING: u32 = 1;
    pub const FLOOR: u32 = 2;
    pub const WINDOW: u32 = 3;
    pub const SOFA: u32 = 4;
    pub const TABLE: u32 = 5;
    pub const SHELF: u32 = 6;
    pub const RUG: u32 = 7;
    /// Emitted radiosity of the window (a bluish daylight).
    pub const WINDOW_EMISSION: [f64; 3] = [900.0, 950.0, 1050.0];
}

/// A furnished 5 x 2.8 x 4 m room (see the module header) lit by a 2 x 1.4 m window: an
/// emitting quad (`Kd` 0.1) filling an opening of the wall z = 0 (x 1.5 to 3.5 m, sill 0.8 m),
/// flush with it and facing into the room. A sofa (seat, back and arms, against the wall
/// z = 4), a table on legs standing on a 1 cm rug, a shelf of four boards against the wall
/// x = 5. 100 probes on floor, ceiling, walls, the rug, the table top, the sofa, the shelf's
/// boards and its outer side.
pub fn window_room() -> Interior {
    use window_room_materials::*;
    let mut b = Builder::new("generator:window_room");
    let table = [
        ("wall", [0.7, 0.68, 0.64], [0.0; 3]),
        ("ceiling", [0.82, 0.82, 0.82], [0.0; 3]),
        ("floor", [0.45, 0.32, 0.2], [0.0; 3]),
        ("window", [0.1, 0.1, 0.1], WINDOW_EMISSION),
        ("sofa", [0.3, 0.36, 0.5], [0.0; 3]),
        ("table", [0.5, 0.36, 0.22], [0.0; 3]),
        ("shelf", [0.56, 0.46, 0.32], [0.0; 3]),
        ("rug", [0.62, 0.22, 0.16], [0.0; 3]),
    ];
    for (name, kd, ke) in table {
        b.material(name, kd, ke);
    }
    let (w, h, d) = (5.0, 2.8, 4.0);
    let (win_lo, win_hi) = (v(1.5, 0.8, 0.0), v(3.5, 2.2, 0.0));
    b.shell(
        DVec3::ZERO,
        v(w, h, d),
        [WALL, WALL, FLOOR, CEILING, WALL, WALL],
        [
            Some("wall"),
            Some("wall"),
            Some("floor"),
            Some("ceiling"),
            Some("wall"),
            Some("wall"),
        ],
        Some((4, win_lo, win_hi)),
    );
    b.emitter(win_lo, win_hi, DVec3::Z, WINDOW);
    // Sofa: seat, back against the wall z = 4, two arms.
    b.solid(
        v(1.4, 0.0, 3.1),
        v(3.6, 0.42, 3.8),
        SOFA,
        [
            None,
            None,
            None,
            Some("sofa seat"),
            Some("sofa front"),
            None,
        ],
    );
    b.solid(
        v(1.4, 0.0, 3.8),
        v(3.6, 0.85, 4.0),
        SOFA,
        [None, None, None, None, Some("sofa back"), None],
    );
    b.solid(v(1.2, 0.0, 3.1), v(1.4, 0.6, 4.0), SOFA, NONE6);
    b.solid(v(3.6, 0.0, 3.1), v(3.8, 0.6, 4.0), SOFA, NONE6);
    // Rug and a table standing on it.
    b.solid(
        v(1.2, 0.0, 1.0),
        v(3.8, 0.01, 2.8),
        RUG,
        [None, None, None, Some("rug"), None, None],
    );
    let (tx, tz, tw, td, top) = (1.9, 1.5, 1.2, 0.8, 0.75);
    b.solid(
        v(tx, top - 0.03, tz),
        v(tx + tw, top, tz + td),
        TABLE,
        [None, None, None, Some("table top"), None, None],
    );
    for (lx, lz) in [
        (tx + 0.04, tz + 0.04),
        (tx + tw - 0.09, tz + 0.04),
        (tx + 0.04, tz + td - 0.09),
        (tx + tw - 0.09, tz + td - 0.09),
    ] {
        b.solid(
            v(lx, 0.01, lz),
            v(lx + 0.05, top - 0.03, lz + 0.05),
            TABLE,
            NONE6,
        );
    }
    // Shelf against the wall x = 5: two side panels and four boards.
    let (sx0, sz0, sz1, sh) = (4.65, 0.6, 1.6, 1.8);
    let t = 0.02;
    b.solid(
        v(sx0, 0.0, sz0),
        v(w, sh, sz0 + t),
        SHELF,
        [None, None, None, None, Some("shelf side"), None],
    );
    b.solid(v(sx0, 0.0, sz1 - t), v(w, sh, sz1), SHELF, NONE6);
    for y in [0.0, 0.6, 1.2, sh - t] {
        b.solid(
            v(sx0, y, sz0 + t),
            v(w, y + t, sz1 - t),
            SHELF,
            [None, None, None, Some("shelf board"), None, None],
        );
    }
    let mut rng = Rng::new(0x3a7d0);
    let mut probes = Vec::new();
    for (label, count, margin, clearance) in [
        ("floor", 14, 0.1, 0.1),
        ("ceiling", 12, 0.1, 0.1),
        ("wall", 24, 0.1, 0.1),
        ("rug", 12, 0.1, 0.1),
        ("table top", 8, 0.1, 0.1),
        ("sofa seat", 8, 0.1, 0.1),
        ("sofa back", 4, 0.1, 0.1),
        ("sofa front", 4, 0.1, 0.1),
        ("shelf board", 10, 0.1, 0.1),
        ("shelf side", 4, 0.1, 0.1),
    ] {
        b.probes(&mut rng, label, count, margin, clearance, &mut probes);
    }
    Interior {
        scene: b.scene,
        probes,
    }
}

// ---------------------------------------------------------------------------------------------
// The corridor.

/// Material indices of [`corridor`].
pub mod corridor_materials {
    pub const WALL: u32 = 0;
    pub const CEILING: u32 = 1;
    pub const FLOOR: u32 = 2;
    pub const LAMP: u32 = 3;
    /// Emitted radiosity of every 0.2 x 0.2 m lamp.
    pub const LAMP_EMISSION: [f64; 3] = [20000.0, 19000.0, 17000.0];
}

/// A 12 m corridor (z from 4 to 6 m, 3 m tall) between two rows of three 4 m rooms (see the
/// module header), inside one closed 12 x 3 x 10 m shell. Walls are 0.15 m thick boxes from
/// floor to ceiling; each room has one 0.9 x 2.1 m door opening onto the corridor (a lintel
/// box above it). Lamps: 0.2 x 0.2 m emitting quads 1 cm below the ceiling facing down, one at
/// the centre of each room and three along the corridor. 96 probes on the corridor's floor,
/// ceiling, walls and end walls and on the rooms' floors, ceilings and walls.
pub fn corridor() -> Interior {
    use corridor_materials::*;
    let mut b = Builder::new("generator:corridor");
    let table = [
        ("wall", [0.68, 0.66, 0.6], [0.0; 3]),
        ("ceiling", [0.8, 0.8, 0.8], [0.0; 3]),
        ("floor", [0.4, 0.3, 0.22], [0.0; 3]),
        ("lamp", [0.7, 0.7, 0.7], LAMP_EMISSION),
    ];
    for (name, kd, ke) in table {
        b.material(name, kd, ke);
    }
    let (w, h, d) = (12.0, 3.0, 10.0);
    let (c0, c1) = (4.0, 6.0);
    let t = 0.15;
    b.shell(
        DVec3::ZERO,
        v(w, h, d),
        [WALL, WALL, FLOOR, CEILING, WALL, WALL],
        [None; 6],
        None,
    );
    // Cross walls between rooms, both rows.
    let xs = [4.0, 8.0];
    for &x in &xs {
        for (z0, z1) in [(0.0, c0 - t), (c1 + t, d)] {
            b.solid(
                v(x - 0.5 * t, 0.0, z0),
                v(x + 0.5 * t, h, z1),
                WALL,
                [Some("room wall"), Some("room wall"), None, None, None, None],
            );
        }
    }
    // Corridor walls with one door per room: (room index along x, door offset from the room's
    // left end), south then north.
    let (door_w, door_h) = (0.9, 2.1);
    let rooms_x = [
        (0.0, 4.0 - 0.5 * t),
        (4.0 + 0.5 * t, 8.0 - 0.5 * t),
        (8.0 + 0.5 * t, w),
    ];
    for (row, (z0, z1), corridor_face, room_face) in [
        (0, (c0 - t, c0), 5usize, 4usize),
        (1, (c1, c1 + t), 4usize, 5usize),
    ] {
        let offsets = if row == 0 {
            [1.5, 0.6, 2.4]
        } else {
            [2.3, 1.1, 0.5]
        };
        let mut x = 0.0;
        let mut labels = [None; 6];
        labels[corridor_face] = Some("corridor wall");
        labels[room_face] = Some("room wall");
        for (k, &(rx0, _)) in rooms_x.iter().enumerate() {
            let dx = rx0 + offsets[k];
            b.solid(v(x, 0.0, z0), v(dx, h, z1), WALL, labels);
            b.solid(v(dx, door_h, z0), v(dx + door_w, h, z1), WALL, NONE6);
            x = dx + door_w;
        }
        b.solid(v(x, 0.0, z0), v(w, h, z1), WALL, labels);
    }
    // Regions of the shell, by part: rooms and corridor.
    let zs_rooms = [(0.0, c0 - t), (c1 + t, d)];
    for &(z0, z1) in &zs_rooms {
        for &(x0, x1) in &rooms_x {
            b.region("room floor", v(x0, 0.0, z0), v(x1, 0.0, z1), DVec3::Y, 0);
            b.region("room ceiling", v(x0, h, z0), v(x1, h, z1), DVec3::NEG_Y, 0);
        }
        b.region("room wall", v(0.0, 0.0, z0), v(0.0, h, z1), DVec3::X, 0);
        b.region("room wall", v(w, 0.0, z0), v(w, h, z1), DVec3::NEG_X, 0);
    }
    b.region("room wall", v(0.0, 0.0, 0.0), v(w, h, 0.0), DVec3::Z, 0);
    b.region("room wall", v(0.0, 0.0, d), v(w, h, d), DVec3::NEG_Z, 0);
    b.region(
        "corridor floor",
        v(0.0, 0.0, c0),
        v(w, 0.0, c1),
        DVec3::Y,
        0,
    );
    b.region(
        "corridor ceiling",
        v(0.0, h, c0),
        v(w, h, c1),
        DVec3::NEG_Y,
        0,
    );
    b.region("corridor end", v(0.0, 0.0, c0), v(0.0, h, c1), DVec3::X, 0);
    b.region("corridor end", v(w, 0.0, c0), v(w, h, c1), DVec3::NEG_X, 0);
    // Lamps.
    let s = 0.1;
    let y = h - 0.01;
    let lamp = |b: &mut Builder, cx: f64, cz: f64| {
        b.emitter(
            v(cx - s, y, cz - s),
            v(cx + s, y, cz + s),
            DVec3::NEG_Y,
            LAMP,
        );
    };
    for &(z0, z1) in &zs_rooms {
        for &(x0, x1) in &rooms_x {
            lamp(&mut b, 0.5 * (x0 + x1), 0.5 * (z0 + z1));
        }
    }
    for cx in [2.0, 6.0, 10.0] {
        lamp(&mut b, cx, 0.5 * (c0 + c1));
    }
    let mut rng = Rng::new(0xc0441d0);
    let mut probes = Vec::new();
    for (label, count, margin, clearance) in [
        ("corridor floor", 10, 0.1, 0.1),
        ("corridor ceiling", 8, 0.1, 0.1),
        ("corridor wall", 16, 0.1, 0.1),
        ("corridor end", 4, 0.1, 0.1),
        ("room floor", 18, 0.1, 0.1),
        ("room ceiling", 12, 0.1, 0.1),
        ("room wall", 28, 0.1, 0.1),
    ] {
        b.probes(&mut rng, label, count, margin, clearance, &mut probes);
    }
    Interior {
        scene: b.scene,
        probes,
    }
}

// ---------------------------------------------------------------------------------------------
// Thin slabs.

/// Where the light of a [`thin_slab`] box comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SlabLight {
    /// A 0.5 x 0.5 m panel filling an opening in the middle of the wall x = 0, facing +x: the
    /// slab's -x face is lit directly, its +x face only by light reflected from the walls.
    Side,
    /// A 0.15 x 0.6 m strip filling an opening of the ceiling at x from 0.3 to 0.45 m (beside
    /// the slab's plane), facing down: light rakes across the slab's top edge and reaches its
    /// -x face at grazing angles.
    Top,
}

/// Material indices of [`thin_slab`].
pub mod thin_slab_materials {
    pub const WALL: u32 = 0;
    pub const SLAB: u32 = 1;
    pub const PANEL: u32 = 2;
    /// Emitted radiosity of the panel.
    pub const PANEL_EMISSION: [f64; 3] = [100.0, 100.0, 100.0];
    /// The resolution whose voxel the thickness is counted in.
    pub const RESOLUTION: u32 = 128;
}

/// The voxel edge at resolution 128 of the unit box (voxrad's grid puts the bounding planes
/// through voxel centres, so the edge is 1 / 127 m).
pub fn thin_slab_voxel() -> f64 {
    1.0 / (thin_slab_materials::RESOLUTION - 1) as f64
}

/// A closed 1 m box (walls `Kd` 0.5, fronts facing in) with a 0.6 x 0.6 m slab (`Kd` 0.5) of
/// `thickness_voxels` voxels at resolution 128 floating at the centre (0.5, 0.5, 0.5), its
/// faces normal to x before the tilt. `tilt_deg = [about_y, about_x]`: the slab is rotated about
/// its centre by `about_x` degrees about x, then `about_y` degrees about y. Lit per `light`
/// (`E` = 100). Probes: a 5 x 5 grid on each large face of the slab (labels `slab -x` and
/// `slab +x`, the local side before the tilt) inside 10 % margins, and three on each wall.
/// A thickness that is not finite and positive is replaced by 1 voxel.
pub fn thin_slab(thickness_voxels: f64, tilt_deg: [f64; 2], light: SlabLight) -> Interior {
    use thin_slab_materials::*;
    let t_vox = if thickness_voxels.is_finite() && thickness_voxels > 0.0 {
        thickness_voxels
    } else {
        1.0
    };
    let [about_y, about_x] = tilt_deg.map(|a| if a.is_finite() { a } else { 0.0 });
    let mut b = Builder::new(&format!(
        "generator:thin_slab(thickness={t_vox} voxels at {RESOLUTION}, tilt_y={about_y}, \
         tilt_x={about_x}, light={light:?})"
    ));
    b.material("wall", [0.5; 3], [0.0; 3]);
    b.material("slab", [0.5; 3], [0.0; 3]);
    b.material("panel", [0.5; 3], PANEL_EMISSION);
    let (opening, face, facing) = match light {
        SlabLight::Side => ((v(0.0, 0.25, 0.25), v(0.0, 0.75, 0.75)), 0, DVec3::X),
        SlabLight::Top => ((v(0.3, 1.0, 0.2), v(0.45, 1.0, 0.8)), 3, DVec3::NEG_Y),
    };
    b.shell(
        DVec3::ZERO,
        DVec3::ONE,
        [WALL; 6],
        [None; 6],
        Some((face, opening.0, opening.1)),
    );
    b.emitter(opening.0, opening.1, facing, PANEL);
    let t = t_vox * thin_slab_voxel();
    let (lo, hi) = (v(0.5 - 0.5 * t, 0.2, 0.2), v(0.5 + 0.5 * t, 0.8, 0.8));
    let rotation = if about_y != 0.0 || about_x != 0.0 {
        Some(
            DMat3::from_rotation_y(about_y.to_radians())
                * DMat3::from_rotation_x(about_x.to_radians()),
        )
    } else {
        None
    };
    b.solid_rotated(lo, hi, rotation, [SLAB; 6], NONE6);
    let r = rotation.unwrap_or(DMat3::IDENTITY);
    let centre = 0.5 * (lo + hi);
    let mut probes = Vec::new();
    for (label, x, n) in [("slab -x", lo.x, DVec3::NEG_X), ("slab +x", hi.x, DVec3::X)] {
        for i in 0..5 {
            for j in 0..5 {
                let (a, c) = (0.1 + 0.2 * i as f64, 0.1 + 0.2 * j as f64);
                let local = v(x, lo.y + a * (hi.y - lo.y), lo.z + c * (hi.z - lo.z));
                probes.push(Probe {
                    point: centre + r * (local - centre),
                    normal: r * n,
                    surface: label.to_string(),
                });
            }
        }
    }
    // Three probes per wall, clear of the emitter (in each wall's (u, v) = next two axes).
    for (f, &outward) in FACE_NORMALS.iter().enumerate() {
        let axis = f / 2;
        let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
        for (a, c) in [(0.15, 0.15), (0.85, 0.5), (0.5, 0.85)] {
            let mut p = DVec3::ZERO;
            p[axis] = if f % 2 == 0 { 0.0 } else { 1.0 };
            p[u] = a;
            p[w] = c;
            probes.push(Probe {
                point: p,
                normal: -outward,
                surface: "wall".to_string(),
            });
        }
    }
    Interior {
        scene: b.scene,
        probes,
    }
}

// ---------------------------------------------------------------------------------------------
// Twins of the furnace hard cases.

/// Which twin of a furnace hard case (`tests/hard_cases.rs`) [`hard_twin`] builds. A furnace
/// (every wall glowing alike) cannot show a surfel that gathers from the wrong partner, since all
/// partners have the same radiosity; each twin keeps the hard case's geometry and reflectance and
/// lights it from one place instead.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HardTwin {
    /// The closed unit box with walls of reflectance 0.999, lit by one small lamp in the
    /// ceiling (twin of the reflectance-0.999 furnace cases).
    WhiteBox,
    /// The same box and lamp with every reflectance 0: the walls receive direct light only
    /// (twin of the black furnace).
    BlackBox,
    /// A grey box (reflectance 0.5) holding the hard case's slab 0.01 thick and its cube whose
    /// edges lie on voxel corners at resolution 25, lit by a panel in the wall x = 0 (twin of the
    /// thin slab and aligned cube in a furnace).
    Slab,
    /// The same with the slab tilted by 0.05 rad about x (twin of the tilted thin slab).
    SlabTilted,
}

impl HardTwin {
    /// Every twin, in the order of their reference directories.
    pub const ALL: [HardTwin; 4] = [
        HardTwin::WhiteBox,
        HardTwin::BlackBox,
        HardTwin::Slab,
        HardTwin::SlabTilted,
    ];

    /// The name of its reference directory (`tests/data/reference/<name>`).
    pub fn name(self) -> &'static str {
        match self {
            HardTwin::WhiteBox => "twin-white-box",
            HardTwin::BlackBox => "twin-black-box",
            HardTwin::Slab => "twin-slab",
            HardTwin::SlabTilted => "twin-slab-tilted",
        }
    }
}

/// Constants of [`hard_twin`].
pub mod hard_twin_constants {
    /// Reflectance of every surface of the white box (walls and lamp).
    pub const WHITE_REFLECTANCE: f64 = 0.999;
    /// Reflectance of every surface of the slab boxes (walls, slab, cube and lamp).
    pub const GREY_REFLECTANCE: f64 = 0.5;
    /// Emitted radiosity of every twin's lamp.
    pub const LAMP_EMISSION: f64 = 100.0;
    /// The boxes' lamp: `[x0, x1] x [y0, y1]` in the ceiling z = 1, facing down: 2 x 2 voxels
    /// at resolution 13 (voxel 1/12), its edges on voxel boundaries there (and at resolutions 37
    /// and 61). A lamp that fills an opening shares its rim voxels with the wall around it, and
    /// such a voxel's one surfel takes one material, drawn by area share (see
    /// `voxel::voxelize`): off the boundaries the lamp's area would come out in whole voxels, right
    /// only on average over its rim (with the material covering most of each voxel, as first
    /// done, a 0.2 x 0.2 lamp at x 0.15 to 0.35, y 0.4 to 0.6 emitted 50 % of its power at
    /// resolution 11, 83 % at 12, 67 % at 16, 108.5 % at 25).
    pub const CEILING_LAMP: [f64; 4] = [3.0 / 24.0, 7.0 / 24.0, 9.0 / 24.0, 13.0 / 24.0];
    /// The slab boxes' lamp: `[y0, y1] x [z0, z1]` in the wall x = 0, facing +x, all of it above
    /// the slab's plane: 13 x 10 voxels at resolution 25, its edges on voxel boundaries there.
    pub const SIDE_LAMP: [f64; 4] = [11.0 / 48.0, 37.0 / 48.0, 21.0 / 48.0, 41.0 / 48.0];
    /// The hard case's slab: `[0.2, 0.8]^2` in x and y, `SLAB_THICKNESS` thick from z =
    /// `SLAB_BOTTOM`, rotated by the tilt about the x axis through (0.5, 0.5, `SLAB_BOTTOM`).
    pub const SLAB_THICKNESS: f64 = 0.01;
    pub const SLAB_BOTTOM: f64 = 0.3;
    /// Tilt of [`super::HardTwin::SlabTilted`], radians.
    pub const SLAB_TILT: f64 = 0.05;
    /// The cube `[CUBE_MIN, CUBE_MAX]^3`: from voxel corner to voxel corner at resolution 25
    /// (voxel centres at multiples of 1/24, corners half a voxel off).
    pub const CUBE_MIN: f64 = 13.5 / 24.0;
    pub const CUBE_MAX: f64 = 18.5 / 24.0;
    /// The resolution the slab, the cube and the probe margins are measured in (voxel 1/24).
    pub const RESOLUTION: u32 = 25;
}

/// Twins of the furnace hard cases under light from one place, in the hard cases' frame (the unit
/// box `[0, 1]^3`, z up: the floor is z = 0, the ceiling z = 1). All closed; every lamp is a
/// one-sided quad (`Ke` 100) filling an opening of the shell, facing in, with the reflectance of
/// the walls.
///
/// - [`HardTwin::WhiteBox`] / [`HardTwin::BlackBox`]: walls and lamp of reflectance 0.999 / 0;
///   the lamp is 1/6 x 1/6 ([`hard_twin_constants::CEILING_LAMP`], off-centre) in the ceiling.
///   Probes (labels `floor`, `ceiling`, `wall x=0`, `wall x=1`, `wall y=0`, `wall y=1`): a
///   3 x 3 grid at 15, 50 and 85 % of each wall (the ceiling's point on the lamp left out), plus
///   seven by the lamp (three on the wall x = 0 below it, two on the ceiling beside it, two on the
///   floor).
/// - [`HardTwin::Slab`] / [`HardTwin::SlabTilted`]: walls of reflectance 0.5, the hard case's
///   slab and cube (reflectance 0.5), a 0.54 x 0.42 panel ([`hard_twin_constants::SIDE_LAMP`]) in
///   the wall x = 0 above the slab's plane: the slab's top is lit directly, its bottom only by
///   reflected light, the cube's -x face directly and its +x face not at all. Probes: a 5 x 5
///   grid on the slab's top and bottom at 10 to 90 % (labels `slab top`, `slab bottom`; before
///   the tilt), three along each edge of both faces 0.6 voxel (at resolution 25) from it
///   (`slab top rim`, `slab bottom rim`), a 3 x 3 grid at 20, 50 and 80 % on each face of the
///   cube (`cube -x`, ..., by its normal), and 19 on the walls near them.
pub fn hard_twin(which: HardTwin) -> Interior {
    use hard_twin_constants::*;
    let mut b = Builder::new(&format!("generator:hard_twin({which:?})"));
    match which {
        HardTwin::WhiteBox | HardTwin::BlackBox => {
            let rho = if which == HardTwin::WhiteBox {
                WHITE_REFLECTANCE
            } else {
                0.0
            };
            let wall = b.material("wall", [rho; 3], [0.0; 3]);
            let lamp = b.material("lamp", [rho; 3], [LAMP_EMISSION; 3]);
            let [x0, x1, y0, y1] = CEILING_LAMP;
            let (lo, hi) = (v(x0, y0, 1.0), v(x1, y1, 1.0));
            b.shell(DVec3::ZERO, DVec3::ONE, [wall; 6], NONE6, Some((5, lo, hi)));
            b.emitter(lo, hi, DVec3::NEG_Z, lamp);
            let mut probes = Vec::new();
            for (f, &outward) in FACE_NORMALS.iter().enumerate() {
                let axis = f / 2;
                let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
                for a in [0.15, 0.5, 0.85] {
                    for c in [0.15, 0.5, 0.85] {
                        let mut p = DVec3::ZERO;
                        p[axis] = if f % 2 == 0 { 0.0 } else { 1.0 };
                        p[u] = a;
                        p[w] = c;
                        let on_lamp = f == 5
                            && (x0 - 0.05..=x1 + 0.05).contains(&p.x)
                            && (y0 - 0.05..=y1 + 0.05).contains(&p.y);
                        if !on_lamp {
                            probes.push(twin_probe(p, -outward));
                        }
                    }
                }
            }
            for p in [
                v(0.0, 0.5, 0.92),
                v(0.0, 0.5, 0.75),
                v(0.25, 0.68, 1.0),
                v(0.45, 0.5, 1.0),
                v(0.25, 0.5, 0.0),
                v(0.6, 0.3, 0.0),
                v(0.0, 0.7, 0.9),
            ] {
                let n = match p {
                    _ if p.x == 0.0 => DVec3::X,
                    _ if p.z == 1.0 => DVec3::NEG_Z,
                    _ => DVec3::Z,
                };
                probes.push(twin_probe(p, n));
            }
            Interior {
                scene: b.scene,
                probes,
            }
        }
        HardTwin::Slab | HardTwin::SlabTilted => {
            let rho = GREY_REFLECTANCE;
            let wall = b.material("wall", [rho; 3], [0.0; 3]);
            let solid = b.material("solid", [rho; 3], [0.0; 3]);
            let lamp = b.material("lamp", [rho; 3], [LAMP_EMISSION; 3]);
            let [y0, y1, z0, z1] = SIDE_LAMP;
            let (lo, hi) = (v(0.0, y0, z0), v(0.0, y1, z1));
            b.shell(DVec3::ZERO, DVec3::ONE, [wall; 6], NONE6, Some((0, lo, hi)));
            b.emitter(lo, hi, DVec3::X, lamp);
            let tilt = if which == HardTwin::SlabTilted {
                SLAB_TILT
            } else {
                0.0
            };
            let (c, s) = (tilt.cos(), tilt.sin());
            // The hard case's rotation: about the x axis through (0.5, 0.5, SLAB_BOTTOM), applied
            // to the slab `[0.2, 0.8]^2 x [0, SLAB_THICKNESS]` (local z from its bottom).
            let place = |x: f64, y: f64, z: f64| {
                if tilt == 0.0 {
                    return v(x, y, SLAB_BOTTOM + z);
                }
                let y = y - 0.5;
                v(x, 0.5 + c * y - s * z, SLAB_BOTTOM + s * y + c * z)
            };
            let turn = |n: DVec3| {
                if tilt == 0.0 {
                    n
                } else {
                    v(n.x, c * n.y - s * n.z, s * n.y + c * n.z)
                }
            };
            let (smin, smax) = (v(0.2, 0.2, 0.0), v(0.8, 0.8, SLAB_THICKNESS));
            for (f, &n) in FACE_NORMALS.iter().enumerate() {
                let corners = box_face(smin, smax, f).map(|q| place(q.x, q.y, q.z));
                add_facing(&mut b.scene, &corners, turn(n), solid);
            }
            super::add_solid_box(
                &mut b.scene,
                DVec3::splat(CUBE_MIN),
                DVec3::splat(CUBE_MAX),
                [solid; 6],
                false,
            );
            let mut probes = Vec::new();
            let voxel = 1.0 / (RESOLUTION - 1) as f64;
            for (label, rim, z, n) in [
                ("slab top", "slab top rim", SLAB_THICKNESS, DVec3::Z),
                ("slab bottom", "slab bottom rim", 0.0, DVec3::NEG_Z),
            ] {
                for i in 0..5 {
                    for j in 0..5 {
                        let (x, y) = (0.26 + 0.12 * i as f64, 0.26 + 0.12 * j as f64);
                        probes.push(Probe {
                            point: place(x, y, z),
                            normal: turn(n),
                            surface: label.to_string(),
                        });
                    }
                }
                let near = 0.6 * voxel;
                for along in [0.35, 0.5, 0.65] {
                    for (x, y) in [
                        (0.2 + near, along),
                        (0.8 - near, along),
                        (along, 0.2 + near),
                        (along, 0.8 - near),
                    ] {
                        probes.push(Probe {
                            point: place(x, y, z),
                            normal: turn(n),
                            surface: rim.to_string(),
                        });
                    }
                }
            }
            const CUBE_LABELS: [&str; 6] = [
                "cube -x", "cube +x", "cube -y", "cube +y", "cube -z", "cube +z",
            ];
            for (f, &n) in FACE_NORMALS.iter().enumerate() {
                let axis = f / 2;
                let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
                for a in [0.2, 0.5, 0.8] {
                    for c in [0.2, 0.5, 0.8] {
                        let mut p = DVec3::ZERO;
                        p[axis] = if f % 2 == 0 { CUBE_MIN } else { CUBE_MAX };
                        p[u] = CUBE_MIN + a * (CUBE_MAX - CUBE_MIN);
                        p[w] = CUBE_MIN + c * (CUBE_MAX - CUBE_MIN);
                        probes.push(Probe {
                            point: p,
                            normal: n,
                            surface: CUBE_LABELS[f].to_string(),
                        });
                    }
                }
            }
            for p in [
                v(0.35, 0.35, 0.0),
                v(0.65, 0.35, 0.0),
                v(0.35, 0.65, 0.0),
                v(0.65, 0.65, 0.0),
                v(0.67, 0.67, 1.0),
                v(0.5, 0.3, 1.0),
                v(0.3, 0.7, 1.0),
                v(1.0, 0.67, 0.67),
                v(1.0, 0.5, 0.3),
                v(1.0, 0.3, 0.5),
                v(0.5, 0.0, 0.3),
                v(0.7, 0.0, 0.67),
                v(0.3, 0.0, 0.15),
                v(0.5, 1.0, 0.3),
                v(0.67, 1.0, 0.67),
                v(0.3, 1.0, 0.15),
                v(0.0, 0.5, 0.3),
                v(0.0, 0.5, 0.15),
                v(0.0, 0.12, 0.6),
            ] {
                let n = if p.z == 0.0 {
                    DVec3::Z
                } else if p.z == 1.0 {
                    DVec3::NEG_Z
                } else if p.x == 0.0 {
                    DVec3::X
                } else if p.x == 1.0 {
                    DVec3::NEG_X
                } else if p.y == 0.0 {
                    DVec3::Y
                } else {
                    DVec3::NEG_Y
                };
                probes.push(twin_probe(p, n));
            }
            Interior {
                scene: b.scene,
                probes,
            }
        }
    }
}

/// A probe on a wall of the unit box, labelled by the wall (`floor`, `ceiling`, `wall x=0`, ...).
fn twin_probe(point: DVec3, normal: DVec3) -> Probe {
    let surface = match axis_of(normal) {
        2 if normal.z > 0.0 => "floor".to_string(),
        2 => "ceiling".to_string(),
        axis => format!(
            "wall {}={}",
            ["x", "y"][axis],
            if normal[axis] > 0.0 { 0 } else { 1 }
        ),
    };
    Probe {
        point,
        normal,
        surface,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Triangle;

    fn all() -> Vec<(&'static str, Interior)> {
        let mut v = vec![
            ("office", office()),
            ("window-room", window_room()),
            ("corridor", corridor()),
        ];
        for light in [SlabLight::Side, SlabLight::Top] {
            for tilt in [[0.0, 0.0], [20.0, 10.0]] {
                for t in [0.3, 0.5, 1.0, 2.0] {
                    v.push(("thin", thin_slab(t, tilt, light)));
                }
            }
        }
        for twin in HardTwin::ALL {
            v.push((twin.name(), hard_twin(twin)));
        }
        v
    }

    /// Möller-Trumbore; returns the distance along `d` (unit) if the ray hits the triangle.
    fn hit(o: DVec3, d: DVec3, t: &Triangle) -> Option<f64> {
        let [a, b, c] = t.vertices;
        let (e1, e2) = (b - a, c - a);
        let p = d.cross(e2);
        let det = e1.dot(p);
        if det.abs() < 1e-14 {
            return None;
        }
        let s = o - a;
        let u = s.dot(p) / det;
        let q = s.cross(e1);
        let w = d.dot(q) / det;
        let dist = e2.dot(q) / det;
        (u >= -1e-12 && w >= -1e-12 && u + w <= 1.0 + 1e-12 && dist > 1e-9).then_some(dist)
    }

    fn first_hit(scene: &Scene, o: DVec3, d: DVec3) -> Option<(f64, &Triangle)> {
        scene
            .triangles
            .iter()
            .filter_map(|t| hit(o, d, t).map(|h| (h, t)))
            .min_by(|a, b| a.0.total_cmp(&b.0))
    }

    fn unit_dir(rng: &mut Rng) -> DVec3 {
        loop {
            let d = DVec3::new(
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            );
            if d.length_squared() > 1e-3 && d.length_squared() <= 1.0 {
                return d.normalize();
            }
        }
    }

    #[test]
    fn scenes_validate_and_stay_small() {
        for (name, s) in all() {
            assert_eq!(s.scene.validate(), Ok(()), "{name}");
            let n = s.scene.triangles.len();
            assert!((24..=4000).contains(&n), "{name}: {n} triangles");
            assert!(s.scene.triangles.iter().all(|t| t.area() > 0.0), "{name}");
            assert!(s.scene.materials.iter().any(|m| m.is_emitter()), "{name}");
        }
    }

    #[test]
    fn deterministic() {
        let key = |s: &Interior| format!("{:?}{:?}", s.scene.triangles, s.probes);
        assert_eq!(key(&office()), key(&office()));
        assert_eq!(key(&corridor()), key(&corridor()));
        let a = thin_slab(0.5, [20.0, 10.0], SlabLight::Top);
        let b = thin_slab(0.5, [20.0, 10.0], SlabLight::Top);
        assert_eq!(key(&a), key(&b));
    }

    /// Closed: every vertex (emitters included) lies inside the shell's bounds, and rays from
    /// the air just in front of the probes, in random directions, always hit something (no light
    /// escapes), and what they hit first shows its front (or is the back of a one-sided emitter).
    #[test]
    fn closed_with_every_emitter_inside() {
        let mut rng = Rng::new(3);
        for (name, s) in all() {
            let bounds = s.scene.bounds();
            for t in &s.scene.triangles {
                for p in t.vertices {
                    assert!(
                        (p - bounds.min).min_element() >= 0.0
                            && (bounds.max - p).min_element() >= 0.0
                    );
                }
            }
            for (k, p) in s.probes.iter().enumerate().step_by(3) {
                let o = p.point + 1e-6 * p.normal;
                for _ in 0..4 {
                    let d = unit_dir(&mut rng);
                    let h = first_hit(&s.scene, o, d);
                    assert!(
                        h.is_some(),
                        "{name}: a ray from probe {k} escapes along {d}"
                    );
                    // From the air, the first surface seen shows its front, except the backs of
                    // the (one-sided) emitters, which reflect like every other surface.
                    let (_, t) = h.unwrap();
                    let front = t.cross().dot(d) < 0.0;
                    let emitter = s.scene.materials[t.material as usize].is_emitter();
                    assert!(
                        front || emitter,
                        "{name}: probe {k} sees a back face along {d}"
                    );
                }
            }
        }
    }

    #[test]
    fn emitters_face_into_the_room() {
        let checks: [(&str, Interior, DVec3); 4] = [
            ("office", office(), DVec3::NEG_Y),
            ("window-room", window_room(), DVec3::Z),
            ("corridor", corridor(), DVec3::NEG_Y),
            (
                "thin top",
                thin_slab(1.0, [0.0; 2], SlabLight::Top),
                DVec3::NEG_Y,
            ),
        ];
        for (name, s, facing) in checks {
            let emitting: Vec<&Triangle> = s
                .scene
                .triangles
                .iter()
                .filter(|t| s.scene.materials[t.material as usize].is_emitter())
                .collect();
            assert!(!emitting.is_empty(), "{name}");
            for t in emitting {
                let n = t.cross().normalize();
                assert!((n - facing).length() < 1e-12, "{name}: emitter faces {n}");
            }
        }
        let side = thin_slab(1.0, [0.0; 2], SlabLight::Side);
        for t in &side.scene.triangles {
            if side.scene.materials[t.material as usize].is_emitter() {
                assert!((t.cross().normalize() - DVec3::X).length() < 1e-12);
            }
        }
    }

    /// The twins' lamps face in, and their edges lie on voxel boundaries at the resolutions the
    /// tests use, so that the voxelized lamp has exactly its area (a voxel shared by a lamp and
    /// the wall around it takes one material); the slab and the cube are the hard case's.
    #[test]
    fn hard_twins_keep_the_hard_cases_geometry_and_exact_lamps() {
        use crate::voxel::voxelize::{voxelize, GridSpec};
        use hard_twin_constants::*;
        for (twin, facing, resolutions, area) in [
            (
                HardTwin::WhiteBox,
                DVec3::NEG_Z,
                &[13, 37, 61][..],
                1.0 / 36.0,
            ),
            (HardTwin::BlackBox, DVec3::NEG_Z, &[13, 37][..], 1.0 / 36.0),
            (
                HardTwin::Slab,
                DVec3::X,
                &[25][..],
                (26.0 / 48.0) * (20.0 / 48.0),
            ),
            (
                HardTwin::SlabTilted,
                DVec3::X,
                &[25][..],
                (26.0 / 48.0) * (20.0 / 48.0),
            ),
        ] {
            let s = hard_twin(twin);
            let mut lamp_area = 0.0;
            for t in &s.scene.triangles {
                if s.scene.materials[t.material as usize].is_emitter() {
                    assert!(
                        (t.cross().normalize() - facing).length() < 1e-12,
                        "{twin:?}"
                    );
                    lamp_area += t.area();
                }
            }
            assert!((lamp_area - area).abs() < 1e-12, "{twin:?}: {lamp_area}");
            for &r in resolutions {
                let set = voxelize(&s.scene, GridSpec::Resolution(r)).unwrap();
                let unit = set.grid.voxel_size * set.grid.voxel_size;
                let emitting: f64 = set
                    .surfels
                    .iter()
                    .filter(|x| set.materials[x.material[0] as usize].is_emitter())
                    .map(|x| x.area as f64 * unit)
                    .sum();
                assert!(
                    (emitting - area).abs() < 1e-5 * area,
                    "{twin:?} at {r}: voxelized lamp {emitting} for {area}"
                );
            }
        }
        // The slab: 0.01 thick, [0.2, 0.8]^2, from z = 0.3; tilted, about the x axis through
        // (0.5, 0.5, 0.3) as the hard case turns it; the cube from voxel corner to voxel corner.
        let slab = |s: &Interior| -> Vec<DVec3> {
            let solid = s
                .scene
                .materials
                .iter()
                .position(|m| m.name == "solid")
                .unwrap();
            let mut points: Vec<DVec3> = s
                .scene
                .triangles
                .iter()
                .filter(|t| t.material as usize == solid)
                .flat_map(|t| t.vertices)
                .filter(|p| p.z < 0.5)
                .collect();
            points.sort_by(|a, b| a.to_array().partial_cmp(&b.to_array()).unwrap());
            points.dedup();
            points
        };
        let flat = slab(&hard_twin(HardTwin::Slab));
        assert_eq!(flat.len(), 8);
        for p in &flat {
            assert!([0.2, 0.8].contains(&p.x) && [0.2, 0.8].contains(&p.y));
            assert!([SLAB_BOTTOM, SLAB_BOTTOM + SLAB_THICKNESS].contains(&p.z));
        }
        let (c, sn) = (SLAB_TILT.cos(), SLAB_TILT.sin());
        for p in slab(&hard_twin(HardTwin::SlabTilted)) {
            // Undo the rotation: back on the flat slab's corners.
            let (y, z) = (p.y - 0.5, p.z - SLAB_BOTTOM);
            let back = DVec3::new(p.x, 0.5 + c * y + sn * z, SLAB_BOTTOM - sn * y + c * z);
            assert!(flat.iter().any(|q| q.distance(back) < 1e-12), "{p}");
        }
        let voxel = 1.0 / (RESOLUTION - 1) as f64;
        for edge in [CUBE_MIN, CUBE_MAX] {
            let k = edge / voxel - 0.5;
            assert!(
                (k - k.round()).abs() < 1e-12,
                "cube edge {edge} is not on a voxel corner"
            );
        }
    }

    /// Each probe is on a triangle of its scene whose plane it lies in, on no emitter, and the
    /// triangle under it shows its front to the probe (all probed sides are fronts here).
    #[test]
    fn probes_lie_on_fronts_and_counts_are_in_range() {
        for (name, s) in all() {
            assert!(
                (60..=150).contains(&s.probes.len()),
                "{name}: {}",
                s.probes.len()
            );
            for (k, p) in s.probes.iter().enumerate() {
                assert!((p.normal.length() - 1.0).abs() < 1e-12);
                let o = p.point + 1e-4 * p.normal;
                let (dist, t) = first_hit(&s.scene, o, -p.normal)
                    .unwrap_or_else(|| panic!("{name}: probe {k} is over nothing"));
                assert!(
                    (dist - 1e-4).abs() < 1e-7,
                    "{name}: probe {k} off its surface"
                );
                assert!(
                    t.cross().normalize().dot(p.normal) > 1.0 - 1e-9,
                    "{name}: {k}"
                );
                let m = &s.scene.materials[t.material as usize];
                assert!(!m.is_emitter(), "{name}: probe {k} is on an emitter");
            }
        }
    }

    /// No probe of the realistic scenes is within 0.1 m of an emitter in front of it (housing
    /// sides: 2 cm; a housing's top is close to its own lamp, but behind it).
    #[test]
    fn probes_keep_clear_of_emitters() {
        for (name, s) in [
            ("office", office()),
            ("window-room", window_room()),
            ("corridor", corridor()),
        ] {
            let emitters: Vec<&Triangle> = s
                .scene
                .triangles
                .iter()
                .filter(|t| s.scene.materials[t.material as usize].is_emitter())
                .collect();
            for p in &s.probes {
                let limit = if p.surface == "housing side" {
                    0.02
                } else {
                    0.1
                };
                for t in &emitters {
                    if t.vertices
                        .iter()
                        .all(|&q| (q - p.point).dot(p.normal) < 0.0)
                    {
                        continue;
                    }
                    let lo = t.vertices[0].min(t.vertices[1]).min(t.vertices[2]);
                    let hi = t.vertices[0].max(t.vertices[1]).max(t.vertices[2]);
                    let d = (lo - p.point).max(p.point - hi).max(DVec3::ZERO).length();
                    assert!(
                        d >= limit - 1e-9,
                        "{name}: {} probe {} near a lamp",
                        p.surface,
                        p.point
                    );
                }
            }
        }
    }

    #[test]
    fn every_surface_kind_gets_its_probes() {
        let count =
            |s: &Interior, label: &str| s.probes.iter().filter(|p| p.surface == label).count();
        let o = office();
        for (label, n) in [
            ("partition", 20),
            ("housing side", 8),
            ("desk top", 16),
            ("floor", 16),
        ] {
            assert_eq!(count(&o, label), n, "office {label}");
        }
        let w = window_room();
        assert_eq!(count(&w, "rug"), 12);
        let c = corridor();
        assert_eq!(count(&c, "room floor"), 18);
        assert_eq!(count(&c, "corridor wall"), 16);
        // Both faces of the partitions are probed.
        let faces: std::collections::HashSet<String> = o
            .probes
            .iter()
            .filter(|p| p.surface == "partition")
            .map(|p| format!("{:?}", p.normal))
            .collect();
        assert!(faces.len() >= 3, "{faces:?}");
    }

    #[test]
    fn thin_slab_has_the_asked_thickness_and_faces_out() {
        for t in [0.3, 0.5, 1.0, 2.0] {
            for tilt in [[0.0, 0.0], [20.0, 10.0]] {
                let s = thin_slab(t, tilt, SlabLight::Side);
                let slab: Vec<&Triangle> = s
                    .scene
                    .triangles
                    .iter()
                    .filter(|tr| tr.material == thin_slab_materials::SLAB)
                    .collect();
                assert_eq!(slab.len(), 12);
                let centre = DVec3::splat(0.5);
                for tr in &slab {
                    let c = (tr.vertices[0] + tr.vertices[1] + tr.vertices[2]) / 3.0;
                    assert!(tr.cross().dot(c - centre) > 0.0, "slab faces point out");
                }
                // Distance between the two probed faces along their normal.
                let a = &s.probes[0];
                let b = &s.probes[25];
                let gap = (b.point - a.point).dot(b.normal);
                assert!((gap - t * thin_slab_voxel()).abs() < 1e-12, "{t}: {gap}");
                assert!((a.normal + b.normal).length() < 1e-12);
            }
        }
        // Bad thickness falls back to one voxel.
        let s = thin_slab(f64::NAN, [0.0; 2], SlabLight::Top);
        assert_eq!(s.scene.validate(), Ok(()));
    }

    /// Same text, numbers compared with a tolerance (the tilted slabs' `sin` and `cos` may differ
    /// in the last bit between maths libraries).
    fn same_numbers(a: &str, b: &str) -> bool {
        let split = |s: &str| {
            s.split(|c: char| c.is_whitespace() || c == ',')
                .map(str::to_string)
                .collect::<Vec<_>>()
        };
        let (ta, tb) = (split(a), split(b));
        ta.len() == tb.len()
            && ta.iter().zip(&tb).all(|(x, y)| {
                x == y
                    || matches!((x.parse::<f64>(), y.parse::<f64>()),
                        (Ok(p), Ok(q)) if (p - q).abs() <= 1e-12 * (1.0 + p.abs()))
            })
    }

    /// The scenes and probes committed under `tests/data/reference/` are what the generators
    /// write today, and each `reference.csv` has one row per probe, at the probe.
    #[test]
    fn committed_reference_data_matches_the_generators() {
        use std::path::Path;
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/reference");
        let mut scenes = vec![
            ("office".to_string(), office()),
            ("window-room".to_string(), window_room()),
            ("corridor".to_string(), corridor()),
        ];
        for (light, name) in [(SlabLight::Side, "side"), (SlabLight::Top, "top")] {
            for (tilt, suffix) in [([0.0, 0.0], ""), ([20.0, 10.0], "-tilted")] {
                for t in [0.3, 0.5, 1.0, 2.0] {
                    scenes.push((
                        format!("thin-{name}-t{t}{suffix}"),
                        thin_slab(t, tilt, light),
                    ));
                }
            }
        }
        for twin in HardTwin::ALL {
            // The twins' tests need their data: it must be there.
            assert!(
                root.join(twin.name()).join("reference.csv").exists(),
                "tests/data/reference/{} is missing: run tools/reference/make_data.py",
                twin.name()
            );
            scenes.push((twin.name().to_string(), hard_twin(twin)));
        }
        let dir = tempfile::tempdir().unwrap();
        let mut checked = 0;
        for (name, s) in &scenes {
            let committed = root.join(name);
            if !committed.join("reference.csv").exists() {
                continue;
            }
            let obj = dir.path().join("scene.obj");
            crate::gen::write_obj(&s.scene, &obj).unwrap();
            let fresh = [
                ("scene.obj", std::fs::read_to_string(&obj).unwrap()),
                (
                    "scene.mtl",
                    std::fs::read_to_string(obj.with_extension("mtl")).unwrap(),
                ),
                ("probes.csv", probes_csv(&s.probes)),
                ("surfaces.csv", surfaces_csv(&s.probes)),
            ];
            for (file, text) in fresh {
                let old = std::fs::read_to_string(committed.join(file)).unwrap_or_default();
                assert!(
                    same_numbers(&text, &old),
                    "tests/data/reference/{name}/{file} is stale: rerun tools/reference/make_data.py"
                );
            }
            let reference = std::fs::read_to_string(committed.join("reference.csv")).unwrap();
            let rows: Vec<&str> = reference.lines().skip(1).collect();
            assert_eq!(rows.len(), s.probes.len(), "{name}");
            for (row, p) in rows.iter().zip(&s.probes) {
                let v: Vec<f64> = row.split(',').map(|f| f.parse().unwrap()).collect();
                assert_eq!(v.len(), 19, "{name}");
                assert!(
                    (DVec3::new(v[0], v[1], v[2]) - p.point).length() < 1e-9,
                    "{name}"
                );
                assert!(v[6..9].iter().all(|b| b.is_finite() && *b >= 0.0), "{name}");
            }
            checked += 1;
        }
        assert!(
            checked >= 3,
            "only {checked} committed reference scenes found"
        );
        // The Cornell box's probes are the study's 300 points (seed 0x5eed).
        let cornell: Vec<Probe> =
            crate::study::probe_points(&crate::gen::cornell_box(), 300, 0x5eed)
                .into_iter()
                .map(|(point, normal)| Probe {
                    point,
                    normal,
                    surface: String::new(),
                })
                .collect();
        let old = std::fs::read_to_string(root.join("cornell/probes.csv")).unwrap();
        assert!(
            same_numbers(&probes_csv(&cornell), &old),
            "cornell/probes.csv is stale"
        );
    }

    #[test]
    fn csv_rows_match_probes() {
        let s = window_room();
        let text = probes_csv(&s.probes);
        assert_eq!(text.lines().count(), s.probes.len() + 1);
        assert!(text.starts_with("x,y,z,nx,ny,nz\n"));
        let labels = surfaces_csv(&s.probes);
        assert_eq!(
            labels.lines().nth(1),
            Some(format!("0,{}", s.probes[0].surface).as_str())
        );
    }
}
