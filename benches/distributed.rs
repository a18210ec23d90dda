//! The MPI modes measured, and a model that predicts them on more ranks (needs the `mpi` feature
//! and Open MPI's `mpirun`).
//!
//! 1. **Speed-up at 2 ranks** for each mode against one process (one thread per rank, so the
//!    machine's two cores are used once): the wall-clock seconds of the whole solve call (the
//!    `solve` phase of `report.json`), and the data mode's phases on every rank.
//! 2. **Exchanged fraction and imbalance for 2 to 64 ranks** in the data mode (and hybrid): more
//!    ranks than cores are oversubscribed, which ruins their times but not these two figures, which
//!    depend only on the distribution.
//! 3. **The model**: a solve of `I` iterations on `P` ranks with `n` surfels and `D` directions,
//!    the first iteration searching for partners and writing the links down, the later ones
//!    replaying them (in every mode, when the links fit in memory):
//!    - directions: `T = (c1 + (I - 1) cr) n D / P + I T_sum`, where the sum of `6 n` values is a
//!      reduce-scatter and an all-gather: `T_sum = 2 (alpha (P - 1) + 48 n (P - 1) / (P beta))`;
//!    - data: the first iteration `(c1 + o) n D imb(P) / P + D (alpha (P - 1) + f(P) (n / P) b /
//!      beta)`, each later one `cr n D imb(P) / P` (no surfel moves: the light stays on the rank
//!      that gathers it), and every iteration ends with `T_end = 2 alpha (P - 1) + m(P) (n / P) 76
//!      / beta`: each rank sends its part of the light of the `m(P) n / P` surfels it has met to
//!      their owners (52 bytes; 20 in a grey scene, which gathers one channel) and gets their
//!      radiosity back (24; 8). The Cornell box measured here is coloured. `o` is the data
//!      mode's own work per held surfel and direction (balance, fill, merge), `b` the bytes sent
//!      per exchanged surfel, `f` the exchanged fraction, `imb` the imbalance;
//!    - hybrid with `G` groups of `Q = P / G` ranks: the data mode's terms on `Q` ranks for `D / G`
//!      directions, and the same end of iteration over all `P` ranks with `m(Q)`;
//!    - without the links (they do not fit): every iteration is a first one;
//!    - the data mode out of core: each iteration takes the in-memory data mode's time for it,
//!      or the time its disk takes to move the bytes measured at 2 ranks (per surfel-direction
//!      of the scene, shared by the ranks) if that is longer. The first iteration's bytes and a
//!      later one's (replaying the links from disk) are measured apart, from runs of 1 and 3
//!      iterations; where the links do not fit the disk, every iteration is a first one. The
//!      disk's bandwidth per rank is assumed (`--disk`).
//!
//!    `c1` and `cr` (seconds per voxel-direction of a first and of a later iteration) come from
//!    one-process runs of 1 and `I` iterations, `o` from the 2-rank data run's phases (the
//!    direct-light pass off in both), `beta` from the bytes and seconds of the 2-rank data
//!    exchange (shared memory here; a cluster's network is slower, so both are printed), `alpha`
//!    is a latency per peer per exchange (assumed, printed), `f`, `imb` and `m` are measured up
//!    to 64 ranks and extrapolated beyond by a power law fitted to them.
//!
//! ```text
//! cargo bench --features mpi --bench distributed
//! cargo bench --features mpi --bench distributed -- --resolution 96 --directions 193 --iterations 4 \
//!     --sweep-ranks 2,4,8,16,32,64 --sweep-resolution 64 --sweep-directions 589
//! cargo bench --features mpi --bench distributed -- --speedup-only   # part 1 alone
//! cargo bench --features mpi --bench distributed -- --speedup-only --repeat 5   # best of 5 rounds
//! ```

use serde_json::Value;
use std::path::Path;
use std::process::Command;

struct Args {
    resolution: u32,
    directions: usize,
    iterations: usize,
    sweep_ranks: Vec<usize>,
    sweep_resolution: u32,
    sweep_directions: usize,
    /// Latency per peer per exchange assumed by the model (seconds).
    alpha: f64,
    /// A cluster network's bandwidth per rank for the model's second column (bytes/s).
    network_beta: f64,
    /// A node's disk bandwidth per rank for the data mode out of core (bytes/s).
    disk: f64,
    /// Only the speed-up at 2 ranks (for a quiet machine), no sweep and no model.
    speedup_only: bool,
    /// Rounds of the speed-up runs: every round runs one process and each mode once, one
    /// after another, and the table gives each one's best and median (a shared machine's
    /// speed drifts between minutes).
    repeat: usize,
}

fn parse_args() -> Args {
    let mut a = Args {
        resolution: 96,
        directions: 193,
        iterations: 4,
        sweep_ranks: vec![2, 4, 8, 16, 32, 64],
        sweep_resolution: 64,
        sweep_directions: 589,
        alpha: 5e-6,
        network_beta: 5e9,
        disk: 2e9,
        speedup_only: false,
        repeat: 1,
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let mut k = 0;
    while k < argv.len() {
        let value = argv.get(k + 1).cloned().unwrap_or_default();
        let number = |v: &str| -> f64 { v.parse().unwrap_or_else(|_| panic!("bad value {v}")) };
        match argv[k].as_str() {
            "--speedup-only" => {
                a.speedup_only = true;
                k += 1;
                continue;
            }
            "--resolution" => a.resolution = number(&value) as u32,
            "--directions" => a.directions = number(&value) as usize,
            "--iterations" => a.iterations = number(&value) as usize,
            "--repeat" => a.repeat = (number(&value) as usize).max(1),
            "--sweep-resolution" => a.sweep_resolution = number(&value) as u32,
            "--sweep-directions" => a.sweep_directions = number(&value) as usize,
            "--alpha" => a.alpha = number(&value),
            "--network-beta" => a.network_beta = number(&value),
            "--disk" => a.disk = number(&value),
            "--sweep-ranks" => {
                a.sweep_ranks = value.split(',').map(|r| number(r) as usize).collect()
            }
            _ => {
                k += 1;
                continue;
            }
        }
        k += 2;
    }
    a
}

/// Runs `voxrad solve` on the Cornell box (under `mpirun -n ranks` unless `ranks` is `None`) and
/// returns its report.
fn solve(
    ranks: Option<usize>,
    extra: &[&str],
    resolution: u32,
    directions: usize,
    iterations: usize,
) -> Value {
    let out = tempfile::tempdir().expect("temporary directory");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let binary = env!("CARGO_BIN_EXE_voxrad");
    let mut command = match ranks {
        None => Command::new(binary),
        Some(p) => {
            let mut c = Command::new("mpirun");
            c.args(["-n", &p.to_string(), "--oversubscribe"])
                .args(["--mca", "btl", "self,vader"])
                .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
                .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
                .arg(binary);
            c
        }
    };
    let output = command
        .arg("solve")
        .arg(&scene)
        .arg("--out")
        .arg(out.path())
        .args(["--resolution", &resolution.to_string()])
        .args(["--directions", &directions.to_string()])
        .args(["--iterations", &iterations.to_string()])
        .args(["--threads", "1", "--image-size", "64x48"])
        .args(extra)
        .output()
        .expect("run voxrad (and mpirun)");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let text = std::fs::read(out.path().join("report.json")).expect("report.json");
    serde_json::from_slice(&text).expect("report.json parses")
}

fn seconds(report: &Value, phase: &str) -> f64 {
    report["seconds"][phase].as_f64().unwrap_or(0.0)
}

/// Least-squares fit of `y = a x^b` on log axes.
fn power_law(points: &[(f64, f64)]) -> (f64, f64) {
    let pts: Vec<(f64, f64)> = points
        .iter()
        .filter(|p| p.0 > 0.0 && p.1 > 0.0)
        .map(|&(x, y)| (x.ln(), y.ln()))
        .collect();
    let m = pts.len() as f64;
    let (sx, sy) = pts.iter().fold((0.0, 0.0), |a, p| (a.0 + p.0, a.1 + p.1));
    let (sxx, sxy) = pts
        .iter()
        .fold((0.0, 0.0), |a, p| (a.0 + p.0 * p.0, a.1 + p.0 * p.1));
    let b = (m * sxy - sx * sy) / (m * sxx - sx * sx);
    let a = ((sy - b * sx) / m).exp();
    (a, b)
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let args = parse_args();
    let (res, dirs, iters) = (args.resolution, args.directions, args.iterations);

    let rounds = args.repeat;
    println!("## Speed-up at 2 ranks (Cornell box, resolution {res}, {dirs} directions, {iters} iterations, 1 thread per rank, {rounds} round(s))\n");
    let runs: [(&str, &[&str]); 4] = [
        ("directions", &["--distribute", "directions"]),
        ("data", &["--distribute", "data"]),
        // Two groups of one rank (one group of two is the data mode).
        (
            "hybrid, 2 groups",
            &["--distribute", "hybrid", "--groups", "2"],
        ),
        (
            "data, zstd exchange",
            &["--distribute", "data", "--compress-exchange"],
        ),
    ];
    // Seconds by round: the one process first, then each mode.
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); runs.len() + 1];
    let mut single = Value::Null;
    let mut data2 = Value::Null;
    for _ in 0..rounds {
        let report = solve(None, &[], res, dirs, iters);
        times[0].push(seconds(&report, "solve"));
        single = report;
        for (k, (name, extra)) in runs.iter().enumerate() {
            let report = solve(Some(2), extra, res, dirs, iters);
            times[k + 1].push(seconds(&report, "solve"));
            if *name == "data" {
                data2 = report;
            }
        }
    }
    let best = |t: &[f64]| t.iter().copied().fold(f64::INFINITY, f64::min);
    let median = |t: &[f64]| {
        let mut v = t.to_vec();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let n = single["surfels"].as_f64().unwrap_or(0.0);
    let d = single["directions"].as_f64().unwrap_or(0.0);
    let t1 = best(&times[0]);
    println!("| mode | ranks | solve s (best) | speed-up | efficiency (best against best) | efficiency (median of the rounds' own) |");
    println!("|---|---|---|---|---|---|");
    println!("| one process | 1 | {t1:.2} | 1.00 | 100% | 100% |");
    for (k, (name, _)) in runs.iter().enumerate() {
        let t = best(&times[k + 1]);
        let own: Vec<f64> = times[0]
            .iter()
            .zip(&times[k + 1])
            .map(|(one, here)| one / here / 2.0)
            .collect();
        println!(
            "| {name} | 2 | {t:.2} | {:.2} | {:.0}% | {:.0}% |",
            t1 / t,
            100.0 * t1 / t / 2.0,
            100.0 * median(&own)
        );
    }
    let phases = &data2["data_distribution"]["per_rank"];
    println!("\nData mode, 2 ranks, seconds per phase:\n");
    println!("| rank | balance | fill | exchange | merge | dispatch | propagate | reduce |");
    println!("|---|---|---|---|---|---|---|---|");
    for (r, p) in phases.as_array().into_iter().flatten().enumerate() {
        let f = |k: &str| p[k].as_f64().unwrap_or(0.0);
        println!(
            "| {r} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} |",
            f("balance"),
            f("fill"),
            f("exchange"),
            f("merge"),
            f("dispatch"),
            f("propagate"),
            f("reduce")
        );
    }

    if args.speedup_only {
        return;
    }
    let (sres, sdirs) = (args.sweep_resolution, args.sweep_directions);
    println!("\n## Exchanged fraction and imbalance (Cornell box, resolution {sres}, {sdirs} directions, 1 iteration)\n");
    println!("| mode | ranks | groups | exchanged mean | exchanged max | imbalance mean | imbalance max | bytes sent per surfel-direction | met per rank / (n / P) |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut fractions = Vec::new();
    let mut imbalances = Vec::new();
    let mut sent_per_moved = Vec::new();
    let mut met = Vec::new();
    for &p in &args.sweep_ranks {
        let mut modes = vec!["data"];
        if p >= 4 {
            modes.push("hybrid");
        }
        for mode in modes {
            let r = solve(Some(p), &["--distribute", mode], sres, sdirs, 1);
            let dd = &r["data_distribution"];
            let f = |k: &str| dd[k].as_f64().unwrap_or(0.0);
            let (surfels, directions) = (
                r["surfels"].as_f64().unwrap_or(1.0),
                r["directions"].as_f64().unwrap_or(1.0),
            );
            let per_update = f("bytes_sent") / (surfels * directions);
            println!(
                "| {mode} | {p} | {} | {:.4} | {:.3} | {:.4} | {:.3} | {per_update:.2} | {:.2} |",
                dd["groups"],
                f("exchanged_fraction"),
                f("max_exchanged_fraction"),
                f("imbalance"),
                f("max_imbalance"),
                f("end_of_iteration_bytes") / 76.0 / surfels,
            );
            if mode == "data" {
                // Surfels each rank has met over the iteration, over its share n / P: the end of
                // the iteration moves 76 bytes for each of the coloured Cornell box's (one
                // iteration here).
                let met_per_rank = f("end_of_iteration_bytes") / 76.0 / p as f64;
                met.push((p as f64, met_per_rank / (surfels / p as f64)));
                fractions.push((p as f64, f("exchanged_fraction")));
                imbalances.push((p as f64, f("imbalance") - 1.0));
                let moved = f("exchanged_fraction") * surfels * directions;
                if moved > 0.0 {
                    sent_per_moved.push(f("bytes_sent") / moved);
                }
            }
        }
    }

    // The model's parameters: first and later iterations apart, without the direct-light pass
    // (the model is of the bounces).
    let plain = ["--direct-directions", "0"];
    let first = solve(None, &plain, res, dirs, 1);
    let all = solve(None, &plain, res, dirs, iters.max(2));
    let c1 = seconds(&first, "solve") / (n * d);
    let cr = (seconds(&all, "solve") - seconds(&first, "solve")).max(0.0)
        / (n * d * (iters.max(2) - 1) as f64);
    let link_bytes = all["links"]["bytes_per_surfel_direction"]
        .as_f64()
        .unwrap_or(0.0);
    let data_first = solve(
        Some(2),
        &["--distribute", "data", "--direct-directions", "0"],
        res,
        dirs,
        1,
    );
    let phases = data_first["data_distribution"]["per_rank"].clone();
    let phase = |r: usize, k: &str| phases[r][k].as_f64().unwrap_or(0.0);
    let exchange_seconds = (phase(0, "exchange") + phase(1, "exchange")) / 2.0;
    let own_seconds = (0..2)
        .map(|r| phase(r, "balance") + phase(r, "fill") + phase(r, "merge"))
        .sum::<f64>()
        / 2.0;
    let o = own_seconds / (n / 2.0 * d);
    let bytes2 = data_first["data_distribution"]["bytes_sent"]
        .as_f64()
        .unwrap_or(0.0)
        / 2.0;
    let beta_here = if exchange_seconds > 0.0 {
        bytes2 / exchange_seconds
    } else {
        f64::INFINITY
    };
    // The data mode out of core at 2 ranks: the bytes each rank reads and writes per
    // surfel-direction of the scene in its first iteration (searching, links written to disk)
    // and in each later one (replaying them), from runs of 1 and 3 iterations.
    let ooc_run = |iterations: usize| {
        solve(
            Some(2),
            &[
                "--distribute",
                "data",
                "--direct-directions",
                "0",
                "--memory",
                "4MiB",
            ],
            res,
            dirs,
            iterations,
        )
    };
    let moved_per_rank = |report: &Value| {
        report["data_distribution"]["out_of_core"]
            .as_array()
            .map(|ranks| {
                ranks
                    .iter()
                    .map(|r| {
                        r["bytes_read"].as_f64().unwrap_or(0.0)
                            + r["bytes_written"].as_f64().unwrap_or(0.0)
                    })
                    .sum::<f64>()
                    / ranks.len().max(1) as f64
            })
            .unwrap_or(0.0)
    };
    let (ooc1, ooc3) = (ooc_run(1), ooc_run(3));
    let ooc_first_bytes = moved_per_rank(&ooc1) / (n * d);
    let ooc_later_bytes =
        ((moved_per_rank(&ooc3) - moved_per_rank(&ooc1)) / 2.0).max(0.0) / (n * d);
    let ooc_link_bytes = ooc3["links"]["bytes_per_surfel_direction"]
        .as_f64()
        .unwrap_or(0.0);
    let b = sent_per_moved.iter().sum::<f64>() / sent_per_moved.len().max(1) as f64;
    let (fa, fb) = power_law(&fractions);
    let (ia, ib) = power_law(&imbalances);
    let (ma, mb) = power_law(&met);
    let measured = |table: &[(f64, f64)], p: f64| table.iter().find(|x| x.0 == p).map(|x| x.1);
    let fraction = |p: f64| {
        if p <= 1.0 {
            return 0.0;
        }
        measured(&fractions, p).unwrap_or(fa * p.powf(fb)).min(1.0)
    };
    let imbalance = |p: f64| {
        if p <= 1.0 {
            return 1.0;
        }
        1.0 + measured(&imbalances, p).unwrap_or(ia * p.powf(ib))
    };
    // A rank meets at least its share and at most the whole scene.
    let met_share = |p: f64| measured(&met, p).unwrap_or(ma * p.powf(mb)).clamp(1.0, p);
    println!("\n## Model\n");
    println!(
        "c1 = {c1:.3e} s per voxel-direction in a first iteration, cr = {cr:.3e} in a later one \
         (one process, one thread, links kept: {link_bytes:.2} bytes per surfel-direction); \
         o = {o:.3e} s per held surfel and direction (data mode, first iteration: balance, fill, \
         merge); b = {b:.1} bytes sent per exchanged surfel; beta = {:.2} GB/s measured here \
         (shared memory), {:.2} GB/s assumed for a network; alpha = {:.1} us per peer per \
         exchange (assumed); f(P) = {fa:.4} P^{fb:.3}, imbalance(P) - 1 = {ia:.4} P^{ib:.3}, \
         m(P) = {ma:.3} P^{mb:.3} beyond the measured ranks; the data mode out of core moved \
         {ooc_first_bytes:.0} bytes per surfel-direction of the scene through each of 2 ranks' \
         disks (read and written) in its first iteration and {ooc_later_bytes:.0} in each later \
         one (replaying its links from disk, {ooc_link_bytes:.2} bytes per surfel-direction), \
         so {:.0} and {:.0} per surfel-direction of the scene in all, and a disk of {:.2} GB/s \
         per rank is assumed.\n",
        beta_here / 1e9,
        args.network_beta / 1e9,
        args.alpha * 1e6,
        2.0 * ooc_first_bytes,
        2.0 * ooc_later_bytes,
        args.disk / 1e9,
    );
    let (big_n, big_d, big_i) = (1e10, 589.0, 10.0);
    println!(
        "Predicted seconds for a solve of {big_i} iterations, n = 10^10 surfels, D = {big_d} \
         directions, with the network's beta (parallel efficiency against one process; links \
         per rank: the bytes each rank's links would take, in memory beside the scene or on its \
         disk out of core; without links, against one process that searches in every iteration \
         too; out of core, an iteration takes the longer of its disk's time for the bytes \
         measured at 2 ranks, shared by the ranks, and the in-memory data mode's time):\n"
    );
    println!("| ranks | links per rank (memory) | links per rank (disk) | directions | data | hybrid G = sqrt P | data, links not kept | data, shared-memory beta | data out of core, links on disk | data out of core, links not kept |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for p in [8.0f64, 64.0, 512.0] {
        let one = (c1 + (big_i - 1.0) * cr) * big_n * big_d;
        let sum = |ranks: f64, values: f64, beta: f64| {
            2.0 * (args.alpha * (ranks - 1.0) + 8.0 * values * (ranks - 1.0) / ranks / beta)
        };
        let directions_mode = |beta: f64| one / p + big_i * sum(p, 6.0 * big_n, beta);
        // The data mode's iterations on `q` ranks of a group taking `dirs` directions, with
        // `p` ranks in all adding the light at the ends of iterations.
        // The data mode's first iteration, a later one (replaying the links) and the end of
        // each, on `q` ranks of a group taking `dirs` directions, with `p` ranks in all adding
        // the light at the ends of iterations.
        let data_parts = |p: f64, q: f64, dirs: f64, beta: f64| {
            let first = (c1 + o) * big_n * dirs * imbalance(q) / q
                + dirs * (args.alpha * (q - 1.0) + fraction(q) * (big_n / q) * b / beta);
            let later = cr * big_n * dirs * imbalance(q) / q;
            let end = 2.0 * args.alpha * (p - 1.0) + met_share(q) * (big_n / q) * 76.0 / beta;
            (first, later, end)
        };
        let data_mode = |p: f64, q: f64, dirs: f64, beta: f64, links: bool| {
            let (first, later, end) = data_parts(p, q, dirs, beta);
            let later = if links { later } else { first };
            first + (big_i - 1.0) * later + big_i * end
        };
        let g = (p.sqrt().floor()).max(1.0);
        let beta = args.network_beta;
        let eff = |t: f64| 100.0 * one / p / t;
        // Against one process that cannot keep its links either.
        let one_searching = big_i * c1 * big_n * big_d;
        // Out of core an iteration moves its bytes through the disk, which sets the pace
        // unless the computing is slower: the first searches and writes the links down, the
        // later ones replay them from disk, or search again where the disk cannot hold them.
        let disk = |bytes: f64| 2.0 * bytes * big_n * big_d / p / args.disk;
        let (first, later, end) = data_parts(p, p, big_d, beta);
        let ooc_first = disk(ooc_first_bytes).max(first + end);
        let tooc_links = ooc_first + (big_i - 1.0) * disk(ooc_later_bytes).max(later + end);
        let tooc = big_i * ooc_first;
        let (tdir, tdata, thyb, tnolinks, tdata_here) = (
            directions_mode(beta),
            data_mode(p, p, big_d, beta, true),
            data_mode(p, p / g, big_d / g, beta, true),
            data_mode(p, p, big_d, beta, false),
            data_mode(p, p, big_d, beta_here, true),
        );
        println!(
            "| {p} | {:.0} GB | {:.0} GB | {tdir:.0} ({:.0}%) | {tdata:.0} ({:.0}%) | {thyb:.0} ({:.0}%) | {tnolinks:.0} ({:.0}%) | {tdata_here:.0} ({:.0}%) | {tooc_links:.0} ({:.0}%) | {tooc:.0} ({:.0}%) |",
            link_bytes * big_n * big_d / p / 1e9,
            ooc_link_bytes * big_n * big_d / p / 1e9,
            eff(tdir),
            eff(tdata),
            eff(thyb),
            100.0 * one_searching / p / tnolinks,
            eff(tdata_here),
            eff(tooc_links),
            100.0 * one_searching / p / tooc,
        );
    }
}
