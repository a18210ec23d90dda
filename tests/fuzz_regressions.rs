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
