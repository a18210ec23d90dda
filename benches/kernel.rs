//! The per-direction kernel of the in-memory solver (dispatch, partner search, gather) on one
//! real scene: **nanoseconds per surfel-direction** and updates per second per core.
//!
//! Unlike `throughput` (procedural buildings, a grid of sizes), this runs one OBJ scene at one
//! setting, in-process, so that it can be run under `perf` and compared across commits. It also
//! prints a hash of the bits of the resulting radiosity: an optimisation of the kernel must leave
//! it unchanged.
//!
//! **Measured:** `dispatch + propagate` seconds as the solver times them, summed over
//! directions and iterations, times the thread count, over `surfels x directions x iterations`.
//! With more than one iteration it also solves the first iteration alone and reports the two
//! kinds apart: the first pass (dispatch, partner search, gather, and writing the links down
//! where they are kept) and each later iteration (replaying kept links, or searching again
//! without them), the difference of the two solves over the iterations between.
//! **Left out:** loading, voxelization, the solver's set-up, the `B` update after each
//! iteration, and the direct-light pass (switched off here: it is a different kernel).
//!
//! ```text
//! cargo bench --bench kernel -- [SCENE.obj] [--resolution 128] [--directions 589]
//!                               [--iterations 2] [--threads 1] [--repeat 1]
//!                               [--links-memory BYTES]
//! ```
//! Without `--bench` (as under `cargo test --benches`) a tiny smoke run is done.

use std::hash::{Hash, Hasher};
use std::path::PathBuf;
use voxrad::scene::obj::load_obj;
use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn main() {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let full = args.iter().any(|a| a == "--bench");
    args.retain(|a| a != "--bench");
    let mut scene = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/examples/cornell_box.obj"
    ));
    let (mut resolution, mut directions, mut iterations, mut threads, mut repeat) = if full {
        (128, 589, 2, 1, 1)
    } else {
        (16, 13, 1, 1, 1)
    };
    // Bytes of partner links kept between iterations (`SolveOptions::links_memory`): 0 searches
    // every iteration, as the first pass does; unset, the solver's default.
    let mut links_memory = None;
    let mut it = args.into_iter();
    while let Some(a) = it.next() {
        let mut value = |name: &str| -> usize {
            it.next()
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("{name} needs a number"))
        };
        match a.as_str() {
            "--resolution" => resolution = value("--resolution"),
            "--directions" => directions = value("--directions"),
            "--iterations" => iterations = value("--iterations"),
            "--threads" => threads = value("--threads"),
            "--repeat" => repeat = value("--repeat"),
            "--links-memory" => links_memory = Some(value("--links-memory") as u64),
            _ if !a.starts_with("--") => scene = PathBuf::from(a),
            _ => panic!("unknown option {a}"),
        }
    }
    let loaded = load_obj(&scene).expect("load the scene");
    let set = voxelize(&loaded, GridSpec::Resolution(resolution as u32)).expect("voxelize");
    let options = SolveOptions {
        directions,
        max_iterations: iterations,
        tolerance: None,
        threads,
        links_memory,
        ..Default::default()
    };
    for _ in 0..repeat {
        if iterations > 1 {
            let first = solve(
                &set,
                &SolveOptions {
                    max_iterations: 1,
                    ..options.clone()
                },
            )
            .expect("solve");
            let all = solve(&set, &options).expect("solve");
            let seconds = |s: &voxrad::solve::SolveStats| s.dispatch_seconds + s.propagate_seconds;
            let per = (set.surfels.len() * all.stats.directions) as f64 / 1e9 / threads as f64;
            let first_ns = seconds(&first.stats) / per;
            let later_ns =
                (seconds(&all.stats) - seconds(&first.stats)) / per / (iterations - 1) as f64;
            println!(
                "first pass {first_ns:.1} ns per surfel-direction per core, later iterations \
                 {later_ns:.1} ns ({:.3e} updates/s/core); links kept for {} of {} directions",
                1e9 / later_ns,
                all.stats.links.as_ref().map_or(0, |l| l.kept_directions),
                all.stats.directions
            );
        }
        let solution = solve(&set, &options).expect("solve");
        let st = &solution.stats;
        let timed = st.dispatch_seconds + st.propagate_seconds;
        let mut hasher = std::collections::hash_map::DefaultHasher::new();
        for v in solution.radiosity.iter().flatten().flatten() {
            v.to_bits().hash(&mut hasher);
        }
        println!(
            "{}: {} surfels x {} directions x {} iterations, {} thread(s): dispatch {:.3} s, \
             propagate {:.3} s, {:.1} ns per surfel-direction per core, {:.3e} updates/s/core, \
             radiosity hash {:016x}",
            scene.display(),
            set.surfels.len(),
            st.directions,
            iterations,
            threads,
            st.dispatch_seconds,
            st.propagate_seconds,
            timed * threads as f64 / st.updates as f64 * 1e9,
            st.updates as f64 / timed / threads as f64,
            hasher.finish()
        );
    }
}
