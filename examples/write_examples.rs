//! Regenerates the committed example scenes (`examples/cornell_box.obj` and `.mtl`) from the
//! generators, so the files in the repository are exactly what `voxrad::gen` produces.
//! Run from the crate root: `cargo run --example write_examples`.

use std::path::Path;

fn main() -> std::io::Result<()> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
    let obj = dir.join("cornell_box.obj");
    voxrad::gen::write_obj(&voxrad::gen::cornell_box(), &obj)?;
    println!("wrote {} and its .mtl", obj.display());
    let obj = dir.join("office.obj");
    voxrad::gen::write_obj(&voxrad::gen::office().scene, &obj)?;
    println!("wrote {} and its .mtl", obj.display());
    Ok(())
}
