//! The partner links a rank keeps in the data and hybrid modes (in memory): each rank's lines'
//! links, written down on its first gather of a direction and replayed in later iterations
//! (`solve::links` keeps them; this names their surfels).

use crate::comm::Comm;
use crate::solve::kept_links::{Blocks, KeptLinks};
use crate::solve::links::DirectionLinks;
use crate::solve::propagate::DirectionInput;
use crate::solve::stats::LinkStats;
use crate::solve::update::{Gathered, Radiosity};

/// The partner links of this rank's lines, kept between iterations (`solve::links`, in blocks
/// of steps as `solve::kept_links` keeps them). They name surfels by their place in `Held`,
/// which a surfel keeps for the rest of the solve once met: a replay reads and adds there
/// directly, whatever the rank holds for the direction then.
pub(super) struct HeldLinks {
    /// By step: the group's directions are `first..first + steps`.
    kept: KeptLinks,
    first: usize,
    /// The group's directions.
    steps: usize,
}

impl HeldLinks {
    /// Nothing kept yet for the group's directions `directions`, with `budget` bytes.
    pub(super) fn new(directions: std::ops::Range<usize>, budget: u64) -> Self {
        HeldLinks {
            kept: KeptLinks::new(directions.len(), budget),
            first: directions.start,
            steps: directions.len(),
        }
    }

    /// Whether direction `k`'s links are kept.
    pub(super) fn kept(&self, k: usize) -> bool {
        self.kept.kept(k - self.first)
    }

    /// Whether direction `k`'s links were written down once (kept or not).
    pub(super) fn tried(&self, k: usize) -> bool {
        self.kept.tried(k - self.first)
    }

    /// Memory for a direction's links to be written down into (`KeptLinks::spare_words`).
    pub(super) fn spare_words(&mut self) -> Vec<u64> {
        self.kept.spare_words()
    }

    /// Whether every direction of the group has its links kept.
    pub(super) fn all_kept(&self) -> bool {
        self.kept.all_kept()
    }

    /// An iteration starts, replaying blocks of links where `blocks` says (see
    /// `KeptLinks::begin_iteration`).
    pub(super) fn begin_iteration(&mut self, blocks: Blocks) {
        self.kept.begin_iteration(blocks);
    }

    /// Whether the light can be saved `done` steps into the iteration.
    pub(super) fn can_save_within(&self, done: usize) -> bool {
        self.kept.can_save_within(done)
    }

    /// Replays direction `k`'s links into `acc` if they are kept (or the block that holds them
    /// has replayed in this iteration); false (nothing done) if not.
    pub(super) fn replay(
        &mut self,
        k: usize,
        input: &DirectionInput,
        acc: &mut [[[f64; 3]; 2]],
    ) -> bool {
        self.kept
            .replay(k - self.first, input.radiosity, input.channels, acc)
    }

    /// Keeps `recorded` (numbered by place) as direction `k`'s links if the budget allows.
    pub(super) fn keep(&mut self, k: usize, recorded: DirectionLinks) {
        self.kept.keep(k - self.first, recorded);
    }

    /// Whether direction `k`'s first gather only writes its links down, its run being left to
    /// one replay (`KeptLinks::defers`).
    pub(super) fn defers(&self, k: usize) -> bool {
        self.kept.defers(k - self.first)
    }

    /// Keeps direction `k`'s links, written down without gathering, for its run's replay (or
    /// gathers them at once into `acc` where the budget refuses them).
    pub(super) fn keep_deferred(
        &mut self,
        k: usize,
        recorded: DirectionLinks,
        input: &DirectionInput,
        acc: &mut [[[f64; 3]; 2]],
    ) {
        self.kept.keep_deferred(
            k - self.first,
            recorded,
            input.radiosity,
            input.channels,
            acc,
        );
    }

    /// Gathers the directions whose links wait for their run's replay, apart and in order.
    pub(super) fn settle(
        &mut self,
        radiosity: &[Radiosity],
        channels: usize,
        acc: &mut [Gathered],
    ) {
        self.kept.settle(radiosity, channels, acc);
    }

    /// Whether the run of steps `b * BLOCK_STEPS ..` is replayed as one block at its end
    /// (`KeptLinks::agree_on_run`; collective on `world`).
    pub(super) fn agree_on_run(&self, b: usize, world: &dyn Comm, surfels: usize) -> Option<bool> {
        self.kept.agree_on_run(b, surfels, world)
    }

    /// The end of run `b`: its directions waiting are gathered into `acc` (the first
    /// `channels` channels of `radiosity`), as one block where `fuse` ([`Self::agree_on_run`])
    /// says, else apart in order.
    pub(super) fn finish_run(
        &mut self,
        b: usize,
        fuse: bool,
        radiosity: &[Radiosity],
        channels: usize,
        acc: &mut [Gathered],
    ) {
        self.kept.finish_run(b, fuse, radiosity, channels, acc);
    }

    /// What the report says of the links: the directions whose links every rank kept, and
    /// the bytes of all ranks' links. Collective on `world`.
    pub(super) fn stats(&self, directions: usize, surfels: usize, world: &dyn Comm) -> LinkStats {
        let mut bytes = [self.kept.held().1 as f64];
        world.sum_in_place(&mut bytes);
        // Each rank keeps its lines of its group's directions; a direction that some rank did
        // not keep (or never reached) is searched again there.
        let mine = self.first..self.first + self.steps;
        let tried = |k: usize| mine.contains(&k) && self.tried(k);
        let mut missing: Vec<f64> = (0..directions)
            .map(|k| (tried(k) && !self.kept(k)) as u8 as f64)
            .chain((0..directions).map(|k| tried(k) as u8 as f64))
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
