//! Radiosity between the ranks and canonical order (data mode out of core): rank 0 gathers
//! every rank's `(id, B)` into a canonical file for the results and the checkpoints, sends each
//! rank its slice of a canonical file (a checkpoint's radiosity on resume, the direct light),
//! and writes a checkpoint of the canonical radiosity; while the Chebyshev semi-iteration runs,
//! the radiosity before last travels the same ways (`held::OLDER_AT`).

use super::held::{self, Held, HeldReader, HeldWriter};
use super::route::{exchange_files, Router};
use super::Solver;
use crate::checkpoint::{CheckpointFile, Saver, State};
use crate::outcore::budget::MemoryPlan;
use crate::outcore::files::{
    decode_radiosity, encode_radiosity, IoCounters, RecordFile, SeqReader, RADIOSITY_LEN,
};
use crate::outcore::source::SourceInfo;
use crate::outcore::OocError;
use std::path::{Path, PathBuf};

impl Solver<'_> {
    /// Puts the radiosity of a checkpoint (`file`, on rank 0) into the held files of every rank,
    /// which hold their slices in canonical order (from `first`): rank 0 reads it, checks it, and
    /// sends each rank its slice in bounded rounds. The lines then carry it (less `E` with the
    /// direct pass, which ran before). With `older` (the state's Chebyshev semi-iteration
    /// runs, which every rank knows), its radiosity before last goes into the older field the
    /// same way.
    pub(super) fn restore(
        &self,
        mut held: Held,
        first: u64,
        (file, older): (Option<&CheckpointFile>, bool),
        generation: &mut u64,
        router: &Router,
        io: &mut IoCounters,
    ) -> Result<Held, OocError> {
        let plan = router.plan;
        let name = file
            .as_ref()
            .map(|f| f.path.display().to_string())
            .unwrap_or_else(|| "the checkpoint".to_string());
        let info = self.source.info();
        let direct = self.direct();
        // The radiosity (array 0), then the radiosity before last (array 1).
        for array in 0..1 + older as usize {
            let read = |piece: &mut dyn FnMut(&[u8]) -> Result<(), OocError>| {
                let file = file.ok_or_else(|| OocError::BadData {
                    source_name: "the checkpoint".to_string(),
                    what: "rank 0 did not open it".to_string(),
                })?;
                let skip = |_: &[u8]| Ok(());
                match array {
                    0 => file.read_payload::<OocError>(plan.io_bytes, piece, skip, skip, skip),
                    _ => file.read_payload::<OocError>(plan.io_bytes, skip, piece, skip, skip),
                }
            };
            let mine = self.send_slices(None, first, RADIOSITY_LEN, &name, read, router, io)?;
            let mine = mine.expect("every rank receives its slice");
            *generation += 1;
            let at = if array == 0 {
                held::RADIOSITY_AT
            } else {
                held::OLDER_AT
            };
            held = self.place_slice::<RADIOSITY_LEN>(
                held,
                (&mine, false),
                *generation,
                router,
                io,
                |w, b| {
                    w[at..at + RADIOSITY_LEN].copy_from_slice(b);
                    if array == 0 {
                        carry(w, info, direct);
                    }
                },
            )?;
        }
        Ok(held)
    }

    /// Rank 0 cuts the canonical records of `len` bytes that `read` hands it (in pieces of whole
    /// records; `name` names their origin in errors) into the slices of the ranks, whose first
    /// canonical index this rank's `first` is, and sends each rank of group `group` (`None`: of
    /// every group) its own in bounded rounds; returns the file that holds this rank's slice
    /// where it receives one. Collective; `read` runs on rank 0 only.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn send_slices(
        &self,
        group: Option<usize>,
        first: u64,
        len: usize,
        name: &str,
        read: impl FnOnce(&mut dyn FnMut(&[u8]) -> Result<(), OocError>) -> Result<(), OocError>,
        router: &Router,
        io: &mut IoCounters,
    ) -> Result<Option<PathBuf>, OocError> {
        let me = self.comm.rank();
        let group_size = self.group.size();
        let receives = |r: usize| group.is_none_or(|g| r / group_size == g);
        let plan = router.plan;
        let dir = router.dir;
        let n = self.source.info().count;
        // Every group holds the scene in the same slices: rank 0 cuts one file per slice and
        // sends it to the rank at that place in every group.
        let starts = self.slice_starts(first);
        let slices = starts.len();
        // Named by the group sent to: a rank's own slice for one group must outlive the cutting
        // of the next group's.
        let to = group.map_or_else(|| "all".to_string(), |g| format!("group{g}"));
        let path = |r: usize| dir.join(format!("slice-{to}-{r}.bin"));
        let mut failure = None;
        if me == 0 {
            let cut = || -> Result<(), OocError> {
                let buffer = plan.bucket_buffer(slices as u64);
                let mut outs = (0..slices)
                    .map(|r| crate::outcore::files::SeqWriter::create(&path(r), buffer))
                    .collect::<Result<Vec<_>, _>>()?;
                let mut index = 0u64;
                read(&mut |piece: &[u8]| {
                    for record in piece.chunks_exact(len) {
                        let owner = starts[1..].partition_point(|&s| s <= index);
                        outs[owner].write(record)?;
                        index += 1;
                    }
                    Ok(())
                })?;
                if index != n {
                    return Err(OocError::BadData {
                        source_name: name.to_string(),
                        what: format!("it holds {index} surfels, the scene {n}"),
                    });
                }
                for out in outs {
                    io.written += out.finish()?;
                }
                io.read += n * len as u64;
                Ok(())
            };
            failure = cut().err();
        }
        // Every rank learns whether rank 0 could read it before any waits for its slice.
        if self.comm.max_u64(failure.is_some() as u64) == 1 {
            return Err(failure.unwrap_or_else(|| {
                crate::checkpoint::let_rank_0_speak_first();
                OocError::BadData {
                    source_name: name.to_string(),
                    what: "rank 0 could not read it (see rank 0's message)".to_string(),
                }
            }));
        }
        let outgoing: Vec<Option<PathBuf>> = (0..self.comm.size())
            .map(|r| (me == 0 && r != 0 && receives(r)).then(|| path(r % slices)))
            .collect();
        let mine = if me == 0 { path(0) } else { path(me) };
        let mut received = if me == 0 || !receives(me) {
            None
        } else {
            Some(crate::outcore::files::SeqWriter::create(
                &mine,
                plan.io_bytes,
            )?)
        };
        exchange_files(
            self.comm,
            &outgoing,
            len,
            router.round_bytes(),
            io,
            &mut |_, bytes| match received.as_mut() {
                Some(out) => out.write(bytes),
                None => Ok(()),
            },
        )?;
        if let Some(out) = received {
            io.written += out.finish()?;
        }
        if me == 0 {
            let own = receives(0) as usize;
            for r in own..slices {
                let p = path(r);
                std::fs::remove_file(&p).map_err(|e| OocError::io(&p, "remove", e))?;
            }
        }
        Ok(receives(me).then_some(mine))
    }

    /// The first canonical index of every slice of the group, from this rank's `first`
    /// (collective in the group).
    pub(super) fn slice_starts(&self, first: u64) -> Vec<u64> {
        let mut starts = vec![0.0f64; self.group.size()];
        starts[self.group.rank()] = first as f64;
        self.group.sum_in_place(&mut starts);
        starts.iter().map(|&s| s as u64).collect()
    }

    /// Rewrites the held files (in canonical order, as read) with the records of `slice` (one
    /// of `L` bytes per held surfel, in the same order) put in by `place`; removes `slice`.
    /// `adds_direct`: `place` puts the direct light in (the new files then keep it).
    pub(super) fn place_slice<const L: usize>(
        &self,
        held: Held,
        (slice, adds_direct): (&Path, bool),
        generation: u64,
        router: &Router,
        io: &mut IoCounters,
        place: impl Fn(&mut held::Wire, &[u8]),
    ) -> Result<Held, OocError> {
        let plan = router.plan;
        let mut values = SeqReader::<L>::open(slice, plan.io_bytes)?;
        let mut reader = HeldReader::consuming(&held, plan.io_bytes)?;
        let direct = held.direct || adds_direct;
        let mut writer = HeldWriter::create(router.dir, generation, plan.io_bytes, None, direct)?;
        while let Some(mut w) = reader.next(io)? {
            place(&mut w, &values.expect_record()?);
            writer.write(&w)?;
        }
        drop((reader, values));
        io.read += held.count * L as u64;
        std::fs::remove_file(slice).map_err(|e| OocError::io(slice, "remove", e))?;
        held.remove()?;
        Ok(writer.finish(io)?.0)
    }

    /// Sends every held `(id, B)` to rank 0, which places them in a canonical radiosity file
    /// (returned there; `None` elsewhere). `last`: the held files are read for the last time
    /// (the solve's results), and give their disk back as they are read, so that they and the
    /// canonical file do not both lie whole on rank 0's disk.
    pub(super) fn gather_results(
        &self,
        held: &Held,
        surfels: u64,
        (dir, plan): (&Path, &MemoryPlan),
        last: bool,
        io: &mut IoCounters,
    ) -> Result<Option<PathBuf>, OocError> {
        // Group 0 holds every surfel once (the hybrid mode's other groups hold copies).
        let name = "radiosity-canonical.bin";
        let reader = if last {
            HeldReader::consuming(held, plan.io_bytes)?
        } else {
            HeldReader::open(held, plan.io_bytes)?
        };
        self.gather_canonical::<RADIOSITY_LEN>(reader, 0, surfels, name, (dir, plan), io, |w| {
            w[held::RADIOSITY_AT..held::RADIOSITY_AT + RADIOSITY_LEN]
                .try_into()
                .expect("a radiosity record")
        })
    }

    /// Sends every held `(id, radiosity before last)` to rank 0, which places them in canonical
    /// file `name` (returned there; `None` elsewhere): the Chebyshev semi-iteration's state for
    /// a checkpoint. Collective.
    pub(super) fn gather_older(
        &self,
        held: &Held,
        surfels: u64,
        name: &str,
        (dir, plan): (&Path, &MemoryPlan),
        io: &mut IoCounters,
    ) -> Result<Option<PathBuf>, OocError> {
        let reader = HeldReader::open(held, plan.io_bytes)?;
        self.gather_canonical::<RADIOSITY_LEN>(reader, 0, surfels, name, (dir, plan), io, |w| {
            w[held::OLDER_AT..held::OLDER_AT + RADIOSITY_LEN]
                .try_into()
                .expect("a radiosity record")
        })
    }

    /// Sends `value` of every surfel that the ranks of group `group` hold (each surfel once,
    /// read by `reader` from the held files) to rank 0 with its id, which places them in a file
    /// of `surfels` records of `L` bytes in canonical order, `name` in `dir` (returned there;
    /// `None` elsewhere). Collective.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn gather_canonical<const L: usize>(
        &self,
        mut reader: HeldReader,
        group: usize,
        surfels: u64,
        name: &str,
        (dir, plan): (&Path, &MemoryPlan),
        io: &mut IoCounters,
        value: impl Fn(&held::Wire) -> [u8; L],
    ) -> Result<Option<PathBuf>, OocError> {
        let me = self.comm.rank();
        let pair_len = 4 + L;
        let canonical_path = dir.join(name);
        let canonical = if me == 0 {
            let f = RecordFile::create(&canonical_path)?;
            f.set_len(surfels * L as u64)?;
            Some(f)
        } else {
            None
        };
        let out_path = dir.join("gather-out.bin");
        let mut out = crate::outcore::files::SeqWriter::create(&out_path, plan.io_bytes)?;
        let sends = self.group_index == group;
        while let Some(w) = reader.next(io)?.filter(|_| sends) {
            let id = held::id(&w) as u64;
            let v = value(&w);
            match canonical.as_ref() {
                Some(f) => f.write_at(id * L as u64, &v, io)?,
                None => {
                    out.write(&(id as u32).to_le_bytes())?;
                    out.write(&v)?;
                }
            }
        }
        drop(reader);
        io.written += out.finish()?;
        let mut outgoing: Vec<Option<PathBuf>> = vec![None; self.comm.size()];
        if me != 0 && sends {
            outgoing[0] = Some(out_path.clone());
        }
        // The closure's own counter: `io` is lent to the exchange.
        let mut placed = IoCounters::default();
        let router = Router {
            comm: self.comm,
            plan,
            dir,
        };
        exchange_files(
            self.comm,
            &outgoing,
            pair_len,
            router.round_bytes(),
            io,
            &mut |_, bytes| {
                let f = canonical.as_ref().expect("only rank 0 receives");
                for pair in bytes.chunks_exact(pair_len) {
                    let id = u32::from_le_bytes([pair[0], pair[1], pair[2], pair[3]]) as u64;
                    f.write_at(id * L as u64, &pair[4..], &mut placed)?;
                }
                Ok(())
            },
        )?;
        io.written += placed.written;
        std::fs::remove_file(&out_path).map_err(|e| OocError::io(&out_path, "remove", e))?;
        Ok(canonical.map(|_| canonical_path))
    }
}

/// Sets what the lines carry from the radiosity `B` of held record `w`: `B` itself, or with
/// the direct pass (`direct`) its reflected part `B - E`, as the one-process out-of-core solver
/// sends them to its axis copies.
pub(super) fn carry(w: &mut held::Wire, info: &SourceInfo, direct: bool) {
    let b = decode_radiosity(&w[held::RADIOSITY_AT..]);
    let carried = if direct {
        let (_, _, material) = held::scene_data(w);
        let emission = material.map(|m| info.materials[m as usize].emission.map(|e| e as f32));
        crate::solve::update::reflected_part(&b, &emission)
    } else {
        b
    };
    encode_radiosity(&carried, &mut w[held::CARRIED_AT..]);
}

/// Writes a checkpoint whose radiosity arrays are the canonical files `canonical` (rank 0's:
/// the radiosity, then while Chebyshev runs the radiosity before last; the other ranks have
/// none and write nothing).
pub(super) fn save(
    saver: &mut Saver,
    state: State,
    canonical: &[&Path],
    plan: &MemoryPlan,
) -> Result<(), crate::checkpoint::CheckpointError> {
    saver.save(state, plan.io_bytes, |w| {
        for path in canonical {
            let mut reader = SeqReader::<RADIOSITY_LEN>::open(path, plan.io_bytes)
                .map_err(std::io::Error::other)?;
            while let Some(record) = reader.next_record().map_err(std::io::Error::other)? {
                w.write_all(&record)?;
            }
        }
        Ok(())
    })
}
