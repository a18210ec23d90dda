//! Moving held surfels between ranks without holding them: fill (every held record goes to the
//! kept run or to the outgoing run of the rank that owns it now, in held order), exchange (the
//! outgoing runs sent in rounds of bounded bytes, the received pieces appended to one run per
//! source), merge (the kept run and the received runs, each sorted in copy order, merged k-way
//! into the new held files; an external sort instead when the held order was another axis's).
//!
//! Inside an axis a rank's rows of each layer are one interval before a step and after it, so
//! the fill reads only the rows that leave, and the merge lays the new held files out layer by
//! layer, the kept rows left where they are between the received rows below and above them,
//! which alone are written ([`Router::merge_by_layers`]).

use super::held::{
    merge_runs, sort_runs, voxel, AxisKey, Held, HeldRangeReader, HeldReader, HeldWriter,
    RunWriter, Source, Wire, MOST_SETS, WIRE_LEN,
};
use crate::distribute::data::PhaseSeconds;
use crate::distribute::Comm;
use crate::outcore::budget::MemoryPlan;
use crate::outcore::files::IoCounters;
use crate::outcore::OocError;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Where and within what a rank moves its records.
pub struct Router<'a> {
    pub comm: &'a dyn Comm,
    pub plan: &'a MemoryPlan,
    pub dir: &'a Path,
}

impl Router<'_> {
    /// Bytes a rank sends in one exchange round, over all destinations. A round holds the
    /// outgoing pieces, their packed copy, the received bytes and their unpacked copy: four
    /// times this, an eighth of the working memory each.
    pub fn round_bytes(&self) -> u64 {
        (self.plan.working / 8).max(WIRE_LEN as u64)
    }

    /// Runs merged at once, and the read buffer of each: a quarter of the working memory.
    fn fan_in(&self) -> (usize, usize) {
        let quarter = (self.plan.working / 4) as usize;
        let fan_in = (quarter / (16 << 10)).clamp(2, 256);
        let buffer = (quarter / fan_in).clamp(4 << 10, self.plan.io_bytes.max(4 << 10));
        (fan_in, buffer)
    }

    /// Records of a sort piece: half the working memory.
    fn sort_records(&self) -> usize {
        (self.plan.working / 2 / (WIRE_LEN as u64 + 32)).max(1) as usize
    }

    /// Sends every record of `held` to the rank `owner` names, after `transform`; returns the
    /// new held files (generation `generation`, sorted by `key`), their row histogram (in the
    /// reused vector `histogram`) and the records this rank sent away. `sorted`: `held` is
    /// sorted by `key` already, so the received runs are merged rather than sorted.
    ///
    /// `kept_rows`, with `sorted`: the rows `v` of each layer of `key` whose records stay here
    /// (`lo..hi`; `owner` names this rank for exactly these), so that only the other rows' records
    /// are read to be sent (found in the held files through `histogram`, their row counts),
    /// not every record.
    #[allow(clippy::too_many_arguments)]
    pub fn redistribute(
        &self,
        held: Held,
        generation: u64,
        key: AxisKey,
        sorted: bool,
        histogram: Vec<u32>,
        owner: &dyn Fn(&Wire) -> usize,
        kept_rows: Option<&dyn Fn(usize) -> (u64, u64)>,
        transform: &mut dyn FnMut(&mut Wire),
        io: &mut IoCounters,
        seconds: &mut PhaseSeconds,
    ) -> Result<(Held, Vec<u32>, u64), OocError> {
        let (ranks, me) = (self.comm.size(), self.comm.rank());
        if ranks == 1 && sorted {
            // Alone, in order already: nothing to move, nothing to read.
            return Ok((held, histogram, 0));
        }
        // Fill: the records that leave are written to the outgoing runs. Inside an axis the
        // kept ones are not read at all (they stay where they are, or are read once by the
        // merge). At a re-sort every record is read here anyway, and a run holds a record in
        // a few bytes (its byte planes compressed: about 9 of a wire record's 232 in a
        // building, where the held files take about 141), so the kept records go to a run of
        // their own, and the old held files are not read again by the sort.
        let t = Instant::now();
        let buffer = self.plan.bucket_buffer(ranks as u64 + 1);
        let mut outgoing: Vec<Option<RunWriter>> = (0..ranks)
            .map(|d| {
                (d != me)
                    .then(|| RunWriter::create(&self.dir.join(format!("out-{d}.run")), buffer))
                    .transpose()
            })
            .collect::<Result<_, _>>()?;
        let mut kept_run = (!sorted)
            .then(|| RunWriter::create(&self.dir.join("kept.run"), buffer))
            .transpose()?;
        let mut moved = 0u64;
        let mut send = |mut w: Wire| -> Result<(), OocError> {
            transform(&mut w);
            if let Some(out) = outgoing[owner(&w)].as_mut() {
                out.write(&w)?;
                moved += 1;
            } else if let Some(kept) = kept_run.as_mut() {
                kept.write(&w)?;
            }
            Ok(())
        };
        match kept_rows.filter(|_| sorted) {
            Some(kept_rows) => {
                let ranges = leaving_ranges(&histogram, key.rows(), kept_rows);
                let mut reader = HeldRangeReader::open(&held, ranges.clone(), self.plan.io_bytes)?;
                while let Some(w) = reader.next(io)? {
                    send(w)?;
                }
                // They are in the outgoing runs now, and no run of the new held files reads them.
                held.release(&ranges)?;
            }
            None if sorted => {
                let mut reader = HeldReader::open(&held, self.plan.io_bytes)?;
                while let Some(w) = reader.next(io)? {
                    send(w)?;
                }
            }
            None => {
                // Every record is in a run after this reading: the old files give their disk
                // back as it goes, and are removed below.
                let mut reader = HeldReader::consuming(&held, self.plan.io_bytes)?;
                while let Some(w) = reader.next(io)? {
                    send(w)?;
                }
            }
        }
        let kept_run = kept_run.map(|run| run.finish(&mut *io)).transpose()?;
        let outgoing: Vec<Option<PathBuf>> = outgoing
            .into_iter()
            .map(|o| o.map(|o| o.finish(&mut *io)).transpose())
            .collect::<Result<_, _>>()?;
        seconds.fill += t.elapsed().as_secs_f64();

        // Exchange.
        let t = Instant::now();
        let mut incoming: Vec<Option<RunWriter>> = (0..ranks)
            .map(|s| {
                (s != me)
                    .then(|| RunWriter::create(&self.dir.join(format!("in-{s}.run")), buffer))
                    .transpose()
            })
            .collect::<Result<_, _>>()?;
        exchange_files(
            self.comm,
            &outgoing,
            WIRE_LEN,
            self.round_bytes(),
            io,
            &mut |source, bytes| match incoming[source].as_mut() {
                // The sender's run file, compressed as it was written.
                Some(run) => run.append_frames(bytes),
                None => Ok(()),
            },
        )?;
        for path in outgoing.iter().flatten() {
            std::fs::remove_file(path).map_err(|e| OocError::io(path, "remove", e))?;
        }
        let received: u64 = incoming.iter().flatten().map(|r| r.appended).sum();
        let mut runs = Vec::new();
        for run in incoming.into_iter().flatten() {
            runs.push(run.finish(io)?);
        }
        seconds.exchange += t.elapsed().as_secs_f64();
        if sorted && moved == 0 && received == 0 {
            // Nothing left or arrived, and the order holds: the held files stay as they are
            // (`transform` changes records only when the order changes).
            for path in &runs {
                std::fs::remove_file(path).map_err(|e| OocError::io(path, "remove", e))?;
            }
            return Ok((held, histogram, 0));
        }

        if let Some(kept_rows) = kept_rows.filter(|_| sorted) {
            let t = Instant::now();
            let (next, histogram) =
                self.merge_by_layers(held, generation, key, histogram, kept_rows, runs, io)?;
            seconds.merge += t.elapsed().as_secs_f64();
            return Ok((next, histogram, moved));
        }

        // Merge (or sort) the kept records and the received runs into the new held files.
        let t = Instant::now();
        let mut writer = HeldWriter::create(
            self.dir,
            generation,
            self.plan.io_bytes,
            Some((key, histogram)),
            held.direct,
        )?;
        let (fan_in, read_buffer) = self.fan_in();
        let mut sink = |w: &Wire| writer.write(w);
        match kept_run {
            Some(kept_run) => {
                // Every record is sorted again (a change of main axis, or the hybrid mode's
                // canonical order), from the runs alone: the old held files go before the new
                // ones are written, so that they do not lie on the disk at once.
                held.remove()?;
                runs.push(kept_run);
                let records = self.sort_records();
                sort_runs(
                    runs,
                    key,
                    records,
                    fan_in,
                    read_buffer,
                    self.dir,
                    io,
                    &mut sink,
                )?;
            }
            None => {
                // In order already: the kept records are read from the held files as the
                // merge takes them.
                let mut reader = HeldReader::consuming(&held, self.plan.io_bytes)?;
                let kept: Source = Box::new(move |io: &mut IoCounters| {
                    while let Some(mut w) = reader.next(io)? {
                        transform(&mut w);
                        if owner(&w) == me {
                            return Ok(Some(w));
                        }
                    }
                    Ok(None)
                });
                merge_runs(
                    Some(kept),
                    runs,
                    key,
                    fan_in,
                    read_buffer,
                    self.dir,
                    io,
                    &mut sink,
                )?;
                held.remove()?;
            }
        }
        let (held, histogram) = writer.finish(io)?;
        seconds.merge += t.elapsed().as_secs_f64();
        Ok((held, histogram.unwrap_or_default(), moved))
    }
}

impl Router<'_> {
    /// The merge of a step inside an axis (`held` sorted by `key`, `histogram` its records per
    /// row): in each layer the records this rank keeps are the rows it held and still holds
    /// (`kept_rows`), one range of the held files, and each received row lies below or above
    /// them (a row is one rank's whole, and a rank's rows of a layer are one interval before
    /// the step and after it). So the new held files are, layer by layer, the received records
    /// below the kept range, the kept range, and the received records above it: the received
    /// records are written to new files (merged among themselves only), and the kept ranges
    /// stay in the old files, which the new held files take over (`HeldWriter::keep`; copied
    /// as bytes instead when the old ones lie in too many files, `held::MOST_SETS`). Returns
    /// the new held files and their histogram (`histogram` reused).
    #[allow(clippy::too_many_arguments)]
    fn merge_by_layers(
        &self,
        held: Held,
        generation: u64,
        key: AxisKey,
        mut histogram: Vec<u32>,
        kept_rows: &dyn Fn(usize) -> (u64, u64),
        runs: Vec<PathBuf>,
        io: &mut IoCounters,
    ) -> Result<(Held, Vec<u32>), OocError> {
        let rows = key.rows().max(1);
        // Per layer: the kept records (first, count) and the first and last kept rows. The
        // histogram keeps the kept rows' counts; the received rows are counted as written.
        let mut spans: Vec<((u64, u64), (usize, usize))> = Vec::with_capacity(key.layers());
        let mut first = 0u64;
        for (layer, counts) in histogram.chunks_mut(rows).enumerate() {
            let (lo, hi) = kept_rows(layer);
            let (lo, hi) = (lo.min(rows as u64) as usize, hi.min(rows as u64) as usize);
            let total: u64 = counts.iter().map(|&c| c as u64).sum();
            let (mut below, mut kept) = (0u64, 0u64);
            let (mut first_row, mut last_row) = (usize::MAX, 0);
            for (row, count) in counts.iter_mut().enumerate() {
                if lo <= row && row < hi {
                    kept += *count as u64;
                    if *count > 0 {
                        first_row = first_row.min(row);
                        last_row = row;
                    }
                } else {
                    if row < lo {
                        below += *count as u64;
                    }
                    *count = 0;
                }
            }
            spans.push(((first + below, kept), (first_row, last_row)));
            first += total;
        }
        // The kept ranges stay where they are, in the files of `held`, unless its records lie
        // in too many sets already, or its sets hold as many records that left as records in
        // use: then they are copied, and the result is one set again.
        let keep_in_place = held.sets.len() < MOST_SETS && held.stored_records()? <= 2 * held.count;
        let from = if keep_in_place {
            None
        } else {
            Some(held.open_files()?)
        };
        let mut writer =
            HeldWriter::create(self.dir, generation, self.plan.io_bytes, None, held.direct)?;
        let base = if keep_in_place {
            writer.adopt(&held)
        } else {
            0
        };
        let chunk = (self.plan.io_bytes / WIRE_LEN).max(1) as u64;
        let mut buffer = Vec::new();
        let mut copied = IoCounters::default();
        // Layers before `next_layer` are written whole; `copied_layer`: the kept range of
        // layer `next_layer` is written.
        let (mut next_layer, mut copied_layer) = (0usize, false);
        let mut copy_through = |layer: usize,
                                row: usize,
                                next_layer: &mut usize,
                                copied_layer: &mut bool,
                                writer: &mut HeldWriter|
         -> Result<(), OocError> {
            // What the layout rests on, checked rather than assumed: a received record comes
            // in key order and lies outside the kept rows of its layer.
            let (below_kept, inside_kept) =
                spans.get(layer).map_or((false, false), |&(_, (lo, hi))| {
                    (row < lo, lo <= row && row <= hi)
                });
            let after_copy = layer == *next_layer && *copied_layer;
            if layer < *next_layer || inside_kept || after_copy && below_kept {
                return Err(OocError::BadData {
                    source_name: self.dir.display().to_string(),
                    what: format!(
                        "a record received for layer {layer}, row {row} falls among the rows \
                         this rank kept or before them: the ranks' column cuts disagree"
                    ),
                });
            }
            while *next_layer < layer || *next_layer == layer && !*copied_layer {
                let Some(&(range, (first_row, _))) = spans.get(*next_layer) else {
                    // Past the last layer: everything is written.
                    return Ok(());
                };
                if *next_layer == layer && row < first_row {
                    // A received row below the kept ones: it comes first.
                    return Ok(());
                }
                if !*copied_layer {
                    match &from {
                        Some(from) => {
                            writer.copy_records(from, range, chunk, &mut buffer, &mut copied)?;
                            // Copied: the old files' bytes go as the new ones grow.
                            held.release(&[range])?;
                        }
                        None => writer.keep(&held, base, range),
                    }
                }
                if *next_layer < layer {
                    *next_layer += 1;
                    *copied_layer = false;
                } else {
                    *copied_layer = true;
                }
            }
            Ok(())
        };
        let (fan_in, read_buffer) = self.fan_in();
        merge_runs(
            None,
            runs,
            key,
            fan_in,
            read_buffer,
            self.dir,
            io,
            &mut |w: &Wire| {
                let v = voxel(w);
                let (layer, row) = (v[key.main] as usize, v[key.v] as usize);
                copy_through(layer, row, &mut next_layer, &mut copied_layer, &mut writer)?;
                histogram[key.row(v)] += 1;
                writer.write(w)
            },
        )?;
        // The layers after the last received record.
        copy_through(
            spans.len(),
            0,
            &mut next_layer,
            &mut copied_layer,
            &mut writer,
        )?;
        io.read += copied.read;
        if keep_in_place {
            // The new held files own the old ones' files now (the sets no run reads are
            // removed as it finishes).
            drop(held);
        } else {
            held.remove()?;
        }
        let (held, _) = writer.finish(io)?;
        Ok((held, histogram))
    }
}

/// The records of held files in their row order (`histogram`: records per row, `rows` rows a
/// layer) that lie outside the rows `kept_rows(layer)` of their layer, as (first record,
/// records): at most two ranges a layer, below and above the kept rows.
fn leaving_ranges(
    histogram: &[u32],
    rows: usize,
    kept_rows: &dyn Fn(usize) -> (u64, u64),
) -> Vec<(u64, u64)> {
    let mut ranges = Vec::new();
    let mut first = 0u64;
    for (layer, counts) in histogram.chunks(rows.max(1)).enumerate() {
        let (lo, hi) = kept_rows(layer);
        let (lo, hi) = (lo.min(rows as u64) as usize, hi.min(rows as u64) as usize);
        let records = |r: std::ops::Range<usize>| counts[r].iter().map(|&c| c as u64).sum::<u64>();
        let total = records(0..rows);
        if lo >= hi {
            ranges.push((first, total));
        } else {
            let below = records(0..lo);
            let kept = records(lo..hi);
            ranges.push((first, below));
            ranges.push((first + below + kept, total - below - kept));
        }
        first += total;
    }
    ranges.retain(|&(_, count)| count > 0);
    ranges
}

/// Takes the bytes that arrived from one source rank.
pub type Received<'a> = dyn FnMut(usize, &[u8]) -> Result<(), OocError> + 'a;

/// Sends the file `outgoing[d]` to rank `d` (none: nothing) in rounds of at most `round_bytes`
/// per rank in all, cut at whole records of `record` bytes; hands what arrives to
/// `received(source, bytes)`, in order for each source. Collective: the number of rounds is
/// agreed with `max_u64`.
pub fn exchange_files(
    comm: &dyn Comm,
    outgoing: &[Option<PathBuf>],
    record: usize,
    round_bytes: u64,
    io: &mut IoCounters,
    received: &mut Received,
) -> Result<(), OocError> {
    let ranks = comm.size();
    let record = record as u64;
    // Each destination gets at most its share of a round, so each rank also receives at most
    // a round's bytes.
    let piece = (round_bytes / (ranks.saturating_sub(1).max(1)) as u64 / record).max(1) * record;
    let mut files = Vec::with_capacity(ranks);
    let mut left = Vec::with_capacity(ranks);
    for path in outgoing {
        match path {
            Some(p) => {
                let f = std::fs::File::open(p).map_err(|e| OocError::io(p, "open", e))?;
                let len = f.metadata().map_err(|e| OocError::io(p, "read", e))?.len();
                files.push(Some((
                    p.as_path(),
                    std::io::BufReader::with_capacity(1 << 12, f),
                )));
                left.push(len);
            }
            None => {
                files.push(None);
                left.push(0);
            }
        }
    }
    let mine = left.iter().map(|&l| l.div_ceil(piece)).max().unwrap_or(0);
    let rounds = comm.max_u64(mine);
    for _ in 0..rounds {
        let mut packs = Vec::with_capacity(ranks);
        for (file, left) in files.iter_mut().zip(left.iter_mut()) {
            let take = piece.min(*left) as usize;
            let mut pack = vec![0u8; take];
            if let Some((path, reader)) = file.as_mut() {
                reader
                    .read_exact(&mut pack)
                    .map_err(|e| OocError::io(path, "read", e))?;
                io.read += take as u64;
            }
            *left -= take as u64;
            packs.push(pack);
        }
        let arrived = comm.exchange(packs);
        for (source, bytes) in arrived.iter().enumerate() {
            if !bytes.is_empty() {
                received(source, bytes)?;
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::leaving_ranges;

    /// The ranges name exactly the records, in row order, whose row lies outside its layer's
    /// kept rows: against listing every record with its layer and row.
    #[test]
    fn leaving_ranges_name_the_records_outside_the_kept_rows() {
        let rows = 5;
        // Three layers of five rows: some empty rows, an empty layer.
        let histogram: Vec<u32> = vec![2, 0, 3, 1, 4, 0, 0, 0, 0, 0, 1, 2, 0, 5, 1];
        let kept = [(1u64, 4u64), (0, 5), (3, 99)];
        let cases: [&dyn Fn(usize) -> (u64, u64); 3] = [
            &|layer| kept[layer],
            // Nothing kept (a rank whose columns lie past the layer).
            &|_| (7, 7),
            // Everything kept.
            &|_| (0, u64::MAX),
        ];
        for kept_rows in cases {
            let mut expected = Vec::new();
            let mut record = 0u64;
            for (at, &count) in histogram.iter().enumerate() {
                let (layer, row) = (at / rows, (at % rows) as u64);
                let (lo, hi) = kept_rows(layer);
                for _ in 0..count {
                    if !(lo <= row && row < hi) {
                        expected.push(record);
                    }
                    record += 1;
                }
            }
            let got: Vec<u64> = leaving_ranges(&histogram, rows, kept_rows)
                .into_iter()
                .flat_map(|(first, count)| first..first + count)
                .collect();
            assert_eq!(got, expected);
        }
    }
}
