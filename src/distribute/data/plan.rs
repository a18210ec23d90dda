//! The exchange plan of each direction in the data and hybrid modes: which held surfels leave
//! for which rank, and where the arrivals go in the new order, written down the first time a
//! direction is distributed and followed in later iterations instead of placing every surfel on
//! its line's bin and merging again.
//!
//! Why a plan can be followed: the surfels a rank holds after a direction's exchange are those
//! whose lines the direction's remembered distribution gives it, listed in that direction's
//! octant order (ties by id), a total order (`wire::compare`). So what a rank holds before and
//! after an exchange depends only on the distribution it comes from (`Origin`) and the one it
//! goes to, never on the iteration, and each entry's place in `Held::order` is the same every
//! time (the places of `Held` its data sits at may differ after a resume). A plan records
//! positions in the order, not places.

use super::held::Held;
use crate::solve::dispatch::OrderedEntry;

/// What the held surfels were last distributed by: the canonical blocks of ids (where a solve
/// starts), or a direction's distribution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Origin {
    Blocks,
    After(usize),
}

/// How the new order is made from the kept entries (in their old order) and the arrivals (in
/// the order they were decoded: pack by pack, each pack as its sender held them).
#[derive(Clone, Debug, PartialEq)]
enum Recipe {
    /// The kept entries keep their order: arrival `arrive_from[i]` goes to place `arrive_at[i]`
    /// (ascending), the kept ones fill the places between. The common case: the octant order
    /// did not change.
    Merge {
        arrive_at: Vec<u32>,
        arrive_from: Vec<u32>,
    },
    /// Every place's source: below the kept count a kept entry, above it an arrival. When the
    /// octant order changes (a few directions an iteration) or the ids become the order.
    Permute(Vec<u32>),
}

/// One direction's exchange, as the first distribution by its remembered lines made it.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct ExchangePlan {
    from: Origin,
    /// Places in the old order that leave, ascending, with the rank each goes to.
    leave: Vec<(u32, u32)>,
    /// Entries that arrive (added over the packs).
    arrivals: usize,
    recipe: Recipe,
}

impl ExchangePlan {
    /// The plan of an exchange just done the full way: `leave` as the fill found it, `kept`
    /// (old order) and `arrived` (decode order) as they were before merging, `order` the new
    /// order, `places` the number of places entries can name.
    pub(super) fn record(
        from: Origin,
        leave: Vec<(u32, u32)>,
        kept: &[OrderedEntry],
        arrived: &[OrderedEntry],
        order: &[OrderedEntry],
        places: usize,
    ) -> Self {
        let mut source = vec![u32::MAX; places];
        for (i, e) in kept.iter().chain(arrived).enumerate() {
            source[e.index as usize] = i as u32;
        }
        let sources: Vec<u32> = order.iter().map(|e| source[e.index as usize]).collect();
        let kept_len = kept.len() as u32;
        let mut next_kept = 0u32;
        let in_old_order = sources.iter().all(|&s| {
            if s < kept_len {
                let ok = s == next_kept;
                next_kept += 1;
                ok
            } else {
                true
            }
        });
        let recipe = if in_old_order {
            let (arrive_at, arrive_from) = sources
                .iter()
                .enumerate()
                .filter(|&(_, &s)| s >= kept_len)
                .map(|(place, &s)| (place as u32, s - kept_len))
                .unzip();
            Recipe::Merge {
                arrive_at,
                arrive_from,
            }
        } else {
            Recipe::Permute(sources)
        };
        ExchangePlan {
            from,
            leave,
            arrivals: arrived.len(),
            recipe,
        }
    }

    /// Whether this plan applies to held surfels distributed by `from`.
    pub(super) fn fits(&self, from: Origin) -> bool {
        self.from == from
    }

    /// Bytes the plan takes in memory.
    pub(super) fn bytes(&self) -> u64 {
        let recipe = match &self.recipe {
            Recipe::Merge {
                arrive_at,
                arrive_from,
            } => arrive_at.len() + arrive_from.len(),
            Recipe::Permute(sources) => sources.len(),
        };
        (self.leave.len() * 8 + recipe * 4 + std::mem::size_of::<Self>()) as u64
    }

    /// Fill by the plan: takes `held.order` apart into the entries that stay (returned, in old
    /// order) and the ones that leave, encoded into `packs` by destination (in old order, as
    /// the full fill packs them).
    pub(super) fn fill(&self, held: &mut Held, packs: &mut [Vec<u8>]) -> Vec<OrderedEntry> {
        let entries = std::mem::take(&mut held.order);
        let mut kept = Vec::with_capacity(entries.len() - self.leave.len());
        let mut start = 0;
        for &(place, dest) in &self.leave {
            let place = place as usize;
            kept.extend_from_slice(&entries[start..place]);
            held.encode(entries[place].index, &mut packs[dest as usize]);
            start = place + 1;
        }
        kept.extend_from_slice(&entries[start..]);
        kept
    }

    /// The new order from the kept entries and the arrivals, by the recipe. Panics if the
    /// arrivals are not the ones recorded in number (a broken invariant, not bad input).
    pub(super) fn order(
        &self,
        kept: &[OrderedEntry],
        arrived: &[OrderedEntry],
    ) -> Vec<OrderedEntry> {
        assert_eq!(
            arrived.len(),
            self.arrivals,
            "an exchange plan met other arrivals than it recorded"
        );
        match &self.recipe {
            Recipe::Merge {
                arrive_at,
                arrive_from,
            } => {
                let mut order = Vec::with_capacity(kept.len() + arrived.len());
                let mut next_kept = 0;
                for (&place, &from) in arrive_at.iter().zip(arrive_from) {
                    let run = place as usize - order.len();
                    order.extend_from_slice(&kept[next_kept..next_kept + run]);
                    next_kept += run;
                    order.push(arrived[from as usize]);
                }
                order.extend_from_slice(&kept[next_kept..]);
                order
            }
            Recipe::Permute(sources) => {
                let kept_len = kept.len();
                sources
                    .iter()
                    .map(|&s| {
                        let s = s as usize;
                        if s < kept_len {
                            kept[s]
                        } else {
                            arrived[s - kept_len]
                        }
                    })
                    .collect()
            }
        }
    }
}

/// The plans of a rank's directions.
pub(super) struct ExchangePlans {
    by_direction: Vec<Option<ExchangePlan>>,
}

impl ExchangePlans {
    pub(super) fn new(directions: usize) -> Self {
        ExchangePlans {
            by_direction: vec![None; directions],
        }
    }

    /// The plan for the exchange to direction `k` from held surfels distributed by `from`, if
    /// one was recorded from there.
    pub(super) fn usable(&self, k: usize, from: Origin) -> Option<&ExchangePlan> {
        self.by_direction[k].as_ref().filter(|p| p.fits(from))
    }

    /// Keeps `plan` for exchanges to direction `k` (replacing one recorded from elsewhere).
    pub(super) fn keep(&mut self, k: usize, plan: ExchangePlan) {
        self.by_direction[k] = Some(plan);
    }

    /// Bytes all plans take.
    pub(super) fn bytes(&self) -> u64 {
        self.by_direction
            .iter()
            .flatten()
            .map(ExchangePlan::bytes)
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(place: u32) -> OrderedEntry {
        OrderedEntry {
            voxel: [place as i32, 0, 0],
            index: place,
        }
    }

    /// A plan recorded from one exchange rebuilds the same order from the same entries at
    /// other places, in both recipes.
    #[test]
    fn a_recorded_plan_rebuilds_the_order_from_other_places() {
        let kept: Vec<_> = [3, 0, 5, 7].map(entry).to_vec();
        let arrived: Vec<_> = [9, 2, 8].map(entry).to_vec();
        // Kept in their old order, arrivals between them.
        let merged: Vec<_> = [2, 3, 0, 9, 5, 7, 8].map(entry).to_vec();
        // Kept reordered (the octant order changed).
        let permuted: Vec<_> = [7, 2, 0, 9, 3, 8, 5].map(entry).to_vec();
        for (order, is_merge) in [(&merged, true), (&permuted, false)] {
            let plan = ExchangePlan::record(Origin::After(4), vec![], &kept, &arrived, order, 10);
            assert_eq!(matches!(plan.recipe, Recipe::Merge { .. }), is_merge);
            // The same surfels at other places: place p is now p + 20.
            let moved = |v: &[OrderedEntry]| -> Vec<OrderedEntry> {
                v.iter()
                    .map(|e| OrderedEntry {
                        voxel: e.voxel,
                        index: e.index + 20,
                    })
                    .collect()
            };
            assert_eq!(plan.order(&moved(&kept), &moved(&arrived)), moved(order));
        }
    }

    #[test]
    fn plans_apply_only_from_where_they_were_recorded() {
        let plan = ExchangePlan::record(Origin::Blocks, vec![], &[], &[], &[], 0);
        let mut plans = ExchangePlans::new(3);
        plans.keep(1, plan);
        assert!(plans.usable(1, Origin::Blocks).is_some());
        assert!(plans.usable(1, Origin::After(0)).is_none());
        assert!(plans.usable(2, Origin::Blocks).is_none());
    }
}
