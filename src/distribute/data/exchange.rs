//! The data mode's distribution of one direction: the balance of its lines over the group's
//! ranks (from histograms added over them), and the exchange that brings every surfel to the
//! rank owning its line (fill, all-to-all, merge).

use super::*;

impl DataSolver<'_> {
    /// The elastic distribution of direction `k` over the group, from histograms added over
    /// the group's ranks.
    pub(super) fn balance(
        &self,
        k: usize,
        held: &Held,
        group_comm: &dyn Comm,
        preferred_bands: Option<usize>,
    ) -> Distribution {
        let d = &self.directions.directions[k];
        let projection = self.projection(k);
        let line_bins = projection.lines(&self.frames[k], d.vector);
        let bins: Vec<(usize, usize)> = self.pool.install(|| {
            held.order
                .par_iter()
                .map(|e| line_bins.bin(e.voxel))
                .collect()
        });
        let width = projection.bins();
        let mut rows = vec![0.0f64; width];
        for &(r, _) in &bins {
            rows[r] += 1.0;
        }
        group_comm.sum_in_place(&mut rows);
        balance::distribute(group_comm.size(), &rows, preferred_bands, |row_cuts| {
            let bands = row_cuts.len() - 1;
            let mut columns = vec![0.0f64; bands * width];
            for &(r, c) in &bins {
                let band = row_cuts.partition_point(|&x| x <= r).clamp(1, bands) - 1;
                columns[band * width + c] += 1.0;
            }
            group_comm.sum_in_place(&mut columns);
            columns.chunks(width).map(<[f64]>::to_vec).collect()
        })
    }

    /// Sends every held surfel to the rank `owner` names (from its voxel and id), and leaves
    /// `held` with what this rank holds then, sorted in octant order `order` (by id when
    /// `direction` is `usize::MAX`, the canonical distribution). `held_order` is the order
    /// `held` is sorted in now.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn redistribute(
        &self,
        held: &mut Held,
        held_order: Option<usize>,
        order: usize,
        group_comm: &dyn Comm,
        tally: &mut Tally,
        direction: usize,
        owner: impl Fn([i32; 3], &dyn Fn() -> u32) -> usize + Sync,
    ) {
        let (ranks, me) = (group_comm.size(), group_comm.rank());
        let canonical = direction == usize::MAX;
        // Fill: destinations in held order, so every pack is sorted as `held` is.
        let t = Instant::now();
        let mut kept = Vec::with_capacity(held.len());
        let mut packs: Vec<Vec<u8>> = vec![Vec::new(); ranks];
        if ranks == 1 {
            kept = std::mem::take(&mut held.order);
        } else {
            let owners: Vec<u32> = self.pool.install(|| {
                held.order
                    .par_iter()
                    // The id only when the owner needs it: reading it is a random access.
                    .map(|e| owner(e.voxel, &|| held.ids[e.index as usize]) as u32)
                    .collect()
            });
            let entries = std::mem::take(&mut held.order);
            for (e, &dest) in entries.iter().zip(&owners) {
                if dest as usize == me {
                    kept.push(*e);
                } else {
                    held.encode(e.index, &mut packs[dest as usize]);
                    held.free.push(e.index);
                }
            }
        }
        let moved = packs.iter().map(Vec::len).sum::<usize>() / RECORD_BYTES;
        if !canonical {
            tally.moved[direction] += moved as f64;
        }
        tally.bytes_packed += (moved * RECORD_BYTES) as u64;
        let compress = self.compress;
        let packs: Vec<Vec<u8>> = self
            .pool
            .install(|| packs.into_par_iter().map(|p| seal(p, compress)).collect());
        tally.bytes_sent += packs.iter().map(|p| p.len() as u64).sum::<u64>();
        tally.seconds.fill += t.elapsed().as_secs_f64();

        let t = Instant::now();
        let received = if ranks == 1 {
            Vec::new()
        } else {
            group_comm.exchange(packs)
        };
        tally.seconds.exchange += t.elapsed().as_secs_f64();

        // Merge: the received packs (each sorted) into one run, then with the kept run.
        let t = Instant::now();
        let mut arrived = Vec::new();
        for pack in received.iter().filter(|p| !p.is_empty()) {
            held.decode_all(&unseal(pack), &self.surfels, &mut arrived);
        }
        let ids = &held.ids;
        held.order = if canonical {
            kept.extend_from_slice(&arrived);
            kept.sort_unstable_by_key(|e| ids[e.index as usize]);
            kept
        } else {
            let cmp = |x: &OrderedEntry, y: &OrderedEntry| compare(order, ids, x, y);
            if held_order == Some(order) {
                // The packs are sorted runs: a stable sort merges them as runs.
                arrived.sort_by(cmp);
                merge_two(&kept, &arrived, cmp)
            } else {
                kept.extend_from_slice(&arrived);
                kept.sort_unstable_by(cmp);
                kept
            }
        };
        tally.seconds.merge += t.elapsed().as_secs_f64();
    }
}
