//! `voxrad-shard convert` inside an address-space limit far below its output: the real binary in
//! a child process whose `RLIMIT_AS` is set before it starts, with `MALLOC_ARENA_MAX=2` and one
//! thread, converting a generated building into a shard set at least 16 times the limit. It must
//! succeed, stay within its `--memory` budget plus a stated allowance in peak RSS (read with
//! `getrusage(RUSAGE_CHILDREN)` once it has exited), sort through several runs on disk, and
//! produce a set that verifies. `reshard` of that set runs under the same limit and budget.
//!
//! Sizes are parameters, so that a larger run can be made by hand:
//! - `VOXRAD_MEMTEST_LIMIT_MIB`: the address-space limit (default 16);
//! - `VOXRAD_MEMTEST_SET_MIB`: the shard-set size to aim for (default 17 times the limit, so that
//!   the set is at least 16 times the limit whatever the estimate's error).
//!
//! The budget given to `--memory` is the limit less 10 MiB, the address space the process needs
//! before it holds any data (code, libraries, stack, the scene and the allocator's arena): with
//! the plotting and compression libraries linked in, a budget of the limit less 8 MiB no longer
//! fitted under 16 MiB (it had at first), less 9 MiB did; the peak RSS allowance over the budget
//! is the same 10 MiB.
//!
//! This file holds one test only: `RUSAGE_CHILDREN` is the maximum over every child the test
//! process has waited for, so no other child may run in it.

use std::path::Path;
use std::process::Command;
use tempfile::TempDir;
use voxrad::convert::commands::{convert, ConvertOptions};
use voxrad::voxel::voxelize::GridSpec;

const MIB: u64 = 1 << 20;
/// Address space the process needs besides its budget, and the RSS allowed over the budget.
const OVERHEAD: u64 = 10 * MIB;

fn env_mib(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse::<u64>().ok())
        .unwrap_or(default)
}

/// Peak resident set of the waited-for children, in bytes (Linux reports KiB).
fn children_peak_rss() -> u64 {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: `getrusage` fills the struct it is given; `RUSAGE_CHILDREN` is a valid selector.
    let rc = unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, usage.as_mut_ptr()) };
    assert_eq!(rc, 0, "getrusage");
    // SAFETY: initialised by the successful call above (and zeroed before it).
    let usage = unsafe { usage.assume_init() };
    usage.ru_maxrss as u64 * 1024
}

fn shard_bytes(set: &Path) -> u64 {
    std::fs::read_dir(set)
        .unwrap()
        .map(|e| e.unwrap())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".vxs"))
        .map(|e| e.metadata().unwrap().len())
        .sum()
}

#[test]
fn convert_stays_inside_an_address_space_limit_16_times_below_its_output() {
    let limit = env_mib("VOXRAD_MEMTEST_LIMIT_MIB", 16) * MIB;
    let target = env_mib("VOXRAD_MEMTEST_SET_MIB", 17 * limit / MIB) * MIB;
    let budget = limit - OVERHEAD;
    let tmp = TempDir::new().unwrap();
    let obj = tmp.path().join("building.obj");
    voxrad::gen::write_obj(&voxrad::gen::building(3, 3, 2, 1), &obj).unwrap();

    // Calibrate in this process (not a child: it would count in RUSAGE_CHILDREN): surfels grow
    // with the square of the resolution.
    let r0 = 120u32;
    let probe = tmp.path().join("probe");
    let small = convert(&ConvertOptions {
        scene: obj.clone(),
        out: probe.clone(),
        spec: GridSpec::Resolution(r0),
        ranks: 1,
        memory: 64 * MIB,
        order: 0,
        threads: 1,
    })
    .unwrap();
    let bytes0: u64 = small.shards.iter().map(|s| s.bytes).sum();
    std::fs::remove_dir_all(&probe).unwrap();
    let resolution = (r0 as f64 * (target as f64 / bytes0 as f64).sqrt() * 1.02).ceil() as u32;

    let set = tmp.path().join("set");
    let started = std::time::Instant::now();
    let out = limited(limit)
        .args(["convert", &obj.display().to_string()])
        .args(["--resolution", &resolution.to_string()])
        .args(["--out", &set.display().to_string()])
        .args(["--ranks", "2", "--threads", "1"])
        .args(["--memory", &budget.to_string()])
        .output()
        .unwrap();
    let seconds = started.elapsed().as_secs_f64();
    let peak = children_peak_rss();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "convert under a {limit}-byte limit failed: {:?}\n{stdout}\n{stderr}",
        out.status
    );
    let bytes = shard_bytes(&set);
    eprintln!(
        "limit {} MiB, --memory {} MiB, resolution {resolution}: shard set {:.1} MiB ({:.1}x the \
         limit), peak RSS {:.1} MiB, {seconds:.1} s\n{stdout}",
        limit / MIB,
        budget / MIB,
        bytes as f64 / MIB as f64,
        bytes as f64 / limit as f64,
        peak as f64 / MIB as f64
    );
    assert!(
        bytes >= 16 * limit,
        "the shard set ({bytes} bytes) must be at least 16 times the limit ({limit})"
    );
    assert!(
        peak <= budget + OVERHEAD,
        "peak RSS {peak} bytes exceeds the budget {budget} + allowance {OVERHEAD}"
    );
    // The data went through disk: many runs, not one buffer.
    let runs: u64 = stdout
        .split("sorted in ")
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .expect("the summary names the number of runs");
    assert!(runs >= 8, "{stdout}");

    // Re-split the big set under the same limit: a streaming merge and a verification pass.
    let resharded = tmp.path().join("resharded");
    let started = std::time::Instant::now();
    let out = limited(limit)
        .args(["reshard", &set.display().to_string(), "--ranks", "3"])
        .args(["--out", &resharded.display().to_string()])
        .args(["--memory", &budget.to_string()])
        .output()
        .unwrap();
    let seconds = started.elapsed().as_secs_f64();
    let peak = children_peak_rss();
    assert!(
        out.status.success(),
        "reshard under the limit failed: {:?}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!(
        "reshard 2 -> 3 shards under the same limit: {seconds:.1} s, peak RSS of both {:.1} MiB",
        peak as f64 / MIB as f64
    );
    assert!(
        peak <= budget + OVERHEAD,
        "peak RSS {peak} bytes after reshard"
    );
    assert_eq!(
        shard_bytes(&resharded),
        bytes + 52,
        "one more header and footer"
    );

    // Unlimited from here on (the peak has been read).
    for dir in [&set, &resharded] {
        let v = Command::new(env!("CARGO_BIN_EXE_voxrad-shard"))
            .args(["verify", &dir.display().to_string()])
            .output()
            .unwrap();
        assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stderr));
    }
}

/// `voxrad-shard` with `RLIMIT_AS` set to `limit` before it starts, one allocator arena pair.
fn limited(limit: u64) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_voxrad-shard"));
    cmd.env("MALLOC_ARENA_MAX", "2").env_remove("RUST_LOG");
    use std::os::unix::process::CommandExt;
    let limit = limit as libc::rlim_t;
    // SAFETY: the closure runs in the child between fork and exec and only calls `setrlimit`,
    // which is async-signal-safe, on a struct on its own stack.
    unsafe {
        cmd.pre_exec(move || {
            let rl = libc::rlimit {
                rlim_cur: limit,
                rlim_max: limit,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &rl) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    cmd
}
