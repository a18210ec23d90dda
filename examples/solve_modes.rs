//! Measures what the solve shapes save: tail extrapolation (iterations and time to a given
//! error) and one-channel solves of grey scenes (time), on the furnace and the Cornell box.
//!
//! `cargo run --release --example solve_modes [RESOLUTION] [DIRECTIONS] [accel|grey]` (defaults
//! 24, 193 and both parts).
//! The figures in the README come from this program.

use std::time::Instant;
use voxrad::scene::Scene;
use voxrad::solve::{solve, Solution, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::SurfelSet;

fn timed(set: &SurfelSet, options: &SolveOptions) -> (Solution, f64) {
    let t = Instant::now();
    let s = solve(set, options).expect("solve");
    (s, t.elapsed().as_secs_f64())
}

/// Mean relative difference of all sides and channels with radiosity above 1e-6.
fn mean_error(a: &Solution, reference: &[[[f32; 3]; 2]]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for (x, r) in a.radiosity.iter().zip(reference) {
        for (&v, &w) in x.iter().flatten().zip(r.iter().flatten()) {
            if w > 1e-6 {
                sum += ((v - w) as f64 / w as f64).abs();
                n += 1;
            }
        }
    }
    sum / n.max(1) as f64
}

fn grey_cornell() -> Scene {
    let mut scene = voxrad::gen::cornell_box();
    for m in &mut scene.materials {
        let r = m.reflectance.iter().sum::<f64>() / 3.0;
        let e = m.emission.iter().sum::<f64>() / 3.0;
        m.reflectance = [r; 3];
        m.emission = [e; 3];
    }
    scene
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let resolution: u32 = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(24);
    let directions: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(193);
    let base = SolveOptions {
        directions,
        max_iterations: 100_000,
        ..Default::default()
    };
    let part = args.get(3).map(String::as_str).unwrap_or("both");
    println!("resolution {resolution}, {directions} directions requested\n");
    if part != "grey" {
        extrapolation(resolution, &base);
    }
    if part != "accel" {
        one_channel(resolution, &base);
    }
}

fn extrapolation(resolution: u32, base: &SolveOptions) {
    println!("## Tail extrapolation: iterations and seconds to tolerance 1e-4\n");
    println!("| scene | plain iterations | plain s | plain error | extrapolated iterations | extrapolated s | extrapolated error |");
    println!("|---|---|---|---|---|---|---|");
    let scenes: Vec<(String, Scene, Option<f64>)> = vec![
        (
            "furnace rho 0.9".into(),
            voxrad::gen::furnace(1.0, 0.9),
            Some(10.0),
        ),
        (
            "furnace rho 0.99".into(),
            voxrad::gen::furnace(1.0, 0.99),
            Some(100.0),
        ),
        ("Cornell box".into(), voxrad::gen::cornell_box(), None),
    ];
    for (name, scene, analytic) in &scenes {
        let set = voxelize(scene, GridSpec::Resolution(resolution)).expect("voxelize");
        let reference: Vec<[[f32; 3]; 2]> = match analytic {
            // Every inner side at E / (1 - rho); outer (back) sides are 0 in both.
            Some(b) => set
                .surfels
                .iter()
                .map(|_| [[*b as f32; 3], [0.0; 3]])
                .collect(),
            None => {
                // 1e-6 is about as far as f32 storage lets the estimate go (see hard_cases.rs).
                let tight = SolveOptions {
                    tolerance: Some(1e-6),
                    max_iterations: 2_000,
                    ..base.clone()
                };
                timed(&set, &tight).0.radiosity
            }
        };
        let furnace_error = |s: &Solution| -> f64 {
            // Compare the side that carries light (the larger) only.
            let (mut sum, mut n) = (0.0, 0usize);
            for (x, r) in s.radiosity.iter().zip(&reference) {
                let side = if x[0][0] >= x[1][0] { 0 } else { 1 };
                sum += ((x[side][0] - r[0][0]) as f64 / r[0][0] as f64).abs();
                n += 1;
            }
            sum / n as f64
        };
        let err = |s: &Solution| {
            if analytic.is_some() {
                furnace_error(s)
            } else {
                mean_error(s, &reference)
            }
        };
        let options = SolveOptions {
            tolerance: Some(1e-4),
            ..base.clone()
        };
        let (plain, tp) = timed(&set, &options);
        let (fast, tf) = timed(
            &set,
            &SolveOptions {
                accelerate: true,
                ..options.clone()
            },
        );
        println!(
            "| {name} | {} | {tp:.2} | {:.1e} | {} ({} extrapolations) | {tf:.2} | {:.1e} |",
            plain.stats.iterations,
            err(&plain),
            fast.stats.iterations,
            fast.stats.extrapolations,
            err(&fast)
        );
    }
}

fn one_channel(resolution: u32, base: &SolveOptions) {
    println!("\n## One channel for grey scenes: seconds per iteration\n");
    println!("| scene | surfels | three channels s/iteration | one channel s/iteration | saved |");
    println!("|---|---|---|---|---|");
    for (name, scene) in [
        ("furnace rho 0.9", voxrad::gen::furnace(1.0, 0.9)),
        ("grey Cornell box", grey_cornell()),
    ] {
        let set = voxelize(&scene, GridSpec::Resolution(resolution)).expect("voxelize");
        let fixed = SolveOptions {
            max_iterations: 10,
            tolerance: None,
            ..base.clone()
        };
        // Alternate to spread the machine's load evenly; keep the best of five.
        let (mut rgb, mut grey) = (f64::MAX, f64::MAX);
        for _ in 0..5 {
            let (s, t) = timed(&set, &fixed);
            rgb = rgb.min(t / s.stats.iterations as f64);
            let (s, t) = timed(
                &set,
                &SolveOptions {
                    grey: true,
                    ..fixed.clone()
                },
            );
            assert_eq!(s.stats.channels, 1);
            grey = grey.min(t / s.stats.iterations as f64);
        }
        println!(
            "| {name} | {} | {rgb:.4} | {grey:.4} | {:.1} % |",
            set.surfels.len(),
            100.0 * (1.0 - grey / rgb)
        );
    }
}
