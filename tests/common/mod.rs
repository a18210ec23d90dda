//! Helpers shared by the integration tests: small scenes built in code.
#![allow(dead_code)]

pub mod cli;
pub mod files;
pub mod mpi;
pub mod process;

use glam::DVec3;
use voxrad::scene::{Material, Scene};
use voxrad::voxel::{Surfel, SurfelSet, FRONT};

/// A closed cube `[0, 1]^3` whose six walls face inwards, all emitting `e` with reflectance `rho`.
pub fn furnace(e: f64, rho: f64) -> Scene {
    let mut scene = Scene::default();
    let m = scene.add_material(Material::new("wall", [rho; 3], [e; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, m, true);
    scene
}

/// The side of a surfel that faces into the unit cube's centre.
pub fn inner_side(s: &Surfel, set: &SurfelSet) -> usize {
    let centre = set.grid.to_voxel_units(DVec3::splat(0.5));
    if (centre - s.position()).dot(s.side_normal(FRONT)) > 0.0 {
        0
    } else {
        1
    }
}

/// Writes `set` as a shard set of `shards` files in order 0 (what `voxrad-shard convert` makes
/// of the same scene, made here from the in-memory voxelization).
pub fn write_shard_set(set: &SurfelSet, dir: &std::path::Path, shards: usize) {
    voxrad::storage::write_shard_set(set, dir, shards, 0).expect("write shard set");
}

/// The largest relative difference between two radiosity lists, value by value, relative to
/// the larger of the two values but at least 1e-3 of the largest radiosity in `reference` (so
/// that values near zero compare by absolute difference).
pub fn worst_relative_difference(got: &[[[f32; 3]; 2]], reference: &[[[f32; 3]; 2]]) -> f64 {
    assert_eq!(got.len(), reference.len(), "different surfel counts");
    let peak = reference
        .iter()
        .flatten()
        .flatten()
        .fold(0f32, |a, &b| a.max(b)) as f64;
    let mut worst = 0f64;
    for (a, b) in got.iter().zip(reference) {
        for (&x, &y) in a.iter().flatten().zip(b.iter().flatten()) {
            let (x, y) = (x as f64, y as f64);
            let scale = x.abs().max(y.abs()).max(1e-3 * peak);
            if scale > 0.0 {
                worst = worst.max((x - y).abs() / scale);
            }
        }
    }
    worst
}

/// [`worst_relative_difference`] between the radiosity in the results file `results` and
/// `radiosity`, that of `set`'s surfels, matched by identity (voxel, then the bits of normal and
/// point): a solve from a shard set writes its results in the set's order, not in `set`'s.
pub fn worst_against_results(
    set: &SurfelSet,
    radiosity: &[[[f32; 3]; 2]],
    results: &std::path::Path,
) -> f64 {
    let key = |voxel: [i32; 3], normal: [f32; 3], point: [f32; 3]| {
        (voxel, normal.map(f32::to_bits), point.map(f32::to_bits))
    };
    let mut expected: Vec<_> = set
        .surfels
        .iter()
        .zip(radiosity)
        .map(|(s, b)| (key(s.voxel, s.normal, s.point), *b))
        .collect();
    expected.sort_by_key(|e| e.0);
    let records = voxrad::output::results::read_results(results)
        .expect("read results")
        .records;
    let mut got: Vec<_> = records
        .iter()
        .map(|r| (key(r.voxel, r.normal, r.point), r.radiosity))
        .collect();
    got.sort_by_key(|e| e.0);
    assert_eq!(got.len(), expected.len(), "different surfel counts");
    for (a, b) in got.iter().zip(&expected) {
        assert_eq!(a.0, b.0, "different surfels");
    }
    let got: Vec<_> = got.iter().map(|e| e.1).collect();
    let expected: Vec<_> = expected.iter().map(|e| e.1).collect();
    worst_relative_difference(&got, &expected)
}

/// The bits of a solution's radiosity, for comparisons that must be exact.
pub fn radiosity_bits(solution: &voxrad::solve::Solution) -> Vec<u32> {
    solution
        .radiosity
        .iter()
        .flat_map(|sides| sides.iter().flat_map(|rgb| rgb.iter().map(|v| v.to_bits())))
        .collect()
}
