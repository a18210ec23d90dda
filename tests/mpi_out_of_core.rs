//! The data mode out of core under real `mpirun` (`--distribute data --memory SIZE`; built only
//! with the `mpi` feature, run by `.ci/run`): every rank count gives the single-process
//! out-of-core radiosity bit for bit and the in-memory one within 1e-5, each rank's memory stays
//! within the budget while its share of the scene is larger, a run stopped by SIGTERM resumes
//! (on another rank count) to the same bytes, what cannot work is refused, and the Slurm
//! recipe (`tools/slurm/solve.sbatch`) requeues and resumes with its work files on each
//! "node's" own directory.
//!
//! Memory is read from the report: each rank's peak RSS (`VmHWM`) at the end, minus its peak
//! before the scene was read (the program and the MPI library, which the budget does not
//! cover).
#![cfg(feature = "mpi")]

mod common;

use common::process::{describe, Child, HANG_LIMIT};
use std::path::Path;
use std::process::{Command, Output};
use voxrad::output::results::read_results;
use voxrad::voxel::voxelize::{voxelize, GridSpec};

/// Waits until the run logging to `log` has written a checkpoint inside the iteration after
/// its `completed`-th (checkpoints are due at every step, spaced by their writing time), so
/// that a signal sent then comes inside that iteration; fails with the log when none comes.
fn wait_for_a_checkpoint_inside(child: &mut Child, log: &Path, completed: usize) {
    let iteration = format!("iteration={completed} ");
    let inside = |text: &str| {
        text.lines().any(|l| {
            l.contains("checkpoint written") && l.contains(&iteration) && !l.contains("within=0 ")
        })
    };
    assert!(
        child.wait_for(HANG_LIMIT, || {
            std::fs::read_to_string(log).is_ok_and(|t| inside(&t))
        }),
        "no checkpoint inside iteration {}:\n{}",
        completed + 1,
        child.log()
    );
}

/// As in the single-process out-of-core tests (`tests/memory_limit.rs`): code, stacks, the
/// allocator's bookkeeping and fragmentation beyond the budget.
const ALLOWANCE_BYTES: u64 = 16 << 20;

/// `mpirun -n ranks voxrad args`, oversubscribed, loopback and shared memory only.
fn mpirun(ranks: usize, args: &[&str]) -> Output {
    mpirun_command(ranks, args)
        .output()
        .expect("run mpirun (is Open MPI installed?)")
}

fn mpirun_command(ranks: usize, args: &[&str]) -> Command {
    let mut c = common::mpi::command(ranks);
    c.args(args).env("NO_COLOR", "1");
    c
}

fn ok(o: &Output, what: &str) {
    assert!(
        o.status.success(),
        "{what}: status {:?}\n{}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
}

fn radiosity(out: &Path) -> Vec<[[f32; 3]; 2]> {
    read_results(&out.join("surfels.bin"))
        .expect("results")
        .records
        .iter()
        .map(|r| r.radiosity)
        .collect()
}

fn report(out: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap()
}

/// The Cornell box voxelized at `resolution`, written as a shard set of `shards` shards.
fn cornell_set(dir: &Path, resolution: u32, shards: usize) -> usize {
    let obj = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let scene = voxrad::scene::obj::load_obj(&obj).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(resolution)).unwrap();
    common::write_shard_set(&set, dir, shards);
    set.surfels.len()
}

/// Each rank's peak RSS beyond its peak before the scene was read, and its largest share.
fn rank_memory(report: &serde_json::Value) -> Vec<(u64, u64)> {
    report["data_distribution"]["out_of_core"]
        .as_array()
        .expect("out_of_core per rank")
        .iter()
        .map(|r| {
            let peak = r["peak_rss_bytes"].as_u64().unwrap();
            let start = r["start_rss_bytes"].as_u64().unwrap();
            assert!(peak >= start && start > 0, "{r}");
            (peak - start, r["largest_share_bytes"].as_u64().unwrap())
        })
        .collect()
}

#[test]
fn data_mode_out_of_core_matches_one_process_for_1_to_4_ranks() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    // Three shards: ranks start reading at the shard that holds their slice.
    let surfels = cornell_set(&set, 48, 3);
    let set = set.to_str().unwrap();
    let budget = 512u64 << 10;
    // Plain: the share must not fit the budget, which the direct-light pass's parts would need
    // here (it is compared in `direct_light_pass_gives_the_one_process_answer`).
    let common_args = [
        "--directions",
        "49",
        "--iterations",
        "3",
        "--memory",
        "512KiB",
        "--direct-directions",
        "0",
    ];
    let solve = |out: &Path, threads: &str| -> Vec<String> {
        [
            "solve",
            set,
            "--out",
            out.to_str().unwrap(),
            "--threads",
            threads,
        ]
        .iter()
        .chain(&common_args)
        .map(|s| s.to_string())
        .collect()
    };
    // One process, out of core.
    let single = tmp.path().join("single");
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(solve(&single, "1"))
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    ok(&o, "one process out of core");
    let reference = radiosity(&single);
    assert_eq!(reference.len(), surfels);
    assert_eq!(report(&single)["links"]["kept_in"], "files");
    // The in-memory data mode.
    let memory = tmp.path().join("memory");
    let o = mpirun(
        2,
        &[
            "solve",
            set,
            "--out",
            memory.to_str().unwrap(),
            "--directions",
            "49",
            "--iterations",
            "3",
            "--threads",
            "1",
            "--direct-directions",
            "0",
            "--distribute",
            "data",
        ],
    );
    ok(&o, "in memory");
    let in_memory = radiosity(&memory);
    for ranks in 1..=4 {
        let out = tmp.path().join(format!("ranks{ranks}"));
        // Threads inside ranks too: the answer must not depend on them.
        let threads = if ranks % 2 == 0 { "1" } else { "2" };
        let mut args = solve(&out, threads);
        args.extend(["--distribute", "data"].map(String::from));
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = mpirun(ranks, &args);
        ok(&o, &format!("{ranks} ranks"));
        let got = radiosity(&out);
        let worst = common::worst_relative_difference(&got, &in_memory);
        let r = report(&out);
        let data = &r["data_distribution"];
        let memory = rank_memory(&r);
        println!(
            "{ranks} ranks: against in memory {worst:.2e}, exchanged {:.4}, imbalance {:.4}, \
             peak beyond start and largest share per rank {memory:?}",
            r["exchanged_fraction"], r["imbalance"]
        );
        // Every line gathered from the same surfels in the same order, every surfel's
        // directions and axes added in the same order as in one process.
        assert!(got == reference, "{ranks} ranks differ from one process");
        assert!(worst <= 1e-5, "{ranks} ranks: {worst:e}");
        assert_eq!(r["mode"], "data");
        assert_eq!(r["ranks"], ranks);
        assert_eq!(memory.len(), ranks);
        for (beyond, share) in &memory {
            assert!(*beyond <= budget + ALLOWANCE_BYTES, "{r}");
            assert!(*share > budget, "the share must not fit the budget: {r}");
        }
        let exchanged = r["exchanged_fraction"].as_f64().unwrap();
        let imbalance = r["imbalance"].as_f64().unwrap();
        if ranks == 1 {
            assert_eq!((exchanged, imbalance), (0.0, 1.0));
        } else {
            assert!(exchanged > 0.0 && exchanged < 0.5, "{r}");
            assert!((1.0..1.1).contains(&imbalance), "{r}");
        }
        for rank in data["out_of_core"].as_array().unwrap() {
            assert!(rank["bytes_read_per_voxel_direction"].as_f64().unwrap() > 0.0);
            assert!(rank["bytes_written_per_voxel_direction"].as_f64().unwrap() > 0.0);
        }
        // Directions of one slope along `v` were gathered together, in passes over each
        // rank's held files that read every band once for all of them (nothing moves between
        // them: the same columns), and the answer above is still one process's to the bit.
        // Iterations 2 and 3 skip the steps that moved nothing in the first without reading
        // the held files (at most the 49 directions but the three that start an axis, twice).
        for rank in data["out_of_core"].as_array().unwrap() {
            let joint = rank["joint_directions"].as_u64().unwrap();
            assert!(joint > 0 && joint < 3 * 49, "{r}");
        }
        let quiet = data["quiet_steps_skipped"].as_u64().unwrap();
        assert!(quiet <= 2 * (49 - 3), "{quiet} quiet steps: {r}");
        // The energy balance is that of one process (its sums added in another grouping).
        same_energy(&r, &report(&single), 1e-9);
        // Each rank kept its lines' links in files and replayed them in iterations 2 and 3.
        let links = &r["links"];
        assert_eq!(links["kept_in"], "files", "{links}");
        assert_eq!(links["kept_directions"], 49, "{links}");
    }
    // Searching again in every iteration on each rank: the same bits as replaying.
    let out = tmp.path().join("searched");
    let mut args = solve(&out, "1");
    args.extend(["--distribute", "data", "--links-disk", "0"].map(String::from));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    ok(&mpirun(2, &args), "2 ranks searching again");
    assert_eq!(report(&out)["links"]["kept_in"], "none");
    assert!(radiosity(&out) == reference, "searching again changes bits");
    // The ranks' work files under --work-dir (a node-local disk on a cluster): the same bits,
    // and nothing left there or in --out.
    let out = tmp.path().join("work-dir");
    let local = tmp.path().join("local");
    let mut args = solve(&out, "1");
    args.extend(
        [
            "--distribute",
            "data",
            "--work-dir",
            local.to_str().unwrap(),
        ]
        .map(String::from),
    );
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    ok(&mpirun(2, &args), "2 ranks with --work-dir");
    assert!(radiosity(&out) == reference, "--work-dir changes bits");
    let names = |dir: &Path| -> Vec<String> {
        std::fs::read_dir(dir)
            .map(|d| {
                d.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default()
    };
    assert!(names(&local).is_empty(), "{:?}", names(&local));
    assert!(
        !names(&out).iter().any(|n| n.starts_with(".voxrad")),
        "{:?}",
        names(&out)
    );
}

/// With the direct-light pass (run by rank 0 on the whole source, its light sent to every
/// rank's share): the data mode out of core gives the one-process out-of-core radiosity bit for
/// bit at every rank count, the in-memory data mode's within 1e-5, and its energy balance; the
/// hybrid mode out of core both within 1e-5.
#[test]
fn direct_light_pass_gives_the_one_process_answer() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    cornell_set(&set, 40, 2);
    let set = set.to_str().unwrap();
    let run = |out: &Path, ranks: Option<(usize, &str)>, memory: bool| -> serde_json::Value {
        let out_str = out.to_str().unwrap();
        let mut args = vec![
            "solve",
            set,
            "--out",
            out_str,
            "--directions",
            "49",
            "--iterations",
            "3",
            "--threads",
            "1",
            "--direct-directions",
            "300",
        ];
        if memory {
            args.extend(["--memory", "4MiB"]);
        }
        let o = match ranks {
            Some((n, mode)) => {
                args.extend(["--distribute", mode]);
                if mode == "hybrid" {
                    args.extend(["--groups", "2"]);
                }
                mpirun(n, &args)
            }
            None => Command::new(env!("CARGO_BIN_EXE_voxrad"))
                .args(&args)
                .env("NO_COLOR", "1")
                .output()
                .unwrap(),
        };
        ok(&o, &format!("{ranks:?} ranks, memory {memory}"));
        let r = report(out);
        assert!(
            r["seconds"]["direct"].as_f64().unwrap_or(0.0) > 0.0,
            "the direct-light pass did not run: {r}"
        );
        r
    };
    let single = tmp.path().join("single");
    let one = run(&single, None, true);
    let reference = radiosity(&single);
    let memory = tmp.path().join("memory");
    run(&memory, Some((2, "data")), false);
    let in_memory = radiosity(&memory);
    // Without the pass the answer moves by far more than 1e-5: the comparison can fail.
    let plain = tmp.path().join("plain");
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args([
            "solve",
            set,
            "--out",
            plain.to_str().unwrap(),
            "--directions",
            "49",
            "--iterations",
            "3",
            "--direct-directions",
            "0",
        ])
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    ok(&o, "plain");
    let apart = common::worst_relative_difference(&radiosity(&plain), &reference);
    assert!(apart > 1e-3, "the pass changes nothing here: {apart:e}");
    for ranks in 1..=3 {
        let out = tmp.path().join(format!("ranks{ranks}"));
        let r = run(&out, Some((ranks, "data")), true);
        let got = radiosity(&out);
        let worst = common::worst_relative_difference(&got, &in_memory);
        println!("{ranks} ranks with the pass: against in memory {worst:.2e}");
        assert!(got == reference, "{ranks} ranks differ from one process");
        assert!(worst <= 1e-5, "{ranks} ranks: {worst:e}");
        same_energy(&r, &one, 1e-9);
    }
    // The hybrid mode out of core: 2 groups of 1 rank, and of 2 ranks. The groups' light is
    // added across them, another grouping of the same terms: equal to rounding.
    let hybrid = tmp.path().join("hybrid-memory");
    run(&hybrid, Some((2, "hybrid")), false);
    let hybrid_in_memory = radiosity(&hybrid);
    for ranks in [2, 4] {
        let out = tmp.path().join(format!("hybrid{ranks}"));
        let r = run(&out, Some((ranks, "hybrid")), true);
        let got = radiosity(&out);
        let against_one = common::worst_relative_difference(&got, &reference);
        let against_memory = common::worst_relative_difference(&got, &hybrid_in_memory);
        println!(
            "hybrid out of core on {ranks} ranks: against one process out of core \
             {against_one:.2e}, against hybrid in memory {against_memory:.2e}"
        );
        assert_eq!(r["mode"], "hybrid");
        assert_eq!(r["data_distribution"]["groups"], 2, "{r}");
        assert!(against_one <= 1e-5, "{ranks} ranks: {against_one:e}");
        assert!(against_memory <= 1e-5, "{ranks} ranks: {against_memory:e}");
        same_energy(&r, &one, 1e-6);
    }
}

/// The emitted and absorbed power of two reports agree within `tolerance` (relative).
fn same_energy(r: &serde_json::Value, one: &serde_json::Value, tolerance: f64) {
    for what in ["emitted_power", "absorbed_power"] {
        for ch in 0..3 {
            let (a, b) = (
                r["energy"][what][ch].as_f64().unwrap(),
                one["energy"][what][ch].as_f64().unwrap(),
            );
            assert!((a - b).abs() <= tolerance * b.abs(), "{what}: {a} {b}");
        }
    }
}

#[test]
fn each_rank_stays_within_the_budget_while_its_share_is_larger() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    cornell_set(&set, 192, 2);
    let out = tmp.path().join("out");
    let budget = 4u64 << 20;
    let o = mpirun(
        2,
        &[
            "solve",
            set.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--directions",
            "13",
            "--iterations",
            "1",
            "--threads",
            "1",
            "--memory",
            "4MiB",
            "--distribute",
            "data",
            // The bands and the exchange are what this measures (the direct-light pass, run by
            // rank 0 as one process runs it, has its test in `tests/memory_limit.rs`).
            "--direct-directions",
            "0",
        ],
    );
    ok(&o, "2 ranks at 4 MiB");
    let r = report(&out);
    for (rank, (beyond, share)) in rank_memory(&r).into_iter().enumerate() {
        println!(
            "rank {rank}: peak {:.1} MiB beyond its start, share {:.1} MiB, budget 4 MiB",
            beyond as f64 / (1 << 20) as f64,
            share as f64 / (1 << 20) as f64
        );
        // The share would not fit even in the budget and the allowance together.
        assert!(share > budget + ALLOWANCE_BYTES, "{r}");
        assert!(beyond <= budget + ALLOWANCE_BYTES, "rank {rank}: {r}");
    }
}

#[test]
fn what_cannot_work_out_of_core_is_refused_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    cornell_set(&set, 16, 1);
    let set = set.to_str().unwrap();
    let out = tmp.path().join("out");
    let out = out.to_str().unwrap();
    let base = ["solve", set, "--out", out, "--iterations", "1"];
    let cases: [(&[&str], &[&str]); 2] = [
        (
            &["--memory", "16KiB", "--distribute", "data"],
            &["too small", "--memory"],
        ),
        (
            &["--memory", "8MiB", "--distribute", "directions"],
            &["directions", "--distribute data or hybrid"],
        ),
    ];
    for (extra, words) in cases {
        let args: Vec<&str> = base.iter().chain(extra).copied().collect();
        let o = mpirun(2, &args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {err}");
        for w in words {
            assert!(err.contains(w), "{extra:?}: no '{w}' in {err}");
        }
        assert!(!err.contains("panicked"), "{err}");
    }
}

#[test]
fn a_run_stopped_by_sigterm_resumes_on_another_rank_count_to_the_same_bytes() {
    // Resumed on three ranks: rank 0 sends each its slice of the checkpoint.
    stopped_by_sigterm_resumes_to_the_same_bytes(&["--distribute", "data"], 2, 3, PLAIN);
}

/// The same with the Chebyshev semi-iteration running when the signal comes: the checkpoint
/// also holds the radiosity before last, which rank 0 gathers by id and sends back in slices
/// (and which one process out of core reads too).
#[test]
fn a_chebyshev_run_stopped_by_sigterm_resumes_to_the_same_bytes() {
    stopped_by_sigterm_resumes_to_the_same_bytes(&["--distribute", "data"], 2, 3, CHEBYSHEV);
}

/// How the runs of [`stopped_by_sigterm_resumes_to_the_same_bytes`] iterate, and the iteration
/// whose end precedes the one stopped inside: 8 plain iterations, stopped in the third; or to a
/// tolerance with `--chebyshev` (which starts at the third), stopped in the sixth.
type Iterating = (&'static [&'static str], usize);
const PLAIN: Iterating = (&["--iterations", "8"], 2);
const CHEBYSHEV: Iterating = (&["--tolerance", "1e-6", "--chebyshev"], 5);

/// The hybrid mode out of core (2 groups of 2 ranks) stopped by SIGTERM resumes on 2 groups of
/// 1 rank to the bytes of an uninterrupted run: rank 0 sends each group's light so far to that
/// group's ranks, the radiosity to the rank at each place of every group.
#[test]
fn hybrid_out_of_core_stopped_by_sigterm_resumes_to_the_same_bytes() {
    stopped_by_sigterm_resumes_to_the_same_bytes(
        &["--distribute", "hybrid", "--groups", "2"],
        4,
        2,
        PLAIN,
    );
}

/// A solve (Cornell box at 48, 1 MiB per rank) in `mode` on `ranks` ranks, iterating as
/// `iterating` says, stopped by SIGTERM to rank 1 between two steps of an iteration and resumed
/// inside it on `resume_ranks`, ends with the bytes of an uninterrupted run on `ranks`.
fn stopped_by_sigterm_resumes_to_the_same_bytes(
    mode: &[&'static str],
    ranks: usize,
    resume_ranks: usize,
    (iterating, completed): Iterating,
) {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    cornell_set(&set, 48, 2);
    let set = set.to_str().unwrap();
    let args = |out: &Path, extra: &[&'static str]| -> Vec<String> {
        [
            "solve",
            set,
            "--out",
            out.to_str().unwrap(),
            "--directions",
            "49",
            "--threads",
            "1",
            "--memory",
            "1MiB",
        ]
        .iter()
        .chain(iterating)
        .chain(mode)
        .chain(extra)
        .map(|s| s.to_string())
        .collect()
    };
    let reference = tmp.path().join("reference");
    let a = args(&reference, &[]);
    ok(
        &mpirun(ranks, &a.iter().map(String::as_str).collect::<Vec<_>>()),
        "reference",
    );

    // Stopped between two steps of an iteration (again if the signal came at a boundary):
    // the checkpoint holds every group's light so far, and the resume goes on from there.
    for attempt in 1..=4 {
        let out = tmp.path().join(format!("out{attempt}"));
        let log = tmp.path().join(format!("run{attempt}.log"));
        let a = args(&out, &["--checkpoint-every", "0"]);
        let mut child = Child::spawn(
            mpirun_command(ranks, &a.iter().map(String::as_str).collect::<Vec<_>>()),
            &log,
        );
        wait_for_a_checkpoint_inside(&mut child, &log, completed);
        common::mpi::signal_rank(child.pid(), 1, libc::SIGTERM);
        let status = child.wait_at_most(HANG_LIMIT);
        let text = child.log();
        assert_eq!(status.code(), Some(3), "{}:\n{text}", describe(&status));
        let path = voxrad::checkpoint::path_in(&out);
        let saved = voxrad::checkpoint::CheckpointFile::open(&path)
            .unwrap_or_else(|e| panic!("no checkpoint ({e}):\n{text}"));
        let Some(done) = saved.header.state.within else {
            let said = text
                .lines()
                .filter(|l| l.contains("interrupted"))
                .collect::<Vec<_>>();
            println!("attempt {attempt}: stopped at an iteration boundary ({said:?}), again");
            continue;
        };
        println!(
            "attempt {attempt}: stopped {done} steps into iteration {}",
            saved.header.state.iteration + 1
        );
        assert_eq!(
            saved.header.state.extrapolation.chebyshev.is_some(),
            iterating.contains(&"--chebyshev"),
            "the checkpoint holds the semi-iteration's state if it runs"
        );
        if mode.contains(&"data") {
            // One process on a copy: the layout by groups is not its own, so it starts that
            // iteration again, from the same radiosity: the same bytes (the data mode out of
            // core is the one-process out-of-core solve bit for bit).
            let copy = tmp.path().join(format!("one{attempt}"));
            common::files::copy_dir(&out, &copy);
            let a: Vec<String> = args(&copy, &["--resume"])
                .into_iter()
                .filter(|a| !mode.contains(&a.as_str()))
                .collect();
            let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
                .args(&a)
                .output()
                .unwrap();
            ok(&o, "one process resuming");
            let text = String::from_utf8_lossy(&o.stderr);
            assert!(text.contains("starts from its beginning"), "{text}");
            assert!(
                radiosity(&copy) == radiosity(&reference),
                "one process resumed to other results"
            );
        }
        let a = args(&out, &["--resume"]);
        let o = mpirun(
            resume_ranks,
            &a.iter().map(String::as_str).collect::<Vec<_>>(),
        );
        ok(&o, "resume");
        let text = String::from_utf8_lossy(&o.stderr);
        assert!(text.contains("resumed from a checkpoint"), "{text}");
        assert!(
            text.contains("continuing inside an iteration")
                && text.contains(&format!("within={done}")),
            "{text}"
        );
        assert!(
            radiosity(&out) == radiosity(&reference),
            "resumed results differ"
        );
        assert!(!path.exists());
        return;
    }
    panic!("four SIGTERMs, none inside an iteration");
}

/// With `--chebyshev` the data and hybrid modes out of core give the one-process out-of-core
/// bytes: each record carries the radiosity before last through every exchange.
#[test]
fn chebyshev_out_of_core_gives_the_one_process_bytes_in_the_data_and_hybrid_modes() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    cornell_set(&set, 40, 2);
    let args = |out: &Path| -> Vec<String> {
        [
            "solve",
            set.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--directions",
            "49",
            "--tolerance",
            "1e-6",
            "--chebyshev",
            "--threads",
            "1",
            "--memory",
            "2MiB",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let one = tmp.path().join("one");
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(args(&one))
        .output()
        .unwrap();
    ok(&o, "one process");
    let reference = report(&one);
    let ran = |r: &serde_json::Value| {
        r["effects"]
            .as_array()
            .and_then(|e| e.iter().find(|e| e["name"] == "Chebyshev semi-iteration"))
            .map(|e| e["simulated"] == true)
    };
    assert_eq!(ran(&reference), Some(true), "{reference}");
    for (mode, ranks) in [
        (&["--distribute", "data"][..], 2),
        (&["--distribute", "hybrid", "--groups", "2"][..], 4),
    ] {
        let out = tmp.path().join(format!("{}{ranks}", mode[1]));
        let mut a = args(&out);
        a.extend(mode.iter().map(|s| s.to_string()));
        ok(
            &mpirun(ranks, &a.iter().map(String::as_str).collect::<Vec<_>>()),
            mode[1],
        );
        let r = report(&out);
        assert_eq!(ran(&r), Some(true), "{r}");
        assert_eq!(r["iterations"], reference["iterations"], "{}", mode[1]);
        assert!(
            radiosity(&out) == radiosity(&one),
            "{}: other results than one process",
            mode[1]
        );
    }
}

/// The data mode out of core simulates what the one-process solvers do: a grey furnace
/// (`rho = 0.99`, about 900 plain iterations to 1e-4) is solved in one channel with the tail
/// extrapolated, lands on `E / (1 - rho)` in a few iterations, and gives the one-process
/// out-of-core bytes at 2 ranks; the report lists the effects.
#[test]
fn grey_furnace_is_extrapolated_as_in_one_process() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("set");
    let (e, rho) = (1.0, 0.99);
    let set = voxelize(&common::furnace(e, rho), GridSpec::Resolution(16)).unwrap();
    common::write_shard_set(&set, &dir, 2);
    let dir = dir.to_str().unwrap();
    let args = |out: &Path| -> Vec<String> {
        [
            "solve",
            dir,
            "--out",
            out.to_str().unwrap(),
            "--directions",
            "49",
            "--tolerance",
            "1e-4",
            "--direct-directions",
            "0",
            "--memory",
            "512KiB",
            "--threads",
            "1",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let single = tmp.path().join("single");
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .args(args(&single))
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    ok(&o, "one process out of core");
    let ranks = tmp.path().join("ranks");
    let mut a = args(&ranks);
    a.extend(["--distribute".to_string(), "data".to_string()]);
    let a: Vec<&str> = a.iter().map(|s| s.as_str()).collect();
    let o = mpirun(2, &a);
    ok(&o, "data mode out of core, 2 ranks");
    let (one, two) = (radiosity(&single), radiosity(&ranks));
    assert!(one == two, "2 ranks differ from one process");
    let expected = e / (1.0 - rho);
    let mut worst = 0.0f64;
    for (s, b) in set.surfels.iter().zip(&one) {
        for &v in &b[common::inner_side(s, &set)] {
            worst = worst.max((v as f64 - expected).abs() / expected);
        }
    }
    let r = report(&ranks);
    let iterations = r["iterations"].as_u64().unwrap();
    println!(
        "furnace rho {rho}, data mode out of core: {iterations} iterations, worst {worst:.2e}"
    );
    assert!(worst < 1e-4, "worst error {worst}");
    assert!(iterations <= 10, "{iterations} iterations");
    let effects = r["effects"].to_string();
    assert!(effects.contains("one channel"), "{effects}");
    assert!(effects.contains("extrapolations"), "{effects}");
}

/// `tools/slurm/solve.sbatch`, the recipe for a scene that fits no node, run as far as one
/// machine can: `mpirun` for `srun` (2 ranks), each rank's `--work-dir` made its own directory
/// (a node's local disk, at the same path on every node), a "time limit" signal (SIGTERM to rank
/// 1 once a checkpoint inside an iteration is written) after which the script asks to be
/// requeued, and the requeued run on other "nodes" (another work directory) resuming to the
/// bytes of an uninterrupted run; nothing is left on the nodes' disks or in the out directory.
#[test]
fn the_slurm_recipe_requeues_and_resumes_on_other_nodes_to_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    cornell_set(&set, 48, 2);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/slurm/solve.sbatch");
    // Stands in for nodes: `--work-dir W` becomes `W/node<rank>` for each rank.
    let node = tmp.path().join("node.sh");
    std::fs::write(
        &node,
        "#!/bin/sh\ncount=$#\ntake=0\nfor a in \"$@\"; do\n  if [ \"$take\" = 1 ]; then \
         a=\"$a/node$OMPI_COMM_WORLD_RANK\"; fi\n  if [ \"$a\" = \"--work-dir\" ]; then take=1; \
         else take=0; fi\n  set -- \"$@\" \"$a\"\ndone\nshift \"$count\"\nexec \"$@\"\n",
    )
    .unwrap();
    let requeue = tmp.path().join("requeue.sh");
    std::fs::write(
        &requeue,
        "#!/bin/sh\necho \"$1\" > \"$(dirname \"$0\")/requeued\"\n",
    )
    .unwrap();
    for file in [&node, &requeue] {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(file, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    let mut launch = common::mpi::launcher(2);
    launch.push(node.display().to_string());
    let out = tmp.path().join("out");
    let job = |work: &Path| {
        let mut c = Command::new("bash");
        c.arg(&script)
            .env("SHARDS", &set)
            .env("OUT", &out)
            .env("MEMORY", "1MiB")
            .env("WORK", work)
            .env("DIRECTIONS", "49")
            .env("CHECKPOINT_EVERY", "0")
            .env("EXTRA", "--iterations 8")
            .env("VOXRAD", env!("CARGO_BIN_EXE_voxrad"))
            .env("LAUNCH", launch.join(" "))
            .env("REQUEUE", &requeue)
            .env("SLURM_JOB_ID", "4242")
            .env("SLURM_CPUS_PER_TASK", "1")
            .envs(common::mpi::AS_ROOT);
        c
    };
    // The uninterrupted answer.
    let reference = tmp.path().join("reference");
    let o = mpirun(
        2,
        &[
            "solve",
            set.to_str().unwrap(),
            "--out",
            reference.to_str().unwrap(),
            "--distribute",
            "data",
            "--memory",
            "1MiB",
            "--directions",
            "49",
            "--iterations",
            "8",
            "--threads",
            "1",
        ],
    );
    ok(&o, "reference");
    // The first run, stopped inside its third iteration as the time limit's signal would.
    let first = tmp.path().join("first-nodes");
    let log = tmp.path().join("job1.log");
    let mut child = Child::spawn(job(&first), &log);
    wait_for_a_checkpoint_inside(&mut child, &log, 2);
    // Both ranks ran in their own "node" directory.
    for rank in 0..2 {
        let dir = first.join(format!("node{rank}"));
        assert!(dir.is_dir(), "no work directory {}", dir.display());
    }
    let mpirun_pid = *common::process::children_of(child.pid())
        .first()
        .expect("mpirun under the job script");
    common::mpi::signal_rank(mpirun_pid, 1, libc::SIGTERM);
    let status = child.wait_at_most(HANG_LIMIT);
    let text = child.log();
    assert_eq!(status.code(), Some(3), "{}:\n{text}", describe(&status));
    assert!(text.contains("starting from the beginning"), "{text}");
    assert_eq!(
        std::fs::read_to_string(tmp.path().join("requeued"))
            .unwrap_or_default()
            .trim(),
        "4242",
        "the job did not ask to be requeued:\n{}",
        child.log()
    );
    assert!(
        voxrad::checkpoint::path_in(&out).exists(),
        "{}",
        child.log()
    );
    // The requeued job, on other nodes: it goes on from the checkpoint to the same bytes.
    let second = tmp.path().join("second-nodes");
    let log = tmp.path().join("job2.log");
    let mut child = Child::spawn(job(&second), &log);
    let status = child.wait_at_most(HANG_LIMIT);
    let text = child.log();
    assert!(status.success(), "{}:\n{text}", describe(&status));
    assert!(
        text.contains("continuing inside an iteration from the checkpoint"),
        "{text}"
    );
    assert!(
        radiosity(&out) == radiosity(&reference),
        "the requeued run differs from an uninterrupted one:\n{text}"
    );
    let names = |dir: &Path| -> Vec<String> {
        walk(dir)
            .into_iter()
            .filter(|p| p.is_file())
            .map(|p| p.display().to_string())
            .collect()
    };
    for nodes in [&first, &second] {
        assert!(
            names(nodes).is_empty(),
            "left on the nodes: {:?}",
            names(nodes)
        );
    }
    let left: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".voxrad") || n.starts_with("checkpoint"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

/// Every path under `dir` (directories and files), depth first.
fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut all = Vec::new();
    if let Ok(entries) = std::fs::read_dir(dir) {
        for e in entries.flatten() {
            let p = e.path();
            all.push(p.clone());
            if p.is_dir() {
                all.extend(walk(&p));
            }
        }
    }
    all
}

/// Shards staged on each node's own disk: a rank other than 0 reads only the shards its slice
/// of the set touches (its part, and the records at its ends that decide where its voxels
/// begin and end), so its node needs neither the whole set nor the scene's materials pass that
/// every rank used to make (rank 0 makes it and sends it). With 4 shards on 2 ranks, rank 1's
/// node holds the manifest and shards 1 to 3: the one-process answer to the bit. Without
/// shard 1, which rank 1's first voxel may begin in, it stops with a message naming the file.
/// A set from `voxrad-shard convert --ranks 2` is cut where the slices are: rank 1's node holds
/// shard 1 alone, and the answer is the one process's.
#[test]
fn a_rank_needs_only_the_shards_of_its_slice_on_its_node() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    cornell_set(&set, 32, 4);
    let single = tmp.path().join("single");
    solve_staged_on_one_process(&set, &single);
    let manifest = voxrad::storage::Manifest::read_dir(&set).unwrap();
    let shard_file = |k: usize| manifest.shards[k].file.clone();
    // Shards cut by count: rank 1's slice begins in shard 1 and ends in shard 2 or 3.
    let nodes = tmp.path().join("nodes");
    let out = tmp.path().join("staged");
    ok(
        &run_staged(&set, &nodes, &[&[0, 1, 2, 3], &[1, 2, 3]], &out),
        "2 ranks, shards staged per node",
    );
    assert!(
        radiosity(&out) == radiosity(&single),
        "staged shards change bits"
    );
    // Without shard 1 on rank 1's node.
    let o = run_staged(
        &set,
        &tmp.path().join("nodes2"),
        &[&[0, 1, 2, 3], &[2, 3]],
        &tmp.path().join("missing"),
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(
        stderr.contains(&shard_file(1)) && stderr.contains("is not on this node"),
        "{stderr}"
    );
    // A set cut by `voxrad-shard convert --ranks 2` (at voxel boundaries, one shard per rank):
    // rank 1's node holds shard 1 alone.
    let cut = tmp.path().join("cut");
    let obj = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad-shard"))
        .arg("convert")
        .arg(&obj)
        .arg("--out")
        .arg(&cut)
        .args(["--resolution", "32", "--ranks", "2"])
        .output()
        .unwrap();
    ok(&o, "voxrad-shard convert --ranks 2");
    let cut_manifest = voxrad::storage::Manifest::read_dir(&cut).unwrap();
    assert!(cut_manifest.voxel_aligned);
    let single_cut = tmp.path().join("single_cut");
    solve_staged_on_one_process(&cut, &single_cut);
    let out = tmp.path().join("one_each");
    ok(
        &run_staged(&cut, &tmp.path().join("nodes3"), &[&[0, 1], &[1]], &out),
        "2 ranks, one shard each",
    );
    assert!(
        radiosity(&out) == radiosity(&single_cut),
        "one shard per rank changes bits"
    );
}

/// The options of the staged runs: small, quick.
const STAGED_ARGS: [&str; 10] = [
    "--memory",
    "1MiB",
    "--directions",
    "49",
    "--iterations",
    "2",
    "--direct-directions",
    "0",
    "--threads",
    "1",
];

/// Solves `set` on one process into `out` with [`STAGED_ARGS`].
fn solve_staged_on_one_process(set: &Path, out: &Path) {
    let o = Command::new(env!("CARGO_BIN_EXE_voxrad"))
        .arg("solve")
        .arg(set)
        .arg("--out")
        .arg(out)
        .args(STAGED_ARGS)
        .output()
        .unwrap();
    ok(&o, &format!("one process, {}", set.display()));
}

/// Copies the manifest of `set` and, for each rank `r`, the shards `shards[r]` into
/// `nodes/node{r}/set` (the rank's "node-local disk"), then solves in the data mode on 2 ranks,
/// each rank given its own node's copy at one path as on a cluster.
fn run_staged(set: &Path, nodes: &Path, shards: &[&[usize]], out: &Path) -> Output {
    let manifest = voxrad::storage::Manifest::read_dir(set).unwrap();
    for (rank, list) in shards.iter().enumerate() {
        let dir = nodes.join(format!("node{rank}/set"));
        std::fs::create_dir_all(&dir).unwrap();
        let copy = |name: &str| std::fs::copy(set.join(name), dir.join(name)).unwrap();
        copy(voxrad::storage::MANIFEST_FILE);
        for &k in *list {
            copy(&manifest.shards[k].file);
        }
    }
    let pick = nodes.join("pick.sh");
    std::fs::write(
        &pick,
        format!(
            "#!/bin/sh\nbin=$1\nshift\nexec \"$bin\" solve \"{}/node$OMPI_COMM_WORLD_RANK/set\" \
             \"$@\"\n",
            nodes.display()
        ),
    )
    .unwrap();
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&pick, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    let launcher = common::mpi::launcher(2);
    Command::new(&launcher[0])
        .args(&launcher[1..])
        .arg(&pick)
        .arg(env!("CARGO_BIN_EXE_voxrad"))
        .arg("--out")
        .arg(out)
        .args(STAGED_ARGS)
        .args(["--distribute", "data"])
        .envs(common::mpi::AS_ROOT)
        .env("NO_COLOR", "1")
        .output()
        .unwrap()
}
