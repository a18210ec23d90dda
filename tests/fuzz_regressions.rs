//! Inputs that once made a reader crash, hang or run out of memory (found by the fuzz targets in
//! `fuzz/`, or alongside them), fed to the real readers: each must now give a clean error that
//! names the file.

use std::path::Path;
use voxrad::output::probe::read_points_from;
use voxrad::scene::obj::load_obj;

/// A points file without line ends (here, endless zeros) is refused at its first long line
/// instead of being read into memory whole.
#[test]
fn probe_points_without_line_ends_are_refused() {
    let endless = std::io::BufReader::new(std::io::repeat(0));
    let e = read_points_from(Path::new("points.csv"), endless).unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("points.csv:1:"), "{msg}");
    assert!(msg.contains("longer than"), "{msg}");
}

/// An OBJ that names a device as its material library, and a device given as the OBJ: refused,
/// not read until memory runs out.
#[test]
fn devices_are_not_read_as_scenes() {
    let tmp = tempfile::TempDir::new().unwrap();
    let obj = tmp.path().join("zero.obj");
    std::fs::write(
        &obj,
        "mtllib /dev/zero\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let e = load_obj(&obj).unwrap_err();
    assert!(e.is_bad_input());
    assert_eq!(e.line(), Some(1));
    assert!(e.to_string().contains("not a regular file"), "{e}");
    let e = load_obj(Path::new("/dev/zero")).unwrap_err();
    assert!(e.is_bad_input());
    assert!(e.to_string().contains("/dev/zero"), "{e}");
}

/// The files of `fuzz/seeds/TARGET` (and `fuzz/regressions/TARGET`, where crash inputs are kept),
/// with their names.
fn inputs(target: &str) -> Vec<(String, Vec<u8>)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut out = Vec::new();
    for kind in ["seeds", "regressions"] {
        let Ok(dir) = std::fs::read_dir(root.join(kind).join(target)) else {
            continue;
        };
        for e in dir {
            let path = e.unwrap().path();
            out.push((path.display().to_string(), std::fs::read(&path).unwrap()));
        }
    }
    out.sort();
    out
}

/// Every kept fuzz input, fed to its reader as the fuzz target does: an answer or an error
/// naming the file, never a panic.
#[test]
fn kept_fuzz_inputs_read_cleanly() {
    let tmp = tempfile::TempDir::new().unwrap();
    let mut fed = 0;
    for (name, data) in inputs("obj_mtl") {
        let (obj, mtl) = match data.iter().position(|&b| b == 0) {
            Some(i) => (&data[..i], &data[i + 1..]),
            None => (&data[..], &[][..]),
        };
        let path = tmp.path().join("scene.obj");
        std::fs::write(&path, obj).unwrap();
        std::fs::write(tmp.path().join("scene.mtl"), mtl).unwrap();
        if let Err(e) = load_obj(&path) {
            assert!(e.to_string().contains("scene."), "{name}: {e}");
        }
        fed += 1;
    }
    for (name, data) in inputs("shard_file") {
        let path = tmp.path().join("shard-00000.vxs");
        std::fs::write(&path, &data).unwrap();
        if let Err(e) = voxrad::storage::shard::verify(&path) {
            assert!(e.to_string().contains("shard-00000.vxs"), "{name}: {e}");
        }
        fed += 1;
    }
    for (name, data) in inputs("manifest") {
        let path = Path::new("set/manifest.json");
        if let Err(e) = voxrad::storage::Manifest::parse(path, &data) {
            assert!(e.to_string().contains("manifest.json"), "{name}: {e}");
        }
        fed += 1;
    }
    for (name, data) in inputs("probe_csv") {
        if let Err(e) = read_points_from(Path::new("points.csv"), &data[..]) {
            assert!(e.to_string().contains("points.csv"), "{name}: {e}");
        }
        fed += 1;
    }
    for (name, data) in inputs("results_file") {
        let path = tmp.path().join("surfels.bin");
        std::fs::write(&path, &data).unwrap();
        if let Err(e) = voxrad::output::read_results(&path) {
            assert!(e.to_string().contains("surfels.bin"), "{name}: {e}");
        }
        fed += 1;
    }
    assert!(fed >= 8, "only {fed} kept inputs found");
}

/// Found by the `manifest` target: a grid origin written with many digits parsed to a value one
/// unit in the last place away from the correctly rounded one, so the same manifest, written
/// again and read back, had another origin (serde_json's default float parsing is not exact; the
/// `float_roundtrip` feature makes it so). A manifest must read back exactly as it was written.
#[test]
fn a_manifest_reads_back_exactly_as_written() {
    let tmp = tempfile::TempDir::new().unwrap();
    for (name, data) in inputs("manifest") {
        let Ok(m) = voxrad::storage::Manifest::parse(Path::new("manifest.json"), &data) else {
            continue;
        };
        let written = m.write(tmp.path()).unwrap();
        let back = voxrad::storage::Manifest::read(&written).unwrap();
        assert_eq!(back, m, "{name}");
    }
}
