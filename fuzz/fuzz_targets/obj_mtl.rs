//! The OBJ + MTL reader (`voxrad::scene::obj::load_obj`) on arbitrary bytes.
//!
//! The input is split at its first NUL byte: the part before is `scene.obj`, the part after is
//! `scene.mtl`, both written into a fresh directory, so that `mtllib scene.mtl` in the OBJ reads
//! the second part through the real file path (the reader resolves libraries on disk). Every
//! outcome except a panic, a hang or running out of memory is acceptable; an error must name the
//! OBJ file.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let (obj, mtl) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, &[][..]),
    };
    let dir = tempfile::TempDir::new().expect("temporary directory");
    let obj_path = dir.path().join("scene.obj");
    std::fs::write(&obj_path, obj).expect("write obj");
    std::fs::write(dir.path().join("scene.mtl"), mtl).expect("write mtl");
    match voxrad::scene::obj::load_obj(&obj_path) {
        Ok(scene) => {
            // A scene that loads must be one the solver accepts.
            scene.validate().expect("a loaded scene validates");
        }
        Err(e) => {
            assert!(e.to_string().contains("scene."), "{e}");
        }
    }
});
