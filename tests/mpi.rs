//! Distributed solves under real `mpirun` (built only with the `mpi` feature; `.ci/run` installs
//! Open MPI and runs these). Every rank count gives the single-process answer, and launches that
//! do not fit are refused clearly.
#![cfg(feature = "mpi")]

mod common;

use std::path::Path;
use std::process::{Command, Output};
use voxrad::geometry::directions::DirectionSet;
use voxrad::output::results::read_results;
use voxrad::solve::jacobi::solve_with;
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::{voxelize, GridSpec};

/// `mpirun -n ranks voxrad args`: oversubscribed (more ranks than cores), loopback and shared
/// memory transports only, allowed to run as root (CI containers).
fn mpirun(ranks: usize, args: &[&str]) -> Output {
    Command::new("mpirun")
        .args(["-n", &ranks.to_string(), "--oversubscribe"])
        .args([
            "--mca",
            "btl",
            "self,vader",
            "--mca",
            "btl_vader_single_copy_mechanism",
            "none",
        ])
        .arg(env!("CARGO_BIN_EXE_voxrad"))
        .args(args)
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("NO_COLOR", "1")
        .output()
        .expect("run mpirun (is Open MPI installed?)")
}

fn cornell() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples/cornell_box.obj")
        .display()
        .to_string()
}

#[test]
fn directions_mode_matches_one_process_for_1_to_4_ranks() {
    let scene = voxrad::scene::obj::load_obj(Path::new(&cornell())).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(32)).unwrap();
    let options = SolveOptions {
        directions: 49,
        max_iterations: 4,
        tolerance: None,
        threads: 1,
        // As the command line runs `--iterations` without `--tolerance`: plain iterations.
        ..SolveOptions::default()
    };
    let reference = solve_with(&set, &DirectionSet::with_count(49), &options).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    for ranks in 1..=4 {
        let out = tmp.path().join(format!("ranks{ranks}"));
        let o = mpirun(
            ranks,
            &[
                "solve",
                &cornell(),
                "--out",
                out.to_str().unwrap(),
                "--resolution",
                "32",
                "--directions",
                "49",
                "--iterations",
                "4",
                "--threads",
                "1",
                "--distribute",
                "directions",
            ],
        );
        assert!(
            o.status.success(),
            "{ranks} ranks: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let results = read_results(&out.join("surfels.bin")).unwrap();
        assert_eq!(results.records.len(), set.surfels.len());
        let got: Vec<_> = results.records.iter().map(|r| r.radiosity).collect();
        let worst = common::worst_relative_difference(&got, &reference.radiosity);
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
        println!("{ranks} ranks: worst relative difference {worst:.2e}");
        assert!(worst <= 1e-5, "{ranks} ranks: {worst:e}");
        assert_eq!(report["ranks"], ranks);
        assert_eq!(report["mode"], "directions");
        if ranks > 1 {
            // Every rank solved its share of the directions.
            let per_rank = report["per_rank"].as_array().expect("per_rank");
            assert_eq!(per_rank.len(), ranks);
            for r in per_rank {
                assert!(r["propagate"].as_f64().unwrap() > 0.0, "{report}");
            }
        }
    }
}

#[test]
fn launches_that_do_not_fit_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    // mpirun with two ranks but no --distribute: each would solve alone and write the same files.
    let o = mpirun(
        2,
        &[
            "solve",
            &cornell(),
            "--out",
            out.to_str().unwrap(),
            "--resolution",
            "16",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("started 2 processes") && err.contains("--distribute"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    // Hybrid groups that do not divide the rank count.
    let o = mpirun(
        2,
        &[
            "solve",
            &cornell(),
            "--out",
            out.to_str().unwrap(),
            "--resolution",
            "16",
            "--distribute",
            "hybrid",
            "--groups",
            "3",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("--groups 3") && err.contains("divisor"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(!out.exists(), "a refused launch wrote {}", out.display());
}

#[test]
fn data_and_hybrid_modes_match_one_process_for_1_to_4_ranks() {
    let scene = voxrad::scene::obj::load_obj(Path::new(&cornell())).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(32)).unwrap();
    let options = SolveOptions {
        directions: 49,
        max_iterations: 4,
        tolerance: None,
        threads: 1,
        ..SolveOptions::default()
    };
    let reference = solve_with(&set, &DirectionSet::with_count(49), &options).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    for mode in ["data", "hybrid"] {
        for ranks in 1..=4 {
            let out = tmp.path().join(format!("{mode}{ranks}"));
            let o = mpirun(
                ranks,
                &[
                    "solve",
                    &cornell(),
                    "--out",
                    out.to_str().unwrap(),
                    "--resolution",
                    "32",
                    "--directions",
                    "49",
                    "--iterations",
                    "4",
                    "--threads",
                    // Threads inside ranks too: the answer must not depend on them.
                    if ranks % 2 == 0 { "1" } else { "2" },
                    "--distribute",
                    mode,
                ],
            );
            assert!(
                o.status.success(),
                "{mode}, {ranks} ranks: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let results = read_results(&out.join("surfels.bin")).unwrap();
            let got: Vec<_> = results.records.iter().map(|r| r.radiosity).collect();
            let worst = common::worst_relative_difference(&got, &reference.radiosity);
            let report: serde_json::Value =
                serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
            let data = &report["data_distribution"];
            println!(
                "{mode}, {ranks} ranks: worst relative difference {worst:.2e}, exchanged {:.4}, \
                 imbalance {:.4}, groups {}",
                report["exchanged_fraction"], report["imbalance"], data["groups"]
            );
            assert!(worst <= 1e-5, "{mode}, {ranks} ranks: {worst:e}");
            if mode == "data" || ranks < 4 {
                // One group: every line is gathered from the same surfels in the same order and
                // every surfel adds its directions in the same order as on one process.
                assert_eq!(worst, 0.0, "{mode}, {ranks} ranks");
            }
            assert_eq!(report["mode"], mode);
            assert_eq!(report["ranks"], ranks);
            let groups = if mode == "hybrid" && ranks == 4 { 2 } else { 1 };
            assert_eq!(data["groups"], groups, "{report}");
            let exchanged = report["exchanged_fraction"].as_f64().unwrap();
            let imbalance = report["imbalance"].as_f64().unwrap();
            if ranks / groups == 1 {
                assert_eq!(exchanged, 0.0);
                assert_eq!(imbalance, 1.0);
            } else {
                // Surfels do move, but most stay where they are from one direction to the next.
                assert!(exchanged > 0.0 && exchanged < 0.5, "{report}");
                assert!((1.0..1.5).contains(&imbalance), "{report}");
            }
            // The energy balance is that of the single-process solve.
            let emitted = report["energy"]["emitted_power"][0].as_f64().unwrap();
            assert!(emitted > 0.0);
            let per_rank = data["per_rank"].as_array().expect("per_rank");
            assert_eq!(per_rank.len(), ranks);
            for r in per_rank {
                assert!(r["propagate"].as_f64().unwrap() > 0.0, "{report}");
            }
        }
    }
}

#[test]
fn large_sums_across_ranks_match_one_process() {
    // 6 values per surfel and rank above 2^20 in all: the sum goes as a reduce-scatter and an
    // all-gather instead of through rank 0.
    let scene = voxrad::scene::obj::load_obj(Path::new(&cornell())).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(96)).unwrap();
    assert!(set.surfels.len() * 6 * 3 > voxrad::distribute::mpi_comm::GATHER_LIMIT);
    let options = SolveOptions {
        directions: 13,
        max_iterations: 2,
        tolerance: None,
        threads: 1,
        ..SolveOptions::default()
    };
    let reference = solve_with(&set, &DirectionSet::with_count(13), &options).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("large");
    let o = mpirun(
        3,
        &[
            "solve",
            &cornell(),
            "--out",
            out.to_str().unwrap(),
            "--resolution",
            "96",
            "--directions",
            "13",
            "--iterations",
            "2",
            "--threads",
            "1",
            "--distribute",
            "directions",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let results = read_results(&out.join("surfels.bin")).unwrap();
    let got: Vec<_> = results.records.iter().map(|r| r.radiosity).collect();
    let worst = common::worst_relative_difference(&got, &reference.radiosity);
    println!(
        "3 ranks, {} surfels: worst relative difference {worst:.2e}",
        set.surfels.len()
    );
    assert!(worst <= 1e-5, "{worst:e}");
}
