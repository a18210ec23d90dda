//! Measures the direct-light pass on the Cornell box against the study's reference
//! (`cargo run --release --example direct_light [REFERENCE_DENSE_DIRECTIONS]`): plain solves and
//! solves with the direct pass at a few bounce direction counts, the errors at the study's
//! probes, and the time. With an argument the reference itself uses a direct pass of that many
//! dense directions (default: the study's plain reference).
use voxrad::study::{run, Plan, StudyScene};

fn main() {
    let reference_direct: usize = std::env::args()
        .nth(1)
        .map(|a| a.parse().expect("a direction count"))
        .unwrap_or(0);
    let scene = StudyScene::builtin("cornell").expect("built in");
    let mut plan = Plan::full();
    plan.directions = vec![49, 109, 193, 589];
    plan.tolerances.clear();
    plan.resolutions.clear();
    plan.presets = false;
    plan.reference.direct = reference_direct;
    let study = run(&scene, &plan, |r| {
        eprintln!(
            "{} {} + {}: {:.2} s, mean {:.4}",
            r.knob, r.directions_used, r.direct_used, r.seconds, r.mean_error
        )
    })
    .expect("study");
    println!("reference: {}", study.reference);
    print!("{}", study.csv());
}
