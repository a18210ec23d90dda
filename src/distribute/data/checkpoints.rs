//! The data mode's checkpoints: the owners' radiosity gathered by id for a boundary, every
//! rank's part of the light for a save inside an iteration, and the rebuild of what each rank
//! held when a solve resumes inside an iteration.

use super::*;

impl DataSolver<'_> {
    /// A mid-iteration checkpoint `done` steps into iteration `state.iteration + 1`: the
    /// radiosity it gathers from and every rank's part of the light, by surfel id (see
    /// `checkpoint::State::data_groups`). Collective: every rank calls it.
    pub(super) fn save_within(
        &self,
        world: &dyn Comm,
        saver: &mut Saver,
        mut state: State,
        done: usize,
        held: &Held,
        owned: &Owned,
    ) -> Result<(), CheckpointError> {
        let t = Instant::now();
        let radiosity = self.gather_by_id(owned, &owned.radiosity, world);
        let older = state
            .extrapolation
            .chebyshev
            .map(|_| self.gather_by_id(owned, &owned.previous, world));
        let mut acc: Vec<Gathered> = vec![[[0.0; 3]; 2]; self.set.surfels.len()];
        for (&id, a) in held.ids.iter().zip(&held.acc) {
            acc[id as usize] = *a;
        }
        state.data_groups = self.groups as u32;
        let result = saver.save_within(
            world,
            state,
            done as u64,
            (&radiosity, older.as_deref()),
            &acc,
        );
        // The gathering is part of what a checkpoint costs here: it spaces the next ones too.
        saver.took(t.elapsed());
        result
    }

    /// Rebuilds what this rank held after its group's directions `done` (the first ones of an
    /// iteration) from a mid-iteration checkpoint, `held` holding the canonical block: their distributions, found again as the first
    /// iteration found them (each from the histograms, which do not depend on who holds the
    /// surfels, and the bands of the one before), then the surfels the last one gives this rank,
    /// with the checkpoint's `radiosity`, in that direction's order (the uninterrupted run held
    /// exactly these there), and this rank's part of the light, `sums` (every surfel it has a
    /// part of is met). Returns the octant order `held` is sorted in (`None`: the canonical
    /// block by id, when the group had no direction yet). Collective in the group.
    pub(super) fn rebuild_within(
        &self,
        held: &mut Held,
        done: &[usize],
        remembered: &mut [Option<Distribution>],
        group_comm: &dyn Comm,
        radiosity: &[Radiosity],
        sums: &[Gathered],
    ) -> Option<usize> {
        for (i, &k) in done.iter().enumerate() {
            if remembered[k].is_none() {
                let previous = i
                    .checked_sub(1)
                    .and_then(|p| remembered[done[p]].as_ref())
                    .map(Distribution::bands);
                remembered[k] = Some(self.balance(k, held, group_comm, previous).0);
            }
        }
        let Some(&last) = done.last() else {
            // `held` is the block it starts from.
            self.meet_parts(held, radiosity, sums);
            return None;
        };
        let d = &self.directions.directions[last];
        let o = order::order_of(d.vector);
        let bins = self.projection(last).lines(&self.frames[last], d.vector);
        let distribution = remembered[last].as_ref()?;
        let table = distribution.table();
        let me = group_comm.rank();
        // The block stays met (with no part of the light, which adds nothing).
        held.order.clear();
        for (id, prop) in self.surfels.iter().enumerate() {
            let (row, col) = bins.bin(prop.voxel);
            if group_comm.size() == 1 || table.owner(row, col) == me {
                let place = held.meet(id as u32, *prop, radiosity[id], &self.emission[id]);
                held.order.push(OrderedEntry {
                    voxel: prop.voxel,
                    index: place,
                });
            }
        }
        let ids = &held.ids;
        held.order.sort_unstable_by(|x, y| compare(o, ids, x, y));
        self.meet_parts(held, radiosity, sums);
        Some(o)
    }

    /// Puts this rank's part of the light back (`sums`, by id), meeting the surfels it has a
    /// part of. A surfel whose part is zero need not be met: meeting it later adds the same.
    fn meet_parts(&self, held: &mut Held, radiosity: &[Radiosity], sums: &[Gathered]) {
        for (id, part) in sums.iter().enumerate() {
            if part.iter().flatten().any(|&v| v != 0.0) {
                let place = held.meet(
                    id as u32,
                    self.surfels[id],
                    radiosity[id],
                    &self.emission[id],
                );
                held.acc[place as usize] = *part;
            }
        }
    }

    /// `values` of the owners' blocks (their radiosity, or the radiosity before last) of every
    /// surfel by id, on every rank (added over the world; in a grey solve the one channel
    /// copied to all three, as the solver returns it).
    pub(super) fn gather_by_id(
        &self,
        owned: &Owned,
        values: &[Radiosity],
        world: &dyn Comm,
    ) -> Vec<Radiosity> {
        let n = self.set.surfels.len();
        let mut flat = vec![0.0f64; n * 6];
        for (b, id) in values.iter().zip(owned.ids.clone()) {
            for side in 0..2 {
                for ch in 0..3 {
                    flat[id * 6 + side * 3 + ch] = b[side][ch] as f64;
                }
            }
        }
        world.sum_in_place(&mut flat);
        flat.chunks_exact(6)
            .map(|c| {
                [
                    [c[0] as f32, c[1] as f32, c[2] as f32],
                    [c[3] as f32, c[4] as f32, c[5] as f32],
                ]
            })
            .collect()
    }
}
