//! Compatibility: the shard set of format v1 saved in `tests/data/shardset-v1/` must stay
//! readable, with the same values, whatever the format becomes.
//!
//! The files were written once by `write_v1_sample` (ignored; run it with `--ignored` only to
//! recreate a lost sample with a build that still writes v1). Never regenerate them to make this
//! test pass after a format change: that would defeat it. The checksums below are those of the
//! saved files, so a regenerated sample that differs is caught too.

use std::path::{Path, PathBuf};
use voxrad::scene::Material;
use voxrad::storage::shard::{self, ShardReader, ShardWriter};
use voxrad::storage::{Manifest, ShardEntry, WindowedRecords};
use voxrad::voxel::{Grid, Surfel};

const ORDER: usize = 3;
/// Footer checksums of the two saved shards.
const CRC32: [u32; 2] = [0xf22b_2a8e, 0x1d94_d079];

fn sample_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/shardset-v1")
}

fn normals() -> Vec<[f32; 3]> {
    vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, -0.8, 0.0]]
}

/// The sample's surfels per shard (shard k holds the voxels with z = k), in order 3: two surfels
/// in each voxel of a 3 x 3 x 2 block, with values exact in binary so they compare exactly.
fn sample_shards() -> [Vec<Surfel>; 2] {
    let normals = normals();
    let mut shards: [Vec<Surfel>; 2] = [Vec::new(), Vec::new()];
    for (z, shard) in shards.iter_mut().enumerate() {
        for y in 0..3 {
            for x in 0..3 {
                for k in 0..2u32 {
                    let id = (x + y + k as i32) as usize % normals.len();
                    shard.push(Surfel {
                        voxel: [x - 1, y + 4, z as i32 - 2],
                        point: [0.25 * k as f32, 0.5, 0.125 * (x + 1) as f32],
                        normal: normals[id],
                        normal_id: id as u32,
                        group: 10 * z as u32 + k,
                        area: 0.5 + 0.25 * y as f32,
                        material: [k, 1 - k],
                        extent: [
                            [0.0, 0.125 * k as f32, 0.0],
                            [1.0, 0.75, 0.5 + 0.5 * k as f32],
                        ],
                    });
                }
            }
        }
        // Stable: the two surfels of a voxel keep their order.
        shard.sort_by_key(|s| shard::key(ORDER, s));
    }
    shards
}

fn sample_grid() -> Grid {
    Grid {
        origin: [-2.5, 1.0, 0.75],
        voxel_size: 0.5,
        dims: [4, 8, 4],
    }
}

#[test]
#[ignore = "writes the saved v1 sample; run once, never to make the compatibility test pass"]
fn write_v1_sample() {
    let dir = sample_dir();
    std::fs::create_dir_all(&dir).unwrap();
    let mut entries = Vec::new();
    for (k, surfels) in sample_shards().iter().enumerate() {
        let mut w = ShardWriter::create(&dir.join(format!("shard-{k:05}.vxs")), ORDER).unwrap();
        for s in surfels {
            w.push(s).unwrap();
        }
        let info = w.finish().unwrap();
        println!("shard {k}: crc32 {:#010x}", info.crc32);
        entries.push(ShardEntry::from_info(&info).unwrap());
    }
    let materials = [
        Material::new("white wall", [0.75, 0.75, 0.75], [0.0; 3]),
        Material::new("lamp", [0.5, 0.25, 0.0], [16.0, 12.0, 8.0]),
    ];
    Manifest::new(sample_grid(), &materials, normals(), ORDER, entries)
        .write(&dir)
        .unwrap();
}

#[test]
fn reads_shardset_v1() {
    let dir = sample_dir();
    let m = Manifest::read_dir(&dir).unwrap();
    assert_eq!(m.format_version, 1);
    assert_eq!(m.grid, sample_grid());
    assert_eq!(m.bounds(), [[-2.5, 1.0, 0.75], [-0.5, 5.0, 2.75]]);
    assert_eq!(m.order, ORDER);
    assert_eq!(m.normals, normals());
    let materials = m.materials();
    assert_eq!(materials.len(), 2);
    assert_eq!(materials[0].name, "white wall");
    assert_eq!(materials[1].emission, [16.0, 12.0, 8.0]);
    assert_eq!(m.records(), 36);
    let files: Vec<&str> = m.shards.iter().map(|s| s.file.as_str()).collect();
    assert_eq!(files, ["shard-00000.vxs", "shard-00001.vxs"]);
    for (entry, crc) in m.shards.iter().zip(CRC32) {
        assert_eq!(entry.records, 18);
        assert_eq!(entry.bytes, 32 + 18 * 80 + 20);
        assert_eq!(entry.crc32, crc, "{}", entry.file);
    }

    let readers = m.check_shards(&dir).unwrap();
    let expected = sample_shards();
    let mut read = Vec::new();
    for (k, reader) in readers.iter().enumerate() {
        let path = reader.path();
        assert_eq!(shard::verify(path).unwrap(), *reader.info());
        assert_eq!(reader.header().version, 1);
        let buffered: Vec<Surfel> = ShardReader::open(path)
            .unwrap()
            .records(4096)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        let mapped: Vec<Surfel> = WindowedRecords::new(reader, 4096)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(buffered, expected[k], "{}", path.display());
        assert_eq!(mapped, expected[k], "{}", path.display());
        read.push(mapped);
    }

    // A few values as read, spelled out independently of the generator above. Order 3 walks x
    // and y downwards, so a shard starts at the voxel with the largest x and y.
    let first = read[0][0];
    assert_eq!(first.voxel, [1, 6, -2]);
    assert_eq!(first.point, [0.0, 0.5, 0.375]);
    assert_eq!(first.normal_id, 1);
    assert_eq!(first.normal, [1.0, 0.0, 0.0]);
    assert_eq!(first.area, 1.0);
    assert_eq!(first.material, [0, 1]);
    let last = read[1][17];
    assert_eq!(last.voxel, [-1, 4, -1]);
    assert_eq!(last.group, 11);
    assert_eq!(last.extent, [[0.0, 0.125, 0.0], [1.0, 0.75, 1.0]]);
}
