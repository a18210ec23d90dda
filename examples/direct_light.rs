//! Measures the direct-light pass on the Cornell box at the study's probes, against the study's
//! reference (`voxrad study cornell`'s, a plain solve at resolution 64 and 2353 directions).
//!
//! `cargo run --release --example direct_light pairs [REFERENCE_DENSE]`: plain solves and solves
//! with the direct pass at a few (bounce directions, dense directions) pairs, from the study's
//! base (resolution 32, tolerance 1e-5). `... presets [REFERENCE_DENSE]`: the quality presets
//! and candidates with the direct pass. With `REFERENCE_DENSE` the reference itself runs a
//! direct pass of that many dense directions. `... cost RESOLUTION DIRECTIONS`: the time of the
//! default preset's solve (tolerance 1e-4, extrapolation) without and with the pass at 4,801,
//! 20,173 and 80,689 dense directions, best of five, interleaved (a busy machine's noise), and
//! the pass's own share. `... preset-cost`: the solve time of the quality presets before the
//! pass (draft 32/109/1e-2, default 32/589/1e-4, high 64/1201/1e-5, no pass) and now, best of
//! three, interleaved (`... preset-cost NAME`: that preset only).
use voxrad::study::{run, Plan, Settings, StudyScene};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let what = args.first().map(String::as_str).unwrap_or("pairs");
    if what == "cost" {
        let number = |i: usize, default: usize| {
            args.get(i)
                .map_or(default, |a| a.parse().expect("a number"))
        };
        cost(number(1, 32) as u32, number(2, 193));
        return;
    }
    if what == "preset-cost" {
        preset_cost();
        return;
    }
    let reference_direct: usize = args.get(1).map_or(0, |a| a.parse().expect("a count"));
    let scene = StudyScene::builtin("cornell").expect("built in");
    let mut plan = Plan::full();
    plan.tolerances.clear();
    plan.resolutions.clear();
    plan.reference.direct = reference_direct;
    match what {
        "pairs" => {
            plan.directions = vec![49, 109, 193, 589];
            plan.presets = false;
        }
        "presets" => {
            plan.directions.clear();
            plan.direct.clear();
            let at = |resolution, directions, tolerance, direct| Settings {
                resolution,
                directions,
                tolerance,
                accelerate: true,
                chebyshev: false,
                direct,
            };
            // The presets before the direct pass.
            plan.candidates = vec![
                at(32, 109, 1e-2, 0),
                at(32, 589, 1e-4, 0),
                at(64, 1201, 1e-5, 0),
            ];
        }
        other => panic!("{other}: pairs or presets"),
    }
    let study = run(&scene, &plan, |r| {
        eprintln!(
            "{} res {} {} + {} tol {:e}: {:.2} s, {} iterations, mean {:.4}, max {:.3}",
            r.knob,
            r.settings.resolution,
            r.directions_used,
            r.direct_used,
            r.settings.tolerance,
            r.seconds,
            r.iterations,
            r.mean_error,
            r.max_error
        )
    })
    .expect("study");
    println!("reference: {}", study.reference);
    print!("{}", study.csv());
}

fn cost(resolution: u32, directions: usize) {
    use std::time::Instant;
    use voxrad::solve::direct::DirectPass;
    use voxrad::solve::{solve, SolveOptions};
    use voxrad::voxel::voxelize::{voxelize, GridSpec};
    let set = voxelize(
        &voxrad::gen::cornell_box(),
        GridSpec::Resolution(resolution),
    )
    .unwrap();
    let dense = [0, 4_801, 20_173, 80_689];
    let mut best = [(f64::MAX, 0.0, 0usize); 4];
    for _ in 0..5 {
        for (k, &n) in dense.iter().enumerate() {
            let t = Instant::now();
            let s = solve(
                &set,
                &SolveOptions {
                    directions,
                    tolerance: Some(1e-4),
                    accelerate: true,
                    direct: if n == 0 {
                        DirectPass::Off
                    } else {
                        DirectPass::On(n)
                    },
                    ..Default::default()
                },
            )
            .unwrap();
            let seconds = t.elapsed().as_secs_f64();
            if seconds < best[k].0 {
                let pass = s.stats.direct.as_ref().map_or(0.0, |d| d.seconds);
                best[k] = (seconds, pass, s.stats.iterations);
            }
        }
    }
    println!(
        "resolution {resolution}, {directions} directions, {} surfels",
        set.surfels.len()
    );
    for (n, (seconds, pass, iterations)) in dense.iter().zip(best) {
        println!(
            "dense {n}: {seconds:.3} s ({:+.0} %), pass {pass:.3} s, {iterations} iterations",
            100.0 * (seconds / best[0].0 - 1.0)
        );
    }
}

fn preset_cost() {
    use std::time::Instant;
    use voxrad::quality::Quality;
    use voxrad::solve::direct::DirectPass;
    use voxrad::solve::{solve, SolveOptions};
    use voxrad::voxel::voxelize::{voxelize, GridSpec};
    let scene = voxrad::gen::cornell_box();
    let only = std::env::args().nth(2);
    for (quality, old_directions) in [
        (Quality::Draft, 109),
        (Quality::Default, 589),
        (Quality::High, 1201),
    ] {
        if only.as_deref().is_some_and(|name| name != quality.name()) {
            continue;
        }
        let p = quality.preset();
        let set = voxelize(&scene, GridSpec::Resolution(p.resolution)).unwrap();
        let runs = [
            (old_directions, DirectPass::Off),
            (p.directions, DirectPass::Auto(p.direct)),
        ];
        let mut best = [f64::MAX; 2];
        let mut pass = 0.0;
        for _ in 0..3 {
            for (k, &(directions, direct)) in runs.iter().enumerate() {
                let t = Instant::now();
                let s = solve(
                    &set,
                    &SolveOptions {
                        directions,
                        tolerance: Some(p.tolerance),
                        accelerate: true,
                        direct,
                        ..Default::default()
                    },
                )
                .unwrap();
                let seconds = t.elapsed().as_secs_f64();
                if seconds < best[k] {
                    best[k] = seconds;
                    if let Some(d) = &s.stats.direct {
                        pass = d.seconds;
                    }
                }
            }
        }
        println!(
            "{}: before {:.2} s ({old_directions} directions), now {:.2} s ({} + {} dense, pass \
             {pass:.2} s)",
            quality.name(),
            best[0],
            best[1],
            p.directions,
            p.direct
        );
    }
}
