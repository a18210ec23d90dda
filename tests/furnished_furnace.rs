//! The generalised furnace: in a closed enclosure where every surface emits `E` from its front and
//! reflects `rho`, every front side that looks into the enclosure sees only surfaces of radiosity
//! `B`, so `B = E / (1 - rho)` everywhere, however cluttered the room. A furnished room (tables on
//! legs, cabinets, shelves) checks that the partner rule loses little light around furniture,
//! edges and corners.
//!
//! Exceptions that are physics, not error: faces in contact (the floor under a cabinet, a leg's
//! foot) see the unlit inside of a solid and come out near `E`; they are the few percent of
//! surfels with errors near 0.5. The test therefore bounds the median and the 90th percentile.
//! Measured at this setting: median 2.3e-3, 90th percentile 9.2e-3 (an empty box is exact to
//! 1e-6, see `furnace.rs`); the rest is the boundary voxels of furniture edges.

use voxrad::solve::{solve, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

#[test]
fn furnished_room_furnace() {
    let mut scene = voxrad::gen::room(5.0, 3, 6);
    let (e, rho) = (1.0, 0.5);
    for m in &mut scene.materials {
        m.emission = [e; 3];
        m.reflectance = [rho; 3];
    }
    let set = voxelize(&scene, GridSpec::Resolution(64)).unwrap();
    let options = SolveOptions {
        directions: 300,
        max_iterations: 500,
        tolerance: Some(1e-7),
        threads: 2,
        ..Default::default()
    };
    let solution = solve(&set, &options).unwrap();
    let expected = e / (1.0 - rho);
    let mut errors: Vec<f64> = set
        .surfels
        .iter()
        .zip(&solution.radiosity)
        .filter(|(s, _)| s.area >= 0.05)
        .map(|(_, b)| (b[0][0] as f64 - expected).abs() / expected)
        .collect();
    errors.sort_by(|a, b| a.total_cmp(b));
    let n = errors.len();
    let (median, p90) = (errors[n / 2], errors[n * 9 / 10]);
    let contacts = errors.iter().filter(|&&x| x > 0.3).count();
    println!("{n} front sides: median error {median:.2e}, 90th percentile {p90:.2e}, {contacts} above 0.3 (contacts)");
    assert!(n > 10_000);
    assert!(median < 5e-3, "median {median}");
    assert!(p90 < 1e-2, "90th percentile {p90}");
}
