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
