//! Partner links kept between iterations (`solve::links`): iterations that replay a direction's
//! links instead of searching its lines again give the bits of a solve that searches in every
//! iteration, with every link kept, some, or none, at 1 and 2 threads, with the direct-light
//! pass and the tail extrapolation on, under the non-uniform light of the Cornell box (its lamp,
//! its coloured walls and blocks) and in a furnished room lit by many small lamps with open
//! edges (shares below 1 and extra links on the same line).

mod common;

use voxrad::scene::obj::load_obj;
use voxrad::scene::Scene;
use voxrad::solve::direct::DirectPass;
use voxrad::solve::{solve, Solution, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::SurfelSet;

fn options(threads: usize, links_memory: u64) -> SolveOptions {
    SolveOptions {
        directions: 120,
        max_iterations: 6,
        tolerance: None,
        threads,
        accelerate: true,
        direct: DirectPass::On(200),
        links_memory: Some(links_memory),
        ..Default::default()
    }
}

fn bits(solution: &Solution) -> Vec<u32> {
    common::radiosity_bits(solution)
}

fn assert_links_change_no_bit(name: &str, set: &SurfelSet) {
    let searched = solve(set, &options(1, 0)).expect("solve");
    let none = searched
        .stats
        .links
        .clone()
        .expect("in-memory link figures");
    assert_eq!(none.kept_directions, 0, "{name}");
    for threads in [1, 2] {
        let all = solve(set, &options(threads, u64::MAX)).expect("solve");
        let kept = all.stats.links.clone().expect("in-memory link figures");
        assert_eq!(kept.kept_directions, kept.directions, "{name}");
        assert!(
            kept.bytes > 0 && kept.bytes_per_surfel_direction > 0.0,
            "{name}"
        );
        assert!(bits(&all) == bits(&searched), "{name}: {threads} threads");
        assert_eq!(all.stats.iterations, searched.stats.iterations, "{name}");
        // A budget for about half of them: the others are searched again each iteration.
        let half = solve(set, &options(threads, kept.bytes / 2)).expect("solve");
        let some = half.stats.links.clone().expect("in-memory link figures");
        assert!(
            some.kept_directions > 0 && some.kept_directions < some.directions,
            "{name}: {some:?}"
        );
        assert!(some.bytes <= kept.bytes / 2, "{name}");
        assert!(
            bits(&half) == bits(&searched),
            "{name}: half, {threads} threads"
        );
    }
}

#[test]
fn kept_links_give_the_bits_of_searching_again_on_the_cornell_box() {
    let obj = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let scene: Scene = load_obj(&obj).expect("load");
    let set = voxelize(&scene, GridSpec::Resolution(40)).expect("voxelize");
    assert_links_change_no_bit("cornell box", &set);
}

#[test]
fn kept_links_give_the_bits_of_searching_again_in_a_room_of_small_lamps() {
    let scene = voxrad::gen::office().scene;
    let set = voxelize(&scene, GridSpec::Resolution(40)).expect("voxelize");
    assert_links_change_no_bit("office", &set);
}
