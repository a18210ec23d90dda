//! `voxrad-shard pack` / `unpack`: a shard set survives the round trip byte for byte, and a
//! damaged or truncated pack is refused (exit 2, the pack named) without leaving a set behind.

use std::path::Path;
use std::process::{Command, Output};

fn shard_tool(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_voxrad-shard"))
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .expect("run voxrad-shard")
}

fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

#[test]
fn pack_round_trip_and_damaged_packs() {
    let tmp = tempfile::tempdir().unwrap();
    let obj = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let set = tmp.path().join("set");
    let s = |p: &Path| p.display().to_string();
    let o = shard_tool(&[
        "convert",
        &s(&obj),
        "--resolution",
        "40",
        "--out",
        &s(&set),
        "--ranks",
        "3",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let pack = tmp.path().join("set.vxpack");
    let o = shard_tool(&["pack", &s(&set), "--out", &s(&pack)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let set_bytes: usize = files(&set).iter().map(|f| f.1.len()).sum();
    let pack_bytes = std::fs::metadata(&pack).unwrap().len() as usize;
    println!("set {set_bytes} bytes, pack {pack_bytes} bytes");
    assert!(pack_bytes < set_bytes, "zstd should shrink shard records");

    let back = tmp.path().join("back");
    let o = shard_tool(&["unpack", &s(&pack), "--out", &s(&back)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(files(&back), files(&set));
    let o = shard_tool(&["verify", &s(&back)]);
    assert!(o.status.success());

    let bytes = std::fs::read(&pack).unwrap();
    let cases: Vec<(&str, Vec<u8>)> = vec![
        ("truncated", bytes[..bytes.len() * 2 / 3].to_vec()),
        ("flipped", {
            let mut b = bytes.clone();
            let at = b.len() / 2;
            b[at] ^= 0x5a;
            b
        }),
        ("not a pack", b"hello, this is not a pack".to_vec()),
    ];
    for (name, content) in cases {
        let damaged = tmp
            .path()
            .join(format!("{}.vxpack", name.replace(' ', "_")));
        std::fs::write(&damaged, content).unwrap();
        let target = tmp.path().join(format!("out_{}", name.replace(' ', "_")));
        let o = shard_tool(&["unpack", &s(&damaged), "--out", &s(&target)]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{name}: {err}");
        assert!(
            err.contains(&s(&damaged)) || err.contains("vxpack"),
            "{name}: {err}"
        );
        assert!(!err.contains("panicked"), "{name}: {err}");
        assert!(!target.exists(), "{name}: a damaged pack left a set behind");
    }
}
