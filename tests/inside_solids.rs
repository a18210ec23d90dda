//! Back sides inside closed solids (`voxel::enclosed`) gather nothing and send nothing, and only
//! those: a room lit by a lamp under its ceiling, holding a closed cabinet (a box wound outward),
//! an open bin (a box without its top, whose inner faces are seen from above) and a slab thinner
//! than a voxel. The cabinet's and the slab's back sides are inside their solids; the room's
//! (a box wound inward: its back sides face out of the room) and the bin's are not.
//!
//! Checked on the answer: the sides inside are exactly 0; every side seen from the room is lit,
//! the bin's inner faces included; and what the room absorbs matches what its lamp emits within
//! the closed scenes' allowance, so light is neither created nor lost at the solids.

use glam::DVec3;
use voxrad::scene::{Material, Scene};
use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::{absolute_position, SurfelSet, BACK, FRONT};

const CABINET: [[f64; 3]; 2] = [[0.5, 0.0, 0.5], [1.3, 1.1, 1.0]];
const BIN: [[f64; 3]; 2] = [[2.4, 0.0, 2.4], [3.2, 0.6, 3.2]];
const SLAB: [[f64; 3]; 2] = [[2.2, 1.2, 0.4], [3.4, 1.25, 1.4]];

/// The box `[lo, hi]` wound outward (`Scene::add_box`: two triangles a face, in the order -x,
/// +x, -y, +y, -z, +z), its top (+y) left out if `open`.
fn outward_box(scene: &mut Scene, b: [[f64; 3]; 2], m: u32, open: bool) {
    let first = scene.triangles.len();
    scene.add_box(DVec3::from(b[0]), DVec3::from(b[1]), m, false);
    if open {
        scene.triangles.drain(first + 6..first + 8);
    }
}

fn scene() -> Scene {
    let mut scene = Scene::default();
    let room = scene.add_material(Material::new("room", [0.6; 3], [0.0; 3]));
    let furniture = scene.add_material(Material::new("furniture", [0.5; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.0; 3], [20.0; 3]));
    scene.add_box(DVec3::ZERO, DVec3::new(4.0, 2.5, 4.0), room, true);
    outward_box(&mut scene, CABINET, furniture, false);
    outward_box(&mut scene, BIN, furniture, true);
    outward_box(&mut scene, SLAB, furniture, false);
    // A lamp under the ceiling, facing down.
    let y = 2.45;
    scene.add_polygon(
        &[
            DVec3::new(1.5, y, 1.5),
            DVec3::new(2.5, y, 1.5),
            DVec3::new(2.5, y, 2.5),
            DVec3::new(1.5, y, 2.5),
        ],
        lamp,
    );
    scene
}

/// Whether surfel `s`'s point lies in the box `b` (world units, with a voxel's margin).
fn in_box(set: &SurfelSet, k: usize, b: [[f64; 3]; 2]) -> bool {
    let s = &set.surfels[k];
    let p =
        DVec3::from(set.grid.origin) + absolute_position(s.voxel, s.point) * set.grid.voxel_size;
    let m = set.grid.voxel_size;
    (0..3).all(|i| p[i] > b[0][i] - m && p[i] < b[1][i] + m)
}

#[test]
fn sides_inside_closed_solids_gather_nothing_and_the_rest_is_lit() {
    let scene = scene();
    let set = voxelize(&scene, GridSpec::Resolution(40)).unwrap();
    let inside = |k: usize| set.materials[set.surfels[k].material[BACK] as usize].inside;
    let count = |b: [[f64; 3]; 2]| {
        let all = (0..set.surfels.len()).filter(|&k| in_box(&set, k, b));
        let marked = all.clone().filter(|&k| inside(k)).count();
        (marked, all.count())
    };
    // Every surfel of the cabinet and of the slab (whose boxes hold nothing else but the floor
    // under the cabinet) is marked but the floor's; none of the bin's or the room's walls.
    let (marked, all) = count(CABINET);
    assert!(marked > 20 && marked < all, "cabinet: {marked} of {all}");
    let (marked, all) = count(SLAB);
    assert!(marked > 20, "slab: {marked} of {all}");
    let (marked, all) = count(BIN);
    assert_eq!(marked, 0, "bin: {marked} of {all}");
    for k in 0..set.surfels.len() {
        let s = &set.surfels[k];
        if inside(k) {
            // Marked surfels are the solids' faces: their material's front is the furniture's.
            assert_eq!(s.material[FRONT], 1, "surfel {k}");
        }
    }

    let solution = solve(
        &set,
        &SolveOptions {
            directions: 193,
            threads: 2,
            max_iterations: 60,
            tolerance: Some(1e-5),
            ..Default::default()
        },
    )
    .unwrap();
    let mut inside_sides = 0;
    for (k, b) in solution.radiosity.iter().enumerate() {
        let s = &set.surfels[k];
        if inside(k) {
            inside_sides += 1;
            assert_eq!(b[BACK], [0.0; 3], "surfel {k}'s side inside a solid");
        }
        // Every side seen from the room is lit (a surfel of no area stops rays and nothing else).
        let seen = |side: usize| !(side == BACK && inside(k));
        for side in [FRONT, BACK].into_iter().filter(|&side| seen(side)) {
            if s.area > 0.0 && s.material[FRONT] == 1 && in_box(&set, k, BIN) {
                assert!(
                    b[side][0] > 0.0,
                    "bin surfel {k} side {side}: {:?}",
                    b[side]
                );
            }
        }
    }
    assert!(inside_sides > 0);
    let emitted: f64 = solution.stats.emitted_power.iter().sum();
    let absorbed: f64 = solution.stats.absorbed_power.iter().sum();
    let imbalance = (emitted - absorbed) / emitted;
    println!("{inside_sides} sides inside solids; power imbalance {imbalance:.3e}");
    assert!(imbalance.abs() < 0.02, "imbalance {imbalance}");
}
