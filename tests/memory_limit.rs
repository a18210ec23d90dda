//! The out-of-core solver inside a tiny address-space limit: the real binary, in a child process
//! whose address space is capped (`setrlimit(RLIMIT_AS)`, with `MALLOC_ARENA_MAX=2` so glibc
//! does not reserve an arena per thread), solves a generated building whose shard set is at least
//! 16 times the limit. It must finish, keep its peak RSS within the budget plus a stated
//! allowance, and give the in-memory answer; an impossible budget must fail with a clear message.
//!
//! Sizes (environment, for bigger manual runs): `VOXRAD_LIMIT_MIB` (address-space limit, default
//! 32), `VOXRAD_BUDGET_MIB` (`--memory`, default 12), `VOXRAD_BUILDING_RESOLUTION` (default 800);
//! `VOXRAD_ANY_SIZE` lifts the 16-times rule for quick experiments.

mod common;

use std::io::Read;
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Command, Stdio};
use voxrad::geometry::directions::DirectionSet;
use voxrad::solve::jacobi::solve_with;
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::{voxelize, GridSpec};

/// Code, stacks, the allocator's bookkeeping and fragmentation: measured peak RSS minus budget
/// stayed below 12 MiB in our runs.
const ALLOWANCE_BYTES: u64 = 16 << 20;

fn env_u64(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Runs `voxrad args` with its address space capped at `limit` bytes; returns the exit code,
/// standard error and the child's peak RSS in bytes as `getrusage` reports it. That figure is
/// only an upper bound here: Linux carries a process's high-water mark across `exec`, so it
/// includes what this (large) test process had resident when it forked. The solver's own
/// `VmHWM` is in its report.
fn run_limited(args: &[String], limit: u64) -> (Option<i32>, String, u64) {
    let mut command = Command::new(env!("CARGO_BIN_EXE_voxrad"));
    command
        .args(args)
        .env("MALLOC_ARENA_MAX", "2")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    // SAFETY: `setrlimit` is async-signal-safe, and the closure touches nothing else.
    unsafe {
        command.pre_exec(move || {
            let rlimit = libc::rlimit {
                rlim_cur: limit,
                rlim_max: limit,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &rlimit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    // Reaped below by `wait4`, which also gives its resource usage.
    #[allow(clippy::zombie_processes)]
    let mut child = command.spawn().expect("spawn voxrad");
    let mut stderr = child.stderr.take().expect("stderr");
    let reader = std::thread::spawn(move || {
        let mut text = String::new();
        stderr.read_to_string(&mut text).ok();
        text
    });
    // wait4 gives this child's own resource usage (RUSAGE_CHILDREN would mix in other tests').
    let mut status = 0;
    // SAFETY: a zeroed rusage is a valid value for wait4 to fill.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: the pid is our child's, not yet waited for; the pointers are to live locals.
    let pid = unsafe { libc::wait4(child.id() as libc::pid_t, &mut status, 0, &mut usage) };
    assert_eq!(pid, child.id() as libc::pid_t, "wait4");
    let text = reader.join().expect("stderr reader");
    let code = if libc::WIFEXITED(status) {
        Some(libc::WEXITSTATUS(status))
    } else {
        None
    };
    (code, text, usage.ru_maxrss as u64 * 1024)
}

fn dir_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum()
}

#[test]
fn solves_a_shard_set_16_times_its_memory_limit() {
    let limit = env_u64("VOXRAD_LIMIT_MIB", 32) << 20;
    let budget = env_u64("VOXRAD_BUDGET_MIB", 12) << 20;
    let resolution = env_u64("VOXRAD_BUILDING_RESOLUTION", 800) as u32;
    let tmp = tempfile::tempdir().unwrap();
    let scene = voxrad::gen::building(4, 4, 2, 7);
    let set = voxelize(&scene, GridSpec::Resolution(resolution)).unwrap();
    let shards = tmp.path().join("building.shards");
    common::write_shard_set(&set, &shards, 4);
    let shard_bytes = dir_bytes(&shards);
    println!(
        "{} surfels, grid {:?}, shard set {:.1} MiB, limit {} MiB, budget {} MiB",
        set.surfels.len(),
        set.grid.dims,
        shard_bytes as f64 / (1 << 20) as f64,
        limit >> 20,
        budget >> 20
    );
    assert!(
        shard_bytes >= 16 * limit || std::env::var_os("VOXRAD_ANY_SIZE").is_some(),
        "the shard set must be at least 16 times the limit"
    );

    let out = tmp.path().join("out");
    let args: Vec<String> = [
        "solve",
        shards.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--directions",
        "13",
        "--iterations",
        "2",
        "--threads",
        "2",
        "--memory",
        &format!("{}MiB", budget >> 20),
        // The bands' memory is what this measures (the direct-light pass has its own test).
        "--direct-directions",
        "0",
    ]
    .iter()
    .map(|a| a.to_string())
    .collect();
    let started = std::time::Instant::now();
    let (code, stderr, rusage_peak) = run_limited(&args, limit);
    assert_eq!(code, Some(0), "{stderr}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let peak = report["peak_rss_bytes"].as_u64().unwrap();
    println!(
        "solve under the limit: {:.1} s, peak RSS {:.1} MiB (getrusage, fork included: {:.1} \
         MiB), budget {} MiB; phases {}; out of core {}",
        started.elapsed().as_secs_f64(),
        peak as f64 / (1 << 20) as f64,
        rusage_peak as f64 / (1 << 20) as f64,
        budget >> 20,
        report["seconds"],
        report["out_of_core"]
    );
    assert!(peak > 0);
    assert!(
        peak <= budget + ALLOWANCE_BYTES,
        "peak RSS {peak} above budget {budget} + allowance {ALLOWANCE_BYTES}"
    );

    // The in-memory answer, from this process.
    let directions = DirectionSet::with_count(13);
    let options = SolveOptions {
        directions: 13,
        max_iterations: 2,
        tolerance: None,
        threads: 2,
        ..Default::default()
    };
    let reference = solve_with(&set, &directions, &options).unwrap();
    // The shard set is in order 0 and the set in Morton order: matched by identity.
    let worst = common::worst_against_results(&set, &reference.radiosity, &out.join("surfels.bin"));
    println!("worst relative difference to the in-memory solve: {worst:.2e}");
    assert!(worst <= 1e-5, "{worst:e}");
}

/// Solves the shard set `shards` into `out` with the direct-light pass (`dense` dense
/// directions, 13 directions, one iteration, 2 threads) under `--memory 4MiB`, the address space
/// capped at `limit`; checks that it succeeds with its peak RSS within the budget and the
/// allowance. Returns the pass's parts and standard error.
fn direct_pass_in_4mib(shards: &Path, out: &Path, dense: &str, limit: u64) -> (u64, String) {
    let budget = 4u64 << 20;
    let args: Vec<String> = [
        "solve",
        shards.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--directions",
        "13",
        "--iterations",
        "1",
        "--threads",
        "2",
        "--memory",
        "4MiB",
        "--direct-directions",
        dense,
    ]
    .iter()
    .map(|a| a.to_string())
    .collect();
    let (code, stderr, _) = run_limited(&args, limit);
    assert_eq!(code, Some(0), "{stderr}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let peak = report["peak_rss_bytes"].as_u64().unwrap();
    let parts = report["out_of_core"]["direct_light_parts"]
        .as_u64()
        .unwrap();
    println!(
        "peak RSS {:.1} MiB, budget 4 MiB, the pass in {parts} parts",
        peak as f64 / (1 << 20) as f64
    );
    assert!(
        peak <= budget + ALLOWANCE_BYTES,
        "peak RSS {peak} above budget {budget} + allowance {ALLOWANCE_BYTES}"
    );
    (parts, stderr)
}

/// The direct-light pass out of core (`outcore::direct`) under the same kind of limit: the
/// emitters' lines of its dense directions held in parts within the budget, its answer the
/// in-memory pass's.
#[test]
fn the_direct_light_pass_stays_within_the_budget() {
    let tmp = tempfile::tempdir().unwrap();
    let set = voxelize(&voxrad::gen::cornell_box(), GridSpec::Resolution(96)).unwrap();
    let shards = tmp.path().join("cornell.shards");
    common::write_shard_set(&set, &shards, 2);
    let out = tmp.path().join("out");
    println!("{} surfels", set.surfels.len());
    let (parts, _) = direct_pass_in_4mib(&shards, &out, "3000", 32 << 20);
    assert!(parts > 1, "a small budget takes the pass in parts: {parts}");
    let options = SolveOptions {
        directions: 13,
        max_iterations: 1,
        tolerance: None,
        threads: 2,
        direct: voxrad::solve::direct::DirectPass::On(3000),
        ..Default::default()
    };
    let reference = solve_with(&set, &DirectionSet::with_count(13), &options).unwrap();
    let worst = common::worst_against_results(&set, &reference.radiosity, &out.join("surfels.bin"));
    println!("worst relative difference to the in-memory solve: {worst:.2e}");
    assert!(worst <= 1e-5, "{worst:e}");
}

/// The direct-light pass in a building, whose lamps' lines cross every floor: the voxels on a
/// group's lines are far more than a part of the budget holds, and choosing the parts must not
/// list them all first (it did: 37 to 41 MiB of RSS under a 4 MiB budget on this building).
#[test]
fn the_direct_light_pass_through_a_buildings_floors_stays_within_the_budget() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = voxrad::gen::building(2, 2, 2, 7);
    let set = voxelize(&scene, GridSpec::Resolution(300)).unwrap();
    let shards = tmp.path().join("building.shards");
    common::write_shard_set(&set, &shards, 2);
    drop(set);
    let out = tmp.path().join("out");
    // Address space for the mapped shard set (the RSS is what is checked).
    let (parts, stderr) = direct_pass_in_4mib(&shards, &out, "100", 1 << 30);
    assert!(stderr.contains("parts over the scene"), "{stderr}");
    assert!(parts > 100, "{parts} parts");
}

#[test]
fn an_impossible_budget_fails_clearly_under_the_limit() {
    let tmp = tempfile::tempdir().unwrap();
    let set = voxelize(&voxrad::gen::cornell_box(), GridSpec::Resolution(24)).unwrap();
    let shards = tmp.path().join("cornell.shards");
    common::write_shard_set(&set, &shards, 1);
    let out = tmp.path().join("out");
    let args: Vec<String> = [
        "solve",
        shards.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--memory",
        "64KiB",
    ]
    .iter()
    .map(|a| a.to_string())
    .collect();
    let (code, stderr, _) = run_limited(&args, 48 << 20);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("too small"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}
