//! Distributed solves under real `mpirun` (built only with the `mpi` feature; `.ci/run` installs
//! Open MPI and runs these). Every rank count gives the single-process answer, and launches that
//! do not fit are refused clearly.
#![cfg(feature = "mpi")]

mod common;

use common::process::{self, describe, Child, Ended, Rng, CONTINUED_INSIDE, HANG_LIMIT};
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};
use voxrad::geometry::directions::DirectionSet;
use voxrad::output::results::read_results;
use voxrad::quality::Quality;
use voxrad::solve::direct::DirectPass;
use voxrad::solve::jacobi::solve_with;
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::{voxelize, GridSpec};

/// `mpirun -n ranks voxrad args`: oversubscribed (more ranks than cores), loopback and shared
/// memory transports only, allowed to run as root (CI containers).
fn mpirun(ranks: usize, args: &[&str]) -> Output {
    common::mpi::command(ranks)
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .expect("run mpirun (is Open MPI installed?)")
}

/// `solve` of the Cornell box at resolution 32, 49 directions, 4 plain iterations, into `out`
/// with `threads` per rank, distributed by `mode`.
fn small_solve(out: &Path, threads: &str, mode: &str) -> Vec<String> {
    let out = out.to_str().unwrap();
    [
        "solve",
        &cornell(),
        "--out",
        out,
        "--resolution",
        "32",
        "--directions",
        "49",
        "--iterations",
        "4",
        "--threads",
        threads,
        "--distribute",
        mode,
    ]
    .map(String::from)
    .to_vec()
}

fn as_strs(args: &[String]) -> Vec<&str> {
    args.iter().map(String::as_str).collect()
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
        // As the command line runs `--iterations` without `--tolerance`: plain iterations, and
        // the default preset's direct-light pass, whose dense directions are dealt out too.
        direct: DirectPass::Auto(Quality::Default.preset().direct),
        ..SolveOptions::default()
    };
    let reference = solve_with(&set, &DirectionSet::with_count(49), &options).unwrap();
    assert!(reference.stats.direct.is_some());
    let tmp = tempfile::tempdir().unwrap();
    for ranks in 1..=4 {
        let out = tmp.path().join(format!("ranks{ranks}"));
        let args = small_solve(&out, "1", "directions");
        let o = mpirun(ranks, &as_strs(&args));
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
        // The default preset's direct-light pass, as the command line runs it: the data and
        // hybrid modes must simulate it too (they once dropped it, up to 115 % off).
        direct: DirectPass::Auto(Quality::Default.preset().direct),
        ..SolveOptions::default()
    };
    let reference = solve_with(&set, &DirectionSet::with_count(49), &options).unwrap();
    assert!(reference.stats.direct.is_some());
    let tmp = tempfile::tempdir().unwrap();
    for mode in ["data", "hybrid"] {
        for ranks in 1..=4 {
            let out = tmp.path().join(format!("{mode}{ranks}"));
            // Threads inside ranks too: the answer must not depend on them.
            let threads = if ranks % 2 == 0 { "1" } else { "2" };
            let args = small_solve(&out, threads, mode);
            let o = mpirun(ranks, &as_strs(&args));
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
            if ranks == 1 {
                // Every line is gathered from the same surfels in the same order and every
                // surfel adds its directions in the same order as on one process. (On more
                // ranks each rank adds up its part of a surfel's light and the parts are added
                // at the end of the iteration, and the direct pass's light is added over the
                // ranks, as in the directions mode.)
                assert_eq!(worst, 0.0, "{mode}, {ranks} ranks");
            }
            let pass = report["effects"]
                .as_array()
                .and_then(|e| e.iter().find(|e| e["name"] == "direct-light pass"))
                .expect("the report lists the direct-light pass");
            assert_eq!(pass["simulated"], true, "{mode}, {ranks} ranks: {pass}");
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
            // Every rank kept the links of its lines: iterations 2 to 4 replayed them.
            assert_eq!(report["links"]["kept_directions"], 49, "{report}");
        }
    }
    // Kept links give the bits of searching again in every iteration (which exchanges surfels
    // for every direction, where a replay exchanges nothing until the iteration's end), and so
    // does a budget that keeps the links of some directions only (exchanges for every
    // direction, replays where the links are kept).
    let report_of = |out: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap()
    };
    for (mode, ranks) in [("data", 3), ("hybrid", 4)] {
        let kept = tmp.path().join(format!("{mode}{ranks}"));
        let kept_report = report_of(&kept);
        let link_bytes = kept_report["links"]["bytes"].as_u64().unwrap();
        let per_rank = link_bytes / ranks as u64;
        for (name, budget) in [("searched", 0), ("some kept", per_rank / 2)] {
            let out = tmp.path().join(format!("{mode}{ranks}-{budget}"));
            let mut args = small_solve(&out, "1", mode);
            args.extend(["--links-memory".to_string(), budget.to_string()]);
            let o = mpirun(ranks, &as_strs(&args));
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            let report = report_of(&out);
            let kept_directions = report["links"]["kept_directions"].as_u64().unwrap();
            if budget == 0 {
                assert_eq!(kept_directions, 0, "{report}");
            } else {
                assert!(
                    (1..49).contains(&kept_directions),
                    "{mode}, {name}: {kept_directions} directions kept"
                );
            }
            assert_eq!(
                std::fs::read(kept.join("surfels.bin")).unwrap(),
                std::fs::read(out.join("surfels.bin")).unwrap(),
                "{mode}, {ranks} ranks, {name}"
            );
            // With every link kept, only the first of the 4 iterations moved surfels.
            let moved =
                |r: &serde_json::Value| r["data_distribution"]["bytes_packed"].as_f64().unwrap();
            let ratio = moved(&kept_report) / moved(&report);
            assert!(
                (0.2..0.3).contains(&ratio),
                "{mode}, {name}: surfel bytes moved with all links kept / here: {ratio}"
            );
            assert!(kept_report["data_distribution"]["end_of_iteration_bytes"].as_u64() > Some(0));
        }
    }
}

/// A room lit by many small lamps (the office's twelve luminaires, 6 cm housings over one-sided
/// emitting undersides) with the default preset, whose direct-light pass they call for: every
/// mode, in memory and out of core, gives the one-process answer (the modes once dropped the
/// pass on such rooms).
#[test]
fn many_small_lamps_give_the_one_process_answer_in_every_mode() {
    every_mode_gives_the_one_process_answer("office", &voxrad::gen::office().scene, true);
}

/// The furnished room lit by a window-sized emitter, with the default preset (whose pass its
/// window calls for at this resolution): every mode, in memory and out of core, gives the
/// one-process answer.
#[test]
fn furnished_room_gives_the_one_process_answer_in_every_mode() {
    every_mode_gives_the_one_process_answer("window room", &voxrad::gen::window_room().scene, true);
}

/// The office with every material made grey (each channel the mean of its three): a grey
/// scene gathers one channel, and the data and hybrid modes send only that one, and get one
/// back, at the end of each iteration. Every mode gives the one-process answer.
#[test]
fn a_grey_office_gives_the_one_process_answer_in_every_mode() {
    let mut scene = voxrad::gen::office().scene;
    let grey = |c: [f64; 3]| [(c[0] + c[1] + c[2]) / 3.0; 3];
    for m in &mut scene.materials {
        m.reflectance = grey(m.reflectance);
        m.emission = grey(m.emission);
    }
    let set = voxelize(&scene, GridSpec::Resolution(24)).unwrap();
    assert!(voxrad::solve::effects::is_grey(&set));
    every_mode_gives_the_one_process_answer("grey office", &scene, true);
}

/// `scene` solved at resolution 24 with the default preset (49 directions, 3 iterations) in the
/// directions, data and hybrid modes and in the data and hybrid modes out of core, against the
/// one-process in-memory solve; `pass`: whether the scene calls for the direct-light pass.
fn every_mode_gives_the_one_process_answer(name: &str, scene: &voxrad::scene::Scene, pass: bool) {
    let tmp = tempfile::tempdir().unwrap();
    let obj = tmp.path().join("scene.obj");
    voxrad::gen::write_obj(scene, &obj).unwrap();
    let scene = voxrad::scene::obj::load_obj(&obj).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(24)).unwrap();
    let options = SolveOptions {
        directions: 49,
        max_iterations: 3,
        tolerance: None,
        threads: 1,
        direct: DirectPass::Auto(Quality::Default.preset().direct),
        ..SolveOptions::default()
    };
    let reference = solve_with(&set, &DirectionSet::with_count(49), &options).unwrap();
    assert_eq!(
        reference.stats.direct.is_some(),
        pass,
        "{name}: the direct-light pass"
    );
    // Both rooms are closed: every mode applies the scales that make them absorb what they
    // emit (`solve::closed`), with the sums over every rank.
    let closure = reference.stats.closure.expect("closure stats");
    assert!(closure.verdict.closed, "{name}: {closure:?}");
    for (mode, ranks, memory) in [
        ("directions", 3, None),
        ("data", 2, None),
        ("hybrid", 4, None),
        ("data", 3, Some("8MiB")),
        ("hybrid", 4, Some("8MiB")),
    ] {
        let out = tmp
            .path()
            .join(format!("{mode}{ranks}{}", memory.unwrap_or("")));
        let mut args = vec![
            "solve",
            obj.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--resolution",
            "24",
            "--directions",
            "49",
            "--iterations",
            "3",
            "--threads",
            "1",
            "--distribute",
            mode,
        ];
        if let Some(budget) = memory {
            args.extend(["--memory", budget]);
        }
        if mode == "hybrid" {
            args.extend(["--groups", "2"]);
        }
        let o = mpirun(ranks, &args);
        assert!(
            o.status.success(),
            "{mode}, {ranks} ranks, memory {memory:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        // Out of core the results come in the order of the shard set the scene became.
        let worst =
            common::worst_against_results(&set, &reference.radiosity, &out.join("surfels.bin"));
        println!(
            "{name}, {mode}, {ranks} ranks, memory {memory:?}: worst relative difference \
             {worst:.2e}"
        );
        assert!(
            worst <= 1e-5,
            "{mode}, {ranks} ranks, {memory:?}: {worst:e}"
        );
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
        let closed = report["effects"]
            .as_array()
            .unwrap()
            .iter()
            .find(|e| e["name"] == "energy conservation of a closed scene")
            .map(|e| e["simulated"] == true);
        assert_eq!(closed, Some(true), "{mode}, {ranks} ranks, {memory:?}");
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
            "--direct-directions",
            "0",
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

/// `mpirun -n 2 voxrad solve --distribute directions` of the Cornell box into `out`, with a
/// checkpoint after every iteration unless `extra` says otherwise (the command is not run).
fn mpirun_solve(out: &Path, extra: &[&str]) -> Command {
    mpirun_solve_in(&["--distribute", "directions"], out, extra)
}

/// As [`mpirun_solve`] in the mode `mode` gives (`--distribute ...` and its options).
fn mpirun_solve_in(mode: &[&str], out: &Path, extra: &[&str]) -> Command {
    mpirun_solve_on(2, mode, out, extra)
}

/// As [`mpirun_solve_in`] on `ranks` ranks.
fn mpirun_solve_on(ranks: usize, mode: &[&str], out: &Path, extra: &[&str]) -> Command {
    let mut c = common::mpi::command(ranks);
    c.args(solve_args(out, extra))
        .args(mode)
        .args(extra)
        .env_remove("RUST_LOG");
    c
}

/// `solve` of the Cornell box into `out` (a checkpoint whenever one can be written); an option
/// in `extra` replaces the same one here (`extra` itself is not included).
fn solve_args(out: &Path, extra: &[&str]) -> Vec<String> {
    let base = [
        ("--resolution", "32"),
        ("--directions", "300"),
        ("--tolerance", "1e-6"),
        ("--threads", "1"),
        ("--image-size", "64x48"),
        ("--checkpoint-every", "0"),
    ];
    let mut args = vec![
        "solve".to_string(),
        cornell(),
        "--out".to_string(),
        out.display().to_string(),
    ];
    for (flag, value) in base {
        if !extra.contains(&flag) {
            args.extend([flag.to_string(), value.to_string()]);
        }
    }
    args
}

/// A scene whose single iteration is long: 2,000 directions on the Cornell box at resolution 16.
const LONG_ITERATIONS: [&str; 4] = ["--resolution", "16", "--directions", "2000"];

/// Runs an uninterrupted 2-rank solve into `out`; returns its wall time in seconds.
fn mpi_reference(out: &Path, log: &Path) -> f64 {
    let mut child = Child::spawn(mpirun_solve(out, &[]), log);
    let status = child.wait_at_most(HANG_LIMIT);
    assert!(status.success(), "{}:\n{}", describe(&status), child.log());
    child.started.elapsed().as_secs_f64()
}

/// Waits until the ranks mpirun started have ended (they notice their launcher is gone);
/// fails if any outlives it by 30 s.
fn ranks_end_with_their_launcher(ranks: &[i32]) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while ranks.iter().any(|&p| process::alive(p)) {
        if Instant::now() > deadline {
            process::kill_and_reap(ranks);
            panic!("ranks {ranks:?} outlived mpirun by 30 s");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Resumes with `mpirun -n 2 ... --resume`, which must succeed from a checkpoint; the results
/// must be `reference`'s byte for byte.
fn resume_to_the_end(out: &Path, reference: &Path, log: &Path) {
    resume_to_the_end_with(&[], out, reference, log);
}

/// As [`resume_to_the_end`] with the options `extra`; returns the log.
fn resume_to_the_end_with(extra: &[&str], out: &Path, reference: &Path, log: &Path) -> String {
    resume_to_the_end_in(
        mpirun_solve(out, &[extra, &["--resume"]].concat()),
        out,
        reference,
        log,
    )
}

/// As [`resume_to_the_end`] with the command `resume` (a `--resume` into `out`).
fn resume_to_the_end_in(resume: Command, out: &Path, reference: &Path, log: &Path) -> String {
    let mut child = Child::spawn(resume, log);
    let status = child.wait_at_most(HANG_LIMIT);
    let text = child.log();
    assert!(status.success(), "{}:\n{text}", describe(&status));
    assert!(text.contains("resumed from a checkpoint"), "{text}");
    assert_same_results(out, reference);
    text
}

fn assert_same_results(out: &Path, reference: &Path) {
    let got = std::fs::read(out.join("surfels.bin")).unwrap();
    let want = std::fs::read(reference.join("surfels.bin")).unwrap();
    assert!(
        got == want,
        "resumed results differ from the uninterrupted run's"
    );
    assert!(!voxrad::checkpoint::path_in(out).exists());
}

/// `--chebyshev` in the directions, data and hybrid modes gives the one-process answer: each
/// mode keeps the radiosity before last of the surfels it updates, and the semi-iteration runs
/// in each (the report says so).
#[test]
fn chebyshev_gives_the_one_process_answer_in_every_in_memory_mode() {
    let tmp = tempfile::tempdir().unwrap();
    let one = tmp.path().join("one");
    let mut args = solve_args(&one, &[]);
    args.push("--chebyshev".into());
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(&args)
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let radiosity = |out: &Path| -> Vec<[[f32; 3]; 2]> {
        let results = read_results(&out.join("surfels.bin")).unwrap();
        results.records.iter().map(|r| r.radiosity).collect()
    };
    let reference = radiosity(&one);
    for (mode, ranks) in [("directions", 3), ("data", 2), ("hybrid", 4)] {
        let out = tmp.path().join(mode);
        let mut extra = vec!["--distribute", mode, "--chebyshev"];
        if mode == "hybrid" {
            extra.extend(["--groups", "2"]);
        }
        let o = mpirun_solve_on(ranks, &[], &out, &extra).output().unwrap();
        assert!(
            o.status.success(),
            "{mode}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let worst = common::worst_relative_difference(&radiosity(&out), &reference);
        println!("{mode}, {ranks} ranks, --chebyshev: worst relative difference {worst:.2e}");
        assert!(worst <= 1e-5, "{mode}: {worst:e}");
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
        let effect = report["effects"]
            .as_array()
            .and_then(|e| e.iter().find(|e| e["name"] == "Chebyshev semi-iteration"))
            .expect("the report lists the Chebyshev semi-iteration");
        assert_eq!(effect["simulated"], true, "{mode}: {effect}");
    }
}

#[test]
fn directions_mode_killed_at_random_moments_resumes_to_the_same_bytes() {
    killed_under_mpirun(&[], 0x5eed_0003, 4, 0.4);
}

#[test]
fn directions_mode_killed_inside_long_iterations_resumes_to_the_same_bytes() {
    // A checkpoint every 50 ms, several inside each iteration; short runs, so that most kills
    // land in the first iterations.
    let options = [&LONG_ITERATIONS[..], &["--checkpoint-every", "0.05"]].concat();
    let inside = killed_under_mpirun(&options, 0x5eed_0005, 6, 0.2);
    assert!(inside >= 1, "no run continued inside an iteration");
}

#[test]
fn data_mode_killed_inside_long_iterations_resumes_to_the_same_bytes() {
    // As the directions mode's: each rank's light of the surfels it holds is saved, and the
    // resumed run rebuilds what every rank held there.
    let options = [&LONG_ITERATIONS[..], &["--checkpoint-every", "0.05"]].concat();
    let inside = killed_under_mpirun_in(&["--distribute", "data"], &options, 0x5eed_0007, 5, 0.2);
    assert!(inside >= 1, "no run continued inside an iteration");
}

/// As the data mode's, with `--chebyshev`: its checkpoints also hold the owners' radiosity
/// before last, gathered by id.
#[test]
fn data_mode_with_chebyshev_killed_inside_long_iterations_resumes_to_the_same_bytes() {
    let every = ["--checkpoint-every", "0.05", "--chebyshev"];
    let options = [&LONG_ITERATIONS[..], &every].concat();
    let inside = killed_under_mpirun_in(&["--distribute", "data"], &options, 0x5eed_0009, 5, 0.2);
    assert!(inside >= 1, "no run continued inside an iteration");
}

/// Kills `mpirun -n 2 voxrad solve ... --resume` (options `extra`) at random moments, up to
/// `longest` of the uninterrupted run's time after its first checkpoint, `kills` times unless it
/// finishes first, then lets
/// it finish: the results must be the uninterrupted run's, byte for byte. Returns how many runs
/// continued inside an iteration.
fn killed_under_mpirun(extra: &[&str], seed: u64, kills: usize, longest: f64) -> usize {
    killed_under_mpirun_in(&["--distribute", "directions"], extra, seed, kills, longest)
}

/// As [`killed_under_mpirun`] in the mode `mode` gives.
fn killed_under_mpirun_in(
    mode: &[&str],
    extra: &[&str],
    seed: u64,
    kills: usize,
    longest: f64,
) -> usize {
    let mpirun_solve = |out: &Path, extra: &[&str]| mpirun_solve_in(mode, out, extra);
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    let mut child = Child::spawn(
        mpirun_solve(&reference, extra),
        &tmp.path().join("reference.log"),
    );
    // The kills fall in what follows the first checkpoint: the later iterations, which replay
    // kept links, take a smaller share of the run than the first.
    let reference_checkpoint = voxrad::checkpoint::path_in(&reference);
    child.wait_for(HANG_LIMIT, || reference_checkpoint.exists());
    let checkpointed = child.started.elapsed().as_secs_f64();
    let status = child.wait_at_most(HANG_LIMIT);
    assert!(status.success(), "{}:\n{}", describe(&status), child.log());
    let seconds = child.started.elapsed().as_secs_f64() - checkpointed;
    let out = tmp.path().join("out");
    let ckpt = voxrad::checkpoint::path_in(&out);
    let mut rng = Rng::seeded(seed);
    let (mut killed, mut resumed, mut inside) = (0, 0, 0);
    let mut finished = false;
    let resume = [extra, &["--resume"]].concat();
    // A run that finishes before its first kill (a loaded machine's timing: the reference ran
    // slower than this run) proves nothing: the schedule starts again from scratch with shorter
    // delays, down to a sixteenth.
    let mut scale = 1.0;
    for attempt in 0..5 {
        if attempt > 0 {
            println!("the run finished before its first kill: again, with half the delays");
            std::fs::remove_dir_all(&out).unwrap();
            (finished, scale) = (false, scale / 2.0);
        }
        for run in 1..=kills {
            let mut child = Child::spawn(
                mpirun_solve(&out, &resume),
                &tmp.path().join(format!("run{run}.log")),
            );
            // The first kill after a checkpoint exists, so the resume has one to start from.
            if run == 1 {
                child.wait_for(HANG_LIMIT, || ckpt.exists());
            }
            let delay = Duration::from_secs_f64(rng.uniform(0.05, longest) * seconds * scale);
            std::thread::sleep(delay.saturating_sub(Duration::from_millis(50)));
            let ranks = process::children_of(child.pid());
            let ended = child.run_or_kill_after(Duration::from_millis(50));
            let text = child.log();
            let (was_resumed, was_inside) = process::resumed_and_inside(&text);
            resumed += was_resumed as usize;
            inside += was_inside as usize;
            match ended {
                Ended::Killed => {
                    killed += 1;
                    ranks_end_with_their_launcher(&ranks);
                    println!(
                        "run {run}: mpirun killed after {:.2} s; its {} ranks ended",
                        child.started.elapsed().as_secs_f64(),
                        ranks.len()
                    );
                    // A kill that lands after the solve wrote its outputs and removed its
                    // checkpoint (between that and mpirun's exit, on a loaded machine) leaves
                    // a finished run: a resume would start afresh, and rightly.
                    if !ckpt.exists() && out.join("surfels.bin").exists() {
                        println!("run {run}: its outputs were written before the kill");
                        finished = true;
                        break;
                    }
                }
                Ended::Exited(status) => {
                    assert!(status.success(), "{}:\n{text}", describe(&status));
                    println!("run {run}: finished before its kill");
                    finished = true;
                    break;
                }
            }
        }
        if killed > 0 || !finished {
            break;
        }
    }
    if finished {
        assert_same_results(&out, &reference);
    } else {
        let text = resume_to_the_end_in(
            mpirun_solve(&out, &resume),
            &out,
            &reference,
            &tmp.path().join("final.log"),
        );
        resumed += 1;
        if text.contains(CONTINUED_INSIDE) {
            inside += 1;
        }
    }
    println!(
        "{killed} kills of mpirun, {resumed} resumed runs ({inside} inside an iteration; \
         uninterrupted run after its first checkpoint: {seconds:.1} s)"
    );
    assert!(killed >= 1 && resumed >= 1);
    inside
}

/// Sends SIGTERM to rank 1 of a 2-rank directions-mode solve of [`LONG_ITERATIONS`] into `out`
/// 0.1 s after its first iteration ended (no periodic checkpoint); expects exit status 3 and
/// returns the log.
fn sigterm_rank_1_in_iteration_2(out: &Path, log: &Path) -> String {
    let options = [&LONG_ITERATIONS[..], &["--checkpoint-every", "1000"]].concat();
    sigterm_rank_1_after_iteration_1(mpirun_solve(out, &options), log)
}

/// Runs `solve` (an `mpirun` of a long solve), sends SIGTERM to its rank 1 0.1 s after the
/// first iteration ended; expects exit status 3 and returns the log.
fn sigterm_rank_1_after_iteration_1(solve: Command, log: &Path) -> String {
    let mut child = Child::spawn(solve, log);
    assert!(
        child.wait_for(HANG_LIMIT, || {
            std::fs::read_to_string(log).is_ok_and(|t| t.contains("iteration=1 "))
        }),
        "no iteration 1:\n{}",
        child.log()
    );
    std::thread::sleep(Duration::from_millis(100));
    let ranks = process::children_of(child.pid());
    common::mpi::signal_rank(child.pid(), 1, libc::SIGTERM);
    let status = child.wait_at_most(HANG_LIMIT);
    let text = child.log();
    assert_eq!(status.code(), Some(3), "{}:\n{text}", describe(&status));
    ranks_end_with_their_launcher(&ranks);
    text
}

#[test]
fn directions_mode_sigterm_inside_an_iteration_resumes_to_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    let quiet = [&LONG_ITERATIONS[..], &["--checkpoint-every", "1000"]].concat();
    let mut child = Child::spawn(
        mpirun_solve(&reference, &quiet),
        &tmp.path().join("reference.log"),
    );
    assert!(child.wait_at_most(HANG_LIMIT).success());
    // Retried (a few times at most) if the signal came between two iterations instead.
    let (out, done) = (1..=4)
        .find_map(|attempt| {
            let out = tmp.path().join(format!("out{attempt}"));
            let log = tmp.path().join(format!("run{attempt}.log"));
            let text = sigterm_rank_1_in_iteration_2(&out, &log);
            let file = voxrad::checkpoint::CheckpointFile::open(&voxrad::checkpoint::path_in(&out))
                .unwrap();
            let within = file.header.state.within;
            match within {
                Some(done) => {
                    assert!(text.contains("directions of the next"), "{text}");
                    assert_eq!(file.header.state.ranks, 2);
                    println!(
                        "{}",
                        text.lines()
                            .find(|l| l.contains("checkpoint at"))
                            .unwrap_or("")
                    );
                    Some((out, done))
                }
                None => {
                    println!("attempt {attempt}: stopped between two iterations, again");
                    None
                }
            }
        })
        .expect("four SIGTERMs, none inside an iteration");

    // One process cannot continue inside the 2-rank iteration: it starts it again, and says so.
    let single = tmp.path().join("single");
    std::fs::create_dir_all(&single).unwrap();
    let ckpt = voxrad::checkpoint::path_in(&out);
    std::fs::copy(&ckpt, voxrad::checkpoint::path_in(&single)).unwrap();
    let args = solve_args(&single, &LONG_ITERATIONS);
    let one = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(&args)
        .args(LONG_ITERATIONS)
        .arg("--resume")
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&one.stderr);
    assert!(one.status.success(), "{text}");
    assert!(
        text.contains("resumed from a checkpoint")
            && text.contains("that iteration starts from its beginning")
            && !text.contains(CONTINUED_INSIDE),
        "{text}"
    );

    // Two ranks continue inside it, from each rank's sums, to the uninterrupted run's bytes.
    let text = resume_to_the_end_with(
        &LONG_ITERATIONS,
        &out,
        &reference,
        &tmp.path().join("resume.log"),
    );
    assert!(
        text.contains(CONTINUED_INSIDE) && text.contains(&format!("within={done}")),
        "{text}"
    );
}

#[test]
fn data_mode_sigterm_inside_an_iteration_resumes_to_the_same_bytes() {
    let mode = ["--distribute", "data"];
    let (tmp, stopped, reference) = sigterm_inside_then_resume(2, &mode, 1);

    // One process cannot continue inside the 2-rank iteration: it starts it again, says so,
    // and ends at the uninterrupted answer (the data mode gives the one-process radiosity).
    let args = solve_args(&stopped, &LONG_ITERATIONS);
    let one = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(&args)
        .args(LONG_ITERATIONS)
        .args(mode)
        .arg("--resume")
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&one.stderr);
    assert!(one.status.success(), "{text}");
    assert!(
        text.contains("resumed from a checkpoint")
            && text.contains("that iteration starts from its beginning")
            && !text.contains(CONTINUED_INSIDE),
        "{text}"
    );
    let radiosity = |dir: &Path| -> Vec<_> {
        let results = read_results(&dir.join("surfels.bin")).unwrap();
        results.records.iter().map(|r| r.radiosity).collect()
    };
    let worst = common::worst_relative_difference(&radiosity(&stopped), &radiosity(&reference));
    println!("resumed by one process: worst relative difference {worst:.2e}");
    assert!(worst <= 1e-5, "{worst:e}");
    drop(tmp);
}

#[test]
fn hybrid_mode_sigterm_inside_an_iteration_resumes_to_the_same_bytes() {
    sigterm_inside_then_resume(4, &["--distribute", "hybrid", "--groups", "2"], 2);
}

/// A `ranks`-rank solve of [`LONG_ITERATIONS`] in `mode` (with `groups` groups) stopped by
/// SIGTERM to rank 1 inside an iteration (retried if it came between two) resumes on `ranks`
/// ranks, inside that iteration, to the uninterrupted run's bytes. Returns the temporary
/// directory, a directory holding a copy of the stopped run's checkpoint, and the reference's.
fn sigterm_inside_then_resume(
    ranks: usize,
    mode: &[&str],
    groups: u32,
) -> (tempfile::TempDir, std::path::PathBuf, std::path::PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    // The reference writes no checkpoint (they do not change the answer; other tests show it),
    // which keeps it quick when the tests share a busy machine.
    let options = [&LONG_ITERATIONS[..], &["--checkpoint-every", "1000"]].concat();
    let mut child = Child::spawn(
        mpirun_solve_on(ranks, mode, &reference, &options),
        &tmp.path().join("reference.log"),
    );
    let status = child.wait_at_most(HANG_LIMIT);
    assert!(status.success(), "{}:\n{}", describe(&status), child.log());
    let (out, done) = (1..=4)
        .find_map(|attempt| {
            let out = tmp.path().join(format!("out{attempt}"));
            let log = tmp.path().join(format!("run{attempt}.log"));
            let solve = mpirun_solve_on(ranks, mode, &out, &options);
            let text = sigterm_rank_1_after_iteration_1(solve, &log);
            let file = voxrad::checkpoint::CheckpointFile::open(&voxrad::checkpoint::path_in(&out))
                .unwrap();
            let state = &file.header.state;
            match state.within {
                Some(done) => {
                    assert!(text.contains("directions of the next"), "{text}");
                    assert_eq!((state.ranks, state.data_groups), (ranks as u32, groups));
                    Some((out, done))
                }
                None => {
                    println!("attempt {attempt}: stopped between two iterations, again");
                    None
                }
            }
        })
        .expect("four SIGTERMs, none inside an iteration");
    let copy = tmp.path().join("copy");
    std::fs::create_dir_all(&copy).unwrap();
    let ckpt = voxrad::checkpoint::path_in(&out);
    std::fs::copy(&ckpt, voxrad::checkpoint::path_in(&copy)).unwrap();
    let resume = [&LONG_ITERATIONS[..], &["--resume"]].concat();
    let text = resume_to_the_end_in(
        mpirun_solve_on(ranks, mode, &out, &resume),
        &out,
        &reference,
        &tmp.path().join("resume.log"),
    );
    assert!(
        text.contains(CONTINUED_INSIDE) && text.contains(&format!("within={done}")),
        "{text}"
    );
    println!("{mode:?} on {ranks} ranks: stopped {done} steps into an iteration, same bytes");
    (tmp, copy, reference)
}

#[test]
fn a_rank_that_dies_ends_the_job_and_the_checkpoint_resumes_it() {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    mpi_reference(&reference, &tmp.path().join("reference.log"));
    let out = tmp.path().join("out");
    let ckpt = voxrad::checkpoint::path_in(&out);
    let mut child = Child::spawn(mpirun_solve(&out, &[]), &tmp.path().join("run.log"));
    assert!(
        child.wait_for(HANG_LIMIT, || ckpt.exists()),
        "no checkpoint:\n{}",
        child.log()
    );
    // Rank 1 is the child of mpirun whose environment says so.
    let ranks = process::children_of(child.pid());
    let rank1 = common::mpi::signal_rank(child.pid(), 1, libc::SIGKILL);
    let killed_at = Instant::now();
    let status = child.wait_at_most(HANG_LIMIT);
    let waited = killed_at.elapsed().as_secs_f64();
    let text = child.log();
    assert!(
        !status.success(),
        "mpirun succeeded without rank 1:\n{text}"
    );
    assert!(
        text.contains("rank 1"),
        "the message does not name rank 1:\n{text}"
    );
    ranks_end_with_their_launcher(&ranks);
    println!(
        "rank 1 (pid {rank1}) killed; mpirun ended {waited:.2} s later with {}: {}",
        describe(&status),
        text.lines()
            .find(|l| l.contains("rank 1"))
            .unwrap_or("")
            .trim()
    );
    resume_to_the_end(&out, &reference, &tmp.path().join("resume.log"));
}

#[test]
fn sigterm_to_one_rank_stops_every_rank_with_a_checkpoint() {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    mpi_reference(&reference, &tmp.path().join("reference.log"));
    let out = tmp.path().join("out");
    let ckpt = voxrad::checkpoint::path_in(&out);
    // No periodic checkpoint: the one to resume from is written on the signal.
    let mut child = Child::spawn(
        mpirun_solve(&out, &["--checkpoint-every", "1000"]),
        &tmp.path().join("run.log"),
    );
    let log = tmp.path().join("run.log");
    assert!(
        child.wait_for(HANG_LIMIT, || {
            std::fs::read_to_string(&log).is_ok_and(|t| t.contains("iteration=2 "))
        }),
        "no iteration 2:\n{}",
        child.log()
    );
    assert!(!ckpt.exists());
    // Only rank 1 hears it (the checkpoint writer, rank 0, does not): all must stop together.
    let ranks = process::children_of(child.pid());
    common::mpi::signal_rank(child.pid(), 1, libc::SIGTERM);
    let status = child.wait_at_most(HANG_LIMIT);
    let text = child.log();
    assert_eq!(status.code(), Some(3), "{}:\n{text}", describe(&status));
    assert!(
        text.contains("interrupted by SIGTERM") && text.contains("--resume"),
        "{text}"
    );
    ranks_end_with_their_launcher(&ranks);
    println!(
        "{}",
        text.lines()
            .find(|l| l.contains("checkpoint at"))
            .unwrap_or("")
    );
    assert!(ckpt.exists(), "rank 0 wrote no checkpoint:\n{text}");
    resume_to_the_end(&out, &reference, &tmp.path().join("resume.log"));
}

#[test]
fn a_damaged_checkpoint_is_refused_by_every_rank_without_a_hang() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    let ckpt = voxrad::checkpoint::path_in(&out);
    std::fs::write(&ckpt, b"VXRDCKPT\x01\0\0\0\x08\0\0\0damaged!").unwrap();
    let mut child = Child::spawn(
        mpirun_solve(&out, &["--resume"]),
        &tmp.path().join("run.log"),
    );
    let status = child.wait_at_most(HANG_LIMIT);
    let text = child.log();
    assert_eq!(status.code(), Some(2), "{}:\n{text}", describe(&status));
    assert!(
        text.contains(&ckpt.display().to_string()) && text.contains("truncated checkpoint"),
        "{text}"
    );
    assert!(!text.contains("panicked"), "{text}");
    assert!(!out.join("surfels.bin").exists());
}

#[test]
fn shard_sets_solve_in_every_mode() {
    // Each rank reads the whole set into memory, whatever its number of shards.
    let scene = voxrad::scene::obj::load_obj(Path::new(&cornell())).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(32)).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cornell.shards");
    common::write_shard_set(&set, &dir, 3);
    // The set's own order is the order of its results; solve that order in one process.
    let source = voxrad::outcore::ShardSetSource::open(&dir).unwrap();
    let ordered: Vec<_> = voxrad::outcore::SurfelSource::stream(&source, 1 << 20)
        .unwrap()
        .map(Result::unwrap)
        .collect();
    let in_set_order = voxrad::voxel::SurfelSet {
        surfels: ordered,
        ..set.clone()
    };
    let options = SolveOptions {
        directions: 49,
        max_iterations: 3,
        tolerance: None,
        threads: 1,
        ..SolveOptions::default()
    };
    let reference = solve_with(&in_set_order, &DirectionSet::with_count(49), &options).unwrap();
    for mode in ["directions", "data", "hybrid"] {
        let out = tmp.path().join(mode);
        let o = mpirun(
            2,
            &[
                "solve",
                dir.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--directions",
                "49",
                "--iterations",
                "3",
                "--threads",
                "1",
                // Plain, without the direct pass (whose light is added over the ranks): every
                // line is gathered as on one process; only each surfel's light is added up in
                // another grouping (each rank's part, then the parts), so the data mode agrees
                // to the rounding of the last bit.
                "--direct-directions",
                "0",
                "--distribute",
                mode,
            ],
        );
        assert!(
            o.status.success(),
            "{mode}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let results = read_results(&out.join("surfels.bin")).unwrap();
        let got: Vec<_> = results.records.iter().map(|r| r.radiosity).collect();
        let worst = common::worst_relative_difference(&got, &reference.radiosity);
        println!("shard set, {mode}, 2 ranks: worst relative difference {worst:.2e}");
        assert!(worst <= 1e-5, "{mode}: {worst:e}");
        if mode == "data" {
            assert!(worst <= 1e-6, "{mode}: {worst:e}");
        }
    }
}

#[test]
fn data_and_hybrid_modes_stopped_by_sigterm_resume_to_the_same_bytes() {
    let modes: [&[&str]; 2] = [
        &["--distribute", "data"],
        &["--distribute", "hybrid", "--groups", "2"],
    ];
    for mode in modes {
        let tmp = tempfile::tempdir().unwrap();
        let reference = tmp.path().join("reference");
        let mut child = Child::spawn(
            mpirun_solve_in(mode, &reference, &[]),
            &tmp.path().join("reference.log"),
        );
        let status = child.wait_at_most(HANG_LIMIT);
        assert!(status.success(), "{}:\n{}", describe(&status), child.log());

        let out = tmp.path().join("out");
        let log = tmp.path().join("run.log");
        let mut child = Child::spawn(
            mpirun_solve_in(mode, &out, &["--checkpoint-every", "1000"]),
            &log,
        );
        assert!(
            child.wait_for(HANG_LIMIT, || {
                std::fs::read_to_string(&log).is_ok_and(|t| t.contains("iteration=2 "))
            }),
            "{mode:?}: no iteration 2:\n{}",
            child.log()
        );
        let ranks = process::children_of(child.pid());
        common::mpi::signal_rank(child.pid(), 1, libc::SIGTERM);
        let status = child.wait_at_most(HANG_LIMIT);
        let text = child.log();
        assert_eq!(
            status.code(),
            Some(3),
            "{mode:?}: {}:\n{text}",
            describe(&status)
        );
        ranks_end_with_their_launcher(&ranks);
        assert!(
            voxrad::checkpoint::path_in(&out).exists(),
            "{mode:?}: no checkpoint:\n{text}"
        );
        let mut child = Child::spawn(
            mpirun_solve_in(mode, &out, &["--resume"]),
            &tmp.path().join("resume.log"),
        );
        let status = child.wait_at_most(HANG_LIMIT);
        let text = child.log();
        assert!(status.success(), "{mode:?}: {}:\n{text}", describe(&status));
        assert!(text.contains("resumed from a checkpoint"), "{text}");
        assert_same_results(&out, &reference);
        println!(
            "{mode:?}: stopped by SIGTERM after iteration 2 or later, resumed to the same bytes"
        );
    }
}
