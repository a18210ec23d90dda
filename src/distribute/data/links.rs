//! The partner links a rank keeps in the data and hybrid modes (in memory): each rank's lines'
//! links, written down on its first gather of a direction and replayed in later iterations
//! (`solve::links` keeps them; this names their surfels).

use crate::comm::Comm;
use crate::solve::links::{DirectionLinks, LinkBudget};
use crate::solve::propagate::DirectionInput;
use crate::solve::stats::LinkStats;

/// The partner links of this rank's lines, kept between iterations (`solve::links`). They name
/// surfels by their place in `Held`, which a surfel keeps for the rest of the solve once met:
/// a replay reads and adds there directly, whatever the rank holds for the direction then.
pub(super) struct HeldLinks {
    /// By direction: the links, if kept.
    kept: Vec<Option<DirectionLinks>>,
    /// By direction: whether its links were written down once (kept or not).
    pub(super) tried: Vec<bool>,
    budget: LinkBudget,
}

impl HeldLinks {
    pub(super) fn new(directions: usize, budget: u64) -> Self {
        HeldLinks {
            kept: vec![None; directions],
            tried: vec![false; directions],
            budget: LinkBudget { left: budget },
        }
    }

    /// Whether direction `k`'s links are kept.
    pub(super) fn kept(&self, k: usize) -> bool {
        self.kept[k].is_some()
    }

    /// Replays direction `k`'s links into `acc` if they are kept; false (nothing done) if not.
    pub(super) fn replay(
        &self,
        k: usize,
        input: &DirectionInput,
        acc: &mut [[[f64; 3]; 2]],
    ) -> bool {
        let Some(links) = &self.kept[k] else {
            return false;
        };
        links.replay(input.radiosity, input.channels, acc);
        true
    }

    /// Keeps `recorded` (numbered by place) as direction `k`'s links if the budget allows.
    pub(super) fn keep(&mut self, k: usize, recorded: DirectionLinks) {
        self.tried[k] = true;
        if self.budget.take(recorded.bytes()) {
            self.kept[k] = Some(recorded);
        }
    }

    /// What the report says of the links: the directions whose links every rank kept, and
    /// the bytes of all ranks' links. Collective on `world`.
    pub(super) fn stats(&self, directions: usize, surfels: usize, world: &dyn Comm) -> LinkStats {
        let kept = self.kept.iter().flatten();
        let mut bytes = [kept.map(|l| l.bytes()).sum::<u64>() as f64];
        world.sum_in_place(&mut bytes);
        // Each rank keeps its lines of its group's directions; a direction that some rank did
        // not keep (or never reached) is searched again there.
        let mut missing: Vec<f64> = (0..directions)
            .map(|k| (self.tried[k] && self.kept[k].is_none()) as u8 as f64)
            .chain((0..directions).map(|k| self.tried[k] as u8 as f64))
            .collect();
        world.sum_in_place(&mut missing);
        let kept_directions = (0..directions)
            .filter(|&k| missing[k] == 0.0 && missing[directions + k] > 0.0)
            .count();
        LinkStats {
            kept_directions,
            directions,
            bytes: bytes[0] as u64,
            bytes_per_surfel_direction: bytes[0] / (surfels * kept_directions).max(1) as f64,
            kept_in: if kept_directions > 0 {
                "memory"
            } else {
                "none"
            }
            .to_string(),
        }
    }
}
