//! Throughput of the in-memory Jacobi solver: **voxel-direction updates per second**.
//!
//! An update is one surfel gathering along one line direction (both `s` and `-s`) in one
//! iteration, so `updates = surfels x line directions x iterations` (`SolveStats::updates`), and
//! the rate is `updates / (dispatch + propagate seconds)` as the solver times them
//! (`SolveStats::dispatch_seconds`, `SolveStats::propagate_seconds`), also divided by the thread
//! count. The default grid shows (a) cost against surfels at a fixed direction count (49
//! directions at 10^4 to 10^7 surfels, 193 directions up to 10^6), (b) cost against directions at
//! a fixed size (49, 193, 769 directions at 10^5 surfels; 49 and 193 at 10^6), (c) one thread
//! against two (every point runs with 1 and 2 threads, back to back in the same process).
//!
//! Scenes are procedural buildings (`gen::procedural::building`), voxelized with a fixed voxel
//! size each so that they hold about 10^4, 10^5, 10^6 and 10^7 surfels; the actual counts are
//! printed. Direction counts are the cube sets `12 N^2 + 1` closest to 50, 200 and 800 (49, 193,
//! 769). Iterations are fixed (`tolerance: None`, `max_iterations` 1 by default), so the figures
//! are per iteration; `--tolerance T` instead solves each scene to that tolerance, as the
//! presets do (tail extrapolation and Chebyshev semi-iteration, the links kept between
//! iterations within the default budget), so that the rate is the average over a whole solve:
//! the first iteration's partner search together with the later iterations' replays.
//!
//! **Measured:** dispatch (building the discrete lines of each direction) and propagation
//! (partner search and gather), summed over directions and iterations; the split between them;
//! peak RSS of the process (`getrusage`), the RSS the solve adds on top of the voxelized scene
//! (`/proc/self/clear_refs` + `VmHWM`, where the kernel allows it), and bytes of surfel data per
//! surfel (the `SurfelSet` record and the per-surfel arrays the solver allocates).
//!
//! **Left out of the rate:** scene generation and voxelization, the solver's one-off set-up (energy
//! normalisation, the four presorted orders, line frames, material tables), the `B` update at the
//! end of each iteration, the energy sums, thread-pool start-up, and any output. Everything is in
//! memory: no shards, no disk I/O, no MPI.
//!
//! Each scene size runs in its own child process (this same binary with `--child`), so peak RSS
//! is per size. Runs shorter than `--min-seconds` are repeated (1 and 2 threads alternating) and
//! the best is kept, which damps noise from other work on the machine.
//!
//! Usage (`cargo bench` passes `--bench`; without it, e.g. under `cargo test --benches`, only a
//! tiny smoke run is done):
//!
//! ```text
//! cargo bench --bench throughput                           # default grid, up to 10^7 surfels
//! cargo bench --bench throughput -- --quick                # up to 10^5 surfels, well under 2 min
//! cargo bench --bench throughput -- --max-surfels 1e6      # drop the larger scenes
//! cargo bench --bench throughput -- --sizes 1e5,1e6 --directions 49,193 --threads 1,2
//! cargo bench --bench throughput -- --sizes 1e6 --directions 193 --threads 1 --tolerance 1e-3
//! cargo bench --bench throughput -- --survey 4,3,2,0.05    # surfels of building(4,3,2) at 0.05
//! ```

use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::io::Write;
use std::process::{Command, Stdio};
use std::time::Instant;
use voxrad::gen::procedural::building;
use voxrad::geometry::directions::DirectionSet;
use voxrad::geometry::lines::LineFrame;
use voxrad::solve::dispatch::OrderedEntry;
use voxrad::solve::propagate::PropSurfel;
use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::{Surfel, SurfelSet};

/// One benchmark scene: a building and the voxel size that gives about `target` surfels.
#[derive(Clone, Copy, Debug)]
struct SceneSpec {
    target: u64,
    rooms_x: usize,
    rooms_y: usize,
    floors: usize,
    voxel: f64,
}

const SEED: u64 = 2024;

/// Calibrated with `--survey` (the printed table gives the actual counts).
const SCENES: [SceneSpec; 4] = [
    SceneSpec {
        target: 10_000,
        rooms_x: 1,
        rooms_y: 1,
        floors: 1,
        voxel: 0.155,
    },
    SceneSpec {
        target: 100_000,
        rooms_x: 2,
        rooms_y: 2,
        floors: 1,
        voxel: 0.087,
    },
    SceneSpec {
        target: 1_000_000,
        rooms_x: 4,
        rooms_y: 3,
        floors: 2,
        voxel: 0.06,
    },
    SceneSpec {
        target: 10_000_000,
        rooms_x: 8,
        rooms_y: 6,
        floors: 3,
        voxel: 0.0435,
    },
];

/// Size sweeps: a direction count and the largest scene it runs on (the 10^7 scene only at the
/// lowest count, to keep the default run within about 15 minutes on two cores).
const SIZE_SWEEPS: [(usize, u64); 2] = [(49, 10_000_000), (193, 1_000_000)];
/// Direction counts of the direction sweep, and the scene sizes it runs on.
const DIRECTION_SWEEP: [usize; 3] = [49, 193, 769];
const DIRECTION_SWEEP_SIZES: [u64; 1] = [100_000];

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct RunSpec {
    directions: usize,
    threads: usize,
}

struct Args {
    bench: bool,
    max_surfels: u64,
    sizes: Option<Vec<u64>>,
    directions: Option<Vec<usize>>,
    threads: Vec<usize>,
    iterations: usize,
    /// Solve to this tolerance (with the presets' tail extrapolation and Chebyshev
    /// semi-iteration) instead of a fixed `iterations`.
    tolerance: Option<f64>,
    min_seconds: f64,
    max_repeats: usize,
    child: Option<u64>,
    runs: Vec<RunSpec>,
    survey: Option<String>,
}

fn usage() -> ! {
    eprintln!(
        "usage: throughput [--quick] [--max-surfels N] [--sizes N,..] [--directions D,..] \
         [--threads T,..] [--iterations K | --tolerance T] [--min-seconds S] [--max-repeats R] \
         [--survey X,Y,FLOORS,VOXEL]"
    );
    std::process::exit(2)
}

fn parse_count(s: &str) -> u64 {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => v.round() as u64,
        _ => {
            eprintln!("not a count: {s}");
            usage()
        }
    }
}

fn parse_list(s: &str) -> Vec<u64> {
    s.split(',')
        .filter(|p| !p.is_empty())
        .map(parse_count)
        .collect()
}

fn parse_args() -> Args {
    let mut args = Args {
        bench: false,
        max_surfels: 10_000_000,
        sizes: None,
        directions: None,
        threads: vec![1, 2],
        iterations: 1,
        tolerance: None,
        min_seconds: 3.0,
        max_repeats: 5,
        child: None,
        runs: Vec::new(),
        survey: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut value = || it.next().unwrap_or_else(|| usage());
        match a.as_str() {
            "--bench" => args.bench = true,
            "--quick" => {
                args.bench = true;
                args.max_surfels = 100_000;
            }
            "--max-surfels" => args.max_surfels = parse_count(&value()),
            "--sizes" => args.sizes = Some(parse_list(&value())),
            "--directions" => {
                args.directions = Some(parse_list(&value()).iter().map(|&d| d as usize).collect())
            }
            "--threads" => {
                args.threads = parse_list(&value()).iter().map(|&t| t as usize).collect()
            }
            "--iterations" => args.iterations = parse_count(&value()).max(1) as usize,
            "--tolerance" => {
                args.tolerance = Some(value().parse().unwrap_or_else(|_| usage()));
            }
            "--min-seconds" => {
                args.min_seconds = value().parse().unwrap_or_else(|_| usage());
            }
            "--max-repeats" => args.max_repeats = parse_count(&value()).max(1) as usize,
            "--child" => args.child = Some(parse_count(&value())),
            "--runs" => {
                args.runs = value()
                    .split(',')
                    .filter(|p| !p.is_empty())
                    .map(|p| {
                        let (d, t) = p.split_once(':').unwrap_or_else(|| usage());
                        RunSpec {
                            directions: parse_count(d) as usize,
                            threads: parse_count(t) as usize,
                        }
                    })
                    .collect()
            }
            "--survey" => args.survey = Some(value()),
            "--run" => args.bench = true,
            "-h" | "--help" => usage(),
            // Options libtest-style runners may pass; nothing to do with them.
            _ if a.starts_with("--") => {}
            _ => {}
        }
    }
    args
}

fn main() {
    let args = parse_args();
    if let Some(target) = args.child {
        child(target, &args);
    } else if let Some(spec) = &args.survey {
        survey(spec);
    } else if args.bench {
        parent(&args);
    } else {
        smoke();
    }
}

// ---------------------------------------------------------------------------------------------
// Measurements inside one process.

/// Peak resident set of this process (getrusage), bytes.
fn peak_rss_bytes() -> u64 {
    // SAFETY: `getrusage` only writes the struct we hand it.
    unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        if libc::getrusage(libc::RUSAGE_SELF, &mut usage) == 0 {
            usage.ru_maxrss as u64 * 1024
        } else {
            0
        }
    }
}

/// A `kB` field of /proc/self/status, in bytes.
fn status_kb(field: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status.lines().find_map(|l| {
        let rest = l.strip_prefix(field)?.strip_prefix(':')?;
        let kb: u64 = rest.trim().trim_end_matches("kB").trim().parse().ok()?;
        Some(kb * 1024)
    })
}

/// Resets the kernel's high-water mark of this process's RSS (`VmHWM`) to the current RSS.
fn reset_rss_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

fn build_set(spec: &SceneSpec) -> (SurfelSet, usize, f64) {
    let started = Instant::now();
    let scene = building(spec.rooms_x, spec.rooms_y, spec.floors, SEED);
    let triangles = scene.triangles.len();
    let set = voxelize(&scene, GridSpec::VoxelSize(spec.voxel)).expect("voxelize");
    (set, triangles, started.elapsed().as_secs_f64())
}

/// Mean number of (dense) lines per direction over the set: dispatch walks all of them.
fn mean_lines(set: &SurfelSet, directions: &DirectionSet) -> f64 {
    let total: u64 = directions
        .directions
        .iter()
        .map(|d| LineFrame::new(d.vector, set.grid.dims).line_count)
        .sum();
    total as f64 / directions.len().max(1) as f64
}

/// Bytes per surfel of the arrays `solve::jacobi` allocates per surfel (see `run`): the packed
/// propagation record, four presorted orders, emission (f32) and reflectance (f64) per side and
/// channel, radiosity (f32), the f64 accumulator, and the line member list (u32).
fn solver_bytes_per_surfel() -> usize {
    std::mem::size_of::<PropSurfel>()
        + 4 * std::mem::size_of::<OrderedEntry>()
        + std::mem::size_of::<[[f32; 3]; 2]>() * 2
        + std::mem::size_of::<[[f64; 3]; 2]>() * 2
        + std::mem::size_of::<u32>()
}

fn child(target: u64, args: &Args) {
    let spec = *SCENES
        .iter()
        .find(|s| s.target == target)
        .unwrap_or_else(|| panic!("no scene with target {target}"));
    eprintln!(
        "[{target}] voxelizing building({}, {}, {}) at voxel {} ...",
        spec.rooms_x, spec.rooms_y, spec.floors, spec.voxel
    );
    let (set, triangles, voxelize_seconds) = build_set(&spec);
    let n = set.surfels.len();
    let rss_scene = status_kb("VmRSS").unwrap_or(0);
    let mut lines_per_surfel = BTreeMap::new();
    for r in &args.runs {
        let d = DirectionSet::with_count(r.directions);
        lines_per_surfel
            .entry(d.len().to_string())
            .or_insert_with(|| mean_lines(&set, &d) / n as f64);
    }
    eprintln!(
        "[{target}] {n} surfels, grid {:?}, voxelized in {voxelize_seconds:.1} s",
        set.grid.dims
    );

    // Round-robin repeats: every run once, then again those still under the time budget.
    let mut best: Vec<Option<Value>> = vec![None; args.runs.len()];
    let mut spent = vec![0.0f64; args.runs.len()];
    let mut count = vec![0usize; args.runs.len()];
    let mut solve_growth = 0u64;
    for _round in 0..args.max_repeats {
        let mut any = false;
        for (k, r) in args.runs.iter().enumerate() {
            if count[k] > 0 && spent[k] >= args.min_seconds {
                continue;
            }
            any = true;
            let options = match args.tolerance {
                None => SolveOptions {
                    directions: r.directions,
                    max_iterations: args.iterations,
                    tolerance: None,
                    threads: r.threads,
                    ..Default::default()
                },
                Some(tolerance) => SolveOptions {
                    directions: r.directions,
                    max_iterations: 1000,
                    tolerance: Some(tolerance),
                    accelerate: true,
                    chebyshev: true,
                    threads: r.threads,
                    ..Default::default()
                },
            };
            let before = status_kb("VmRSS").unwrap_or(0);
            let peak_reset = reset_rss_peak();
            let started = Instant::now();
            let solution = solve(&set, &options).expect("solve");
            let wall = started.elapsed().as_secs_f64();
            if peak_reset {
                if let Some(hwm) = status_kb("VmHWM") {
                    solve_growth = solve_growth.max(hwm.saturating_sub(before));
                }
            }
            let st = &solution.stats;
            let timed = st.dispatch_seconds + st.propagate_seconds;
            let rate = st.updates as f64 / timed;
            spent[k] += timed;
            count[k] += 1;
            eprintln!(
                "[{target}] D={} T={} : {:.3e} updates/s ({:.2} s timed, {:.2} s wall)",
                st.directions, st.threads, rate, timed, wall
            );
            let better = best[k]
                .as_ref()
                .is_none_or(|b| rate > b["rate"].as_f64().unwrap_or(0.0));
            if better {
                best[k] = Some(json!({
                    "directions": st.directions,
                    "threads": st.threads,
                    "iterations": st.iterations,
                    "updates": st.updates,
                    "dispatch": st.dispatch_seconds,
                    "propagate": st.propagate_seconds,
                    "rate": rate,
                    "wall": wall,
                }));
            }
            drop(solution);
        }
        if !any {
            break;
        }
    }
    let scene = json!({
        "target": target,
        "building": format!("{}x{}x{}", spec.rooms_x, spec.rooms_y, spec.floors),
        "voxel": spec.voxel,
        "dims": set.grid.dims,
        "triangles": triangles,
        "surfels": n,
        "voxels": set.voxel_count(),
        "voxelize_seconds": voxelize_seconds,
        "set_bytes": std::mem::size_of::<Surfel>(),
        "solver_bytes": solver_bytes_per_surfel(),
        "lines_per_surfel": lines_per_surfel,
        "rss_scene": rss_scene,
        "solve_growth": solve_growth,
        "peak_rss": peak_rss_bytes(),
    });
    let mut out = std::io::stdout().lock();
    writeln!(out, "@scene {scene}").ok();
    for (k, b) in best.into_iter().enumerate() {
        if let Some(mut b) = b {
            b["surfels"] = json!(n);
            b["target"] = json!(target);
            b["repeats"] = json!(count[k]);
            writeln!(out, "@run {b}").ok();
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The parent: plan, one child per scene size, tables.

fn plan(args: &Args) -> BTreeMap<u64, Vec<RunSpec>> {
    let mut plan: BTreeMap<u64, Vec<RunSpec>> = BTreeMap::new();
    let sizes: Vec<u64> = match &args.sizes {
        Some(s) => s.clone(),
        None => SCENES.iter().map(|s| s.target).collect(),
    };
    let sizes: Vec<u64> = sizes
        .into_iter()
        .filter(|&t| t <= args.max_surfels)
        .filter(|&t| {
            let known = SCENES.iter().any(|s| s.target == t);
            if !known {
                eprintln!("no scene for size {t}; known: 1e4, 1e5, 1e6, 1e7");
            }
            known
        })
        .collect();
    let mut add = |t: u64, d: usize| {
        for &threads in &args.threads {
            let r = RunSpec {
                directions: d,
                threads,
            };
            let runs = plan.entry(t).or_default();
            if !runs.contains(&r) {
                runs.push(r);
            }
        }
    };
    match &args.directions {
        Some(ds) => {
            for &t in &sizes {
                for &d in ds {
                    add(t, d);
                }
            }
        }
        None => {
            for &t in &sizes {
                for (d, largest) in SIZE_SWEEPS {
                    if t <= largest {
                        add(t, d);
                    }
                }
                if DIRECTION_SWEEP_SIZES.contains(&t) {
                    for d in DIRECTION_SWEEP {
                        add(t, d);
                    }
                }
            }
        }
    }
    for runs in plan.values_mut() {
        runs.sort();
    }
    plan
}

fn parent(args: &Args) {
    let plan = plan(args);
    if plan.is_empty() {
        eprintln!("nothing to run");
        return;
    }
    let exe = std::env::current_exe().expect("current_exe");
    let started = Instant::now();
    let mut scenes: Vec<Value> = Vec::new();
    let mut runs: Vec<Value> = Vec::new();
    for (target, specs) in &plan {
        let list: Vec<String> = specs
            .iter()
            .map(|r| format!("{}:{}", r.directions, r.threads))
            .collect();
        let output = Command::new(&exe)
            .arg("--child")
            .arg(target.to_string())
            .arg("--runs")
            .arg(list.join(","))
            .arg("--iterations")
            .arg(args.iterations.to_string())
            .args(
                args.tolerance
                    .map(|t| vec!["--tolerance".to_string(), t.to_string()])
                    .unwrap_or_default(),
            )
            .arg("--min-seconds")
            .arg(args.min_seconds.to_string())
            .arg("--max-repeats")
            .arg(args.max_repeats.to_string())
            .stdin(Stdio::null())
            .stderr(Stdio::inherit())
            .output()
            .expect("start child");
        if !output.status.success() {
            eprintln!("child for size {target} failed: {}", output.status);
            continue;
        }
        for line in String::from_utf8_lossy(&output.stdout).lines() {
            if let Some(j) = line.strip_prefix("@scene ") {
                scenes.push(serde_json::from_str(j).expect("scene json"));
            } else if let Some(j) = line.strip_prefix("@run ") {
                runs.push(serde_json::from_str(j).expect("run json"));
            }
        }
    }
    print_tables(args, &scenes, &runs, started.elapsed().as_secs_f64());
}

fn f(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or(f64::NAN)
}

fn u(v: &Value, key: &str) -> u64 {
    v[key].as_u64().unwrap_or(0)
}

fn mib(bytes: u64) -> String {
    format!("{:.0} MiB", bytes as f64 / (1024.0 * 1024.0))
}

fn sci(x: f64) -> String {
    if !x.is_finite() {
        return "-".into();
    }
    let e = x.abs().log10().floor() as i32;
    format!("{:.2}e{e}", x / 10f64.powi(e))
}

fn print_tables(args: &Args, scenes: &[Value], runs: &[Value], seconds: f64) {
    let cpus = std::thread::available_parallelism().map_or(0, |n| n.get());
    let per_run = match args.tolerance {
        Some(t) => format!("solved to tolerance {t:e}"),
        None => format!("{} iteration(s) per run", args.iterations),
    };
    println!(
        "## voxrad throughput ({per_run}, best of up to {} runs, {} CPUs, {:.0} s)\n",
        args.max_repeats, cpus, seconds
    );
    println!("### Scenes\n");
    println!(
        "| target | building | voxel (m) | grid | triangles | surfels | voxels | \
         lines/surfel (per direction) | set B/surfel | solver B/surfel | RSS after voxelize | \
         solve adds B/surfel | peak RSS |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for s in scenes {
        let n = u(s, "surfels").max(1);
        let dims: Vec<String> = s["dims"]
            .as_array()
            .map(|a| a.iter().map(|d| d.to_string()).collect())
            .unwrap_or_default();
        let lines: Vec<String> = s["lines_per_surfel"]
            .as_object()
            .map(|o| {
                let mut v: Vec<(u64, f64)> = o
                    .iter()
                    .map(|(k, x)| (k.parse().unwrap_or(0), x.as_f64().unwrap_or(0.0)))
                    .collect();
                v.sort_by_key(|p| p.0);
                v.iter().map(|(d, x)| format!("{x:.2} (D={d})")).collect()
            })
            .unwrap_or_default();
        let growth = u(s, "solve_growth");
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            sci(f(s, "target")),
            s["building"].as_str().unwrap_or("?"),
            f(s, "voxel"),
            dims.join("x"),
            u(s, "triangles"),
            n,
            u(s, "voxels"),
            lines.join(", "),
            u(s, "set_bytes"),
            u(s, "solver_bytes"),
            mib(u(s, "rss_scene")),
            if growth > 0 {
                format!("{:.0}", growth as f64 / n as f64)
            } else {
                "-".into()
            },
            mib(u(s, "peak_rss")),
        );
    }

    println!("\n### Updates per second\n");
    println!(
        "| surfels | directions | threads | runs | iterations | timed s | dispatch s | propagate s | \
         dispatch % | updates/s | updates/s/thread | ns/update/thread | 2T/1T speedup |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    let rate_of = |n: u64, d: u64, t: u64| {
        runs.iter()
            .find(|r| u(r, "surfels") == n && u(r, "directions") == d && u(r, "threads") == t)
            .map(|r| f(r, "rate"))
    };
    for r in runs {
        let (n, d, t) = (u(r, "surfels"), u(r, "directions"), u(r, "threads"));
        let (disp, prop) = (f(r, "dispatch"), f(r, "propagate"));
        let rate = f(r, "rate");
        let speedup = match (t, rate_of(n, d, 1)) {
            (t, Some(one)) if t > 1 => format!("{:.2}", rate / one),
            _ => "-".into(),
        };
        println!(
            "| {n} | {d} | {t} | {} | {} | {:.2} | {disp:.2} | {prop:.2} | {:.0} % | {} | {} | {:.1} | {speedup} |",
            u(r, "repeats"),
            u(r, "iterations"),
            disp + prop,
            100.0 * disp / (disp + prop),
            sci(rate),
            sci(rate / t as f64),
            1e9 * t as f64 / rate,
        );
    }

    // Derived: cost per iteration against size and against directions, one thread count each.
    for &t in &args.threads {
        let mut by_dir: BTreeMap<u64, Vec<(u64, f64)>> = BTreeMap::new();
        let mut by_size: BTreeMap<u64, Vec<(u64, f64)>> = BTreeMap::new();
        for r in runs.iter().filter(|r| u(r, "threads") == t as u64) {
            let per_iter =
                (f(r, "dispatch") + f(r, "propagate")) / u(r, "iterations").max(1) as f64;
            by_dir
                .entry(u(r, "directions"))
                .or_default()
                .push((u(r, "surfels"), per_iter));
            by_size
                .entry(u(r, "surfels"))
                .or_default()
                .push((u(r, "directions"), per_iter));
        }
        for (d, mut v) in by_dir {
            if v.len() < 2 {
                continue;
            }
            v.sort_by_key(|p| p.0);
            println!("\n### Cost against surfels ({d} directions, {t} thread(s))\n");
            println!("| surfels | s/iteration | x surfels vs previous | x time vs previous | ns/update |");
            println!("|---|---|---|---|---|");
            for (k, &(n, s)) in v.iter().enumerate() {
                let (xn, xs) = if k == 0 {
                    ("-".to_string(), "-".to_string())
                } else {
                    (
                        format!("{:.2}", n as f64 / v[k - 1].0 as f64),
                        format!("{:.2}", s / v[k - 1].1),
                    )
                };
                println!(
                    "| {n} | {s:.3} | {xn} | {xs} | {:.1} |",
                    1e9 * s / (n as f64 * d as f64)
                );
            }
        }
        for (n, mut v) in by_size {
            if v.len() < 2 {
                continue;
            }
            v.sort_by_key(|p| p.0);
            println!("\n### Cost against directions ({n} surfels, {t} thread(s))\n");
            println!("| directions | s/iteration | x directions vs previous | x time vs previous | ns/update |");
            println!("|---|---|---|---|---|");
            for (k, &(d, s)) in v.iter().enumerate() {
                let (xd, xs) = if k == 0 {
                    ("-".to_string(), "-".to_string())
                } else {
                    (
                        format!("{:.2}", d as f64 / v[k - 1].0 as f64),
                        format!("{:.2}", s / v[k - 1].1),
                    )
                };
                println!(
                    "| {d} | {s:.3} | {xd} | {xs} | {:.1} |",
                    1e9 * s / (n as f64 * d as f64)
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Helpers for calibration and for `cargo test --benches`.

/// `--survey X,Y,FLOORS,VOXEL`: surfel count of one building at one voxel size.
fn survey(spec: &str) {
    let p: Vec<&str> = spec.split(',').collect();
    if p.len() != 4 {
        usage();
    }
    let s = SceneSpec {
        target: 0,
        rooms_x: parse_count(p[0]) as usize,
        rooms_y: parse_count(p[1]) as usize,
        floors: parse_count(p[2]) as usize,
        voxel: p[3].parse().unwrap_or_else(|_| usage()),
    };
    let (set, triangles, seconds) = build_set(&s);
    println!(
        "building({}, {}, {}) voxel {}: {} triangles, grid {:?}, {} surfels, {} voxels, {:.1} s, \
         peak RSS {}",
        s.rooms_x,
        s.rooms_y,
        s.floors,
        s.voxel,
        triangles,
        set.grid.dims,
        set.surfels.len(),
        set.voxel_count(),
        seconds,
        mib(peak_rss_bytes())
    );
}

/// What runs without `--bench`: one tiny solve, so `cargo test --benches` checks the code path
/// in about a second instead of running the benchmark.
fn smoke() {
    let spec = SceneSpec {
        target: 0,
        rooms_x: 1,
        rooms_y: 1,
        floors: 1,
        voxel: 0.5,
    };
    let (set, _, _) = build_set(&spec);
    let options = SolveOptions {
        directions: 13,
        max_iterations: 1,
        tolerance: None,
        threads: 1,
        ..Default::default()
    };
    let solution = solve(&set, &options).expect("solve");
    assert_eq!(
        solution.stats.updates,
        (set.surfels.len() * solution.stats.directions) as u64
    );
    println!(
        "throughput smoke run: {} surfels x {} directions in {:.3} s; run `cargo bench --bench \
         throughput` for the benchmark",
        set.surfels.len(),
        solution.stats.directions,
        solution.stats.dispatch_seconds + solution.stats.propagate_seconds
    );
}
