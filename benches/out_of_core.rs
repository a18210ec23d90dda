//! Out-of-core against in-memory throughput on the same scene, in one run.
//!
//! A procedural building is voxelized, written as a shard set, and solved twice with the same
//! directions and a fixed number of iterations: by the in-memory solver, and by the out-of-core
//! solver from the shard set with a budget of `1/--fraction` of the shard set's bytes (16 by
//! default, the issue's goal: at least half the in-memory throughput there). With `--cold`, the
//! page cache is dropped before the out-of-core solve (`/proc/sys/vm/drop_caches`, needs root),
//! so the shard set is read from disk; the solver's own work files are written during the run
//! and stay cached when the machine has the memory for them, which is reported, not hidden.
//!
//! Two rates are printed for each solver, both in voxel-direction updates per second
//! (`surfels x directions x iterations / seconds`):
//! - **directions**: the time spent solving directions (in-memory: dispatch + propagate;
//!   out-of-core: band reads + dispatch + propagate + writes of gathered light);
//! - **end to end**: the whole solve call, set-up and per-iteration updates included (the
//!   in-memory solver's presorting; the out-of-core solver's axis copies and permutations).
//!
//! Also: bytes read and written per voxel-direction, and the split of the out-of-core time.
//!
//! ```text
//! cargo bench --bench out_of_core                                  # ~10^6 surfels, warm cache
//! cargo bench --bench out_of_core -- --cold                        # and with a cold cache
//! cargo bench --bench out_of_core -- --resolution 600 --directions 193 --threads 1,2
//! ```

use std::time::Instant;
use voxrad::geometry::directions::DirectionSet;
use voxrad::outcore::{solve_out_of_core, ShardSetSource};
use voxrad::solve::jacobi::solve_with;
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::{voxelize, GridSpec};

struct Args {
    bench: bool,
    resolution: u32,
    directions: usize,
    iterations: usize,
    threads: Vec<usize>,
    fraction: u64,
    cold: bool,
}

fn parse_args() -> Args {
    let mut a = Args {
        bench: false,
        resolution: 300,
        directions: 49,
        iterations: 2,
        threads: vec![1, 2],
        fraction: 16,
        cold: false,
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let mut k = 0;
    let value = |k: usize| argv.get(k + 1).cloned().unwrap_or_default();
    while k < argv.len() {
        match argv[k].as_str() {
            "--bench" => a.bench = true,
            "--cold" => a.cold = true,
            "--resolution" => {
                a.resolution = value(k).parse().expect("--resolution N");
                k += 1;
            }
            "--directions" => {
                a.directions = value(k).parse().expect("--directions N");
                k += 1;
            }
            "--iterations" => {
                a.iterations = value(k).parse().expect("--iterations N");
                k += 1;
            }
            "--fraction" => {
                a.fraction = value(k).parse().expect("--fraction N");
                k += 1;
            }
            "--threads" => {
                a.threads = value(k)
                    .split(',')
                    .map(|t| t.parse().expect("--threads 1,2"))
                    .collect();
                k += 1;
            }
            _ => {}
        }
        k += 1;
    }
    if !a.bench {
        // `cargo test --benches`: a smoke run only.
        a.resolution = 40;
        a.directions = 13;
        a.iterations = 1;
        a.threads = vec![1];
    }
    a
}

fn drop_page_cache() -> bool {
    // SAFETY: `sync` has no preconditions.
    unsafe { libc::sync() };
    std::fs::write("/proc/sys/vm/drop_caches", "3\n").is_ok()
}

fn main() {
    let args = parse_args();
    let scene = voxrad::gen::procedural::building(4, 4, 2, 7);
    let set = voxelize(&scene, GridSpec::Resolution(args.resolution)).expect("voxelize");
    let n = set.surfels.len() as u64;
    let tmp = tempfile::tempdir().expect("tempdir");
    let shards = tmp.path().join("building.shards");
    voxrad::storage::write_shard_set(&set, &shards, 4, 0).expect("shard set");
    let data: u64 = std::fs::read_dir(&shards)
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();
    let budget = data / args.fraction;
    let directions = DirectionSet::with_count(args.directions);
    println!(
        "building at resolution {}: {n} surfels, grid {:?}, shard set {:.1} MiB, budget {:.1} MiB \
         (1/{}), {} directions, {} iterations",
        args.resolution,
        set.grid.dims,
        data as f64 / (1 << 20) as f64,
        budget as f64 / (1 << 20) as f64,
        args.fraction,
        directions.len(),
        args.iterations
    );
    let updates = (n * directions.len() as u64 * args.iterations as u64) as f64;
    println!(
        "{:>8} {:>7} {:>14} {:>14} {:>9} {:>9} {:>10} {:>10}",
        "mode",
        "threads",
        "dirs upd/s",
        "e2e upd/s",
        "dir ratio",
        "e2e ratio",
        "read B/vd",
        "write B/vd"
    );
    for &threads in &args.threads {
        let options = SolveOptions {
            directions: args.directions,
            max_iterations: args.iterations,
            tolerance: None,
            threads,
            ..Default::default()
        };
        let t = Instant::now();
        let reference = solve_with(&set, &directions, &options).expect("solve");
        let memory_e2e = t.elapsed().as_secs_f64();
        let s = &reference.stats;
        let memory_dirs = s.dispatch_seconds + s.propagate_seconds;
        println!(
            "{:>8} {:>7} {:>14.3e} {:>14.3e} {:>9} {:>9} {:>10} {:>10}",
            "memory",
            threads,
            updates / memory_dirs,
            updates / memory_e2e,
            "1",
            "1",
            "0",
            "0"
        );
        let mut caches = vec![("warm", false)];
        if args.cold {
            caches.push(("cold", true));
        }
        for (name, cold) in caches {
            if cold && !drop_page_cache() {
                println!("(cannot drop the page cache here: not root; cold run skipped)");
                continue;
            }
            let source = ShardSetSource::open(&shards).expect("open shard set");
            let t = Instant::now();
            let solution =
                solve_out_of_core(&source, &directions, &options, budget, tmp.path()).expect("ooc");
            let e2e = t.elapsed().as_secs_f64();
            let o = &solution.stats;
            let dirs = o.read_seconds
                + o.write_seconds
                + o.solve.dispatch_seconds
                + o.solve.propagate_seconds;
            println!(
                "{:>8} {:>7} {:>14.3e} {:>14.3e} {:>9.2} {:>9.2} {:>10.1} {:>10.1}",
                format!("ooc {name}"),
                threads,
                updates / dirs,
                updates / e2e,
                memory_dirs / dirs,
                memory_e2e / e2e,
                o.bytes_read as f64 / updates,
                o.bytes_written as f64 / updates
            );
            println!(
                "         split (s): setup {:.2}, band reads {:.2}, dispatch {:.2}, propagate \
                 {:.2}, band writes {:.2}, updates {:.2}; {} bands, {} columns in blocks, {} \
                 bands replayed in {} groups; {} passes gathered {} directions with others",
                o.setup_seconds,
                o.read_seconds,
                o.solve.dispatch_seconds,
                o.solve.propagate_seconds,
                o.write_seconds,
                o.update_seconds,
                o.bands,
                o.tiled_columns,
                o.replayed_bands,
                o.replay_groups,
                o.joint_passes,
                o.joint_directions
            );
        }
    }
}
