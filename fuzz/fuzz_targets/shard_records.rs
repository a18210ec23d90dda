//! Shard sets whose records are arbitrary but whose checksums are right: what a buggy or hostile
//! writer could hand over. The input's first byte picks the order, the rest is cut into 80-byte
//! records; a valid header, footer and manifest are built around them. The readers must then
//! either accept the set or refuse it with an error naming a file: `verify` (order), and the
//! out-of-core solver's source, which checks every record against the manifest as it streams.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxrad::outcore::{ShardSetSource, SurfelSource};
use voxrad::scene::Material;
use voxrad::storage::shard::{verify, END_MAGIC, MAGIC, VERSION};
use voxrad::storage::{Manifest, ShardEntry, ShardReader, RECORD_LEN};
use voxrad::voxel::Grid;

fuzz_target!(|data: &[u8]| {
    let Some((&order, records)) = data.split_first() else {
        return;
    };
    let order = order as usize % 4;
    let count = records.len() / RECORD_LEN;
    let records = &records[..count * RECORD_LEN];
    let mut bytes = Vec::with_capacity(52 + records.len());
    bytes.extend_from_slice(&MAGIC);
    bytes.extend_from_slice(&VERSION.to_le_bytes());
    bytes.extend_from_slice(&(order as u32).to_le_bytes());
    bytes.extend_from_slice(&(RECORD_LEN as u32).to_le_bytes());
    bytes.extend_from_slice(&0u32.to_le_bytes());
    bytes.extend_from_slice(&(count as u64).to_le_bytes());
    bytes.extend_from_slice(records);
    let crc = crc32fast::hash(&bytes);
    bytes.extend_from_slice(&(count as u64).to_le_bytes());
    bytes.extend_from_slice(&crc.to_le_bytes());
    bytes.extend_from_slice(&END_MAGIC);

    let dir = tempfile::TempDir::new().expect("temporary directory");
    let path = dir.path().join("shard-00000.vxs");
    std::fs::write(&path, &bytes).expect("write shard");
    let reader = ShardReader::open(&path).expect("a shard with a right checksum opens");
    let named = |e: &dyn std::fmt::Display| {
        assert!(e.to_string().contains("shard-00000.vxs"), "{e}");
    };
    if let Err(e) = verify(&path) {
        named(&e);
    }
    let manifest = Manifest::new(
        Grid {
            origin: [0.0; 3],
            voxel_size: 0.5,
            dims: [8, 8, 8],
        },
        &[
            Material::new("wall", [0.5; 3], [0.0; 3]),
            Material::new("lamp", [0.0; 3], [1.0; 3]),
        ],
        vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]],
        order,
        vec![ShardEntry::from_info(reader.info()).expect("entry")],
    );
    manifest.write(dir.path()).expect("write manifest");
    let source = ShardSetSource::open(dir.path()).expect("the set opens");
    let mut seen = 0u64;
    for r in source.stream(4096).expect("stream") {
        match r {
            Ok(_) => seen += 1,
            Err(e) => {
                named(&e);
                return;
            }
        }
    }
    assert_eq!(seen, count as u64);
});
