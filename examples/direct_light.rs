//! Measures the direct-light pass on the Cornell box at the study's probes, against the study's
//! reference (`voxrad study cornell`'s, a plain solve at resolution 64 and 2353 directions).
//!
//! `cargo run --release --example direct_light pairs [REFERENCE_DENSE]`: plain solves and solves
//! with the direct pass at a few (bounce directions, dense directions) pairs, from the study's
//! base (resolution 32, tolerance 1e-5). `... presets [REFERENCE_DENSE]`: the quality presets
//! and candidates with the direct pass. With `REFERENCE_DENSE` the reference itself runs a
//! direct pass of that many dense directions.
use voxrad::study::{run, Plan, Settings, StudyScene};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let what = args.first().map(String::as_str).unwrap_or("pairs");
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
                direct,
            };
            plan.candidates = vec![
                at(32, 49, 1e-2, 20_000),
                at(32, 109, 1e-2, 20_000),
                at(32, 109, 1e-4, 20_000),
                at(32, 193, 1e-4, 20_000),
                at(48, 193, 1e-4, 20_000),
                at(64, 589, 1e-5, 80_000),
                at(64, 1201, 1e-5, 80_000),
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
