//! The direct-light pass in the data mode out of core: the one-process out-of-core pass
//! (`outcore::direct`) run by rank 0 on the whole source, its light sent to every rank's slice
//! and put in the held records, where it travels with the surfel (`held`, the direct slot).
//!
//! Rank 0 reads the whole source anyway (it writes the results from it), and the pass holds
//! only the emitters' lines within the budget: run there, it gives the one-process light bit
//! for bit, so the data mode out of core stays the one-process out-of-core solve's answer. The
//! other ranks wait meanwhile; the pass is one-off, and spreading its direction groups over the
//! ranks would need each rank's partial sums of the whole scene added across ranks.

use super::canonical::carry;
use super::held::{self, Held};
use super::route::Router;
use super::Solver;
use crate::geometry::directions::DirectionSet;
use crate::outcore::files::{IoCounters, SeqReader, LIGHT32_LEN};
use crate::outcore::OocError;
use crate::solve::direct::DirectStats;

impl Solver<'_> {
    /// Runs the pass with `count` dense directions on rank 0 and puts every surfel's direct
    /// light into the held files (canonical order, from `first`), the lines carrying `B - E`
    /// from here on. Collective; returns the pass's statistics (the same on every rank).
    pub(super) fn attach_direct(
        &self,
        held: Held,
        first: u64,
        count: usize,
        generation: u64,
        router: &Router,
        io: &mut IoCounters,
    ) -> Result<(Held, DirectStats), OocError> {
        let plan = router.plan;
        let mut stats = DirectStats::default();
        let pass = (self.comm.rank() == 0).then(|| {
            crate::outcore::direct::gather_direct_out_of_core(
                self.source,
                &DirectionSet::with_count(count),
                plan,
                self.pool,
                router.dir,
                io,
            )
        });
        // The other ranks have nothing to do meanwhile: they leave their cores to rank 0's
        // threads, where ranks share a node. A failure of the pass reaches them through
        // `send_slices`, as one of reading its file would.
        self.comm.wait_quietly();
        let read = |piece: &mut dyn FnMut(&[u8]) -> Result<(), OocError>| {
            let file = pass.expect("rank 0 ran the pass")?;
            stats = file.stats.clone();
            let mut reader = SeqReader::<LIGHT32_LEN>::open(&file.path, plan.io_bytes)?;
            while let Some(record) = reader.next_record()? {
                piece(&record)?;
            }
            drop(reader);
            std::fs::remove_file(&file.path).map_err(|e| OocError::io(&file.path, "remove", e))
        };
        let mut sent = IoCounters::default();
        let name = "the direct light's work file";
        let mine = self.send_slices(None, first, LIGHT32_LEN, name, read, router, &mut sent)?;
        let mine = mine.expect("every rank receives its slice");
        io.read += sent.read;
        io.written += sent.written;
        let info = self.source.info();
        let held = self.place_slice::<LIGHT32_LEN>(
            held,
            (&mine, true),
            generation,
            router,
            io,
            |w, d| {
                w[held::DIRECT_AT..held::DIRECT_AT + LIGHT32_LEN].copy_from_slice(d);
                carry(w, info, true);
            },
        )?;
        // Rank 0's figures for every rank.
        let mut figures = [
            stats.directions as f64,
            stats.emitting_surfels as f64,
            stats.lines as f64,
            stats.line_surfels as f64,
            stats.seconds,
            stats.parts as f64,
            stats.split_groups as f64,
        ];
        self.comm.sum_in_place(&mut figures);
        let [directions, emitting_surfels, lines, line_surfels, seconds, parts, split_groups] =
            figures;
        let stats = DirectStats {
            directions: directions as usize,
            emitting_surfels: emitting_surfels as usize,
            lines: lines as u64,
            line_surfels: line_surfels as u64,
            seconds,
            parts: parts as u64,
            split_groups: split_groups as u64,
        };
        Ok((held, stats))
    }
}
