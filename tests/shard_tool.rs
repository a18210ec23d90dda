//! The real `voxrad-shard` binary, run as a child process: `convert` makes exactly the surfels of
//! the in-memory voxelizer (as a set) under a small memory budget and for several rank counts;
//! `verify` passes on what it makes and names each damaged file (flipped byte, truncation,
//! deletion, swapped shards, broken manifest) with exit status 2; `reshard` keeps the records;
//! `export` writes the same PLY and CSV as the in-memory writers; bad input is exit status 2 with
//! the file named, never a panic; the help texts describe every option.
//!
//! Every test works in its own temporary directory.

mod common;

use common::cli::{assert_bad_input, assert_ok, s, text};
use common::files::{copy_dir, edit};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use tempfile::TempDir;
use voxrad::geometry::order;
use voxrad::scene::obj::load_obj;
use voxrad::storage::{Manifest, RECORD_LEN};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::{Surfel, SurfelSet};

fn shard_tool(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_voxrad-shard"))
        .args(args)
        .env_remove("RUST_LOG")
        .output()
        .expect("run voxrad-shard")
}

fn cornell() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj")
}

fn convert(scene: &Path, out: &Path, resolution: u32, ranks: usize, memory: &str) {
    let o = shard_tool(&[
        "convert",
        &s(scene),
        "--resolution",
        &resolution.to_string(),
        "--out",
        &s(out),
        "--ranks",
        &ranks.to_string(),
        "--memory",
        memory,
    ]);
    assert_ok(&o, "convert");
}

/// Every record of a set, shard after shard, read through the library.
fn records(set: &Path) -> (Manifest, Vec<Vec<Surfel>>) {
    let m = Manifest::read_dir(set).unwrap();
    let shards = m
        .check_shards(set)
        .unwrap()
        .iter()
        .map(|r| {
            r.records(1 << 16)
                .unwrap()
                .collect::<Result<_, _>>()
                .unwrap()
        })
        .collect();
    (m, shards)
}

/// Sorted by every byte of the record: equal as sets of surfels.
fn canonical(mut v: Vec<Surfel>) -> Vec<Surfel> {
    v.sort_by_key(voxrad::storage::record::encode);
    v
}

/// The set equals the in-memory voxelization: grid, tables and surfels; the shards hold equal
/// counts (to one record) and are contiguous in the set's order.
fn assert_matches_in_memory(set: &Path, expected: &SurfelSet, ranks: usize) {
    let (m, shards) = records(set);
    assert_eq!(m.grid, expected.grid);
    assert_eq!(m.normals, expected.normals);
    assert_eq!(m.materials(), expected.materials);
    assert_eq!(shards.len(), ranks);
    let counts: Vec<usize> = shards.iter().map(Vec::len).collect();
    let (lo, hi) = (counts.iter().min().unwrap(), counts.iter().max().unwrap());
    assert!(hi - lo <= 1, "equal counts: {counts:?}");
    let all: Vec<Surfel> = shards.into_iter().flatten().collect();
    assert!(
        all.is_sorted_by_key(|s| order::sort_key(m.order, s.voxel)),
        "one order within and across shards"
    );
    assert_eq!(all.len(), expected.surfels.len());
    assert!(
        canonical(all) == canonical(expected.surfels.clone()),
        "the shard set's surfels differ from the in-memory voxelization"
    );
}

#[test]
fn convert_cornell_equals_the_in_memory_voxelization() {
    let tmp = TempDir::new().unwrap();
    let expected = voxelize(&load_obj(&cornell()).unwrap(), GridSpec::Resolution(24)).unwrap();
    for ranks in [1, 3] {
        let set = tmp.path().join(format!("cornell-{ranks}"));
        // 64 KiB holds a few hundred pieces: many runs on disk.
        convert(&cornell(), &set, 24, ranks, "64KiB");
        assert_matches_in_memory(&set, &expected, ranks);
        let o = shard_tool(&["verify", &s(&set)]);
        assert_ok(&o, "verify");
        assert!(text(&o.stdout).contains(&format!("{ranks} shards")));
        let o = shard_tool(&["inspect", &s(&set)]);
        assert_ok(&o, "inspect");
        let out = text(&o.stdout);
        for needle in ["version 2", "24 x", "light (unlit side)", "shard-00000.vxs"] {
            assert!(out.contains(needle), "inspect lacks {needle:?}:\n{out}");
        }
        let total = format!("{} records", expected.surfels.len());
        assert!(out.contains(&total), "{out}");
        // Nothing but the set: no staging directory, no scratch files left.
        assert_eq!(
            std::fs::read_dir(&set).unwrap().count(),
            ranks + 1,
            "shards and manifest only"
        );
    }
    let leftovers: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(leftovers.len(), 2, "{leftovers:?}");
}

#[test]
fn convert_a_generated_building_equals_the_in_memory_voxelization() {
    let tmp = TempDir::new().unwrap();
    let obj = tmp.path().join("building.obj");
    voxrad::gen::write_obj(&voxrad::gen::building(2, 2, 2, 7), &obj).unwrap();
    // The OBJ as read back is the reference (writing rounds coordinates).
    let expected = voxelize(&load_obj(&obj).unwrap(), GridSpec::Resolution(48)).unwrap();
    let set = tmp.path().join("building");
    convert(&obj, &set, 48, 2, "256KiB");
    assert_matches_in_memory(&set, &expected, 2);
    // Converting again over an existing shard set replaces it.
    convert(&obj, &set, 48, 4, "1MiB");
    assert_matches_in_memory(&set, &expected, 4);
}

/// The sort key of every piece is unique, so the files are the same bytes whatever the budget
/// (one buffer or many runs) and the number of threads.
#[test]
fn the_set_does_not_depend_on_budget_or_threads() {
    let tmp = TempDir::new().unwrap();
    let mut manifests = Vec::new();
    for (memory, threads) in [("64KiB", "1"), ("256MiB", "2"), ("300KiB", "0")] {
        let set = tmp.path().join(format!("set-{memory}-{threads}"));
        let o = shard_tool(&[
            "convert",
            &s(&cornell()),
            "--resolution",
            "28",
            "--out",
            &s(&set),
            "--ranks",
            "2",
            "--memory",
            memory,
            "--threads",
            threads,
        ]);
        assert_ok(&o, "convert");
        manifests.push(std::fs::read_to_string(set.join("manifest.json")).unwrap());
    }
    assert_eq!(manifests[0], manifests[1]);
    assert_eq!(manifests[0], manifests[2]);
}

#[test]
fn reshard_keeps_the_records_in_order() {
    let tmp = TempDir::new().unwrap();
    let three = tmp.path().join("three");
    convert(&cornell(), &three, 20, 3, "128KiB");
    let two = tmp.path().join("two");
    let o = shard_tool(&[
        "reshard",
        &s(&three),
        "--ranks",
        "2",
        "--out",
        &s(&two),
        "--memory",
        "64KiB",
    ]);
    assert_ok(&o, "reshard");
    assert_ok(&shard_tool(&["verify", &s(&two)]), "verify the new set");
    let (m3, before) = records(&three);
    let (m2, after) = records(&two);
    assert_eq!(after.len(), 2);
    assert_eq!(m2.grid, m3.grid);
    assert_eq!(m2.normals, m3.normals);
    assert_eq!(m2.materials, m3.materials);
    let before: Vec<Surfel> = before.into_iter().flatten().collect();
    let after: Vec<Surfel> = after.into_iter().flatten().collect();
    assert!(before == after, "same records, same order");
    // A set cannot be re-split onto itself.
    let o = shard_tool(&["reshard", &s(&two), "--ranks", "1", "--out", &s(&two)]);
    assert_bad_input(&o, "reshard onto itself", &["input set"]);
}

#[test]
fn verify_names_every_damaged_file() {
    let tmp = TempDir::new().unwrap();
    let good = tmp.path().join("good");
    convert(&cornell(), &good, 16, 3, "1MiB");
    assert_ok(&shard_tool(&["verify", &s(&good)]), "verify the good set");
    // A stray file is mentioned, not an error.
    let stray = tmp.path().join("stray");
    copy_dir(&good, &stray);
    std::fs::write(stray.join("shard-00009.vxs"), b"left over").unwrap();
    let o = shard_tool(&["verify", &s(&stray)]);
    assert_ok(&o, "verify with a stray file");
    assert!(text(&o.stdout).contains("not part of the set: shard-00009.vxs"));
    let case = |name: &str, damage: &dyn Fn(&Path), needles: &[&str]| {
        let set = tmp.path().join(name);
        copy_dir(&good, &set);
        damage(&set);
        let o = shard_tool(&["verify", &s(&set)]);
        assert_bad_input(&o, name, needles);
    };
    let shard = |set: &Path, k: usize| set.join(format!("shard-{k:05}.vxs"));
    // One bit in a record's float: only the checksum can tell.
    case(
        "flipped",
        &|set| edit(&shard(set, 1), |b| b[32 + 5 * RECORD_LEN + 14] ^= 0x04),
        &["shard-00001.vxs", "checksum"],
    );
    case(
        "truncated",
        &|set| edit(&shard(set, 0), |b| b.truncate(b.len() - 100)),
        &["shard-00000.vxs", "truncated"],
    );
    case(
        "magic",
        &|set| edit(&shard(set, 2), |b| b[0] = b'X'),
        &["shard-00002.vxs", "not a voxrad shard file"],
    );
    case(
        "deleted",
        &|set| std::fs::remove_file(shard(set, 2)).unwrap(),
        &["shard-00002.vxs", "No such file"],
    );
    case(
        "swapped",
        &|set| {
            let (a, b) = (shard(set, 0), shard(set, 1));
            let tmp = set.join("swap");
            std::fs::rename(&a, &tmp).unwrap();
            std::fs::rename(&b, &a).unwrap();
            std::fs::rename(&tmp, &b).unwrap();
        },
        &["shard-00000.vxs", "shard-00001.vxs", "not the shard"],
    );
    // The manifest's entries swapped too: every file is intact and listed correctly, but the
    // order across shards is broken.
    case(
        "reordered",
        &|set| {
            let mut m = Manifest::read_dir(set).unwrap();
            m.shards.swap(0, 2);
            m.write(set).unwrap();
        },
        &["shard-00000.vxs", "out of order"],
    );
    case(
        "manifest",
        &|set| edit(&set.join("manifest.json"), |b| b.truncate(b.len() / 2)),
        &["manifest.json"],
    );
    // Several problems: each file is named.
    case(
        "two-problems",
        &|set| {
            edit(&shard(set, 0), |b| b[40] ^= 1);
            edit(&shard(set, 2), |b| b.truncate(10));
        },
        &["shard-00000.vxs", "shard-00002.vxs", "2 of the 3 shards"],
    );
    // A damaged input is refused by reshard too, and nothing is written.
    let set = tmp.path().join("flipped");
    let out = tmp.path().join("from-flipped");
    let o = shard_tool(&["reshard", &s(&set), "--ranks", "2", "--out", &s(&out)]);
    assert_bad_input(&o, "reshard of a damaged set", &["shard-00001.vxs"]);
    assert!(!out.exists());
}

#[test]
fn bad_input_is_named_and_exits_2() {
    let tmp = TempDir::new().unwrap();
    let out = tmp.path().join("set");
    let run = |args: &[&str]| shard_tool(args);
    let missing = tmp.path().join("missing.obj");
    let o = run(&[
        "convert",
        &s(&missing),
        "--resolution",
        "8",
        "--out",
        &s(&out),
    ]);
    assert_bad_input(&o, "missing scene", &["missing.obj"]);

    let bad = tmp.path().join("bad.obj");
    std::fs::write(&bad, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n").unwrap();
    let o = run(&["convert", &s(&bad), "--resolution", "8", "--out", &s(&out)]);
    assert_bad_input(&o, "malformed OBJ", &["bad.obj", "4"]);

    let c = s(&cornell());
    let o = run(&["convert", &c, "--resolution", "0", "--out", &s(&out)]);
    assert_bad_input(&o, "resolution 0", &["--resolution 0"]);
    let o = run(&[
        "convert",
        &c,
        "--resolution",
        "8",
        "--out",
        &s(&out),
        "--memory",
        "1KiB",
    ]);
    assert_bad_input(&o, "tiny budget", &["--memory", "too small"]);
    let o = run(&[
        "convert",
        &c,
        "--resolution",
        "8",
        "--out",
        &s(&out),
        "--memory",
        "lots",
    ]);
    assert_bad_input(&o, "unparsable budget", &["not a size"]);
    let o = run(&[
        "convert",
        &c,
        "--resolution",
        "8",
        "--out",
        &s(&out),
        "--ranks",
        "0",
    ]);
    assert_bad_input(&o, "no ranks", &["--ranks 0"]);

    // An existing directory that is not a shard set is left alone.
    let precious = tmp.path().join("precious");
    std::fs::create_dir(&precious).unwrap();
    std::fs::write(precious.join("thesis.txt"), "years of work").unwrap();
    let o = run(&["convert", &c, "--resolution", "8", "--out", &s(&precious)]);
    assert_bad_input(&o, "non-empty --out", &["precious", "not a shard set"]);
    assert_eq!(
        std::fs::read_to_string(precious.join("thesis.txt")).unwrap(),
        "years of work"
    );
    assert_eq!(std::fs::read_dir(&precious).unwrap().count(), 1);
    // A file where the set should go.
    let o = run(&[
        "convert",
        &c,
        "--resolution",
        "8",
        "--out",
        &s(&precious.join("thesis.txt")),
    ]);
    assert_bad_input(&o, "--out is a file", &["thesis.txt"]);

    for cmd in ["inspect", "verify"] {
        let o = run(&[cmd, &s(&tmp.path().join("nowhere"))]);
        assert_bad_input(&o, cmd, &["nowhere"]);
        let o = run(&[cmd, &s(&precious)]);
        assert_bad_input(&o, cmd, &["manifest.json"]);
    }
    let o = run(&[
        "export",
        &s(&precious),
        "--format",
        "csv",
        "--out",
        &s(&out),
    ]);
    assert_bad_input(&o, "export without results", &["surfels.bin"]);
    // No failed command left anything beside its inputs.
    let names: Vec<String> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(!names.iter().any(|n| n.starts_with('.')), "{names:?}");
}

#[test]
fn help_describes_every_command_and_option() {
    let o = shard_tool(&["--help"]);
    assert_ok(&o, "--help");
    let top = text(&o.stdout);
    for c in [
        "convert",
        "inspect",
        "verify",
        "reshard",
        "export",
        "Exit status",
    ] {
        assert!(top.contains(c), "--help lacks {c}:\n{top}");
    }
    let expect: [(&str, &[&str]); 5] = [
        (
            "convert",
            &[
                "--resolution",
                "--out",
                "--ranks",
                "--memory",
                "--voxel-size",
                "--threads",
            ],
        ),
        ("inspect", &["<SET>"]),
        ("verify", &["checksums", "<SET>"]),
        ("reshard", &["--ranks", "--out", "--memory"]),
        ("export", &["--format", "ply", "csv", "--out"]),
    ];
    for (cmd, needles) in expect {
        let o = shard_tool(&[cmd, "--help"]);
        assert_ok(&o, cmd);
        let h = text(&o.stdout);
        for n in needles {
            assert!(h.contains(n), "{cmd} --help lacks {n}:\n{h}");
        }
    }
    // No subcommand is a usage error, not a panic.
    assert_eq!(shard_tool(&[]).status.code(), Some(2));
}

#[test]
fn export_streams_the_same_ply_and_csv_as_the_solver() {
    let tmp = TempDir::new().unwrap();
    let solved = tmp.path().join("solved");
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(["solve", &s(&cornell()), "--out", &s(&solved)])
        .args([
            "--resolution",
            "20",
            "--directions",
            "60",
            "--iterations",
            "3",
        ])
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    assert_ok(&o, "solve");
    let results = voxrad::output::read_results(&solved.join("surfels.bin")).unwrap();
    let sides: usize = results
        .records
        .iter()
        .map(|r| (0..2).filter(|&k| r.side_is_present(k)).count())
        .sum();

    let ply = tmp.path().join("out.ply");
    let o = shard_tool(&["export", &s(&solved), "--format", "ply", "--out", &s(&ply)]);
    assert_ok(&o, "export ply");
    let bytes = std::fs::read(&ply).unwrap();
    let header = String::from_utf8_lossy(&bytes[..400]).into_owned();
    assert!(
        header.contains(&format!("element vertex {sides}\n")),
        "{header}"
    );
    // Byte for byte the solver's own PLY (same tone map, same vertices).
    assert!(bytes == std::fs::read(solved.join("surfels.ply")).unwrap());

    let csv = tmp.path().join("out.csv");
    let bin = solved.join("surfels.bin");
    let o = shard_tool(&["export", &s(&bin), "--format", "csv", "--out", &s(&csv)]);
    assert_ok(&o, "export csv");
    let rows = std::fs::read_to_string(&csv).unwrap();
    assert_eq!(rows.lines().count(), sides + 1);
    let reference = tmp.path().join("reference.csv");
    voxrad::output::write_csv(&reference, &results).unwrap();
    assert_eq!(rows, std::fs::read_to_string(&reference).unwrap());

    // Exporting onto the input is refused (it would replace the results).
    let o = shard_tool(&["export", &s(&solved), "--format", "csv", "--out", &s(&bin)]);
    assert_bad_input(&o, "export onto its input", &["surfels.bin", "itself"]);

    // A corrupted results file: named, exit 2, and the earlier export is untouched.
    edit(&solved.join("surfels.bin"), |b| b[100] ^= 0x10);
    let o = shard_tool(&["export", &s(&solved), "--format", "csv", "--out", &s(&csv)]);
    assert_bad_input(&o, "corrupted results", &["surfels.bin", "checksum"]);
    assert_eq!(std::fs::read_to_string(&csv).unwrap(), rows);
}

/// What the tool makes is what the solver reads: `voxrad solve SET` on a converted set gives
/// the answer of `voxrad solve SCENE.obj` at the same resolution (to 1e-5 of the radiosity,
/// relative, with a floor at 1e-3 of the peak for unlit surfels).
#[test]
fn the_solver_reads_a_converted_set_and_gives_the_obj_answer() {
    let tmp = TempDir::new().unwrap();
    let set = tmp.path().join("set");
    convert(&cornell(), &set, 24, 3, "128KiB");
    let solve = |input: &[&str], out: &Path| {
        let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
            .arg("solve")
            .args(input)
            .args(["--out", &s(out)])
            .args(["--directions", "49", "--iterations", "4", "--threads", "2"])
            // In memory too without the direct-light pass: out of core has none yet.
            .args(["--direct-directions", "0"])
            .env_remove("RUST_LOG")
            .output()
            .unwrap();
        assert_ok(&o, "solve");
        let mut r = voxrad::output::read_results(&out.join("surfels.bin"))
            .unwrap()
            .records;
        r.sort_by_key(|r| {
            (
                r.voxel,
                r.normal.map(f32::to_bits),
                r.point.map(f32::to_bits),
            )
        });
        r
    };
    let reference = solve(
        &[&s(&cornell()), "--resolution", "24"],
        &tmp.path().join("obj"),
    );
    let got = solve(
        &[&s(&set), "--memory", "16MiB"],
        &tmp.path().join("from-set"),
    );
    assert_eq!(got.len(), reference.len());
    let peak = reference
        .iter()
        .flat_map(|r| r.radiosity.iter().flatten())
        .fold(0f32, |a, &b| a.max(b));
    assert!(peak > 0.0);
    for (a, b) in got.iter().zip(&reference) {
        assert_eq!(
            (a.voxel, a.point, a.normal, a.area),
            (b.voxel, b.point, b.normal, b.area)
        );
        for (x, y) in a
            .radiosity
            .iter()
            .flatten()
            .zip(b.radiosity.iter().flatten())
        {
            let rel = (x - y).abs() / x.abs().max(y.abs()).max(1e-3 * peak);
            assert!(rel <= 1e-5, "{a:?} vs {b:?}");
        }
    }
}
