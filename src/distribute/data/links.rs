//! The partner links a rank keeps in the data and hybrid modes (in memory): each rank's lines'
//! links, written down on its first gather of a direction and replayed in later iterations
//! after that direction's exchange (`solve::links` keeps them; this names their surfels).

use crate::comm::Comm;
use crate::solve::dispatch::OrderedEntry;
use crate::solve::links::{DirectionLinks, LinkBudget};
use crate::solve::propagate::DirectionInput;
use crate::solve::stats::LinkStats;

/// The partner links of this rank's lines, kept between iterations (`solve::links`). After a
/// direction's exchange a rank holds the same surfels in the same order in every iteration (the
/// direction's remembered distribution decides which, the octant order how they are listed),
/// but in other slots: so the links number surfels by their place in `Held::order`, and a
/// replay looks their slots up there.
pub(super) struct HeldLinks {
    /// By direction: the links, and a hash of the ids in order they were recorded with.
    kept: Vec<Option<(DirectionLinks, u64)>>,
    /// By direction: whether its links were written down once (kept or not).
    pub(super) tried: Vec<bool>,
    budget: LinkBudget,
    /// Scratch: `Held::order`'s slots, and each slot's place there.
    slots: Vec<u32>,
    places: Vec<u32>,
}

impl HeldLinks {
    pub(super) fn new(directions: usize, budget: u64) -> Self {
        HeldLinks {
            kept: vec![None; directions],
            tried: vec![false; directions],
            budget: LinkBudget { left: budget },
            slots: Vec::new(),
            places: Vec::new(),
        }
    }

    /// The ids of the held surfels in order, folded into one word: what a replay must find
    /// again (a rotate, a xor and a multiply per surfel, little beside the replay itself).
    fn hash(order: &[OrderedEntry], ids: &[u32]) -> u64 {
        order.iter().fold(order.len() as u64, |h, e| {
            (h.rotate_left(5) ^ ids[e.index as usize] as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        })
    }

    /// Replays direction `k`'s links into `acc` if they are kept; false (nothing done) if not.
    pub(super) fn replay(
        &mut self,
        k: usize,
        order: &[OrderedEntry],
        ids: &[u32],
        input: &DirectionInput,
        acc: &mut [[[f64; 3]; 2]],
    ) -> bool {
        let Some((links, hash)) = &self.kept[k] else {
            return false;
        };
        if *hash != Self::hash(order, ids) {
            // Cannot happen while the distribution and the order are remembered; if it did,
            // searching again gives the right light.
            tracing::warn!(direction = k, "the held surfels changed: links dropped");
            self.budget.left += links.bytes();
            self.kept[k] = None;
            self.tried[k] = false;
            return false;
        }
        self.slots.clear();
        self.slots.extend(order.iter().map(|e| e.index));
        links.replay_through(input.radiosity, input.channels, acc, Some(&self.slots));
        true
    }

    /// Keeps `recorded` (numbered by slot) as direction `k`'s links, numbered by place in
    /// `order`, if the budget allows.
    pub(super) fn keep(
        &mut self,
        k: usize,
        recorded: DirectionLinks,
        order: &[OrderedEntry],
        ids: &[u32],
    ) {
        self.tried[k] = true;
        if !self.budget.take(recorded.bytes()) {
            return;
        }
        self.places.clear();
        self.places.resize(ids.len(), u32::MAX);
        for (place, e) in order.iter().enumerate() {
            self.places[e.index as usize] = place as u32;
        }
        let links = recorded.renumbered(&self.places);
        self.kept[k] = Some((links, Self::hash(order, ids)));
    }

    /// What the report says of the links: the directions whose links every rank kept, and
    /// the bytes of all ranks' links. Collective on `world`.
    pub(super) fn stats(&self, directions: usize, surfels: usize, world: &dyn Comm) -> LinkStats {
        let kept = self.kept.iter().flatten();
        let mut bytes = [kept.clone().map(|(l, _)| l.bytes()).sum::<u64>() as f64];
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
