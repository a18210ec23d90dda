//! Procedural scenes for tests and scale runs: a furnished room, a building of any number of
//! rooms (the size knob), two sealed rooms (the light-leak test), the furnace (the energy test) and
//! two parallel squares with their analytic form factor (the transport test).
//!
//! Every generator is deterministic: the same arguments give bit-identical triangles on every
//! platform (the PRNG is the self-contained splitmix64 of `gen`, no floating-point library calls
//! feed into coordinates except plain arithmetic). Solids are closed axis-aligned boxes with their
//! fronts facing out; rooms are closed, so no light can leave a scene except through a leak.
//!
//! Material tables (index: name), fixed per generator so tests can find surfaces by index or name:
//! - [`room`] and [`building`]: see [`furnished`] (0 wall, 1 ceiling, 2 floor, 3 light, 4 table,
//!   5 cabinet, 6 shelf, 7 exterior).
//! - [`sealed_rooms`]: see [`sealed`] (dark room surfaces are named `dark_*`).
//! - [`furnace`]: 0 `furnace`.
//! - [`parallel_squares`]: 0 `emitter`, 1 `receiver`.

use super::{add_facing, add_solid_box, Rng};
use crate::scene::{Material, Scene};
use glam::DVec3;
use std::f64::consts::PI;

/// Material indices of [`room`] and [`building`].
pub mod furnished {
    /// White-ish walls (all wall faces inside the building, including hidden ones).
    pub const WALL: u32 = 0;
    /// Undersides of slabs (room ceilings).
    pub const CEILING: u32 = 1;
    /// Tops of slabs (room floors), coloured.
    pub const FLOOR: u32 = 2;
    /// Ceiling lamps (the only emitter).
    pub const LIGHT: u32 = 3;
    pub const TABLE: u32 = 4;
    pub const CABINET: u32 = 5;
    pub const SHELF: u32 = 6;
    /// Faces on the outside of a building (unlit unless light leaks). Unused by `room`.
    pub const EXTERIOR: u32 = 7;
    /// Emitted radiosity of every lamp.
    pub const LIGHT_EMISSION: [f64; 3] = [12.0, 11.5, 10.0];
}

/// Material indices of [`sealed_rooms`]. The dark room's own surfaces are `DARK_*` (names start
/// with `dark_`); `EXTERIOR` faces the outside and `HIDDEN` faces lie against another solid. All
/// of those must come out black: any light on them has leaked.
pub mod sealed {
    pub const WALL: u32 = 0;
    pub const FLOOR: u32 = 1;
    pub const CEILING: u32 = 2;
    pub const LIGHT: u32 = 3;
    pub const DARK_WALL: u32 = 4;
    pub const DARK_FLOOR: u32 = 5;
    pub const DARK_CEILING: u32 = 6;
    pub const DARK_BLOCK: u32 = 7;
    pub const EXTERIOR: u32 = 8;
    pub const HIDDEN: u32 = 9;
    /// Inner size of each room (x, y, z) and the thickness of every wall and slab.
    pub const ROOM: [f64; 3] = [4.0, 2.5, 4.0];
    pub const THICKNESS: f64 = 0.25;
}

// ---------------------------------------------------------------------------------------------
// Layout: boxes first, triangles last, so tests can check geometry on boxes.

#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    /// Walls and slabs: the building's structure.
    Structure,
    /// One piece of furniture may be several boxes; `item` tells which belong together.
    Furniture { item: usize },
}

#[derive(Clone, Copy, Debug)]
struct Part {
    min: DVec3,
    max: DVec3,
    /// Per-face materials, in `gen::FACE_NORMALS` order (-x, +x, -y, +y, -z, +z).
    faces: [u32; 6],
    // Read by the tests' geometry checks only; kept in release builds for debugging output.
    #[cfg_attr(not(test), allow(dead_code))]
    kind: Kind,
}

/// A downward-facing lamp rectangle at height `y`.
#[derive(Clone, Copy, Debug)]
struct Lamp {
    x: [f64; 2],
    z: [f64; 2],
    y: f64,
}

#[derive(Default, Debug)]
struct Layout {
    parts: Vec<Part>,
    lamps: Vec<Lamp>,
    items: usize,
}

impl Layout {
    fn solid(&mut self, min: DVec3, max: DVec3, faces: [u32; 6]) {
        self.parts.push(Part {
            min,
            max,
            faces,
            kind: Kind::Structure,
        });
    }

    fn emit(&self, scene: &mut Scene, lamp_material: u32) {
        for p in &self.parts {
            add_solid_box(scene, p.min, p.max, p.faces, false);
        }
        for l in &self.lamps {
            let pts = [
                DVec3::new(l.x[0], l.y, l.z[0]),
                DVec3::new(l.x[1], l.y, l.z[0]),
                DVec3::new(l.x[1], l.y, l.z[1]),
                DVec3::new(l.x[0], l.y, l.z[1]),
            ];
            add_facing(scene, &pts, DVec3::NEG_Y, lamp_material);
        }
    }
}

fn furnished_materials(scene: &mut Scene, floor: [f64; 3]) {
    use furnished::*;
    let table = [
        ("wall", [0.78, 0.77, 0.74], [0.0; 3]),
        ("ceiling", [0.8, 0.8, 0.8], [0.0; 3]),
        ("floor", floor, [0.0; 3]),
        ("light", [0.8, 0.8, 0.8], LIGHT_EMISSION),
        ("table", [0.45, 0.3, 0.18], [0.0; 3]),
        ("cabinet", [0.6, 0.6, 0.62], [0.0; 3]),
        ("shelf", [0.5, 0.38, 0.25], [0.0; 3]),
        ("exterior", [0.5, 0.5, 0.5], [0.0; 3]),
    ];
    for (name, kd, ke) in table {
        scene.add_material(Material::new(name, kd, ke));
    }
    debug_assert_eq!(scene.materials.len() as u32, EXTERIOR + 1);
}

/// Floor colours a room may get (wood, terracotta, slate blue, moss), reflectances well below 1.
const FLOOR_COLOURS: [[f64; 3]; 4] = [
    [0.55, 0.35, 0.2],
    [0.6, 0.3, 0.22],
    [0.25, 0.32, 0.5],
    [0.3, 0.45, 0.25],
];

/// An axis-aligned rectangle on the floor plane (x, z).
#[derive(Clone, Copy, Debug)]
struct Rect {
    x: [f64; 2],
    z: [f64; 2],
}

impl Rect {
    fn overlaps(&self, o: &Rect, gap: f64) -> bool {
        self.x[0] < o.x[1] + gap
            && o.x[0] < self.x[1] + gap
            && self.z[0] < o.z[1] + gap
            && o.z[0] < self.z[1] + gap
    }
}

/// Places up to `count` pieces of furniture on the floor of the room `[lo, hi]` (world box of the
/// room's air), clear of the walls, of each other and of the `keep_clear` rectangles (doorways).
/// `unit` is one metre in scene units. Pieces that find no free spot are skipped, so a crowded
/// room gets fewer than asked; heights stay below 80 % of the room so lamps are never touched.
fn furnish(
    layout: &mut Layout,
    rng: &mut Rng,
    lo: DVec3,
    hi: DVec3,
    count: usize,
    unit: f64,
    keep_clear: &[Rect],
) {
    let margin = 0.05 * unit;
    let height_cap = 0.8 * (hi.y - lo.y);
    let mut placed: Vec<Rect> = Vec::new();
    // Each piece needs at least ~0.1 m^2; more than that many cannot fit, and capping keeps the
    // overlap search quadratic in a small number even when asked for millions.
    let room_area = (hi.x - lo.x) * (hi.z - lo.z);
    let cap = (room_area / (0.1 * unit * unit)).max(0.0) as usize;
    let mut failures = 0;
    while placed.len() < count.min(cap) && failures < 64 {
        let kind = rng.below(3);
        let (w, d, h) = match kind {
            0 => (
                rng.range(1.2, 1.8),
                rng.range(0.7, 1.0),
                rng.range(0.72, 0.78),
            ),
            1 => (
                rng.range(0.6, 1.2),
                rng.range(0.4, 0.6),
                rng.range(0.8, 1.9),
            ),
            _ => (
                rng.range(0.8, 1.2),
                rng.range(0.3, 0.4),
                rng.range(1.5, 2.0),
            ),
        };
        let (w, d, h) = (w * unit, d * unit, (h * unit).min(height_cap));
        let swap = rng.chance(0.5);
        let flip = rng.chance(0.5);
        let (fx, fz) = if swap { (d, w) } else { (w, d) };
        let free_x = (hi.x - lo.x) - 2.0 * margin - fx;
        let free_z = (hi.z - lo.z) - 2.0 * margin - fz;
        if free_x <= 0.0 || free_z <= 0.0 || h <= 0.0 {
            failures += 1;
            continue;
        }
        let x0 = lo.x + margin + rng.range(0.0, free_x);
        let z0 = lo.z + margin + rng.range(0.0, free_z);
        let rect = Rect {
            x: [x0, x0 + fx],
            z: [z0, z0 + fz],
        };
        if placed.iter().any(|r| r.overlaps(&rect, margin))
            || keep_clear.iter().any(|r| r.overlaps(&rect, margin))
        {
            failures += 1;
            continue;
        }
        failures = 0;
        placed.push(rect);
        let item = layout.items;
        layout.items += 1;
        // Local frame: a along the width, b along the depth (b = 0 is the back), y up from the
        // floor; mapped to the world by an optional swap of the axes and mirror of the depth.
        let to_world = |a: f64, y: f64, b: f64| {
            let b = if flip { d - b } else { b };
            if swap {
                DVec3::new(x0 + b, lo.y + y, z0 + a)
            } else {
                DVec3::new(x0 + a, lo.y + y, z0 + b)
            }
        };
        let mut add = |a0: f64, y0: f64, b0: f64, a1: f64, y1: f64, b1: f64, m: u32| {
            let p = to_world(a0, y0, b0);
            let q = to_world(a1, y1, b1);
            layout.parts.push(Part {
                min: p.min(q),
                max: p.max(q),
                faces: [m; 6],
                kind: Kind::Furniture { item },
            });
        };
        match kind {
            0 => {
                // Table: a top slab on four legs.
                let m = furnished::TABLE;
                let top = 0.04 * unit;
                let leg = 0.05 * unit;
                let inset = 0.05 * unit;
                add(0.0, h - top, 0.0, w, h, d, m);
                for (a, b) in [
                    (inset, inset),
                    (w - inset - leg, inset),
                    (inset, d - inset - leg),
                    (w - inset - leg, d - inset - leg),
                ] {
                    add(a, 0.0, b, a + leg, h - top, b + leg, m);
                }
            }
            1 => add(0.0, 0.0, 0.0, w, h, d, furnished::CABINET),
            _ => {
                // Shelf: two side panels, a back panel and 3 to 5 boards between them.
                let m = furnished::SHELF;
                let t = 0.02 * unit;
                let back = 0.01 * unit;
                add(0.0, 0.0, 0.0, t, h, d, m);
                add(w - t, 0.0, 0.0, w, h, d, m);
                add(t, 0.0, 0.0, w - t, h, back, m);
                let boards = 3 + rng.below(3) as usize;
                for k in 0..boards {
                    let y = (h - t) * k as f64 / (boards - 1) as f64;
                    add(t, y, back, w - t, y + t, d, m);
                }
            }
        }
    }
}

/// Size fallback for generator arguments that are not finite and positive.
fn positive_or(value: f64, fallback: f64) -> f64 {
    if value.is_finite() && value > 0.0 {
        value
    } else {
        fallback
    }
}

/// A closed room of `size` x `0.5 size` (height) x `0.8 size` (x, y, z), seen from inside: thin
/// walls facing inwards (white-ish), a coloured floor picked by `seed`, one to three lamp
/// rectangles just below the ceiling facing down, and up to `furniture` pieces (tables, cabinets,
/// shelves) standing on the floor, scaled as if the room were 5 m wide (fewer if they do not fit).
///
/// Materials: [`furnished`] (`EXTERIOR` unused). A `size` that is not finite and positive is
/// replaced by 1.
pub fn room(size: f64, seed: u64, furniture: usize) -> Scene {
    let size = positive_or(size, 1.0);
    let mut rng = Rng::new(seed);
    let mut scene = Scene {
        source: format!("generator:room(size={size}, seed={seed}, furniture={furniture})").into(),
        ..Scene::default()
    };
    let floor = FLOOR_COLOURS[rng.below(FLOOR_COLOURS.len() as u64) as usize];
    furnished_materials(&mut scene, floor);
    let hi = DVec3::new(size, 0.5 * size, 0.8 * size);
    let unit = size / 5.0;
    {
        use furnished::*;
        // Inward box: faces in -x, +x, -y, +y, -z, +z order; -y is the floor, +y the ceiling.
        add_solid_box(
            &mut scene,
            DVec3::ZERO,
            hi,
            [WALL, WALL, FLOOR, CEILING, WALL, WALL],
            true,
        );
    }
    let mut layout = Layout::default();
    let lamps = 1 + rng.below(3) as usize;
    let lamp_y = hi.y - 0.004 * hi.y;
    for k in 0..lamps {
        let cx = (k as f64 + 0.5) * hi.x / lamps as f64;
        let (hx, hz) = (0.15 * hi.x / lamps as f64, 0.1 * hi.z);
        layout.lamps.push(Lamp {
            x: [cx - hx, cx + hx],
            z: [0.5 * hi.z - hz, 0.5 * hi.z + hz],
            y: lamp_y,
        });
    }
    furnish(&mut layout, &mut rng, DVec3::ZERO, hi, furniture, unit, &[]);
    layout.emit(&mut scene, furnished::LIGHT);
    scene
}

/// Building dimensions, in metres (the building's scene unit).
mod dims {
    /// Inner room size along x and z, and storey height (floor to ceiling).
    pub const W: f64 = 5.0;
    pub const D: f64 = 4.0;
    pub const H: f64 = 2.7;
    /// Wall thickness and slab thickness.
    pub const T: f64 = 0.2;
    pub const S: f64 = 0.3;
    /// Door width and height.
    pub const DOOR_W: f64 = 0.9;
    pub const DOOR_H: f64 = 2.1;
}

/// The boxes and lamps of [`building`], before triangulation (tests check geometry here).
fn building_layout(rooms_x: usize, rooms_y: usize, floors: usize, seed: u64) -> Layout {
    use dims::*;
    use furnished::{CEILING, EXTERIOR, FLOOR, WALL};
    let mut layout = Layout::default();
    let (px, pz, ph) = (W + T, D + T, S + H);
    let big_x = rooms_x as f64 * px + T;
    let big_z = rooms_y as f64 * pz + T;

    // Slabs: ground (f = 0), between storeys, roof (f = floors). One closed box each.
    for f in 0..=floors {
        let y = f as f64 * ph;
        let bottom = if f == 0 { EXTERIOR } else { CEILING };
        let top = if f == floors { EXTERIOR } else { FLOOR };
        layout.solid(
            DVec3::new(0.0, y, 0.0),
            DVec3::new(big_x, y + S, big_z),
            [EXTERIOR, EXTERIOR, bottom, top, EXTERIOR, EXTERIOR],
        );
    }

    for f in 0..floors {
        let y0 = f as f64 * ph + S;
        let y1 = y0 + H;
        // Doors: a door on the x-wall i (between rooms i-1 and i) in row j, and on the z-wall k
        // (between rows k-1 and k) in column i, each with an offset along the wall.
        let mut x_doors = vec![None; (rooms_x + 1) * rooms_y];
        let mut z_doors = vec![None; rooms_x * (rooms_y + 1)];
        for j in 0..rooms_y {
            for i in 1..rooms_x {
                let mut rng = sub_rng(seed, 1, i, j, f);
                if rng.chance(0.6) {
                    x_doors[i * rooms_y + j] = Some(rng.range(0.3, D - 0.3 - DOOR_W));
                }
            }
        }
        for k in 1..rooms_y {
            for i in 0..rooms_x {
                let mut rng = sub_rng(seed, 2, i, k, f);
                if rng.chance(0.6) {
                    z_doors[k * rooms_x + i] = Some(rng.range(0.3, W - 0.3 - DOOR_W));
                }
            }
        }

        // x-walls (constant x) run the whole depth of the building, cut only at doors.
        for i in 0..=rooms_x {
            let x = i as f64 * px;
            let (minus, plus) = (
                if i == 0 { EXTERIOR } else { WALL },
                if i == rooms_x { EXTERIOR } else { WALL },
            );
            let mut z_start = 0.0;
            for j in 0..rooms_y {
                if let Some(off) = x_doors[i * rooms_y + j] {
                    let za = j as f64 * pz + T + off;
                    let zb = za + DOOR_W;
                    let start_face = if z_start == 0.0 { EXTERIOR } else { WALL };
                    layout.solid(
                        DVec3::new(x, y0, z_start),
                        DVec3::new(x + T, y1, za),
                        [minus, plus, WALL, WALL, start_face, WALL],
                    );
                    // Lintel over the door.
                    layout.solid(
                        DVec3::new(x, y0 + DOOR_H, za),
                        DVec3::new(x + T, y1, zb),
                        [minus, plus, WALL, WALL, WALL, WALL],
                    );
                    z_start = zb;
                }
            }
            let start_face = if z_start == 0.0 { EXTERIOR } else { WALL };
            layout.solid(
                DVec3::new(x, y0, z_start),
                DVec3::new(x + T, y1, big_z),
                [minus, plus, WALL, WALL, start_face, EXTERIOR],
            );
        }

        // z-walls (constant z) fill the spans between x-walls, one per room column.
        for k in 0..=rooms_y {
            let z = k as f64 * pz;
            let (minus, plus) = (
                if k == 0 { EXTERIOR } else { WALL },
                if k == rooms_y { EXTERIOR } else { WALL },
            );
            for i in 0..rooms_x {
                let xa = i as f64 * px + T;
                let xb = (i + 1) as f64 * px;
                let faces = [WALL, WALL, WALL, WALL, minus, plus];
                match z_doors[k * rooms_x + i] {
                    Some(off) => {
                        let (da, db) = (xa + off, xa + off + DOOR_W);
                        layout.solid(DVec3::new(xa, y0, z), DVec3::new(da, y1, z + T), faces);
                        layout.solid(
                            DVec3::new(da, y0 + DOOR_H, z),
                            DVec3::new(db, y1, z + T),
                            faces,
                        );
                        layout.solid(DVec3::new(db, y0, z), DVec3::new(xb, y1, z + T), faces);
                    }
                    None => layout.solid(DVec3::new(xa, y0, z), DVec3::new(xb, y1, z + T), faces),
                }
            }
        }

        // Rooms: lamps in some, furniture in all, doorways kept clear.
        let first_lit = layout.lamps.len();
        for j in 0..rooms_y {
            for i in 0..rooms_x {
                let lo = DVec3::new(i as f64 * px + T, y0, j as f64 * pz + T);
                let hi = DVec3::new((i + 1) as f64 * px, y1, (j + 1) as f64 * pz);
                let mut rng = sub_rng(seed, 3, i, j, f);
                if rng.chance(0.7) {
                    add_room_lamps(&mut layout, &mut rng, lo, hi);
                }
                let mut clear = Vec::new();
                let reach = 1.0;
                for (wall_i, side) in [(i, 1.0), (i + 1, -1.0)] {
                    if let Some(off) = x_doors[wall_i * rooms_y + j] {
                        let x = if side > 0.0 { lo.x } else { hi.x - reach };
                        clear.push(Rect {
                            x: [x, x + reach],
                            z: [lo.z + off, lo.z + off + DOOR_W],
                        });
                    }
                }
                for (wall_k, side) in [(j, 1.0), (j + 1, -1.0)] {
                    if let Some(off) = z_doors[wall_k * rooms_x + i] {
                        let z = if side > 0.0 { lo.z } else { hi.z - reach };
                        clear.push(Rect {
                            x: [lo.x + off, lo.x + off + DOOR_W],
                            z: [z, z + reach],
                        });
                    }
                }
                let pieces = 1 + rng.below(3) as usize;
                furnish(&mut layout, &mut rng, lo, hi, pieces, 1.0, &clear);
            }
        }
        // Every storey gets at least one lamp, so no storey is entirely dark by chance.
        if layout.lamps.len() == first_lit && rooms_x > 0 && rooms_y > 0 {
            let lo = DVec3::new(T, y0, T);
            let hi = DVec3::new(px, y1, pz);
            add_room_lamps(&mut layout, &mut sub_rng(seed, 4, 0, 0, f), lo, hi);
        }
    }
    layout
}

/// The random stream of one wall or room: a hash of the seed and its coordinates, so that a room
/// looks the same whatever the size of the building around it (growing a building only adds
/// rooms; a room on the old +x or +z edge may change, as its outer wall can become a wall with a
/// door), and the random content of a building is a sum of independent per-room parts.
fn sub_rng(seed: u64, tag: u64, a: usize, b: usize, c: usize) -> Rng {
    let mut h = Rng::new(seed).next_u64() ^ tag;
    for x in [a, b, c] {
        h = Rng::new(h ^ x as u64).next_u64();
    }
    Rng::new(h)
}

fn add_room_lamps(layout: &mut Layout, rng: &mut Rng, lo: DVec3, hi: DVec3) {
    let n = 1 + rng.below(2) as usize;
    let y = hi.y - 0.01;
    for k in 0..n {
        let cx = lo.x + (k as f64 + 0.5) * (hi.x - lo.x) / n as f64;
        let cz = 0.5 * (lo.z + hi.z);
        let (hx, hz) = (0.3, 0.3);
        layout.lamps.push(Lamp {
            x: [cx - hx, cx + hx],
            z: [cz - hz, cz + hz],
            y,
        });
    }
}

/// A building of `rooms_x` x `rooms_y` rooms per storey and `floors` storeys, in metres: rooms of
/// 5 x 4 m, 2.7 m high, separated by 0.2 m walls and 0.3 m slabs, each wall and slab a closed box.
/// About 60 % of the walls between neighbouring rooms of a storey have a door (0.9 x 2.1 m);
/// about 70 % of rooms (and at least one per storey) have one or two ceiling lamps; every room has
/// one to three pieces of furniture, clear of walls and doorways. Outer walls have no openings.
///
/// The size knob for scale runs: triangles and surface area grow linearly with
/// `rooms_x * rooms_y * floors`: about 145 triangles and 120 m^2 of surface per room in a large
/// building (including wall faces hidden against slabs), plus the outer shell (a lone room has
/// ~160 triangles and ~230 m^2). With voxels of h metres the surface holds roughly `120 / h^2`
/// voxels per room (more in practice, since a tunnel-free surface is more than one voxel thick):
/// 1 room at h = 0.15 gives ~10^4 voxels, 1000 rooms at h = 0.035 ~10^8.
///
/// Materials: [`furnished`]. Any dimension 0 gives a scene with no triangles (which
/// `Scene::validate` reports as empty).
pub fn building(rooms_x: usize, rooms_y: usize, floors: usize, seed: u64) -> Scene {
    let mut scene = Scene {
        source: format!(
            "generator:building(rooms_x={rooms_x}, rooms_y={rooms_y}, floors={floors}, seed={seed})"
        )
        .into(),
        ..Scene::default()
    };
    furnished_materials(&mut scene, FLOOR_COLOURS[0]);
    if rooms_x == 0 || rooms_y == 0 || floors == 0 {
        return scene;
    }
    building_layout(rooms_x, rooms_y, floors, seed).emit(&mut scene, furnished::LIGHT);
    scene
}

/// Two rooms side by side along x sharing a thick wall (see [`sealed`] for sizes and material
/// indices). The left room (x in [0, 4]) has a lamp; the right room (x in [4.25, 8.25]) has no
/// opening of any kind and holds a cube, so every `dark_*` surface must stay black. Every wall and
/// slab is a closed box; slabs are split at the middle of the shared wall so that each room's floor
/// and ceiling carry that room's material.
pub fn sealed_rooms() -> Scene {
    use sealed::*;
    let mut scene = Scene {
        source: "generator:sealed_rooms".into(),
        ..Scene::default()
    };
    for (name, kd, ke) in [
        ("wall", [0.8; 3], [0.0; 3]),
        ("floor", [0.6, 0.5, 0.4], [0.0; 3]),
        ("ceiling", [0.8; 3], [0.0; 3]),
        ("light", [0.8; 3], [10.0; 3]),
        ("dark_wall", [0.8; 3], [0.0; 3]),
        ("dark_floor", [0.6, 0.5, 0.4], [0.0; 3]),
        ("dark_ceiling", [0.8; 3], [0.0; 3]),
        ("dark_block", [0.7; 3], [0.0; 3]),
        ("exterior", [0.5; 3], [0.0; 3]),
        ("hidden", [0.5; 3], [0.0; 3]),
    ] {
        scene.add_material(Material::new(name, kd, ke));
    }
    let [w, h, d] = ROOM;
    let t = THICKNESS;
    let mid = w + 0.5 * t;
    let far = 2.0 * w + 2.0 * t;
    let (ext, hid) = (EXTERIOR, HIDDEN);
    let v = DVec3::new;
    let mut l = Layout::default();
    // Slabs, split at the middle of the shared wall.
    l.solid(
        v(-t, -t, -t),
        v(mid, 0.0, d + t),
        [ext, hid, ext, FLOOR, ext, ext],
    );
    l.solid(
        v(mid, -t, -t),
        v(far, 0.0, d + t),
        [hid, ext, ext, DARK_FLOOR, ext, ext],
    );
    l.solid(
        v(-t, h, -t),
        v(mid, h + t, d + t),
        [ext, hid, CEILING, ext, ext, ext],
    );
    l.solid(
        v(mid, h, -t),
        v(far, h + t, d + t),
        [hid, ext, DARK_CEILING, ext, ext, ext],
    );
    // x-walls span the full depth; the shared one has one face in each room.
    l.solid(
        v(-t, 0.0, -t),
        v(0.0, h, d + t),
        [ext, WALL, hid, hid, ext, ext],
    );
    l.solid(
        v(w, 0.0, -t),
        v(w + t, h, d + t),
        [WALL, DARK_WALL, hid, hid, ext, ext],
    );
    l.solid(
        v(far - t, 0.0, -t),
        v(far, h, d + t),
        [DARK_WALL, ext, hid, hid, ext, ext],
    );
    // z-walls between the x-walls.
    for (x0, x1, inner) in [(0.0, w, WALL), (w + t, far - t, DARK_WALL)] {
        l.solid(
            v(x0, 0.0, -t),
            v(x1, h, 0.0),
            [hid, hid, hid, hid, ext, inner],
        );
        l.solid(
            v(x0, 0.0, d),
            v(x1, h, d + t),
            [hid, hid, hid, hid, inner, ext],
        );
    }
    // A cube in the dark room, and the lamp in the lit one.
    let c = w + t + 0.5 * w;
    l.solid(v(c - 0.5, 0.0, 1.5), v(c + 0.5, 1.0, 2.5), [DARK_BLOCK; 6]);
    l.lamps.push(Lamp {
        x: [0.5 * w - 0.5, 0.5 * w + 0.5],
        z: [0.5 * d - 0.5, 0.5 * d + 0.5],
        y: h - 0.01,
    });
    l.emit(&mut scene, LIGHT);
    scene
}

/// The closed cube `[0, 1]^3`, six walls facing inwards, all of one grey material `furnace` with
/// `Ke = emission` and `Kd = reflectance` in every channel. Its exact answer is
/// `B = emission / (1 - reflectance)` everywhere. Out-of-range values are kept as given, so
/// `Scene::validate` can report them.
pub fn furnace(emission: f64, reflectance: f64) -> Scene {
    let mut scene = Scene {
        source: format!("generator:furnace(emission={emission}, reflectance={reflectance})").into(),
        ..Scene::default()
    };
    let m = scene.add_material(Material::new("furnace", [reflectance; 3], [emission; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, m, true);
    scene
}

/// Two parallel, directly opposed squares of side `side` at distance `distance`: the emitter
/// (material 0 `emitter`, `Ke = emission`, `Kd = 0`) in the plane z = 0 over `[0, side]^2`, facing
/// +z, and the receiver (material 1 `receiver`, `Kd = 0`, `Ke = 0`) at z = `distance`, facing -z.
/// The receiver's irradiance is `emission * parallel_squares_form_factor(side, distance)` on
/// average. With `Kd = 0` its radiosity is 0: to see the form factor in `B`, use
/// [`parallel_squares_reflecting`].
pub fn parallel_squares(side: f64, distance: f64, emission: f64) -> Scene {
    parallel_squares_reflecting(side, distance, emission, 0.0)
}

/// [`parallel_squares`] with receiver reflectance `rho`. The emitter reflects nothing, so there
/// is exactly one bounce: the receiver's mean radiosity is `rho * emission * F` with
/// `F = parallel_squares_form_factor(side, distance)`.
pub fn parallel_squares_reflecting(side: f64, distance: f64, emission: f64, rho: f64) -> Scene {
    let mut scene = Scene {
        source: format!(
            "generator:parallel_squares(side={side}, distance={distance}, emission={emission}, \
             rho={rho})"
        )
        .into(),
        ..Scene::default()
    };
    let e = scene.add_material(Material::new("emitter", [0.0; 3], [emission; 3]));
    let r = scene.add_material(Material::new("receiver", [rho; 3], [0.0; 3]));
    let sq = |z: f64| {
        [
            DVec3::new(0.0, 0.0, z),
            DVec3::new(side, 0.0, z),
            DVec3::new(side, side, z),
            DVec3::new(0.0, side, z),
        ]
    };
    add_facing(&mut scene, &sq(0.0), DVec3::Z, e);
    add_facing(&mut scene, &sq(distance), DVec3::NEG_Z, r);
    scene
}

/// Form factor between two parallel, directly opposed rectangles `a x b` at distance `c`
/// (Howell's catalogue, configuration C-11): with `X = a / c`, `Y = b / c`,
///
/// `F = 2 / (pi X Y) * [ ln sqrt((1+X^2)(1+Y^2) / (1+X^2+Y^2)) + X sqrt(1+Y^2) atan(X / sqrt(1+Y^2))
///      + Y sqrt(1+X^2) atan(Y / sqrt(1+X^2)) - X atan X - Y atan Y ]`.
///
/// Returns NaN if any argument is not finite and positive (there is no form factor to give).
pub fn parallel_rectangles_form_factor(a: f64, b: f64, c: f64) -> f64 {
    if !(a.is_finite() && b.is_finite() && c.is_finite() && a > 0.0 && b > 0.0 && c > 0.0) {
        return f64::NAN;
    }
    let (x, y) = (a / c, b / c);
    let (x2, y2) = (x * x, y * y);
    let sx = (1.0 + x2).sqrt();
    let sy = (1.0 + y2).sqrt();
    let log = 0.5 * ((1.0 + x2) * (1.0 + y2) / (1.0 + x2 + y2)).ln();
    2.0 / (PI * x * y)
        * (log + x * sy * (x / sy).atan() + y * sx * (y / sx).atan() - x * x.atan() - y * y.atan())
}

/// Form factor between two parallel, directly opposed squares of side `side` at `distance`.
pub fn parallel_squares_form_factor(side: f64, distance: f64) -> f64 {
    parallel_rectangles_form_factor(side, side, distance)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn centroid(t: &crate::scene::Triangle) -> DVec3 {
        (t.vertices[0] + t.vertices[1] + t.vertices[2]) / 3.0
    }

    /// Strict interior overlap of two boxes (touching faces do not count).
    fn boxes_overlap(a: &Part, b: &Part) -> bool {
        (0..3).all(|k| a.min[k] < b.max[k] - 1e-9 && b.min[k] < a.max[k] - 1e-9)
    }

    #[test]
    fn every_scene_validates() {
        let scenes = [
            room(5.0, 1, 6),
            room(0.3, 2, 0),
            room(100.0, 3, 40),
            building(1, 1, 1, 0),
            building(3, 2, 2, 9),
            sealed_rooms(),
            furnace(1.0, 0.9),
            parallel_squares(1.0, 1.0, 1.0),
            parallel_squares_reflecting(2.0, 0.5, 3.0, 0.5),
        ];
        for s in &scenes {
            assert_eq!(s.validate(), Ok(()), "{}", s.source.display());
            assert!(s.materials.iter().any(|m| m.is_emitter()));
            assert!(s.triangles.iter().all(|t| t.area() > 0.0));
        }
    }

    #[test]
    fn bad_arguments_do_not_panic() {
        assert_eq!(room(f64::NAN, 1, 3).validate(), Ok(()));
        assert_eq!(room(-2.0, 1, 3).validate(), Ok(()));
        // A huge furniture request is capped by what fits.
        let crowded = room(5.0, 4, 1_000_000);
        assert_eq!(crowded.validate(), Ok(()));
        assert_eq!(
            building(0, 3, 2, 1).validate(),
            Err(crate::scene::SceneProblem::Empty)
        );
        assert!(furnace(1.0, 1.0).validate().is_err());
        assert!(parallel_squares_form_factor(0.0, 1.0).is_nan());
        assert!(parallel_squares_form_factor(1.0, f64::INFINITY).is_nan());
    }

    #[test]
    fn same_seed_same_scene_other_seed_other_scene() {
        let key = |s: &Scene| format!("{:?}", s.triangles);
        assert_eq!(key(&room(5.0, 11, 8)), key(&room(5.0, 11, 8)));
        assert_ne!(key(&room(5.0, 11, 8)), key(&room(5.0, 12, 8)));
        assert_eq!(key(&building(3, 3, 2, 5)), key(&building(3, 3, 2, 5)));
        assert_ne!(key(&building(3, 3, 2, 5)), key(&building(3, 3, 2, 6)));
    }

    #[test]
    fn building_grows_linearly() {
        let measure = |rx: usize, ry: usize, f: usize| {
            let s = building(rx, ry, f, 42);
            let area: f64 = s.triangles.iter().map(|t| t.area()).sum();
            (s.triangles.len() as f64, area)
        };
        // Along each axis, equal steps in room count add equal amounts (up to the randomness of
        // doors and furniture): the cost is affine, a per-room term plus the outer shell.
        let along = |sizes: [(usize, usize, usize); 4]| {
            let m: Vec<(f64, f64)> = sizes.iter().map(|&(x, y, f)| measure(x, y, f)).collect();
            for pick in [0, 1] {
                let v: Vec<f64> = m
                    .iter()
                    .map(|p| if pick == 0 { p.0 } else { p.1 })
                    .collect();
                let steps = [v[1] - v[0], v[2] - v[1], v[3] - v[2]];
                let mean = steps.iter().sum::<f64>() / 3.0;
                for s in steps {
                    assert!((s / mean - 1.0).abs() < 0.2, "{sizes:?}: steps {steps:?}");
                }
            }
        };
        // Steps of 128 rooms, so the random part of each step (about 5 %) stays far below 20 %.
        along([(16, 8, 1), (32, 8, 1), (48, 8, 1), (64, 8, 1)]);
        along([(8, 16, 1), (8, 32, 1), (8, 48, 1), (8, 64, 1)]);
        along([(8, 8, 2), (8, 8, 4), (8, 8, 6), (8, 8, 8)]);
        // The documented per-room figures (about 145 triangles and 120 m^2 in a large building).
        let (t, a) = measure(16, 8, 4);
        let n = (16 * 8 * 4) as f64;
        assert!(
            (125.0..165.0).contains(&(t / n)),
            "{} triangles per room",
            t / n
        );
        assert!((105.0..140.0).contains(&(a / n)), "{} m^2 per room", a / n);
    }

    #[test]
    fn growing_a_building_keeps_its_rooms() {
        let key = |p: &Part| format!("{:?} {:?}", p.min, p.max);
        let small = building_layout(3, 3, 1, 8);
        let big = building_layout(4, 5, 2, 8);
        let big_keys: std::collections::HashSet<String> = big
            .parts
            .iter()
            .filter(|p| p.kind != Kind::Structure)
            .map(key)
            .collect();
        // Rooms off the small building's +x and +z edges have the same walls in both.
        let inner = |p: &&Part| {
            p.kind != Kind::Structure
                && p.max.x < 2.0 * (dims::W + dims::T)
                && p.max.z < 2.0 * (dims::D + dims::T)
        };
        let kept: Vec<&Part> = small.parts.iter().filter(inner).collect();
        assert!(kept.len() >= 4);
        for p in kept {
            assert!(big_keys.contains(&key(p)));
        }
    }

    #[test]
    fn building_furniture_and_lamps_stay_inside_rooms() {
        use dims::*;
        for seed in 0..6 {
            let (rx, ry, fl) = (4, 3, 2);
            let l = building_layout(rx, ry, fl, seed);
            let structure: Vec<&Part> = l
                .parts
                .iter()
                .filter(|p| p.kind == Kind::Structure)
                .collect();
            let furniture: Vec<&Part> = l
                .parts
                .iter()
                .filter(|p| p.kind != Kind::Structure)
                .collect();
            assert!(furniture.len() >= rx * ry * fl, "every room is furnished");
            for f in &furniture {
                for s in &structure {
                    assert!(!boxes_overlap(f, s), "furniture {f:?} crosses wall {s:?}");
                }
                // Inside one room's air, with the wall margin.
                let (px, pz, ph) = (W + T, D + T, S + H);
                let (i, j, k) = (
                    (f.min.x / px).floor(),
                    (f.min.z / pz).floor(),
                    (f.min.y / ph).floor(),
                );
                assert!(f.min.x >= i * px + T && f.max.x <= (i + 1.0) * px);
                assert!(f.min.z >= j * pz + T && f.max.z <= (j + 1.0) * pz);
                assert!(f.min.y >= k * ph + S && f.max.y <= k * ph + S + 0.8 * H + 1e-9);
            }
            // Pieces of different items never overlap.
            for (n, a) in furniture.iter().enumerate() {
                for b in &furniture[n + 1..] {
                    if a.kind != b.kind {
                        assert!(!boxes_overlap(a, b));
                    }
                }
            }
            // Structure boxes never overlap each other (walls butt, never interpenetrate).
            for (n, a) in structure.iter().enumerate() {
                for b in &structure[n + 1..] {
                    assert!(!boxes_overlap(a, b), "{a:?} overlaps {b:?}");
                }
            }
            // Lamps hang just under a ceiling, inside one room.
            for lamp in &l.lamps {
                let storey = (lamp.y / (S + H)).floor();
                let ceiling = storey * (S + H) + S + H;
                assert!(lamp.y < ceiling && lamp.y > ceiling - 0.05);
                let i = (lamp.x[0] / (W + T)).floor();
                assert!(lamp.x[0] > i * (W + T) + T && lamp.x[1] < (i + 1.0) * (W + T));
            }
        }
    }

    #[test]
    fn building_is_closed_to_the_outside() {
        // Every face on the building's outer boundary carries the exterior material, and no
        // exterior face lies strictly inside the building's bounds (which would mean an opening
        // to the outside had been labelled wrongly).
        let s = building(3, 2, 2, 3);
        let b = s.bounds();
        for t in &s.triangles {
            let c = centroid(t);
            let on_boundary =
                (0..3).any(|k| (c[k] - b.min[k]).abs() < 1e-9 || (c[k] - b.max[k]).abs() < 1e-9);
            let n = t.cross();
            let outward = (0..3).any(|k| {
                ((c[k] - b.min[k]).abs() < 1e-9 && n[k] < 0.0)
                    || ((c[k] - b.max[k]).abs() < 1e-9 && n[k] > 0.0)
            });
            if on_boundary && outward {
                assert_eq!(t.material, furnished::EXTERIOR, "at {c:?}");
            }
        }
    }

    #[test]
    fn room_furniture_stays_inside_and_lamps_face_down() {
        for seed in 0..8 {
            let size = 5.0;
            let s = room(size, seed, 8);
            let (hx, hy, hz) = (size, 0.5 * size, 0.8 * size);
            let mut lamp_area = 0.0;
            for t in &s.triangles {
                match t.material {
                    furnished::TABLE | furnished::CABINET | furnished::SHELF => {
                        for v in &t.vertices {
                            assert!(v.x > 0.0 && v.x < hx && v.z > 0.0 && v.z < hz);
                            assert!(v.y >= 0.0 && v.y <= 0.8 * hy + 1e-9);
                        }
                    }
                    furnished::LIGHT => {
                        assert!(t.cross().normalize().dot(DVec3::NEG_Y) > 1.0 - 1e-12);
                        assert!(t.vertices.iter().all(|v| v.y < hy && v.y > 0.99 * hy));
                        lamp_area += t.area();
                    }
                    _ => {
                        // Room shell: fronts face the inside.
                        let inside = DVec3::new(hx, hy, hz) * 0.5 - centroid(t);
                        assert!(t.cross().dot(inside) > 0.0);
                    }
                }
            }
            assert!(lamp_area > 0.0);
            let furniture = s
                .triangles
                .iter()
                .filter(|t| t.material >= furnished::TABLE)
                .count();
            assert!(furniture >= 12 * 4, "seed {seed}: furniture missing");
        }
    }

    #[test]
    fn sealed_rooms_are_separate() {
        let s = sealed_rooms();
        for (i, m) in s.materials.iter().enumerate() {
            let dark = m.name.starts_with("dark_");
            let expect = matches!(
                i as u32,
                sealed::DARK_WALL | sealed::DARK_FLOOR | sealed::DARK_CEILING | sealed::DARK_BLOCK
            );
            assert_eq!(dark, expect, "{}", m.name);
        }
        let [w, h, d] = sealed::ROOM;
        let t = sealed::THICKNESS;
        for tri in &s.triangles {
            let c = centroid(tri);
            let n = tri.cross().normalize();
            let name = &s.materials[tri.material as usize].name;
            match tri.material {
                sealed::DARK_WALL | sealed::DARK_FLOOR | sealed::DARK_CEILING => {
                    // Faces the dark room's air: x in [w + t, 2w + t].
                    let inside = DVec3::new(1.5 * w + t, 0.5 * h, 0.5 * d);
                    assert!(n.dot(inside - c) > 0.0, "{name} at {c:?}");
                    assert!(c.x >= w + t - 1e-9, "{name} at {c:?}");
                }
                sealed::WALL | sealed::FLOOR | sealed::CEILING | sealed::LIGHT => {
                    let inside = DVec3::new(0.5 * w, 0.5 * h, 0.5 * d);
                    assert!(n.dot(inside - c) > 0.0, "{name} at {c:?}");
                    assert!(c.x <= w + 1e-9, "{name} at {c:?}");
                }
                _ => {}
            }
        }
        // The only emitter is in the lit room.
        let lit: Vec<_> = s
            .triangles
            .iter()
            .filter(|t| t.material == sealed::LIGHT)
            .collect();
        assert_eq!(lit.len(), 2);
        assert!(lit.iter().all(|t| t.vertices.iter().all(|v| v.x < w)));
        assert_eq!(s.materials.iter().filter(|m| m.is_emitter()).count(), 1);
    }

    #[test]
    fn furnace_is_an_inward_unit_cube() {
        let s = furnace(2.0, 0.75);
        assert_eq!(s.triangles.len(), 12);
        assert_eq!(s.materials.len(), 1);
        assert_eq!(s.materials[0].emission, [2.0; 3]);
        assert_eq!(s.materials[0].reflectance, [0.75; 3]);
        let area: f64 = s.triangles.iter().map(|t| t.area()).sum();
        assert!((area - 6.0).abs() < 1e-12);
        for t in &s.triangles {
            assert!(t.cross().dot(DVec3::splat(0.5) - centroid(t)) > 0.0);
        }
    }

    #[test]
    fn parallel_squares_face_each_other() {
        let s = parallel_squares(2.0, 0.5, 3.0);
        assert_eq!(s.triangles.len(), 4);
        for t in &s.triangles {
            let n = t.cross().normalize();
            if t.material == 0 {
                assert!((n - DVec3::Z).length() < 1e-12);
                assert!(t.vertices.iter().all(|v| v.z == 0.0));
            } else {
                assert!((n - DVec3::NEG_Z).length() < 1e-12);
                assert!(t.vertices.iter().all(|v| v.z == 0.5));
            }
        }
        assert_eq!(s.materials[1].reflectance, [0.0; 3]);
        assert_eq!(s.materials[0].emission, [3.0; 3]);
    }

    /// The form factor by quadrature of its definition,
    /// `F = 1/A ∫∫ cos θ1 cos θ2 / (pi r^2) dA1 dA2 = 1/A ∫∫ c^2 / (pi r^4)`. The integrand depends
    /// only on `(x2 - x1, y2 - y1) = (u, v)`, and `∫∫_{[0,a]^2} g(x2 - x1) dx1 dx2 =
    /// ∫_{-a}^{a} (a - |u|) g(u) du`, which leaves a 2-D integral for a fine midpoint rule
    /// (an even cell count puts the kink at u = 0 on a cell boundary).
    fn form_factor_quadrature(a: f64, b: f64, c: f64, n: usize) -> f64 {
        let (hu, hv) = (2.0 * a / n as f64, 2.0 * b / n as f64);
        let mut sum = 0.0;
        for i in 0..n {
            let u = -a + (i as f64 + 0.5) * hu;
            let wu = a - u.abs();
            let mut row = 0.0;
            for j in 0..n {
                let v = -b + (j as f64 + 0.5) * hv;
                let r2 = u * u + v * v + c * c;
                row += (b - v.abs()) / (r2 * r2);
            }
            sum += wu * row;
        }
        sum * hu * hv * c * c / (PI * a * b)
    }

    /// The same definition as a plain 4-D midpoint rule, coarse: checks the reduction above.
    fn form_factor_4d(a: f64, c: f64, n: usize) -> f64 {
        let h = a / n as f64;
        let p = |k: usize| (k as f64 + 0.5) * h;
        let mut sum = 0.0;
        for i1 in 0..n {
            for j1 in 0..n {
                for i2 in 0..n {
                    for j2 in 0..n {
                        let (u, v) = (p(i2) - p(i1), p(j2) - p(j1));
                        let r2 = u * u + v * v + c * c;
                        sum += c * c / (PI * r2 * r2);
                    }
                }
            }
        }
        sum * h.powi(4) / (a * a)
    }

    #[test]
    fn form_factor_matches_quadrature() {
        // Known value for unit squares one unit apart.
        assert!((parallel_squares_form_factor(1.0, 1.0) - 0.19982).abs() < 1e-5);
        for (side, dist) in [(1.0, 1.0), (1.0, 0.2), (2.0, 5.0), (3.0, 0.7), (0.5, 0.05)] {
            let exact = parallel_squares_form_factor(side, dist);
            let numeric = form_factor_quadrature(side, side, dist, 2000);
            assert!(
                (exact - numeric).abs() < 1e-4,
                "side {side}, distance {dist}: {exact} vs {numeric}"
            );
        }
        let exact = parallel_rectangles_form_factor(1.0, 3.0, 0.8);
        assert!((exact - form_factor_quadrature(1.0, 3.0, 0.8, 2000)).abs() < 1e-4);
        // Symmetric in the two sides; 1 in the limit of touching planes, 0 far apart.
        assert_eq!(
            parallel_rectangles_form_factor(1.0, 3.0, 0.8),
            parallel_rectangles_form_factor(3.0, 1.0, 0.8)
        );
        assert!(parallel_squares_form_factor(1.0, 1e-4) > 0.999);
        assert!(parallel_squares_form_factor(1.0, 1e3) < 1e-6);
        // The 2-D reduction agrees with the direct 4-D rule.
        let direct = form_factor_4d(1.0, 1.0, 24);
        assert!((direct - parallel_squares_form_factor(1.0, 1.0)).abs() < 1e-3);
    }
}
