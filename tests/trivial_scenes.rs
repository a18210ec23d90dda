//! Scenes whose answer needs no iteration: the solver must see that and stop at once.
//! - No emitter: every radiosity is exactly 0 and no iteration runs.
//! - Every reflectance 0: light does not bounce, so `B = E` exactly after one pass; in a closed
//!   box whose whole ceiling glows, every watt emitted is absorbed.
//! - With a small lamp (9 voxels wide) hanging in a black box, the power absorbed matches the power
//!   emitted to within the lamp's rim: measured +2.5 % at resolution 24 (it was +24 % before open
//!   edges got their coverage, see `src/solve/coverage.rs`).

use glam::DVec3;
use voxrad::scene::{Material, Scene};
use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn open_box(reflectance: f64, emission: f64) -> Scene {
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [reflectance; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [reflectance; 3], [emission; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, wall, true);
    scene.add_polygon(
        &[
            DVec3::new(0.3, 0.3, 0.95),
            DVec3::new(0.3, 0.7, 0.95),
            DVec3::new(0.7, 0.7, 0.95),
            DVec3::new(0.7, 0.3, 0.95),
        ],
        lamp,
    );
    scene
}

/// Voxelizes at resolution 24 and solves with the default stopping rule.
fn solve_default(
    scene: Scene,
    directions: usize,
) -> (voxrad::voxel::SurfelSet, voxrad::solve::Solution) {
    let set = voxelize(&scene, GridSpec::Resolution(24)).unwrap();
    let solution = solve(
        &set,
        &SolveOptions {
            directions,
            ..Default::default()
        },
    )
    .unwrap();
    (set, solution)
}

#[test]
fn no_emitter_means_nothing_to_solve() {
    let (_, solution) = solve_default(open_box(0.8, 0.0), 100);
    assert_eq!(solution.stats.iterations, 0);
    assert!(solution.stats.converged);
    assert!(solution
        .radiosity
        .iter()
        .flatten()
        .flatten()
        .all(|&b| b == 0.0));
}

#[test]
fn black_scene_is_direct_light_only_in_one_pass() {
    let (set, solution) = solve_default(open_box(0.0, 5.0), 100);
    assert_eq!(
        solution.stats.iterations, 1,
        "a scene that reflects nothing needs one pass"
    );
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        for (&material, side) in s.material.iter().zip(b) {
            let e = set.materials[material as usize].emission[0] as f32;
            assert_eq!(side[0], e, "B must equal E when nothing reflects");
        }
    }
    let (emitted, absorbed) = (
        solution.stats.emitted_power[0],
        solution.stats.absorbed_power[0],
    );
    println!("small lamp: emitted {emitted:.5}, absorbed {absorbed:.5}");
    assert!(
        (absorbed - emitted).abs() < 0.03 * emitted,
        "emitted {emitted}, absorbed {absorbed}"
    );
}

#[test]
fn black_box_with_a_glowing_ceiling_absorbs_all_it_emits() {
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [0.0; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.0; 3], [3.0; 3]));
    // Walls facing inwards; the ceiling (z = 1) is the lamp, facing down.
    scene.add_box(DVec3::ZERO, DVec3::ONE, wall, true);
    let ceiling_start = scene.triangles.len() - 2;
    for t in &mut scene.triangles[ceiling_start..] {
        t.material = lamp;
    }
    let (_, solution) = solve_default(scene, 200);
    assert_eq!(solution.stats.iterations, 1);
    let (emitted, absorbed) = (
        solution.stats.emitted_power[0],
        solution.stats.absorbed_power[0],
    );
    assert!((emitted - 3.0).abs() < 1e-9, "emitted {emitted}");
    // Measured: 0.4 % low at resolution 24 with 193 directions (receivers gather along discrete
    // lines, so the transfer is exact only in the limit); the bound leaves room for that.
    assert!(
        (absorbed - emitted).abs() < 1e-2 * emitted,
        "emitted {emitted}, absorbed {absorbed}"
    );
}
