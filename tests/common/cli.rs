//! Running the real `voxrad` binary to completion and judging what it said: the helpers of the
//! command-line tests.

use std::path::Path;
use std::process::{Command, Output};

/// Every file `voxrad solve` writes into its output directory for an OBJ scene.
pub const SOLVE_OUTPUTS: [&str; 7] = [
    "report.json",
    "surfels.bin",
    "surfels.ply",
    "render.png",
    "render.exr",
    "baked.glb",
    "baked.ply",
];

/// Runs `voxrad ARGS` (without `RUST_LOG`, so that its log is the default one).
pub fn voxrad(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(args)
        .env_remove("RUST_LOG")
        .output()
        .expect("run voxrad")
}

pub fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

pub fn assert_ok(out: &Output, what: &str) {
    assert!(
        out.status.success(),
        "{what}: exit {:?}\nstdout:\n{}\nstderr:\n{}",
        out.status.code(),
        text(&out.stdout),
        text(&out.stderr)
    );
}

/// Exit status 2, no panic, and every `needle` in the message.
pub fn assert_bad_input(out: &Output, what: &str, needles: &[&str]) {
    let stderr = text(&out.stderr);
    assert_eq!(
        out.status.code(),
        Some(2),
        "{what}: expected exit status 2\nstderr:\n{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{what}: panicked:\n{stderr}");
    assert!(!stderr.trim().is_empty(), "{what}: no message");
    for needle in needles {
        assert!(
            stderr.contains(needle),
            "{what}: message does not mention {needle:?}:\n{stderr}"
        );
    }
}

/// The path of `examples/NAME`.
pub fn example(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples")
        .join(name)
        .display()
        .to_string()
}

pub fn s(p: &Path) -> String {
    p.display().to_string()
}
