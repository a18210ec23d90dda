//! Helpers shared by the integration tests: small scenes built in code.
#![allow(dead_code)]

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
    use voxrad::storage::{shard::key, Manifest, ShardEntry, ShardWriter};
    std::fs::create_dir_all(dir).expect("shard set directory");
    let mut surfels = set.surfels.clone();
    surfels.sort_by_key(|s| key(0, s));
    let per = surfels.len().div_ceil(shards.max(1)).max(1);
    let mut entries = Vec::new();
    for (k, part) in surfels.chunks(per).enumerate() {
        let mut w = ShardWriter::create(&dir.join(format!("shard-{k:05}.vxs")), 0).expect("create");
        for s in part {
            w.push(s).expect("push");
        }
        entries.push(ShardEntry::from_info(&w.finish().expect("finish")).expect("entry"));
    }
    Manifest::new(set.grid, &set.materials, set.normals.clone(), 0, entries)
        .write(dir)
        .expect("manifest");
}
