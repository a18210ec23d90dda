//! Thin two-sided geometry: a single quad (zero thickness) in the middle of a closed, glowing box
//! is lit on both sides. By the box's mirror symmetry through the quad's plane, its two sides must
//! receive the same light (to 1e-3: the floor-based line partition is not exactly mirror
//! symmetric; measured 1.7e-4), and a quad modelled twice, back to back, must behave like the single
//! one: each copy's front is one side of the sheet, its back faces into the other copy (dark,
//! `voxelize::mark_doubled`), and the box absorbs what it emits, the sheet counted once.

mod common;

use glam::DVec3;
use voxrad::scene::{Material, Scene};
use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn sheet_scene(back_to_back: bool) -> Scene {
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [0.5; 3], [1.0; 3]));
    let sheet = scene.add_material(Material::new("sheet", [0.7; 3], [0.0; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, wall, true);
    // A square at x = 0.5 (through voxel centres), smaller than the box.
    let quad = [
        DVec3::new(0.5, 0.25, 0.25),
        DVec3::new(0.5, 0.75, 0.25),
        DVec3::new(0.5, 0.75, 0.75),
        DVec3::new(0.5, 0.25, 0.75),
    ];
    scene.add_polygon(&quad, sheet);
    if back_to_back {
        let mut reversed = quad;
        reversed.reverse();
        scene.add_polygon(&reversed, sheet);
    }
    scene
}

/// Mean radiosity of each side of the sheet (side facing -x, side facing +x), area-weighted over
/// the sides that can be seen (not those facing into a copy of the sheet), and the power balance
/// `(emitted - absorbed) / emitted`.
fn sheet_sides(back_to_back: bool) -> (f64, f64, f64) {
    let scene = sheet_scene(back_to_back);
    let set = voxelize(&scene, GridSpec::Resolution(33)).unwrap();
    let options = SolveOptions {
        directions: 300,
        max_iterations: 200,
        tolerance: Some(1e-6),
        threads: 2,
        ..Default::default()
    };
    let solution = solve(&set, &options).unwrap();
    let (mut minus, mut plus, mut area) = ([0.0; 2], [0.0; 2], [0.0; 2]);
    for (k, s) in set.surfels.iter().enumerate() {
        if set.materials[s.material[0] as usize].name != "sheet" {
            continue;
        }
        let a = s.area as f64;
        for side in 0..2 {
            if set.materials[s.material[side] as usize].inside {
                continue;
            }
            let b = solution.radiosity[k][side][0] as f64 * a;
            if s.side_normal(side).x < 0.0 {
                minus[0] += b;
                minus[1] += a;
            } else {
                plus[0] += b;
                plus[1] += a;
            }
        }
        area[0] += a;
    }
    let stats = &solution.stats;
    let (e, absorbed) = (stats.emitted_power[0], stats.absorbed_power[0]);
    assert!(area[0] > 0.0);
    (minus[0] / minus[1], plus[0] / plus[1], (e - absorbed) / e)
}

#[test]
fn a_single_quad_is_lit_equally_on_both_sides() {
    let (minus, plus, balance) = sheet_sides(false);
    println!("single quad: side -x {minus:.6}, side +x {plus:.6}, balance {balance:.2e}");
    assert!(balance.abs() < 1e-4, "balance {balance}");
    assert!(minus > 0.5 && plus > 0.5, "a side of the sheet is dark");
    assert!(
        (minus - plus).abs() < 1e-3 * minus,
        "sides differ: {minus} vs {plus}"
    );
}

#[test]
fn a_quad_modelled_back_to_back_matches_the_single_quad() {
    let single = sheet_sides(false);
    let (minus, plus, balance) = sheet_sides(true);
    println!(
        "back to back: side -x {minus:.6}, side +x {plus:.6}, balance {balance:.2e}; single \
         {single:?}"
    );
    // Counted twice (before `mark_doubled`), the sheet's sides gathered 2.3 % more power than
    // the lines carried, and the closed box's scale (`solve::closed`) took it from every surface
    // in every bounce: the sheet came out 4.5 % dark.
    assert!(balance.abs() < 1e-4, "balance {balance}");
    assert!(
        (minus - plus).abs() < 1e-3 * minus,
        "sides differ: {minus} vs {plus}"
    );
    // Each side of the doubled sheet is one copy's front: the same light as the single sheet's.
    assert!(
        (minus - single.0).abs() < 2e-3 * single.0,
        "{minus} vs {}",
        single.0
    );
}
