//! The shard-set manifest reader (`voxrad::storage::Manifest::parse`) on arbitrary bytes. A
//! manifest that parses must validate and survive a write and a read back unchanged; every error
//! must name the file.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::Path;
use voxrad::storage::Manifest;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("set/manifest.json");
    match Manifest::parse(path, data) {
        Ok(m) => {
            m.validate(path).expect("a parsed manifest validates");
            let _ = m.bounds();
            let _ = m.records();
            let _ = m.materials();
            let dir = tempfile::TempDir::new().expect("temporary directory");
            let written = m
                .write(dir.path())
                .expect("a valid manifest can be written");
            let back = Manifest::read(&written).expect("a written manifest reads back");
            assert_eq!(back, m, "the manifest changed through a write and a read");
            // The shards it lists are absent: an error naming one of them, never a panic.
            if let Err(e) = m.check_shards(dir.path()) {
                assert!(e.path().is_some(), "{e}");
            }
        }
        Err(e) => assert!(e.to_string().contains("manifest.json"), "{e}"),
    }
});
