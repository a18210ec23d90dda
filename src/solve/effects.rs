//! Scene analysis before a solve: which effects the scene calls for, and how to shape the solve so
//! that only those are simulated.
//!
//! The analysis looks at the surfels and the materials their sides carry (not at the material
//! table, which may list materials no surface uses) and decides:
//! - **no emitter** (no side with `E > 0`): nothing to light, nothing to solve (0 iterations);
//! - **every reflectance 0**: light does not bounce, so one pass gives `B = E` (direct light only);
//! - **grey** (every used reflectance and emission equal in its three channels): the three RGB
//!   solves are the same solve, so one channel is solved and copied to the others;
//! - **small emitters** (emitting surfels at most 5 % of all, `direct::small_emitters`): their
//!   direct light is gathered once with a dense direction set from their own lines, and the
//!   iterations gather only the reflected light (`direct`); larger emitters alias less and would
//!   make the pass cost about a full pass per dense direction;
//! - otherwise iterations run until the scene's own convergence (the contraction-aware tolerance
//!   rule in `jacobi`), not a fixed count.
//!
//! [`Analysis::effects`] turns the decisions and what the solve did into the report's `effects`
//! list, each with why, and what it saved where that can be stated.

use super::direct::{DirectPass, Shape};
use super::{SolveOptions, SolveStats};
use crate::voxel::SurfelSet;
use serde::{Deserialize, Serialize};

/// One physical effect and whether this run simulated it (the user asked to "simulate only the
/// effects a scene calls for", so the report says which were and why).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Effect {
    pub name: String,
    pub simulated: bool,
    pub why: String,
}

impl Effect {
    pub fn new(name: &str, simulated: bool, why: &str) -> Self {
        Effect {
            name: name.to_string(),
            simulated,
            why: why.to_string(),
        }
    }
}

/// What a scene calls for.
#[derive(Clone, Debug, PartialEq)]
pub struct Analysis {
    /// Some surfel side emits.
    pub emitters: bool,
    /// Some surfel side reflects (`rho > 0` in some channel).
    pub reflective: bool,
    /// Every used reflectance and emission has three equal channels.
    pub grey: bool,
    /// Largest reflectance of any used side and channel (the bounce count grows as
    /// `1 / (1 - rho)`).
    pub max_reflectance: f64,
    /// Surfels with an emitting side.
    pub emitting_surfels: usize,
    /// All surfels.
    pub surfels: usize,
    /// Voxels along the grid's longest axis.
    pub longest_axis: u32,
    /// Surfels whose back side lies inside a closed solid (`voxel::enclosed`).
    pub inside_sides: usize,
}

/// Analyses the materials on the surfels' sides.
pub fn analyse(set: &SurfelSet) -> Analysis {
    let mut analysis = analyse_sides(&set.materials, set.surfels.iter().map(|s| s.material));
    analysis.longest_axis = set.grid.dims.into_iter().max().unwrap_or(0);
    analysis
}

/// Analyses the materials a stream of surfels carries on their sides (`sides`: each surfel's
/// front and back material index into `materials`), for solvers that never hold the surfels.
/// The grid's longest axis is left 0 for the caller to set.
pub fn analyse_sides(
    materials: &[crate::scene::Material],
    sides: impl Iterator<Item = [u32; 2]>,
) -> Analysis {
    let mut used = vec![false; materials.len()];
    let (mut emitting_surfels, mut surfels, mut inside_sides) = (0, 0, 0);
    for pair in sides {
        surfels += 1;
        inside_sides += materials
            .get(pair[crate::voxel::BACK] as usize)
            .is_some_and(|m| m.inside) as usize;
        let mut emits = false;
        for m in pair {
            if let Some(u) = used.get_mut(m as usize) {
                *u = true;
                emits |= materials[m as usize].is_emitter();
            }
        }
        emitting_surfels += emits as usize;
    }
    let used: Vec<&crate::scene::Material> = materials
        .iter()
        .zip(&used)
        .filter(|(_, &u)| u)
        .map(|(m, _)| m)
        .collect();
    Analysis {
        emitters: emitting_surfels > 0,
        reflective: used.iter().any(|m| m.reflectance.iter().any(|&r| r > 0.0)),
        grey: used.iter().all(|m| m.is_grey()),
        max_reflectance: used.iter().flat_map(|m| m.reflectance).fold(0.0, f64::max),
        emitting_surfels,
        surfels,
        longest_axis: 0,
        inside_sides,
    }
}

/// Whether a solve of `set` may solve one channel and copy it (the solver checks this itself, so
/// a wrong `SolveOptions::grey` can never give a wrong answer).
pub fn is_grey(set: &SurfelSet) -> bool {
    analyse(set).grey
}

impl Analysis {
    /// The options shaped by the analysis: no emitter, no iteration; no reflection, one pass;
    /// grey, one channel; the direct pass decided (`DirectPass::Auto` becomes on or off; no
    /// reflection, no pass: `B = E` reads no gathered light).
    pub fn shape(&self, options: &SolveOptions) -> SolveOptions {
        let mut shaped = options.clone();
        shaped.direct = match options
            .direct
            .resolve(self.direct_shape(options.directions))
        {
            Some(n) if self.reflective => DirectPass::On(n),
            _ => DirectPass::Off,
        };
        if !self.emitters {
            shaped.max_iterations = 0;
        } else if !self.reflective {
            shaped.max_iterations = shaped.max_iterations.min(1);
        }
        shaped.grey = self.grey;
        shaped
    }

    /// The report's list of effects for a solve shaped by [`Analysis::shape`] from `requested`,
    /// with what it did (`stats`). Every solve path runs every effect, so none is ever "not
    /// applied in this mode".
    pub fn effects(&self, requested: &SolveOptions, stats: &SolveStats) -> Vec<Effect> {
        let mut list = Vec::new();
        list.push(Effect::new(
            "direct light",
            self.emitters,
            &if let Some(d) = &stats.direct {
                format!(
                    "{} surfels emit (Ke > 0); gathered along {} dense line directions (the \
                     direct-light pass)",
                    self.emitting_surfels, d.directions
                )
            } else if self.emitters {
                format!(
                    "{} surfels emit (Ke > 0); gathered along {} line directions",
                    self.emitting_surfels, stats.directions
                )
            } else {
                format!(
                    "no surface emits (no Ke > 0): every B is 0; the solve was skipped, saving up \
                     to {} iterations",
                    requested.max_iterations
                )
            },
        ));
        let bounces = self.emitters && self.reflective;
        list.push(Effect::new(
            "interreflection",
            bounces,
            &if !self.emitters {
                "nothing emits, so nothing bounces".to_string()
            } else if !self.reflective {
                "every reflectance is 0: light does not bounce, one pass gives B = E (direct \
                 light only)"
                    .to_string()
            } else {
                let rule = match requested.tolerance {
                    Some(t) => format!(
                        "until the estimated relative error left ({:.1e}) was below the \
                         tolerance {t:.1e}: the scene's own convergence, not a fixed count",
                        stats.residual
                    ),
                    None => format!("for the requested {} iterations", requested.max_iterations),
                };
                format!(
                    "reflectance up to {:.3}; {} iterations, {rule}",
                    self.max_reflectance, stats.iterations,
                )
            },
        ));
        list.push(Effect::new(
            "colour",
            !self.grey,
            if self.grey {
                "every material is grey (equal Kd and Ke channels): one channel solved and \
                 copied to the other two, saving the gather and update of two channels (measured: \
                 4 % of the iteration time on the furnace, nothing measurable on a grey Cornell \
                 box, where finding partners dominates; docs/simulation.md)"
            } else {
                "some material has unequal RGB channels: three channels solved"
            },
        ));
        list.push(self.direct_effect(requested, stats));
        list.push(Effect::new(
            "light inside solids",
            false,
            &if self.inside_sides > 0 {
                format!(
                    "{} of {} surfels have their back side inside a closed solid (a face of a box \
                     wound outward with nothing inside it): nothing there is seen, so those sides \
                     gather no light and their partner searches are skipped",
                    self.inside_sides, self.surfels
                )
            } else {
                "no surfel has a side inside a closed solid wound outward: every side gathers"
                    .to_string()
            },
        ));
        if let Some(effect) = closure_effect(stats) {
            list.push(effect);
        }
        if bounces {
            list.push(Effect::new(
                "tail extrapolation",
                stats.extrapolations > 0,
                &if requested.accelerate {
                    format!(
                        "the geometric tail of the remaining bounces was added at once ({} \
                         extrapolations) when the iteration's change shrank by a steady factor; \
                         measured saving: the furnace exact in 4 iterations instead of 87 \
                         (rho 0.9) or 914 (rho 0.99), 20 to 35 % of the iterations on the \
                         Cornell box at tolerances of 1e-3 and below (docs/simulation.md)",
                        stats.extrapolations
                    )
                } else {
                    "not requested".to_string()
                },
            ));
            list.push(Effect::new(
                "Chebyshev semi-iteration",
                stats.chebyshev_updates.is_some(),
                &match (requested.chebyshev, stats.chebyshev_updates) {
                    (false, _) => {
                        "off (--no-chebyshev, or --iterations without --tolerance)".to_string()
                    }
                    (true, None) => "allowed, not started: the tail extrapolation found a \
                                     geometric tail, or the change fell by 0.89 or more an \
                                     iteration"
                        .to_string(),
                    (true, Some(updates)) => format!(
                        "{updates} updates mixed with the radiosity before last, which follows \
                         several slow modes at once: about a third fewer iterations on scenes \
                         of several rooms (docs/throughput.md); the stopping rule read the \
                         plain iteration's residual"
                    ),
                },
            ));
        }
        list
    }

    /// What the direct pass's decision reads, for a solve asking for about `directions`.
    fn direct_shape(&self, directions: usize) -> Shape {
        Shape {
            emitting: self.emitting_surfels,
            surfels: self.surfels,
            longest_axis: self.longest_axis,
            directions: crate::geometry::directions::DirectionSet::with_count(directions).len(),
        }
    }

    /// The report's entry for the direct-light pass (see `direct`).
    fn direct_effect(&self, requested: &SolveOptions, stats: &SolveStats) -> Effect {
        const NAME: &str = "direct-light pass";
        let affordable = super::direct::affordable_directions(
            self.emitting_surfels,
            self.surfels,
            self.longest_axis,
            stats.directions,
        );
        let share = format!(
            "{} of {} surfels emit ({:.2} %)",
            self.emitting_surfels,
            self.surfels,
            100.0 * self.emitting_surfels as f64 / self.surfels.max(1) as f64
        );
        if let Some(d) = &stats.direct {
            let why = match requested.direct {
                DirectPass::On(_) => "requested (--direct-directions)".to_string(),
                DirectPass::Auto(n) => format!(
                    "small emitters (at most {:.0} % of the surfels), whose direct light aliases \
                     into stripes with the bounces' {} directions{}",
                    100.0 * super::direct::SMALL_EMITTER_FRACTION,
                    stats.directions,
                    if affordable < n {
                        format!(
                            "; {n} dense directions asked, {affordable} afforded (the pass may \
                             cost about {} iterations)",
                            super::direct::BUDGET_ITERATIONS
                        )
                    } else {
                        String::new()
                    }
                ),
                DirectPass::Off => "(no request)".to_string(),
            };
            let gathering = stats.dispatch_seconds + stats.propagate_seconds;
            return Effect::new(
                NAME,
                true,
                &format!(
                    "{share}: {why}. Their direct light was gathered once along {} dense line \
                     directions from the {} lines through them only ({:.3} s, against {:.3} s \
                     for the {} iterations' gathering), and the iterations gathered only the \
                     reflected light B - E along {} directions. {}.",
                    d.directions,
                    d.lines,
                    d.seconds,
                    gathering,
                    stats.iterations,
                    stats.directions,
                    super::direct::MEASURED_GAIN
                ),
            );
        }
        let why = if matches!(
            requested.direct,
            DirectPass::Off | DirectPass::On(0) | DirectPass::Auto(0)
        ) {
            "not requested (--direct-directions 0): the emitters' light is gathered with the \
             iterations' directions"
                .to_string()
        } else if !self.emitters {
            "nothing emits".to_string()
        } else if !self.reflective {
            "every reflectance is 0: B = E reads no gathered light".to_string()
        } else if super::direct::small_emitters(self.emitting_surfels, self.surfels) {
            format!(
                "{share}, small emitters, but the pass affords only {affordable} dense \
                 directions (about {} iterations' cost: one line per emitting surfel through \
                 {} voxels per direction), fewer than twice the solve's {}: no gain",
                super::direct::BUDGET_ITERATIONS,
                self.longest_axis,
                stats.directions
            )
        } else {
            format!(
                "{share}, more than {:.0} %: large emitters alias little, and the pass, which \
                 builds the lines through every emitting surfel, would cost about a full pass \
                 per dense direction",
                100.0 * super::direct::SMALL_EMITTER_FRACTION
            )
        };
        Effect::new(NAME, false, &why)
    }
}

/// The report's word on a closed scene's energy conservation (`closed`), where the solve says
/// whether it checked.
fn closure_effect(stats: &SolveStats) -> Option<Effect> {
    let c = stats.closure?;
    let v = c.verdict;
    let why = if v.unchecked {
        "not checked: the check needed more memory than the solve could give it (four \
         slices of the grid, a label per room and slice, the emitting sides waiting for the \
         slices ahead), and the scene is solved as an open one (the light its rays lose is \
         lost)"
            .to_string()
    } else if v.closed {
        let k = c.scales;
        format!(
            "no emitting side faces air that reaches outside the scene's grid: the light is \
             sealed in, so each update scaled the light gathered along the lines by {:.4} / \
             {:.4} / {:.4} (red, green, blue) and the direct-light pass's by {:.4} / {:.4} / \
             {:.4}, so that the surfaces receive what they send and absorb what the lamps \
             emit (docs/accuracy.md, \"Closed scenes\")",
            k.gathered[0], k.gathered[1], k.gathered[2], k.direct[0], k.direct[1], k.direct[2]
        )
    } else if v.emitting_sides == 0 {
        "nothing emits".to_string()
    } else {
        format!(
            "{} of {} emitting sides face air that reaches outside the scene's grid: the scene \
             is open, and the light its rays lose leaves it",
            v.open_sides, v.emitting_sides
        )
    };
    Some(Effect::new(
        "energy conservation of a closed scene",
        v.closed,
        &why,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Material, Scene};
    use crate::voxel::voxelize::{voxelize, GridSpec};
    use glam::DVec3;

    fn boxed(reflectance: [f64; 3], emission: [f64; 3], unused: Option<Material>) -> SurfelSet {
        let mut scene = Scene::default();
        let m = scene.add_material(Material::new("wall", reflectance, emission));
        if let Some(u) = unused {
            scene.add_material(u);
        }
        scene.add_box(DVec3::ZERO, DVec3::ONE, m, true);
        voxelize(&scene, GridSpec::Resolution(6)).unwrap()
    }

    #[test]
    fn decisions() {
        let a = analyse(&boxed([0.5; 3], [1.0; 3], None));
        assert!(a.emitters && a.reflective && a.grey);
        assert_eq!(a.max_reflectance, 0.5);
        let a = analyse(&boxed([0.5, 0.4, 0.5], [1.0; 3], None));
        assert!(!a.grey);
        let a = analyse(&boxed([0.5; 3], [0.0; 3], None));
        assert!(!a.emitters);
        assert_eq!(a.shape(&SolveOptions::default()).max_iterations, 0);
        let a = analyse(&boxed([0.0; 3], [1.0; 3], None));
        assert!(!a.reflective);
        assert_eq!(a.shape(&SolveOptions::default()).max_iterations, 1);
    }

    #[test]
    fn unused_materials_do_not_count() {
        // A coloured lamp material that no surface uses neither lights nor colours the scene.
        let lamp = Material::new("lamp", [0.2, 0.0, 0.0], [5.0, 1.0, 0.0]);
        let a = analyse(&boxed([0.5; 3], [0.0; 3], Some(lamp)));
        assert!(!a.emitters);
        assert!(a.grey);
    }
}
