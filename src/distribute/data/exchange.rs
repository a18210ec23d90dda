//! The data mode's distribution of one direction: the balance of its lines over the group's
//! ranks (from histograms added over them), and the exchange that brings every surfel to the
//! rank owning its line (fill, all-to-all, merge), the first time in full and later by the
//! direction's plan (`plan`).

use super::*;

impl DataSolver<'_> {
    /// The elastic distribution of direction `k` over the group, from histograms added over
    /// the group's ranks, and the bin of every held surfel (in `held.order`'s order).
    pub(super) fn balance(
        &self,
        k: usize,
        held: &Held,
        group_comm: &dyn Comm,
        preferred_bands: Option<usize>,
    ) -> (Distribution, Vec<(usize, usize)>) {
        let d = &self.directions.directions[k];
        let projection = self.projection(k);
        let line_bins = projection.lines(&self.frames[k], d.vector);
        // One thread: a bin costs a few nanoseconds, and in rayon's pieces this pass took three
        // times as long on one thread and longer on two than alone.
        let bins: Vec<(usize, usize)> = held.order.iter().map(|e| line_bins.bin(e.voxel)).collect();
        let width = projection.bins();
        let mut rows = vec![0.0f64; width];
        for &(r, _) in &bins {
            rows[r] += 1.0;
        }
        group_comm.sum_in_place(&mut rows);
        let distribution =
            balance::distribute(group_comm.size(), &rows, preferred_bands, |row_cuts| {
                let bands = row_cuts.len() - 1;
                let mut columns = vec![0.0f64; bands * width];
                for &(r, c) in &bins {
                    let band = row_cuts.partition_point(|&x| x <= r).clamp(1, bands) - 1;
                    columns[band * width + c] += 1.0;
                }
                group_comm.sum_in_place(&mut columns);
                columns.chunks(width).map(<[f64]>::to_vec).collect()
            });
        (distribution, bins)
    }

    /// Sends every held surfel to its rank in `owners` (in `held.order`'s order) for direction
    /// `k`, and leaves `held.order` with what this rank holds then, sorted in octant order `order`.
    /// `held_order` is the order `held` is sorted in now, `from` what it was distributed by.
    /// Returns the plan of this exchange, which later exchanges from `from` to `k` follow
    /// (`plan`).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn redistribute(
        &self,
        held: &mut Held,
        held_order: Option<usize>,
        order: usize,
        group_comm: &dyn Comm,
        tally: &mut Tally,
        k: usize,
        from: Origin,
        owners: &[u32],
    ) -> ExchangePlan {
        let (ranks, me) = (group_comm.size(), group_comm.rank());
        // Fill: destinations in held order, so every pack is sorted as `held` is.
        let t = Instant::now();
        let mut kept = Vec::with_capacity(held.len());
        let mut leave = Vec::new();
        let mut packs: Vec<Vec<u8>> = vec![Vec::new(); ranks];
        if ranks == 1 {
            kept = std::mem::take(&mut held.order);
        } else {
            let entries = std::mem::take(&mut held.order);
            for (place, (e, &dest)) in entries.iter().zip(owners).enumerate() {
                if dest as usize == me {
                    kept.push(*e);
                } else {
                    held.encode(e.index, &mut packs[dest as usize]);
                    leave.push((place as u32, dest));
                }
            }
        }
        tally.seconds.fill += t.elapsed().as_secs_f64();
        let arrived = self.send_and_receive(held, packs, group_comm, tally, k);

        // Merge: the received packs (each sorted) into one run, then with the kept run.
        let t = Instant::now();
        let ids = &held.ids;
        let cmp = |x: &OrderedEntry, y: &OrderedEntry| compare(order, ids, x, y);
        held.order = if held_order == Some(order) {
            // The packs are sorted runs: a stable sort merges them as runs.
            let mut sorted = arrived.clone();
            sorted.sort_by(cmp);
            merge_two(&kept, &sorted, cmp)
        } else {
            let mut all = kept.clone();
            all.extend_from_slice(&arrived);
            all.sort_unstable_by(cmp);
            all
        };
        tally.seconds.merge += t.elapsed().as_secs_f64();
        ExchangePlan::record(from, leave, &kept, &arrived, &held.order, held.met())
    }

    /// The exchange `plan` recorded, again: the same surfels leave for the same ranks and the
    /// arrivals take the same places, without placing a surfel on its line's bin or comparing
    /// two (the plan's module says why that holds).
    pub(super) fn redistribute_planned(
        &self,
        plan: &ExchangePlan,
        held: &mut Held,
        group_comm: &dyn Comm,
        tally: &mut Tally,
        k: usize,
    ) {
        let t = Instant::now();
        let mut packs: Vec<Vec<u8>> = vec![Vec::new(); group_comm.size()];
        let kept = plan.fill(held, &mut packs);
        tally.seconds.fill += t.elapsed().as_secs_f64();
        let arrived = self.send_and_receive(held, packs, group_comm, tally, k);
        let t = Instant::now();
        held.order = plan.order(&kept, &arrived);
        tally.seconds.merge += t.elapsed().as_secs_f64();
    }

    /// Seals the packs, exchanges them over the group and stores what arrives; returns the
    /// arrivals' entries in pack order.
    fn send_and_receive(
        &self,
        held: &mut Held,
        packs: Vec<Vec<u8>>,
        group_comm: &dyn Comm,
        tally: &mut Tally,
        k: usize,
    ) -> Vec<OrderedEntry> {
        let t = Instant::now();
        let moved = packs.iter().map(Vec::len).sum::<usize>() / RECORD_BYTES;
        tally.moved[k] += moved as f64;
        tally.exchanges[k] += 1;
        tally.bytes_packed += (moved * RECORD_BYTES) as u64;
        let compress = self.compress;
        let packs: Vec<Vec<u8>> = self
            .pool
            .install(|| packs.into_par_iter().map(|p| seal(p, compress)).collect());
        tally.bytes_sent += packs.iter().map(|p| p.len() as u64).sum::<u64>();
        tally.seconds.fill += t.elapsed().as_secs_f64();

        let t = Instant::now();
        let received = if group_comm.size() == 1 {
            Vec::new()
        } else {
            group_comm.exchange(packs)
        };
        tally.seconds.exchange += t.elapsed().as_secs_f64();

        let t = Instant::now();
        let mut arrived = Vec::new();
        for pack in received.iter().filter(|p| !p.is_empty()) {
            held.decode_all(&unseal(pack), &self.surfels, &self.emission, &mut arrived);
        }
        tally.seconds.merge += t.elapsed().as_secs_f64();
        arrived
    }
}
