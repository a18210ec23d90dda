//! Writing a surfel set already in memory as a shard set: sorted in one order, cut into equal
//! parts, each shard finished (checksummed, synced, renamed), then the manifest. For scenes that
//! fit in memory (tests, benchmarks, small conversions); `voxrad-shard convert` streams instead.

use super::shard::key;
use super::{Manifest, ShardEntry, ShardWriter, StorageError};
use crate::voxel::SurfelSet;
use std::path::Path;

/// Writes `set` into the directory `dir` as `shards` shard files in order `order`.
pub fn write_shard_set(
    set: &SurfelSet,
    dir: &Path,
    shards: usize,
    order: usize,
) -> Result<Manifest, StorageError> {
    std::fs::create_dir_all(dir).map_err(|e| StorageError::io(dir, "create", e))?;
    let mut index: Vec<u32> = (0..set.surfels.len() as u32).collect();
    // Stable: surfels of one voxel keep their set order.
    index.sort_by_key(|&k| key(order, &set.surfels[k as usize]));
    let per = index.len().div_ceil(shards.max(1)).max(1);
    let mut entries = Vec::new();
    for (k, part) in index.chunks(per).enumerate() {
        let mut w = ShardWriter::create(&dir.join(format!("shard-{k:05}.vxs")), order)?;
        for &i in part {
            w.push(&set.surfels[i as usize])?;
        }
        entries.push(ShardEntry::from_info(&w.finish()?)?);
    }
    let manifest = Manifest::new(
        set.grid,
        &set.materials,
        set.normals.clone(),
        order,
        entries,
    );
    manifest.write(dir)?;
    Ok(manifest)
}
