//! No light through a closed wall: a lit room beside a sealed dark room, each closed by its own
//! walls with a gap between them. Light may exist only inside the lit room: every other surface
//! side (the outside of the lit room's walls, both sides of every dark-room wall) must stay exactly
//! 0. Rays that graze past the lit room's outer corners are the hard case (see the "missed plane"
//! rule in `src/solve/propagate.rs`).
//!
//! Not tested (a known limit): a single zero-thickness wall shared by both rooms. The voxels on
//! that wall also hold the floor and ceiling pieces of both rooms, merged per plane, so light can
//! cross there; walls need to be at least about a voxel thick.

use glam::DVec3;
use voxrad::scene::{Material, Scene};
use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

/// Room `[x0, x0 + 1] x [0, 1] x [0, 1]` with inward walls; optionally a ceiling lamp.
fn add_room(scene: &mut Scene, x0: f64, wall: u32, lamp: Option<u32>) {
    scene.add_box(
        DVec3::new(x0, 0.0, 0.0),
        DVec3::new(x0 + 1.0, 1.0, 1.0),
        wall,
        true,
    );
    if let Some(lamp) = lamp {
        let z = 0.97;
        let (a, b) = (x0 + 0.3, x0 + 0.7);
        // Facing down (-z): clockwise seen from above.
        scene.add_polygon(
            &[
                DVec3::new(a, 0.3, z),
                DVec3::new(a, 0.7, z),
                DVec3::new(b, 0.7, z),
                DVec3::new(b, 0.3, z),
            ],
            lamp,
        );
    }
}

#[test]
fn sealed_room_stays_dark() {
    let gap = 0.15;
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [0.8; 3], [0.0; 3]));
    let dark = scene.add_material(Material::new("dark_wall", [0.8; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.5; 3], [10.0; 3]));
    add_room(&mut scene, 0.0, wall, Some(lamp));
    add_room(&mut scene, 1.0 + gap, dark, None);
    let set = voxelize(&scene, GridSpec::Resolution(48)).unwrap();
    let options = SolveOptions {
        directions: 400,
        max_iterations: 6,
        tolerance: None,
        threads: 2,
        ..Default::default()
    };
    let solution = solve(&set, &options).unwrap();

    let lit_centre = set.grid.to_voxel_units(DVec3::splat(0.5));
    let dark_centre = set.grid.to_voxel_units(DVec3::new(1.65 + gap, 0.5, 0.5));
    let (mut dark_inside, mut dark_count, mut lit_inside, mut lit_outside) =
        (0.0f64, 0, 0.0f64, 0.0f64);
    for (k, s) in set.surfels.iter().enumerate() {
        let in_dark_room = set.materials[s.material[0] as usize]
            .name
            .starts_with("dark_wall");
        for side in 0..2 {
            let b = solution.radiosity[k][side]
                .iter()
                .fold(0.0f32, |m, &v| m.max(v)) as f64;
            let centre = if in_dark_room {
                dark_centre
            } else {
                lit_centre
            };
            let faces_inside = (centre - s.position()).dot(s.side_normal(side)) > 0.0;
            match (in_dark_room, faces_inside) {
                (true, _) => {
                    dark_inside = dark_inside.max(b);
                    dark_count += 1;
                }
                (false, true) => lit_inside = lit_inside.max(b),
                (false, false)
                    if !set.materials[s.material[side] as usize]
                        .name
                        .contains("lamp") =>
                {
                    lit_outside = lit_outside.max(b)
                }
                _ => {}
            }
        }
    }
    println!(
        "dark room max {dark_inside}, lit inside max {lit_inside}, lit outside max {lit_outside}"
    );
    assert!(
        lit_inside > 1.0 && dark_count > 1000,
        "lit {lit_inside}, dark sides {dark_count}"
    );
    assert_eq!(dark_inside, 0.0, "light leaked into the sealed room");
    assert!(
        lit_outside < 0.002 * lit_inside,
        "light leaks out of the lit room: {lit_outside}"
    );
}

/// The generator's sealed rooms: thick walls and slabs as closed solids pressed against each
/// other, a block in the dark room. Every side whose material is one of the dark room's, the
/// building's exterior, or a face hidden against another solid should stay 0.
///
/// Known defect, bounded here so it cannot grow unnoticed: where several solids meet in one voxel
/// (a wall standing on a slab at a room's corner), coplanar faces of different solids merge into
/// one L-shaped piece whose bounding box covers the whole voxel, and a little light still reaches
/// hidden faces and the inner sides of the walls: at most 0.22 % of the lit room's brightest
/// surface while faces in contact kept their covered area, 0.10 % since
/// (`voxelize::merge_voxel`), 0.04 % since the sides inside closed solids went dark
/// (`voxel::enclosed`). The simpler rooms above, each closed by its own walls, are exact.
#[test]
fn generated_sealed_rooms_stay_dark() {
    let scene = voxrad::gen::sealed_rooms();
    let set = voxelize(&scene, GridSpec::Resolution(64)).unwrap();
    let options = SolveOptions {
        directions: 300,
        max_iterations: 5,
        tolerance: None,
        threads: 2,
        ..Default::default()
    };
    let solution = solve(&set, &options).unwrap();
    let (mut dark, mut dark_count, mut lit) = (0.0f32, 0, 0.0f32);
    let mut worst = String::new();
    for (k, s) in set.surfels.iter().enumerate() {
        for side in 0..2 {
            let name = &set.materials[s.material[side] as usize].name;
            let b = solution.radiosity[k][side]
                .iter()
                .fold(0.0f32, |m, &v| m.max(v));
            if name.starts_with("dark_")
                || name.starts_with("exterior")
                || name.starts_with("hidden")
            {
                dark_count += 1;
                if b > dark {
                    dark = b;
                    worst = format!("{name} side {side} of {s:?}");
                }
            } else {
                lit = lit.max(b);
            }
        }
    }
    println!("dark max {dark} ({worst}), {dark_count} dark sides, lit max {lit}");
    assert!(lit > 1.0 && dark_count > 1000);
    assert!(
        dark < 0.001 * lit,
        "light reached a sealed surface: {worst}"
    );
}
