//! The results file reader (`voxrad::output::results::read_results`) on arbitrary bytes; a file
//! that reads is then probed and rendered small, as `voxrad probe` and `voxrad render` would.
//! Errors must name the file.
#![no_main]

use glam::DVec3;
use libfuzzer_sys::fuzz_target;
use voxrad::output::probe::ProbeIndex;
use voxrad::output::results::read_results;

fuzz_target!(|data: &[u8]| {
    let dir = tempfile::TempDir::new().expect("temporary directory");
    let path = dir.path().join("surfels.bin");
    std::fs::write(&path, data).expect("write results");
    match read_results(&path) {
        Ok(results) => {
            let index = ProbeIndex::new(&results);
            for r in results.records.iter().take(8) {
                let p = results.world_position(r);
                let _ = index.lookup(p, DVec3::Z);
            }
            let png = dir.path().join("render.png");
            let _ = voxrad::app::run_render(dir.path(), &png, None, (16, 12));
        }
        Err(e) => assert!(e.to_string().contains("surfels.bin"), "{e}"),
    }
});
