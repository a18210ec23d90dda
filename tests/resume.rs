//! Checkpoints and resume: a solve killed at any moment and resumed with `--resume` as often as
//! it takes gives the same bytes as one that was never interrupted; SIGTERM and SIGINT stop a
//! solve with a checkpoint and exit status 3; a damaged or foreign checkpoint is refused with
//! exit status 2 and loses nothing. In memory and out of core, through the real binary; and,
//! through the library, a resume from every single iteration boundary.

mod common;

use common::process::{
    describe, resumed_and_inside, Child, Ended, Rng, CONTINUED_INSIDE, HANG_LIMIT,
};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};
use voxrad::checkpoint::{self, CheckpointFile, Identity, Saver};
use voxrad::distribute::SingleProcess;
use voxrad::geometry::directions::DirectionSet;
use voxrad::outcore::{solve_out_of_core_checkpointed, InMemorySource, OocCheckpoints};
use voxrad::solve::direct::DirectPass;
use voxrad::solve::jacobi::{solve_checkpointed, solve_with, Checkpoints};
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn cornell() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples/cornell_box.obj")
        .display()
        .to_string()
}

/// `voxrad solve` of the Cornell box into `out`, with the default preset's tail extrapolation
/// and stopping rule (so the extrapolation and stopping state cross the checkpoints), a
/// checkpoint after every iteration; an option in `extra` replaces the same one here.
fn solve_command(out: &Path, extra: &[&str]) -> Command {
    let base = [
        ("--resolution", "32"),
        ("--directions", "200"),
        ("--tolerance", "1e-6"),
        ("--threads", "2"),
        ("--image-size", "64x48"),
        ("--checkpoint-every", "0"),
    ];
    let mut c = Command::new(env!("CARGO_BIN_EXE_voxrad"));
    c.args(["solve", &cornell(), "--out"]).arg(out);
    for (flag, value) in base {
        if !extra.contains(&flag) {
            c.args([flag, value]);
        }
    }
    c.args(extra).env_remove("RUST_LOG");
    c
}

fn results(out: &Path) -> Vec<u8> {
    std::fs::read(out.join("surfels.bin")).expect("results file")
}

fn report(out: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap()
}

/// Runs to the end (at most two minutes); panics unless it succeeds. Returns its log and time.
fn run_to_end(command: Command, log: &Path) -> (String, f64) {
    let mut child = Child::spawn(command, log);
    let status = child.wait_at_most(HANG_LIMIT);
    assert!(status.success(), "{}:\n{}", describe(&status), child.log());
    (child.log(), child.started.elapsed().as_secs_f64())
}

/// Only the finished outputs are left: no checkpoint, no half-written file, no work directory.
fn assert_clean(out: &Path) {
    for entry in std::fs::read_dir(out).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        assert!(
            common::cli::SOLVE_OUTPUTS.contains(&name.as_str()),
            "{} left in {}",
            name,
            out.display()
        );
    }
}

/// A scene whose single iteration is long: 2,000 directions on the Cornell box at resolution 16
/// (1,777 surfels, about 0.25 s an iteration on two threads).
const LONG_ITERATIONS: [&str; 4] = ["--resolution", "16", "--directions", "2000"];

/// Kills `voxrad solve --resume` with SIGKILL at random moments (the first after a checkpoint
/// exists, so at least one run really resumes), `kills` times unless it finishes first, then lets
/// it finish; the results must be the uninterrupted run's, byte for byte. A run is killed after
/// a random part of the uninterrupted run's time, up to `longest`. Returns how many runs
/// continued inside an iteration (from a mid-iteration checkpoint).
fn killed_and_resumed(extra: &[&str], seed: u64, kills: usize, longest: f64) -> usize {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    let (_, seconds) = run_to_end(
        solve_command(&reference, extra),
        &tmp.path().join("reference.log"),
    );
    let out = tmp.path().join("out");
    let mut rng = Rng::seeded(seed);
    let (mut killed, mut resumed, mut runs, mut inside) = (0, 0, 0, 0);
    let started = Instant::now();
    loop {
        runs += 1;
        let log = tmp.path().join(format!("run{runs}.log"));
        let mut child = Child::spawn(solve_command(&out, &[extra, &["--resume"]].concat()), &log);
        let ended = if killed < kills {
            if killed == 0 {
                let ckpt = checkpoint::path_in(&out);
                child.wait_for(HANG_LIMIT, || ckpt.exists());
            }
            // Short enough that several kills land before the end: some during start-up or a
            // checkpoint's writing, most in mid-iteration.
            let delay = rng.uniform(0.02, longest) * seconds;
            child.run_or_kill_after(Duration::from_secs_f64(delay))
        } else {
            Ended::Exited(child.wait_at_most(HANG_LIMIT))
        };
        let text = child.log();
        let (was_resumed, was_inside) = resumed_and_inside(&text);
        if runs == 1 {
            assert!(
                text.contains("no checkpoint") && text.contains("starting from the beginning"),
                "{text}"
            );
        }
        resumed += was_resumed as usize;
        inside += was_inside as usize;
        match ended {
            Ended::Killed => {
                killed += 1;
                let at = text
                    .lines()
                    .rev()
                    .find(|l| l.contains("checkpoint written"))
                    .and_then(|l| l.split("iteration=").nth(1))
                    .map(|r| r.split(" path").next().unwrap_or(r))
                    .unwrap_or("none");
                println!(
                    "run {runs}: killed after {:.2} s (last checkpoint written in this run: \
                     iteration {at})",
                    child.started.elapsed().as_secs_f64()
                );
            }
            Ended::Exited(status) => {
                assert!(status.success(), "{}:\n{text}", describe(&status));
                println!(
                    "run {runs}: finished in {:.2} s",
                    child.started.elapsed().as_secs_f64()
                );
                break;
            }
        }
    }
    println!(
        "{killed} kills, {resumed} resumed runs ({inside} inside an iteration), {runs} runs in \
         {:.1} s (uninterrupted: {seconds:.1} s)",
        started.elapsed().as_secs_f64()
    );
    assert!(
        killed >= 1 && resumed >= 1,
        "{killed} kills, {resumed} resumes"
    );
    assert!(
        results(&out) == results(&reference),
        "the resumed results differ from the uninterrupted ones"
    );
    let (a, b) = (report(&out), report(&reference));
    assert_eq!(a["iterations"], b["iterations"]);
    assert_eq!(a["residual"], b["residual"]);
    assert_eq!(a["energy"], b["energy"]);
    assert_clean(&out);
    inside
}

#[test]
fn sigkill_at_random_moments_then_resume_gives_the_same_bytes_in_memory() {
    killed_and_resumed(&[], 0x5eed_0001, 6, 0.4);
}

#[test]
fn sigkill_inside_long_iterations_then_resume_gives_the_same_bytes() {
    // A checkpoint every 50 ms: several inside each iteration, so most kills resume from one.
    let every = ["--checkpoint-every", "0.05"];
    // Short runs, so that most kills land in the first iterations.
    let options = [&LONG_ITERATIONS[..], &every].concat();
    let inside = killed_and_resumed(&options, 0x5eed_0004, 8, 0.15);
    assert!(inside >= 1, "no run continued inside an iteration");
}

/// The same through the binary with `--chebyshev`, checkpoints inside the iterations too: its
/// checkpoints hold the radiosity before last beside the radiosity.
#[test]
fn sigkill_then_resume_gives_the_same_bytes_with_chebyshev() {
    let every = ["--checkpoint-every", "0.05", "--chebyshev"];
    let options = [&LONG_ITERATIONS[..], &every].concat();
    killed_and_resumed(&options, 0x5eed_0005, 8, 0.15);
    // The semi-iteration did run in this solve (the report's effects say so).
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    run_to_end(solve_command(&out, &options), &tmp.path().join("log"));
    let effects = report(&out)["effects"].as_array().unwrap().clone();
    let effect = effects
        .iter()
        .find(|e| e["name"] == "Chebyshev semi-iteration")
        .expect("the effect is listed");
    assert_eq!(effect["simulated"], true, "{effect}");
}

#[test]
fn sigkill_at_random_moments_then_resume_gives_the_same_bytes_out_of_core() {
    // 1 MiB for about 6,700 surfels: every array in files, several bands per direction.
    killed_and_resumed(&["--memory", "1MiB"], 0x5eed_0002, 5, 0.4);
}

/// The same with `--chebyshev`, checkpoints inside the main axes too.
#[test]
fn sigkill_then_resume_gives_the_same_bytes_out_of_core_with_chebyshev() {
    let options = [
        "--memory",
        "1MiB",
        "--chebyshev",
        "--checkpoint-every",
        "0.05",
    ];
    killed_and_resumed(&options, 0x5eed_0006, 6, 0.3);
}

/// Starts a solve into `out`, sends `signal` once `ready(log)` holds, and expects exit status 3
/// with a message naming the checkpoint (or, `in_setup`, possibly one saying that the iterations
/// had not started); returns the log.
fn stopped_by(
    signal: i32,
    out: &Path,
    extra: &[&str],
    log: &Path,
    in_setup: bool,
    ready: impl Fn(&str, &Path) -> bool,
) -> String {
    let mut child = Child::spawn(solve_command(out, extra), log);
    let seen = child.wait_for(HANG_LIMIT, || ready(&child_log(log), out));
    assert!(seen, "never ready:\n{}", child_log(log));
    // SAFETY: kill(2) on our own child.
    unsafe {
        libc::kill(child.pid(), signal);
    }
    let status = child.wait_at_most(HANG_LIMIT);
    let text = child.log();
    assert_eq!(status.code(), Some(3), "{}:\n{text}", describe(&status));
    let name = voxrad::interrupt::name(signal);
    let ckpt = checkpoint::path_in(out);
    assert!(
        text.contains(&format!("interrupted by {name}")) && text.contains("--resume"),
        "{text}"
    );
    assert!(!text.contains("panicked"), "{text}");
    if in_setup && text.contains("before the iterations started") {
        assert!(!ckpt.exists(), "{text}");
    } else {
        assert!(
            text.contains(&format!("checkpoint at {}", ckpt.display())),
            "{text}"
        );
        assert!(ckpt.exists());
    }
    text
}

fn child_log(log: &Path) -> String {
    std::fs::read_to_string(log).unwrap_or_default()
}

/// Resumes each stopped solve `(out, extra options)` and compares with `reference`.
fn resume_each(stopped: &[(&Path, &[&str])], reference: &Path) {
    for (dir, extra) in stopped {
        let extra = [*extra, &["--resume"]].concat();
        let had = checkpoint::path_in(dir).exists();
        let (text, _) = run_to_end(
            solve_command(dir, &extra),
            &dir.with_extension("resume.log"),
        );
        assert_eq!(text.contains("resumed from a checkpoint"), had, "{text}");
        assert!(results(dir) == results(reference), "{}", dir.display());
        assert_eq!(report(dir)["resumed_from_iteration"].is_u64(), had);
        assert_clean(dir);
    }
}

/// Options under which only a stop signal writes a checkpoint (none is due in a short run).
const ONLY_ON_SIGNAL: [&str; 2] = ["--checkpoint-every", "1000"];

/// A solve into `tmp/name` (options `extra`, checkpoints only on the signal) stopped by SIGTERM
/// inside its second iteration (0.1 s after the first ended); retried (a few times at most) if
/// the signal came between two iterations instead. Returns the out directory and the
/// checkpoint's position.
fn stopped_inside_an_iteration(tmp: &Path, name: &str, extra: &[&str]) -> (PathBuf, u64) {
    let seen = std::cell::Cell::new(None::<Instant>);
    stopped_inside_when(tmp, name, &[extra, &ONLY_ON_SIGNAL].concat(), |log| {
        if seen.get().is_none() && log.contains("iteration=1 ") {
            seen.set(Some(Instant::now()));
        }
        seen.get()
            .is_some_and(|t| t.elapsed() > Duration::from_millis(100))
    })
}

/// Solves into `tmp/name` with `extra` and sends SIGTERM once `ready(log)`, until (four times at
/// most) the checkpoint it leaves is inside an iteration; returns the out directory and the
/// checkpoint's position.
fn stopped_inside_when(
    tmp: &Path,
    name: &str,
    extra: &[&str],
    ready: impl Fn(&str) -> bool,
) -> (PathBuf, u64) {
    for attempt in 1..=4 {
        let out = tmp.join(format!("{name}{attempt}"));
        let log = tmp.join(format!("{name}{attempt}.log"));
        let text = stopped_by(libc::SIGTERM, &out, extra, &log, false, |log, _| ready(log));
        let saved = CheckpointFile::open(&checkpoint::path_in(&out)).unwrap();
        if let Some(done) = saved.header.state.within {
            assert!(text.contains("directions of the next"), "{text}");
            println!("{}", text.lines().last().unwrap_or(""));
            return (out, done);
        }
        println!("attempt {attempt}: stopped between two iterations, again");
    }
    panic!("four SIGTERMs, none inside an iteration");
}

#[test]
fn sigterm_and_sigint_stop_an_in_memory_solve_with_a_checkpoint_and_exit_status_3() {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    run_to_end(solve_command(&reference, &[]), &tmp.path().join("ref.log"));

    // SIGTERM in mid-solve, once a few iterations are done: the checkpoint is written on it.
    let term = tmp.path().join("term");
    let text = stopped_by(
        libc::SIGTERM,
        &term,
        &ONLY_ON_SIGNAL,
        &tmp.path().join("term.log"),
        false,
        |log, _| log.contains("iteration=3 "),
    );
    println!("{}", text.lines().last().unwrap_or(""));
    assert_eq!(text.matches("checkpoint written").count(), 1, "{text}");
    let saved = CheckpointFile::open(&checkpoint::path_in(&term)).unwrap();
    assert!(saved.header.state.iteration >= 3);

    // SIGINT just before the iterations start: at once, or with the checkpoint of iteration 0.
    let int = tmp.path().join("int");
    let text = stopped_by(
        libc::SIGINT,
        &int,
        &ONLY_ON_SIGNAL,
        &tmp.path().join("int.log"),
        true,
        |log, _| log.contains("voxelized"),
    );
    println!("{}", text.lines().last().unwrap_or(""));
    resume_each(&[(&term, &[]), (&int, &[])], &reference);
}

#[test]
fn sigterm_inside_an_iteration_saves_its_partial_sums_and_resumes_to_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    run_to_end(
        solve_command(&reference, &LONG_ITERATIONS),
        &tmp.path().join("ref.log"),
    );
    let (out, done) = stopped_inside_an_iteration(tmp.path(), "term", &LONG_ITERATIONS);
    // After the first iteration every direction's links are kept and replayed in blocks: the
    // stop waited for a block's end.
    let saved = CheckpointFile::open(&checkpoint::path_in(&out)).unwrap();
    if saved.header.state.iteration >= 1 {
        assert_eq!(
            done % voxrad::solve::kept_links::BLOCK_STEPS as u64,
            0,
            "{done}"
        );
    }
    let (text, _) = run_to_end(
        solve_command(&out, &[&LONG_ITERATIONS[..], &["--resume"]].concat()),
        &tmp.path().join("resume.log"),
    );
    assert!(
        text.contains(CONTINUED_INSIDE) && text.contains(&format!("within={done}")),
        "{text}"
    );
    assert!(results(&out) == results(&reference));
    assert_eq!(report(&out)["energy"], report(&reference)["energy"]);
    assert_clean(&out);
}

/// Out of core with main axes long enough to stop inside: 300 directions (about 100 per axis),
/// every array in files; `extra` adds the checkpoint options.
fn long_axes<'a>(extra: &[&'a str]) -> Vec<&'a str> {
    // Every iteration searches again (`--links-disk 0`): replaying kept links, the iterations
    // after the first took a few hundred milliseconds, and on a loaded machine the signal meant
    // for the second came after the solve had ended. Resuming with links kept out of core is
    // tested by `sigkill_at_random_moments_then_resume_gives_the_same_bytes_out_of_core`.
    [
        &[
            "--memory",
            "1MiB",
            "--directions",
            "300",
            "--links-disk",
            "0",
        ][..],
        extra,
    ]
    .concat()
}

/// The directions done in an iteration at the end of each main axis of the checkpoint's run (in
/// the order the out-of-core solver walks the checkpoint's iteration): where the checkpoints
/// before in-axis ones could only be.
fn axis_ends(saved: &CheckpointFile) -> Vec<u64> {
    // (The identity's direction checksum also covers the direct-light pass's directions.)
    let directions = DirectionSet::with_count(300);
    assert_eq!(directions.len() as u32, saved.header.identity.directions);
    let by_axis = voxrad::outcore::solver::walk_by_axis(&directions);
    let iteration = saved.header.state.iteration as usize + 1;
    voxrad::outcore::solver::walk_of_iteration(&by_axis, iteration)
        .iter()
        .scan(0, |done, (_, axis)| {
            *done += axis.len() as u64;
            Some(*done)
        })
        .collect()
}

/// Whether the checkpoint in `out` is inside a main axis (some of its directions done, not all),
/// with the light of that axis; returns its position.
fn inside_a_main_axis(out: &Path) -> Option<u64> {
    let saved = CheckpointFile::open(&checkpoint::path_in(out)).ok()?;
    let done = saved.header.state.within?;
    let ends = axis_ends(&saved);
    println!(
        "checkpoint {done} directions into iteration {} (axes end at {ends:?})",
        saved.header.state.iteration + 1
    );
    // The out-of-core solver keeps its light in f32, and its checkpoints keep it so: the
    // radiosity, then the sum of the axes done and the axis's light, 24 bytes a surfel each.
    assert!(saved.header.state.sums_in_f32);
    let surfels = saved.header.identity.surfels;
    let payload =
        surfels * 24 * (saved.header.radiosity_arrays() + saved.header.partial_arrays()) as u64;
    let len = std::fs::metadata(&saved.path).unwrap().len();
    assert!(
        len > payload && len < payload + 4096,
        "{len} bytes for a payload of {payload}"
    );
    (!ends.contains(&done) && saved.header.state.axis_in_progress).then_some(done)
}

/// Resumes the solve in `out` (options `options`) and checks that it continued at position
/// `done` and gave `reference`'s bytes.
fn resumed_inside_to_the_same_bytes(out: &Path, options: &[&str], done: u64, reference: &Path) {
    let (text, _) = run_to_end(
        solve_command(out, &[options, &["--resume"]].concat()),
        &out.with_extension("resume.log"),
    );
    assert!(
        text.contains(CONTINUED_INSIDE)
            && text.contains(&format!("within={done}"))
            && text.contains("axis_directions="),
        "{text}"
    );
    assert!(results(out) == results(reference));
    assert_eq!(report(out)["energy"], report(reference)["energy"]);
    assert_clean(out);
}

#[test]
fn out_of_core_stopped_inside_a_main_axis_resumes_to_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    // (`stopped_inside_an_iteration` adds the options under which only the signal saves.)
    let options = long_axes(&[]);
    let reference = tmp.path().join("reference");
    run_to_end(
        solve_command(&reference, &options),
        &tmp.path().join("ref.log"),
    );
    // SIGTERM inside the second iteration, at some direction of an axis: the light of the
    // directions done is kept (before, only the axes done were, so the position was an axis's
    // end). Again if it came at an axis's first direction or between two iterations.
    for attempt in 1..=4 {
        let name = format!("term{attempt}");
        let (out, done) = stopped_inside_an_iteration(tmp.path(), &name, &options);
        if inside_a_main_axis(&out) == Some(done) {
            resumed_inside_to_the_same_bytes(&out, &options, done, &reference);
            return;
        }
        println!("attempt {attempt}: stopped at the end of a main axis, again");
    }
    panic!("four SIGTERMs, none inside a main axis");
}

#[test]
fn out_of_core_due_checkpoint_inside_a_main_axis_resumes_to_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    // A checkpoint due at every direction (spaced by its writing time, see `Saver::due_within`).
    let options = long_axes(&["--checkpoint-every", "0"]);
    let reference = tmp.path().join("reference");
    run_to_end(
        solve_command(&reference, &options),
        &tmp.path().join("ref.log"),
    );
    for attempt in 1..=4 {
        let out = tmp.path().join(format!("due{attempt}"));
        let log = tmp.path().join(format!("due{attempt}.log"));
        let mut child = Child::spawn(solve_command(&out, &options), &log);
        // Once the second iteration has written a checkpoint inside it, SIGKILL: nothing is
        // saved on the way out, the file on disk is what a due save wrote.
        let written_inside = |text: &str| {
            text.lines().any(|l| {
                l.contains("checkpoint written")
                    && l.contains("iteration=1 ")
                    && !l.contains("within=0 ")
            })
        };
        child.wait_for(HANG_LIMIT, || written_inside(&child_log(&log)));
        let ended = child.run_or_kill_after(Duration::ZERO);
        let text = child.log();
        assert!(!text.contains("panicked"), "{text}");
        if matches!(ended, Ended::Killed) {
            if let Some(done) = inside_a_main_axis(&out) {
                resumed_inside_to_the_same_bytes(&out, &options, done, &reference);
                return;
            }
        }
        println!("attempt {attempt}: no checkpoint inside a main axis on disk, again");
    }
    panic!("four kills, none after a checkpoint inside a main axis");
}

#[test]
fn sigterm_stops_an_out_of_core_solve_in_mid_iteration_or_in_its_setup() {
    let tmp = tempfile::tempdir().unwrap();
    let memory: &[&str] = &["--memory", "1MiB"];
    let reference = tmp.path().join("reference");
    run_to_end(
        solve_command(&reference, memory),
        &tmp.path().join("ref.log"),
    );

    // In mid-iteration: the canonical radiosity of the last completed iteration is saved.
    let mid = tmp.path().join("mid");
    let text = stopped_by(
        libc::SIGTERM,
        &mid,
        &[memory, &ONLY_ON_SIGNAL].concat(),
        &tmp.path().join("mid.log"),
        false,
        |log, _| log.contains("iteration=2 "),
    );
    println!("{}", text.lines().last().unwrap_or(""));
    assert_eq!(text.matches("checkpoint written").count(), 1, "{text}");

    // While the work files are being made: the process ends at once, nothing to save.
    let setup = tmp.path().join("setup");
    let text = stopped_by(
        libc::SIGTERM,
        &setup,
        &[memory, &ONLY_ON_SIGNAL].concat(),
        &tmp.path().join("setup.log"),
        true,
        |log, _| log.contains("out-of-core plan"),
    );
    println!("{}", text.lines().last().unwrap_or(""));
    resume_each(&[(&mid, memory), (&setup, memory)], &reference);
}

#[test]
fn damaged_or_foreign_checkpoints_are_refused_and_lose_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    // A checkpoint to damage: from a solve stopped by SIGTERM.
    let stopped = tmp.path().join("stopped");
    stopped_by(
        libc::SIGTERM,
        &stopped,
        &[],
        &tmp.path().join("stopped.log"),
        false,
        |_, out| checkpoint::path_in(out).exists(),
    );
    let good = std::fs::read(checkpoint::path_in(&stopped)).unwrap();
    // And one inside an iteration: its last bytes are the partial sums.
    let (inside, _) = stopped_inside_an_iteration(tmp.path(), "inside", &LONG_ITERATIONS);
    let mid = std::fs::read(checkpoint::path_in(&inside)).unwrap();
    let mut mid_flipped = mid.clone();
    let at = mid.len() - 100;
    mid_flipped[at] ^= 0x40;
    // A format version after this build's.
    let unknown = checkpoint::file::FORMAT_VERSION + 1;
    let mut version_next = mid.clone();
    version_next[8..12].copy_from_slice(&unknown.to_le_bytes());
    let unknown = format!("version {unknown}");
    let unknown_needles = [unknown.as_str()];
    // A finished result in the directory the bad checkpoints go into: it must survive.
    let out = tmp.path().join("out");
    run_to_end(solve_command(&out, &[]), &tmp.path().join("out.log"));
    let before = results(&out);
    let ckpt = checkpoint::path_in(&out);
    let run = |extra: &[&str]| {
        let o = solve_command(&out, &[extra, &["--resume"]].concat())
            .output()
            .unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let mut flipped = good.clone();
    let at = flipped.len() - 100;
    flipped[at] ^= 1;
    let mut wrong_header = good.clone();
    wrong_header[30] ^= 1;
    // What is wrong, the checkpoint's bytes, options of the run, words the message must hold.
    type Case<'a> = (&'a str, Vec<u8>, &'a [&'a str], &'a [&'a str]);
    let cases: Vec<Case> = vec![
        (
            "flipped radiosity bit",
            flipped,
            &[],
            &["damaged", "checksum"],
        ),
        (
            "flipped header bit",
            wrong_header,
            &[],
            &["damaged", "header"],
        ),
        (
            "truncated",
            good[..good.len() / 2].to_vec(),
            &[],
            &["truncated"],
        ),
        (
            "not a checkpoint",
            b"hello".to_vec(),
            &[],
            &["not a voxrad checkpoint"],
        ),
        (
            "flipped partial-sum bit",
            mid_flipped,
            &[],
            &["damaged", "checksum"],
        ),
        (
            "partial sums truncated",
            mid[..mid.len() - 1000].to_vec(),
            &[],
            &["truncated"],
        ),
        (
            "a format version this voxrad does not know",
            version_next,
            &[],
            &unknown_needles,
        ),
        (
            "other directions",
            good.clone(),
            &["--directions", "100"],
            &["another run", "directions"],
        ),
        (
            "other direct-light pass",
            good.clone(),
            &["--direct-directions", "3000"],
            &["another run", "direct-light pass"],
        ),
        (
            "no direct-light pass",
            good.clone(),
            &["--direct-directions", "0"],
            &["another run", "direct-light pass"],
        ),
        (
            "other resolution",
            good.clone(),
            &["--resolution", "24"],
            &["another run", "grid"],
        ),
        (
            "out of core",
            good.clone(),
            &["--memory", "1MiB"],
            &["another run", "out-of-core"],
        ),
    ];
    for (what, bytes, extra, needles) in cases {
        std::fs::write(&ckpt, &bytes).unwrap();
        let (code, text) = run(extra);
        assert_eq!(code, Some(2), "{what}: {text}");
        assert!(!text.contains("panicked"), "{what}: {text}");
        assert!(text.contains(&ckpt.display().to_string()), "{what}: {text}");
        for n in needles {
            assert!(text.contains(n), "{what}: no {n:?} in {text}");
        }
        assert!(
            results(&out) == before,
            "{what}: the earlier results changed"
        );
        assert_eq!(
            std::fs::read(&ckpt).unwrap(),
            bytes,
            "{what}: checkpoint touched"
        );
        println!("{what}: {}", text.lines().last().unwrap_or(""));
    }
}

/// Through the library: for every iteration boundary k of a reference solve, a solve allowed
/// k + 1 iterations leaves the checkpoint of iteration k (written at every boundary it goes on
/// from); resuming from it with the reference's options must give the reference's bits. The
/// default preset's extrapolation is on, so boundaries before, at and after a jump are covered.
#[test]
fn resuming_from_every_iteration_boundary_is_bit_identical() {
    resume_from_every_boundary(DirectPass::Off, false);
}

/// The same with the direct-light pass, which a resumed solve recomputes (`solve::direct`).
#[test]
fn resuming_with_the_direct_pass_from_every_boundary_is_bit_identical() {
    resume_from_every_boundary(DirectPass::On(3000), false);
}

/// The same with the Chebyshev semi-iteration, whose checkpoints also hold the radiosity
/// before last and the recurrence's state (`solve::accelerate`).
#[test]
fn resuming_a_chebyshev_semi_iteration_from_every_boundary_is_bit_identical() {
    resume_from_every_boundary(DirectPass::On(3000), true);
}

fn resume_from_every_boundary(direct: DirectPass, chebyshev: bool) {
    let scene = voxrad::scene::obj::load_obj(Path::new(&cornell())).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(16)).unwrap();
    let directions = DirectionSet::with_count(49);
    let options = SolveOptions {
        directions: 49,
        tolerance: Some(1e-6),
        threads: 2,
        accelerate: true,
        chebyshev,
        direct,
        ..SolveOptions::default()
    };
    let reference = solve_with(&set, &directions, &options).unwrap();
    let total = reference.stats.iterations;
    if chebyshev {
        let updates = reference.stats.chebyshev_updates.unwrap_or(0);
        assert!(updates >= 3, "{updates} Chebyshev updates to cross");
    } else {
        assert!(
            reference.stats.extrapolations >= 1,
            "no extrapolation to cross"
        );
    }
    let bits = |r: &[[[f32; 3]; 2]]| -> Vec<u32> {
        r.iter().flatten().flatten().map(|v| v.to_bits()).collect()
    };
    let tmp = tempfile::tempdir().unwrap();
    let identity = Identity::in_memory(&set, &directions, 3, true)
        .with_direct_pass(direct.directions_for(&set, directions.len()).as_ref())
        .with_chebyshev(chebyshev);
    let saver = |dir: &Path, resumed: Option<u64>| {
        Saver::new(dir, identity.clone(), true, Duration::ZERO, 1, resumed)
    };
    for k in 0..total {
        let dir = tmp.path().join(format!("k{k}"));
        std::fs::create_dir_all(&dir).unwrap();
        let path = checkpoint::path_in(&dir);
        if k > 0 {
            let short = SolveOptions {
                max_iterations: k + 1,
                ..options.clone()
            };
            let mut s = saver(&dir, None);
            let c = Checkpoints {
                saver: &mut s,
                resume: None,
            };
            solve_checkpointed(&set, &directions, &short, &SingleProcess, c).unwrap();
        } else {
            // Iteration 0 is B = E: what a solve stopped before its first iteration leaves.
            let mut s = saver(&dir, None);
            let state = s.state(0, None, &Default::default());
            let emission: Vec<[[f32; 3]; 2]> = set
                .surfels
                .iter()
                .map(|x| {
                    x.material
                        .map(|m| set.materials[m as usize].emission.map(|e| e as f32))
                })
                .collect();
            s.save_memory(state, &emission, None).unwrap();
        }
        let loaded = checkpoint::load_shared(&SingleProcess, &path, &identity, 1000)
            .unwrap()
            .expect("a checkpoint");
        assert_eq!(loaded.state.iteration, k as u64);
        let mut s = saver(&dir, Some(k as u64));
        let c = Checkpoints {
            saver: &mut s,
            resume: Some(loaded),
        };
        let resumed = solve_checkpointed(&set, &directions, &options, &SingleProcess, c).unwrap();
        assert_eq!(resumed.stats.iterations, total, "from {k}");
        assert_eq!(resumed.stats.extrapolations, reference.stats.extrapolations);
        assert_eq!(
            resumed.stats.chebyshev_updates,
            reference.stats.chebyshev_updates
        );
        assert_eq!(
            resumed.stats.residual.to_bits(),
            reference.stats.residual.to_bits()
        );
        assert!(
            bits(&resumed.radiosity) == bits(&reference.radiosity),
            "resumed from iteration {k}: different radiosity"
        );
    }
    println!(
        "{total} iterations, {} extrapolations: resumed from each of the {total} boundaries",
        reference.stats.extrapolations
    );
}

/// The same for the out-of-core solver (from a surfel set in memory, a budget of 256 KiB).
#[test]
fn out_of_core_resume_from_every_iteration_boundary_is_bit_identical() {
    out_of_core_resume_from_every_boundary(false);
}

/// The same with the Chebyshev semi-iteration: its checkpoints also hold the work file of the
/// radiosity before last.
#[test]
fn out_of_core_chebyshev_resume_from_every_iteration_boundary_is_bit_identical() {
    out_of_core_resume_from_every_boundary(true);
}

fn out_of_core_resume_from_every_boundary(chebyshev: bool) {
    let scene = voxrad::scene::obj::load_obj(Path::new(&cornell())).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(16)).unwrap();
    let source = InMemorySource::new(&set);
    let directions = DirectionSet::with_count(49);
    let options = SolveOptions {
        directions: 49,
        tolerance: Some(1e-6),
        threads: 2,
        accelerate: chebyshev,
        chebyshev,
        ..SolveOptions::default()
    };
    let budget = 256 << 10;
    let tmp = tempfile::tempdir().unwrap();
    let identity = Identity {
        solver: checkpoint::Solver::OutOfCore,
        surfels: set.surfels.len() as u64,
        dims: set.grid.dims,
        voxel_size: set.grid.voxel_size,
        directions: directions.len() as u32,
        directions_checksum: checkpoint::directions_checksum(&directions),
        channels: 3,
        accelerate: chebyshev,
        chebyshev,
        scene_checksum: 1,
    };
    let solve = |dir: &PathBuf, max: usize, resume: Option<CheckpointFile>| {
        let mut s = Saver::new(
            dir,
            identity.clone(),
            true,
            Duration::ZERO,
            1,
            resume.as_ref().map(|f| f.header.state.iteration),
        );
        let o = SolveOptions {
            max_iterations: max,
            ..options.clone()
        };
        let c = OocCheckpoints {
            saver: &mut s,
            resume,
        };
        let solution =
            solve_out_of_core_checkpointed(&source, &directions, &o, budget, dir, c).unwrap();
        (
            solution.radiosity().unwrap(),
            solution.stats.solve.iterations,
            solution.stats.solve.chebyshev_updates,
        )
    };
    let reference_dir = tmp.path().join("reference");
    std::fs::create_dir_all(&reference_dir).unwrap();
    let (reference, total, updates) = solve(&reference_dir, 1000, None);
    if chebyshev {
        assert!(updates.is_some_and(|u| u >= 3), "{updates:?}");
    }
    let bits = |r: &[[[f32; 3]; 2]]| -> Vec<u32> {
        r.iter().flatten().flatten().map(|v| v.to_bits()).collect()
    };
    for k in 1..total {
        let dir = tmp.path().join(format!("k{k}"));
        std::fs::create_dir_all(&dir).unwrap();
        solve(&dir, k + 1, None);
        let file = CheckpointFile::open(&checkpoint::path_in(&dir)).unwrap();
        assert_eq!(file.header.state.iteration, k as u64);
        let (resumed, iterations, resumed_updates) = solve(&dir, 1000, Some(file));
        assert_eq!((iterations, resumed_updates), (total, updates));
        assert!(
            bits(&resumed) == bits(&reference),
            "resumed from iteration {k}"
        );
    }
    println!("out of core: resumed from each of {} boundaries", total - 1);
}

/// A mid-iteration checkpoint of the out-of-core solver whose position does not match what it
/// holds (the light of an axis in progress at an axis's end, or an axis's middle without it) is
/// refused naming the file, before anything is solved from it.
#[test]
fn out_of_core_checkpoint_with_a_position_that_does_not_match_its_sums_is_refused() {
    let scene = voxrad::scene::obj::load_obj(Path::new(&cornell())).unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(8)).unwrap();
    let source = InMemorySource::new(&set);
    let directions = DirectionSet::with_count(49);
    let n = set.surfels.len() as u64;
    let identity = Identity {
        solver: checkpoint::Solver::OutOfCore,
        surfels: n,
        dims: set.grid.dims,
        voxel_size: set.grid.voxel_size,
        directions: directions.len() as u32,
        directions_checksum: checkpoint::directions_checksum(&directions),
        channels: 3,
        accelerate: false,
        chebyshev: false,
        scene_checksum: 1,
    };
    // The checkpoints below are inside iteration 2, which walks backwards.
    let by_axis = voxrad::outcore::solver::walk_by_axis(&directions);
    let first_axis = voxrad::outcore::solver::walk_of_iteration(&by_axis, 2)[0]
        .1
        .len() as u64;
    assert!(first_axis >= 2);
    let tmp = tempfile::tempdir().unwrap();
    for (done, axis_in_progress, words) in [
        (first_axis, true, "not inside a main axis"),
        (first_axis - 1, false, "not at the end of a main axis"),
    ] {
        let mut saver = Saver::new(tmp.path(), identity.clone(), true, Duration::ZERO, 1, None);
        let mut state = saver.state(1, None, &Default::default());
        state.within = Some(done);
        state.axis_in_progress = axis_in_progress;
        let arrays = 1 + axis_in_progress as u64;
        saver
            .save(state, 1 << 16, |w| {
                w.write_all(&vec![0u8; (n * (24 + 48 * arrays)) as usize])
            })
            .unwrap();
        let path = checkpoint::path_in(tmp.path());
        let c = OocCheckpoints {
            saver: &mut saver,
            resume: Some(CheckpointFile::open(&path).unwrap()),
        };
        let options = SolveOptions {
            directions: 49,
            threads: 1,
            ..SolveOptions::default()
        };
        let err = match solve_out_of_core_checkpointed(
            &source,
            &directions,
            &options,
            256 << 10,
            tmp.path(),
            c,
        ) {
            Ok(_) => panic!("{done} directions, axis {axis_in_progress}: accepted"),
            Err(e) => e,
        };
        let text = err.to_string();
        assert!(err.is_bad_input(), "{text}");
        assert!(
            text.contains(&path.display().to_string()) && text.contains(words),
            "{text}"
        );
        println!("{text}");
    }
}
