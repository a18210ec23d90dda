//! The closed-box furnace: every wall emits `E` with reflectance `rho`, so every inner surface has
//! `B = E / (1 - rho)` exactly, whatever the direction set (thanks to the per-normal energy
//! normalisation) — provided the partner rule loses no light at edges and corners.

mod common;

use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn furnace_error(rho: f64, resolution: u32, directions: usize) -> (f64, f64, usize) {
    let e = 1.0;
    let scene = common::furnace(e, rho);
    let set = voxelize(&scene, GridSpec::Resolution(resolution)).unwrap();
    let options = SolveOptions {
        directions,
        max_iterations: 20_000,
        tolerance: Some(1e-6),
        threads: 2,
        ..Default::default()
    };
    let solution = solve(&set, &options).unwrap();
    let expected = e / (1.0 - rho);
    let (mut worst, mut sum) = (0.0f64, 0.0);
    for (k, s) in set.surfels.iter().enumerate() {
        let side = common::inner_side(s, &set);
        for ch in 0..3 {
            let err = (solution.radiosity[k][side][ch] as f64 - expected).abs() / expected;
            worst = worst.max(err);
            sum += err;
        }
    }
    (
        worst,
        sum / (3 * set.surfels.len()) as f64,
        solution.stats.iterations,
    )
}

#[test]
fn furnace_rho_0_5() {
    let (worst, mean, it) = furnace_error(0.5, 12, 150);
    println!("rho 0.5: worst {worst:e} mean {mean:e} after {it} iterations");
    assert!(worst < 1e-3);
}

#[test]
fn furnace_rho_0_9() {
    let (worst, mean, it) = furnace_error(0.9, 12, 150);
    println!("rho 0.9: worst {worst:e} mean {mean:e} after {it} iterations");
    assert!(worst < 1e-3);
}

#[test]
fn furnace_rho_0_99() {
    let (worst, mean, it) = furnace_error(0.99, 12, 150);
    println!("rho 0.99: worst {worst:e} mean {mean:e} after {it} iterations");
    assert!(worst < 1e-3);
}
