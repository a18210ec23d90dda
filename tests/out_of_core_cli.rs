//! `voxrad solve SHARDSET` and `voxrad solve --memory`: the real binary on shard sets, against the
//! OBJ path, and with budgets it cannot work in.

mod common;

use std::path::Path;
use std::process::{Command, Output};
use voxrad::output::results::{read_results, Record};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn voxrad(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .expect("run voxrad")
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

fn ok(out: &Output, what: &str) {
    assert!(
        out.status.success(),
        "{what}: status {:?}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Results sorted by surfel identity (voxel, then normal and point bits).
fn sorted_records(dir: &Path) -> Vec<Record> {
    let mut r = read_results(&dir.join("surfels.bin"))
        .expect("results")
        .records;
    r.sort_by_key(|r| {
        (
            r.voxel,
            r.normal.map(f32::to_bits),
            r.point.map(f32::to_bits),
        )
    });
    r
}

#[test]
fn shard_set_and_memory_budget_give_the_obj_answer() {
    let tmp = tempfile::tempdir().unwrap();
    let obj = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let scene = voxrad::scene::obj::load_obj(&obj).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(32)).unwrap();
    let shards = tmp.path().join("cornell.shards");
    common::write_shard_set(&set, &shards, 3);
    // The default preset's direct-light pass (small emitters) in every path: out of core it
    // holds the surfels of its emitters' lines in parts within the budget.
    let common_args = ["--directions", "49", "--iterations", "4", "--threads", "2"];
    let obj_out = tmp.path().join("obj");
    let mut args = vec!["solve", obj.to_str().unwrap(), "--out"];
    let obj_out_s = s(&obj_out);
    args.push(&obj_out_s);
    args.extend(["--resolution", "32"]);
    args.extend(common_args);
    ok(&voxrad(&args), "OBJ solve");
    let reference = sorted_records(&obj_out);

    for (name, extra) in [
        (
            "shard set",
            vec![s(&shards), "--memory".into(), "16MiB".into()],
        ),
        (
            "OBJ under --memory",
            vec![
                s(&obj),
                "--resolution".into(),
                "32".into(),
                "--memory".into(),
                "1MiB".into(),
            ],
        ),
    ] {
        let out_dir = tmp.path().join(name.replace(' ', "_"));
        let mut args: Vec<String> = vec!["solve".into()];
        args.extend(extra);
        args.extend(["--out".into(), s(&out_dir)]);
        args.extend(common_args.iter().map(|a| a.to_string()));
        let argv: Vec<&str> = args.iter().map(String::as_str).collect();
        ok(&voxrad(&argv), name);
        let got = sorted_records(&out_dir);
        assert_eq!(got.len(), reference.len(), "{name}");
        let peak = reference
            .iter()
            .flat_map(|r| r.radiosity.iter().flatten())
            .fold(0f32, |a, &b| a.max(b));
        let mut worst = 0f32;
        for (a, b) in got.iter().zip(&reference) {
            assert_eq!(a.voxel, b.voxel, "{name}");
            for (x, y) in a
                .radiosity
                .iter()
                .flatten()
                .zip(b.radiosity.iter().flatten())
            {
                worst = worst.max((x - y).abs() / x.abs().max(y.abs()).max(1e-3 * peak));
            }
        }
        println!("{name}: worst relative difference {worst:.2e}");
        assert!(worst <= 1e-5, "{name}: {worst:e}");
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out_dir.join("report.json")).unwrap()).unwrap();
        let ooc = &report["out_of_core"];
        assert!(
            ooc["bytes_read_per_voxel_direction"].as_f64().unwrap() > 0.0,
            "{report}"
        );
        let bands = ooc["bands"].as_u64().unwrap();
        let parts = ooc["direct_light_parts"].as_u64().unwrap();
        println!("{name}: the direct-light pass in {parts} part(s)");
        if name == "shard set" {
            assert_eq!(parts, 1, "{name}: a roomy budget holds every line at once");
        } else {
            // The parts add up to the whole pass, as in memory.
            assert!(parts > 1, "{name}: {parts} part(s)");
        }
        if name == "shard set" {
            // A roomy budget: one band per direction, and the previews are written.
            assert_eq!(bands, 49 * 4, "{name}");
            assert!(out_dir.join("render.png").exists(), "{name}");
            assert!(out_dir.join("surfels.ply").exists(), "{name}");
        } else {
            assert!(bands > 2 * 49 * 4, "{name}: {bands} bands");
        }
        // The work directory is gone.
        for entry in std::fs::read_dir(&out_dir).unwrap() {
            let name = entry.unwrap().file_name();
            assert!(
                !name.to_string_lossy().starts_with(".voxrad-work"),
                "{name:?} left"
            );
        }
    }
}

#[test]
fn a_budget_too_small_is_refused_with_what_it_needs() {
    let tmp = tempfile::tempdir().unwrap();
    let obj = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let out = voxrad(&[
        "solve",
        obj.to_str().unwrap(),
        "--out",
        &s(&tmp.path().join("o")),
        "--resolution",
        "32",
        "--memory",
        "100KiB",
    ]);
    assert_eq!(
        out.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("too small") && err.contains("--memory"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    let out = voxrad(&["solve", "x.obj", "--out", "o", "--memory", "lots"]);
    assert_eq!(out.status.code(), Some(2));
}

/// A budget that holds the bands but not one group of the direct-light pass's lines takes the
/// group in pieces of its lines (`outcore::direct`) and gives the bytes a roomy budget gives;
/// the report says how many groups were split.
#[test]
fn a_budget_too_small_for_one_group_of_the_direct_light_pass_splits_it() {
    let tmp = tempfile::tempdir().unwrap();
    let set = voxelize(&voxrad::gen::cornell_box(), GridSpec::Resolution(48)).unwrap();
    let shards = tmp.path().join("cornell.shards");
    common::write_shard_set(&set, &shards, 1);
    let solve = |memory: &str, out: &str| {
        let out = tmp.path().join(out);
        let args = [
            "solve",
            shards.to_str().unwrap(),
            "--out",
            &s(&out),
            "--directions",
            "49",
            "--iterations",
            "1",
            "--memory",
            memory,
        ];
        ok(&voxrad(&args), memory);
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
        let split = report["out_of_core"]["direct_light_split_groups"]
            .as_u64()
            .expect("direct_light_split_groups in the report");
        (std::fs::read(out.join("surfels.bin")).unwrap(), split)
    };
    let (roomy, roomy_split) = solve("64MiB", "roomy");
    let (small, small_split) = solve("512KiB", "small");
    assert_eq!(roomy_split, 0, "a roomy budget holds whole groups");
    assert!(
        small_split > 0,
        "512 KiB holds no whole group of this box's lines"
    );
    assert!(
        roomy == small,
        "the pieces of a group add what the whole group adds"
    );
}

/// The names in `dir` (empty when it does not exist).
fn names_in(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// `--work-dir`: an out-of-core solve of an OBJ scene makes its temporary shard set and work files
/// there (a directory it cannot make there is refused, naming it) and gives the same bits as
/// with them under `--out`; nothing is left in either; a solve in memory refuses the option.
#[test]
fn work_files_go_under_the_work_dir() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = common::cli::example("cornell_box.obj");
    let solve = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "solve",
            &scene,
            "--resolution",
            "24",
            "--directions",
            "13",
            "--iterations",
            "2",
            "--memory",
            "2MiB",
            "--threads",
            "1",
        ];
        let out = s(out);
        args.extend(["--out", &out]);
        args.extend(extra);
        voxrad(&args)
    };
    let plain = tmp.path().join("plain");
    ok(&solve(&plain, &[]), "under --out");
    let local = tmp.path().join("local");
    let moved = tmp.path().join("moved");
    ok(
        &solve(&moved, &["--work-dir", &s(&local)]),
        "under --work-dir",
    );
    assert_eq!(
        std::fs::read(plain.join("surfels.bin")).unwrap(),
        std::fs::read(moved.join("surfels.bin")).unwrap(),
        "--work-dir changed the answer"
    );
    assert!(names_in(&local).is_empty(), "{:?}", names_in(&local));
    assert!(
        !names_in(&moved).iter().any(|n| n.starts_with(".voxrad")),
        "{:?}",
        names_in(&moved)
    );
    // A work directory under a plain file cannot be made: the run fails and says where.
    let file = tmp.path().join("a-file");
    std::fs::write(&file, b"not a directory").unwrap();
    let o = solve(&tmp.path().join("failed"), &["--work-dir", &s(&file)]);
    common::cli::assert_bad_input(
        &o,
        "a work directory under a file",
        &["a-file", "--work-dir"],
    );
    // In memory there are no work files.
    let o = voxrad(&[
        "solve",
        &scene,
        "--out",
        &s(&tmp.path().join("in-memory")),
        "--resolution",
        "12",
        "--work-dir",
        &s(&local),
    ]);
    common::cli::assert_bad_input(&o, "--work-dir in memory", &["--work-dir", "--memory"]);
}
