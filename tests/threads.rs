//! Thread-count invariance: the same scene solved with 1, 2, 3 and 5 threads gives bitwise the
//! same radiosity, the same iteration count and the same energy figures.
//!
//! The brief requires results that do not depend on thread count. The solver is built for more
//! than that: dispatch lays each line's partial lists out in one array whatever the split, and
//! every surfel side receives exactly one gather per direction, accumulated in direction order, so
//! no floating-point sum is ever reordered by the thread split. Comparing `f32` bits (not values
//! to a tolerance) holds the implementation to that design: any race or split-dependent order
//! shows up here as a changed bit. Two scenes: the Cornell box (two blocks, coloured walls, a small
//! lamp) and a furnished procedural room (many plane groups, edges and corners).

mod common;

use voxrad::scene::Scene;
use voxrad::solve::{solve, Solution, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn solve_with_threads(scene: &Scene, resolution: u32, threads: usize) -> (Solution, usize) {
    let set = voxelize(scene, GridSpec::Resolution(resolution)).expect("voxelize");
    let options = SolveOptions {
        directions: 150,
        max_iterations: 5,
        tolerance: None,
        threads,
        ..Default::default()
    };
    let solution = solve(&set, &options).expect("solve");
    (solution, set.surfels.len())
}

fn bits(solution: &Solution) -> Vec<u32> {
    common::radiosity_bits(solution)
}

fn assert_thread_invariant(name: &str, scene: &Scene, resolution: u32) {
    let (reference, surfels) = solve_with_threads(scene, resolution, 1);
    assert!(surfels > 1000, "{name}: only {surfels} surfels");
    assert_eq!(reference.stats.iterations, 5, "{name}");
    assert_eq!(reference.stats.threads, 1);
    let reference_bits = bits(&reference);
    // The test means something only if light actually moved.
    let lit = reference
        .radiosity
        .iter()
        .filter(|s| s.iter().flatten().any(|&v| v > 0.0))
        .count();
    assert!(
        lit * 2 > surfels,
        "{name}: only {lit} of {surfels} surfels lit"
    );
    for threads in [2, 3, 5] {
        let (solution, n) = solve_with_threads(scene, resolution, threads);
        assert_eq!(n, surfels, "{name}: voxelization changed");
        assert_eq!(solution.stats.threads, threads);
        assert_eq!(
            solution.stats.iterations, reference.stats.iterations,
            "{name}: {threads} threads"
        );
        assert_eq!(solution.stats.directions, reference.stats.directions);
        assert_eq!(solution.stats.updates, reference.stats.updates);
        let b = bits(&solution);
        if let Some(k) = (0..b.len()).find(|&k| b[k] != reference_bits[k]) {
            panic!(
                "{name}: {threads} threads: value {k} (surfel {}, side {}, channel {}) is {} \
                 instead of {}",
                k / 6,
                (k / 3) % 2,
                k % 3,
                f32::from_bits(b[k]),
                f32::from_bits(reference_bits[k])
            );
        }
        assert_eq!(
            solution.stats.last_change.to_bits(),
            reference.stats.last_change.to_bits(),
            "{name}: {threads} threads"
        );
        for ch in 0..3 {
            assert_eq!(
                solution.stats.emitted_power[ch].to_bits(),
                reference.stats.emitted_power[ch].to_bits()
            );
            assert_eq!(
                solution.stats.absorbed_power[ch].to_bits(),
                reference.stats.absorbed_power[ch].to_bits(),
                "{name}: {threads} threads, channel {ch}"
            );
        }
    }
}

#[test]
fn cornell_box_is_bitwise_thread_invariant() {
    assert_thread_invariant("cornell", &voxrad::gen::cornell_box(), 40);
}

#[test]
fn furnished_room_is_bitwise_thread_invariant() {
    assert_thread_invariant("room", &voxrad::gen::room(5.0, 11, 6), 40);
}
