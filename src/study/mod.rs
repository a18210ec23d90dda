//! The accuracy/time study (`voxrad study`): what accuracy costs in time.
//!
//! Three knobs are swept one at a time from a base setting, so that each error source shows on
//! its own: the **direction count** (aliasing of the discrete line directions), the
//! **tolerance** (truncated iterations; swept twice, plain and with tail extrapolation, which
//! shows the acceleration's gain), and the **resolution** (voxel size). Each run is timed
//! (voxelize + solve, wall clock) and its error measured against a reference:
//! - the analytic answer where the scene has one (the furnace: `B = E / (1 - rho)` everywhere);
//! - a path-traced reference where one is committed (the Cornell box: `reference`, Mitsuba 3 at
//!   the study's own 300 probe points, built into the program), so that errors voxrad makes at
//!   every setting still show;
//! - otherwise a run at much higher settings than any swept one (stated in the outputs).
//!
//! **Like with like.** Runs at different resolutions have different surfels, so errors are
//! measured at fixed probe points: points sampled on the scene's non-emitting triangles (with a
//! fixed seed, away from triangle edges), looked up with [`crate::output::ProbeIndex`] on the side
//! their triangle faces. The error of a probe is the relative error of `B_r + B_g + B_b`; a run's
//! error is the mean over probes (and the largest is kept too).
//!
//! Outputs ([`write`]): `study.csv`, `study.md` (a Markdown table, the reference, the Pareto
//! front) and `study.png` (error against time on log axes, see `plot`).

pub mod plot;
pub mod reference;

use crate::gen;
use crate::output::{ProbeIndex, Results};
use crate::scene::Scene;
use crate::solve::{solve, SolveOptions};
use crate::voxel::voxelize::{voxelize, GridSpec};
use glam::DVec3;
use std::path::Path;
use std::time::Instant;

/// A scene to study and, where it has one, its analytic radiosity (the same on every surface)
/// or a path-traced reference at fixed probe points (`reference`).
#[derive(Clone, Debug)]
pub struct StudyScene {
    pub name: String,
    pub scene: Scene,
    pub analytic: Option<f64>,
    pub path_traced: Option<reference::Reference>,
}

/// Emission and reflectance of the built-in furnace.
pub const FURNACE: (f64, f64) = (1.0, 0.9);

impl StudyScene {
    /// A built-in scene by name (`furnace`, `cornell`), or `None`.
    pub fn builtin(name: &str) -> Option<StudyScene> {
        match name {
            "furnace" => {
                let (e, rho) = FURNACE;
                Some(StudyScene {
                    name: format!("furnace (E = {e}, rho = {rho})"),
                    scene: gen::furnace(e, rho),
                    analytic: Some(e / (1.0 - rho)),
                    path_traced: None,
                })
            }
            "cornell" => Some(StudyScene {
                name: "Cornell box".to_string(),
                scene: gen::cornell_box(),
                analytic: None,
                path_traced: Some(reference::Reference::cornell()),
            }),
            _ => None,
        }
    }
}

/// One solve's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Settings {
    pub resolution: u32,
    pub directions: usize,
    pub tolerance: f64,
    pub accelerate: bool,
    /// Chebyshev semi-iteration where the tail extrapolation finds no tail (with
    /// `accelerate` only).
    pub chebyshev: bool,
    /// Dense line directions of the direct-light pass (`solve::direct`); 0: no direct pass.
    pub direct: usize,
}

/// What to sweep.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The setting every sweep starts from (one knob changed at a time).
    pub base: Settings,
    pub directions: Vec<usize>,
    pub tolerances: Vec<f64>,
    pub resolutions: Vec<u32>,
    /// (bounce directions, dense directions) pairs run with the direct-light pass (knob
    /// `direct`).
    pub direct: Vec<(usize, usize)>,
    /// The reference run, for scenes without an analytic answer.
    pub reference: Settings,
    /// Also run the quality presets of `voxrad solve --quality` (knob `preset`).
    pub presets: bool,
    /// Further settings to measure as they are (knob `candidate`), such as presets being tuned.
    pub candidates: Vec<Settings>,
    /// Probe points.
    pub probes: usize,
    pub threads: usize,
}

impl Plan {
    /// The full study (about ten minutes on the Cornell box on two busy cores; the reference
    /// takes most of it).
    pub fn full() -> Plan {
        Plan {
            base: Settings {
                resolution: 32,
                directions: 193,
                tolerance: 1e-5,
                accelerate: false,
                chebyshev: false,
                direct: 0,
            },
            directions: vec![13, 49, 109, 193, 301, 589, 1201],
            tolerances: vec![3e-1, 1e-1, 3e-2, 1e-2, 1e-3, 1e-4, 1e-5],
            resolutions: vec![16, 24, 32, 48],
            direct: vec![
                (49, 20_000),
                (109, 20_000),
                (193, 5_000),
                (193, 20_000),
                (193, 80_000),
                (589, 20_000),
            ],
            reference: Settings {
                resolution: 64,
                directions: 2401,
                tolerance: 1e-6,
                accelerate: true,
                chebyshev: false,
                direct: 0,
            },
            presets: true,
            candidates: Vec::new(),
            probes: 300,
            threads: 0,
        }
    }

    /// Only the quality presets, no sweep: what `voxrad study --presets` runs to compare them on
    /// a scene.
    pub fn presets_only() -> Plan {
        Plan {
            directions: Vec::new(),
            tolerances: Vec::new(),
            resolutions: Vec::new(),
            direct: Vec::new(),
            presets: true,
            ..Plan::full()
        }
    }

    /// A small study for tests (seconds).
    pub fn quick() -> Plan {
        Plan {
            base: Settings {
                resolution: 16,
                directions: 49,
                tolerance: 1e-5,
                accelerate: false,
                chebyshev: false,
                direct: 0,
            },
            directions: vec![13, 49, 193],
            tolerances: vec![1e-1, 1e-2, 1e-4],
            resolutions: vec![12, 16, 24],
            direct: vec![(49, 5_000)],
            reference: Settings {
                resolution: 32,
                directions: 301,
                tolerance: 1e-6,
                accelerate: true,
                chebyshev: false,
                direct: 0,
            },
            presets: false,
            candidates: Vec::new(),
            probes: 100,
            threads: 0,
        }
    }
}

/// One run of the study.
#[derive(Clone, Debug)]
pub struct Run {
    /// Which knob this run sweeps: `directions`, `tolerance`, `tolerance+extrapolation` or
    /// `resolution`; or the quality preset it runs (`draft`, `default`, `high`).
    pub knob: &'static str,
    pub settings: Settings,
    /// Line directions actually used (the cube set nearest the request).
    pub directions_used: usize,
    /// Dense line directions the direct-light pass used (0: none).
    pub direct_used: usize,
    pub surfels: usize,
    pub iterations: usize,
    /// Voxelize + solve, wall clock.
    pub seconds: f64,
    pub mean_error: f64,
    pub max_error: f64,
    /// The same errors with each probe answered by gathering (`voxrad probe --gather`,
    /// [`crate::output::sensor`]); NaN unless the reference is path-traced.
    pub gathered_mean_error: f64,
    pub gathered_max_error: f64,
    /// No other run is both faster and more accurate.
    pub pareto: bool,
}

/// A finished study.
#[derive(Clone, Debug)]
pub struct Study {
    pub scene: String,
    /// How the reference was obtained, in words.
    pub reference: String,
    pub probes: usize,
    pub runs: Vec<Run>,
}

/// Fixed probe points `(point, normal)` on the non-emitting triangles of `scene` (on all of them
/// if every one emits, as in the furnace), area-weighted, kept away from triangle edges
/// (barycentric coordinates at least 0.1) where neighbouring surfaces would mix into a probe at
/// coarse resolutions.
pub fn probe_points(scene: &Scene, count: usize, seed: u64) -> Vec<(DVec3, DVec3)> {
    let all_emit = scene
        .triangles
        .iter()
        .all(|t| scene.materials[t.material as usize].is_emitter());
    let candidates: Vec<(usize, f64)> = scene
        .triangles
        .iter()
        .enumerate()
        .filter(|(_, t)| {
            (all_emit || !scene.materials[t.material as usize].is_emitter()) && t.area() > 0.0
        })
        .map(|(i, t)| (i, t.area()))
        .collect();
    let total: f64 = candidates.iter().map(|c| c.1).sum();
    let mut rng = gen::Rng::new(seed);
    let mut points = Vec::with_capacity(count);
    if total <= 0.0 {
        return points;
    }
    for _ in 0..count {
        let mut pick = rng.unit() * total;
        let mut chosen = candidates[candidates.len() - 1].0;
        for &(i, a) in &candidates {
            if pick < a {
                chosen = i;
                break;
            }
            pick -= a;
        }
        let t = &scene.triangles[chosen];
        // Uniform on the inner triangle whose barycentric coordinates are all at least 0.1.
        let (mut u, mut v) = (rng.unit(), rng.unit());
        if u + v > 1.0 {
            (u, v) = (1.0 - u, 1.0 - v);
        }
        let (b1, b2) = (0.1 + 0.7 * u, 0.1 + 0.7 * v);
        let b0 = 1.0 - b1 - b2;
        let [p0, p1, p2] = t.vertices;
        points.push((p0 * b0 + p1 * b1 + p2 * b2, t.cross().normalize()));
    }
    points
}

/// What one solve gave: the probe values (sum of channels; `None` where no surfel side faces
/// the probe), the run's statistics and its time.
struct Measured {
    values: Vec<Option<f64>>,
    /// The probes answered by gathering, where asked.
    gathered: Option<Vec<Option<f64>>>,
    directions: usize,
    direct: usize,
    surfels: usize,
    iterations: usize,
    seconds: f64,
}

fn measure(
    scene: &Scene,
    knob: &str,
    settings: Settings,
    probes: &[(DVec3, DVec3)],
    threads: usize,
    gather: bool,
) -> Result<Measured, String> {
    let started = Instant::now();
    let set = voxelize(scene, GridSpec::Resolution(settings.resolution))
        .map_err(|e| format!("resolution {}: {e}", settings.resolution))?;
    let analysis = crate::solve::effects::analyse(&set);
    let options = analysis.shape(&SolveOptions {
        directions: settings.directions,
        max_iterations: 100_000,
        tolerance: Some(settings.tolerance),
        threads,
        accelerate: settings.accelerate,
        chebyshev: settings.accelerate && settings.chebyshev,
        // The presets as `voxrad solve --quality` runs them (the pass decided by the scene);
        // every other run with the pass as asked.
        direct: match (settings.direct, knob) {
            (0, _) => crate::solve::direct::DirectPass::Off,
            (n, "draft" | "default" | "high") => crate::solve::direct::DirectPass::Auto(n),
            (n, _) => crate::solve::direct::DirectPass::On(n),
        },
        ..Default::default()
    });
    let solution = solve(&set, &options).map_err(|e| e.to_string())?;
    let seconds = started.elapsed().as_secs_f64();
    let results = Results::from_solution(&set, &solution).map_err(|e| e.to_string())?;
    let index = ProbeIndex::new(&results);
    let rows: Vec<_> = probes.iter().map(|&(p, n)| index.lookup(p, n)).collect();
    let sum = |row: &crate::output::ProbeRow| row.found.then(|| row.radiosity.iter().sum());
    let values = rows.iter().map(sum).collect();
    // Not part of the timed solve: an answer read afterwards, as `voxrad probe --gather` does.
    let gathered = gather.then(|| {
        let directions = crate::output::sensor::directions_for(results.grid.dims);
        let field = crate::output::sensor::SensorField::new(&results, directions);
        rows.iter().map(|row| sum(&field.gather_row(row))).collect()
    });
    Ok(Measured {
        values,
        gathered,
        directions: solution.stats.directions,
        direct: solution.stats.direct.as_ref().map_or(0, |d| d.directions),
        surfels: set.surfels.len(),
        iterations: solution.stats.iterations,
        seconds,
    })
}

/// Runs the study; `progress` is told each run as it finishes.
pub fn run(
    scene: &StudyScene,
    plan: &Plan,
    mut progress: impl FnMut(&Run),
) -> Result<Study, String> {
    let probes = match &scene.path_traced {
        Some(r) => r.points(),
        None => probe_points(&scene.scene, plan.probes, 0x5eed),
    };
    let (reference, described): (Vec<Option<f64>>, String) = match scene.analytic {
        _ if scene.path_traced.is_some() => {
            let r = scene.path_traced.as_ref().expect("checked");
            let values: Vec<Option<f64>> = r.probes.iter().map(|p| Some(p.radiosity)).collect();
            let noise = r.compare(&values).reference_noise;
            (
                values,
                format!(
                    "path-traced by Mitsuba 3 ({}, see its README): {} probes, mean relative \
                     standard error {:.2} %",
                    r.dir.display(),
                    r.probes.len(),
                    100.0 * noise
                ),
            )
        }
        Some(b) => (
            vec![Some(3.0 * b); probes.len()],
            format!("analytic: B = E / (1 - rho) = {b:.6} on every surface"),
        ),
        None => {
            let r = plan.reference;
            let m = measure(&scene.scene, "reference", r, &probes, plan.threads, false)?;
            (
                m.values,
                format!(
                    "a converged run at much higher settings: resolution {}, {} directions{}, \
                     tolerance {:.0e} ({} iterations with tail extrapolation, {} surfels, \
                     {:.1} s)",
                    r.resolution,
                    m.directions,
                    if m.direct > 0 {
                        format!(" and a direct-light pass of {} directions", m.direct)
                    } else {
                        String::new()
                    },
                    r.tolerance,
                    m.iterations,
                    m.surfels,
                    m.seconds
                ),
            )
        }
    };
    // Probes the reference sees nearly unlit (the floor under a block, a corner in deep shadow)
    // are left out: a relative error means nothing there.
    let reference = usable(reference);
    let b = plan.base;
    let mut settings: Vec<(&'static str, Settings)> = Vec::new();
    for &d in &plan.directions {
        settings.push(("directions", Settings { directions: d, ..b }));
    }
    for &t in &plan.tolerances {
        settings.push(("tolerance", Settings { tolerance: t, ..b }));
    }
    for &t in &plan.tolerances {
        settings.push((
            "tolerance+extrapolation",
            Settings {
                tolerance: t,
                accelerate: true,
                ..b
            },
        ));
    }
    for &r in &plan.resolutions {
        settings.push(("resolution", Settings { resolution: r, ..b }));
    }
    for &(directions, direct) in &plan.direct {
        settings.push((
            "direct",
            Settings {
                directions,
                direct,
                ..b
            },
        ));
    }
    if plan.presets {
        for q in crate::quality::Quality::ALL {
            let p = q.preset();
            settings.push((
                q.name(),
                Settings {
                    resolution: p.resolution,
                    directions: p.directions,
                    tolerance: p.tolerance,
                    accelerate: p.accelerate,
                    chebyshev: p.chebyshev,
                    direct: p.direct,
                },
            ));
        }
    }
    for &c in &plan.candidates {
        settings.push(("candidate", c));
    }
    let mut runs = Vec::new();
    for (knob, s) in settings {
        let gather = scene.path_traced.is_some();
        let m = measure(&scene.scene, knob, s, &probes, plan.threads, gather)?;
        let (mean_error, max_error) = errors(&m.values, &reference);
        let (gathered_mean_error, gathered_max_error) = m
            .gathered
            .as_ref()
            .map_or((f64::NAN, f64::NAN), |g| errors(g, &reference));
        let run = Run {
            knob,
            settings: s,
            directions_used: m.directions,
            direct_used: m.direct,
            surfels: m.surfels,
            iterations: m.iterations,
            seconds: m.seconds,
            mean_error,
            max_error,
            gathered_mean_error,
            gathered_max_error,
            pareto: false,
        };
        progress(&run);
        runs.push(run);
    }
    mark_pareto(&mut runs);
    Ok(Study {
        scene: scene.name.clone(),
        reference: described,
        probes: probes.len(),
        runs,
    })
}

/// Fraction of the median reference value below which a probe is left out.
const DARK_FRACTION: f64 = 0.05;

fn usable(reference: Vec<Option<f64>>) -> Vec<Option<f64>> {
    let mut lit: Vec<f64> = reference.iter().flatten().copied().collect();
    lit.sort_by(|a, b| a.total_cmp(b));
    let floor = lit.get(lit.len() / 2).copied().unwrap_or(0.0) * DARK_FRACTION;
    reference
        .into_iter()
        .map(|r| r.filter(|&v| v > floor))
        .collect()
}

/// Mean and largest relative error over the probes both runs found.
fn errors(values: &[Option<f64>], reference: &[Option<f64>]) -> (f64, f64) {
    let (mut sum, mut worst, mut n) = (0.0, 0.0f64, 0usize);
    for (v, r) in values.iter().zip(reference) {
        if let (Some(v), Some(r)) = (v, r) {
            if *r > 0.0 {
                let e = (v - r).abs() / r;
                sum += e;
                worst = worst.max(e);
                n += 1;
            }
        }
    }
    if n == 0 {
        (f64::NAN, f64::NAN)
    } else {
        (sum / n as f64, worst)
    }
}

/// Marks the runs that no other run beats in both time and mean error.
fn mark_pareto(runs: &mut [Run]) {
    for i in 0..runs.len() {
        let (t, e) = (runs[i].seconds, runs[i].mean_error);
        runs[i].pareto = !runs.iter().enumerate().any(|(j, o)| {
            j != i && o.seconds <= t && o.mean_error <= e && (o.seconds < t || o.mean_error < e)
        });
    }
}

impl Study {
    /// The CSV table: one row per run.
    pub fn csv(&self) -> String {
        let mut out = String::from(
            "knob,resolution,directions,direct_directions,tolerance,extrapolation,surfels,iterations,seconds,mean_error,max_error,pareto,gathered_mean_error,gathered_max_error,chebyshev\n",
        );
        for r in &self.runs {
            out.push_str(&format!(
                "{},{},{},{},{:e},{},{},{},{:.4},{:.6e},{:.6e},{},{:.6e},{:.6e},{}\n",
                r.knob,
                r.settings.resolution,
                r.directions_used,
                r.direct_used,
                r.settings.tolerance,
                r.settings.accelerate,
                r.surfels,
                r.iterations,
                r.seconds,
                r.mean_error,
                r.max_error,
                r.pareto,
                r.gathered_mean_error,
                r.gathered_max_error,
                r.settings.chebyshev
            ));
        }
        out
    }

    /// The Markdown report: reference, table, Pareto front, how to read the picture.
    pub fn markdown(&self) -> String {
        let mut out = format!(
            "# Accuracy against time: {}\n\nReference: {}.\n\nError: relative error of \
             B_r + B_g + B_b at {} fixed probe points on the non-emitting surfaces (mean and \
             largest over the probes; probes the reference sees below 5 % of its median, such as \
             the floor under a block, are left out). Time: voxelize + solve, wall clock. Each knob is swept \
             from the same base setting with the others fixed. Gathered: the same probes \
             answered by gathering the solved light there (`voxrad probe --gather`, not timed; \
             against a path-traced reference only).\n\n",
            self.scene, self.reference, self.probes
        );
        out.push_str(
            "| knob | resolution | directions | direct directions | tolerance | extrapolation | iterations | seconds | mean error | max error | Pareto | gathered mean | gathered max |\n\
             |---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        );
        for r in &self.runs {
            out.push_str(&format!(
                "| {} | {} | {} | {} | {:.0e} | {} | {} | {:.2} | {:.2e} | {:.2e} | {} | {} | {} |\n",
                r.knob,
                r.settings.resolution,
                r.directions_used,
                r.direct_used,
                r.settings.tolerance,
                match (r.settings.accelerate, r.settings.chebyshev) {
                    (false, _) => "no",
                    (true, false) => "tail",
                    (true, true) => "tail, Chebyshev",
                },
                r.iterations,
                r.seconds,
                r.mean_error,
                r.max_error,
                if r.pareto { "*" } else { "" },
                shown(r.gathered_mean_error),
                shown(r.gathered_max_error)
            ));
        }
        out.push_str(&format!(
            "\n`study.png`: mean error (vertical, log scale from {:.0e} to {:.0e}) against \
             seconds (horizontal, log scale from {:.2e} to {:.2e}); one polyline per knob, in \
             sweep order: {}; the Pareto front (runs no other run beats in both time and error) \
             is the black staircase, its runs ringed in black. The picture has no text: the \
             axes are as stated here.\n",
            plot::error_range(&self.runs).0,
            plot::error_range(&self.runs).1,
            plot::time_range(&self.runs).0,
            plot::time_range(&self.runs).1,
            plot::LEGEND
        ));
        out
    }
}

/// An error for the Markdown table: `-` where it was not measured.
fn shown(e: f64) -> String {
    if e.is_nan() {
        "-".to_string()
    } else {
        format!("{e:.2e}")
    }
}

/// Writes `study.csv`, `study.md` and `study.png` into `dir`.
pub fn write(study: &Study, dir: &Path) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
    let put = |name: &str, bytes: &[u8]| {
        crate::output::atomic::write_atomically(&dir.join(name), |w| w.write_all(bytes))
            .map_err(|e| e.to_string())
    };
    put("study.csv", study.csv().as_bytes())?;
    put("study.md", study.markdown().as_bytes())?;
    let png = plot::render(&study.runs, 640, 480)?;
    put("study.png", &png)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run_at(seconds: f64, mean_error: f64) -> Run {
        Run {
            knob: "directions",
            settings: Plan::quick().base,
            directions_used: 1,
            direct_used: 0,
            surfels: 1,
            iterations: 1,
            seconds,
            mean_error,
            max_error: mean_error,
            gathered_mean_error: f64::NAN,
            gathered_max_error: f64::NAN,
            pareto: false,
        }
    }

    #[test]
    fn pareto_front() {
        let mut runs = vec![
            run_at(1.0, 0.1),
            run_at(2.0, 0.2),
            run_at(2.0, 0.01),
            run_at(3.0, 0.01),
        ];
        mark_pareto(&mut runs);
        let front: Vec<bool> = runs.iter().map(|r| r.pareto).collect();
        assert_eq!(front, [true, false, true, false]);
    }

    #[test]
    fn probes_lie_on_lit_surfaces_facing_their_triangle() {
        let scene = gen::cornell_box();
        let points = probe_points(&scene, 50, 1);
        assert_eq!(points.len(), 50);
        for (p, n) in points {
            assert!((n.length() - 1.0).abs() < 1e-9);
            // Inside the box's bounds.
            let b = scene.bounds();
            assert!(p.cmpge(b.min).all() && p.cmple(b.max).all());
        }
    }
}
