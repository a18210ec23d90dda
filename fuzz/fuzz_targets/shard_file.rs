//! The shard file reader (`voxrad::storage::shard`) on arbitrary bytes: open (magic, version,
//! lengths, checksum), stream the records, and `verify` (also the order). Every outcome except a
//! panic, a hang or running out of memory is acceptable; an error must name the file.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxrad::storage::shard::{verify, ShardReader};

fuzz_target!(|data: &[u8]| {
    let dir = tempfile::TempDir::new().expect("temporary directory");
    let path = dir.path().join("shard-00000.vxs");
    std::fs::write(&path, data).expect("write shard");
    let named = |e: &voxrad::storage::StorageError| {
        assert!(e.to_string().contains("shard-00000.vxs"), "{e}");
    };
    match ShardReader::open_lazy(&path) {
        Ok(reader) => {
            for r in reader.records(4096).expect("records") {
                if let Err(e) = r {
                    named(&e);
                }
            }
            if let Ok(mut it) = voxrad::storage::WindowedRecords::new(&reader, 4096) {
                for r in it.by_ref() {
                    if let Err(e) = r {
                        named(&e);
                    }
                }
            }
        }
        Err(e) => named(&e),
    }
    if let Err(e) = verify(&path) {
        named(&e);
    }
});
