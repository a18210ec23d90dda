//! Partner links out of core: the links of each direction (`solve::links`) kept in a work file
//! of their own, so that the iterations after the first replay them instead of reading the
//! surfels' static records, dispatching the lines and searching partners again.
//!
//! A direction is solved band by band, and the bands of a direction hold the same surfels in the
//! same order in every iteration (they are cut from the copy's row histogram and the budget,
//! neither of which changes), so a band's links are numbered by place in its band, written down
//! one band after the other by the direction's first pass and read back in that order, a
//! sequential stream, by the later ones. Each band's links are preceded by its surfel count and
//! byte length, checked when read back.
//!
//! The files take disk, not memory: at most an allowance (`--links-disk`; by default half of
//! what is free once the work files are made). The directions are recorded in walk order while
//! the allowance lasts; a direction that does not fit, or whose file could not be written (a full
//! disk), is searched again in every iteration, as before. Directions gathered in one pass
//! (`DirectionPass::run_together`) record side by side, each within an equal share of what is
//! left of the allowance. A band holds its links in memory while it is gathered (counted in
//! `budget::BAND_BYTES_PER_SURFEL`).

use super::files::IoCounters;
use super::OocError;
use crate::solve::links::DirectionLinks;
use crate::solve::stats::LinkStats;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

/// What a direction pass does with its bands' links.
pub enum BandLinks<'a> {
    /// Searches partners, as without links.
    Search,
    /// Searches partners and writes each band's links down (one recording per direction of
    /// the pass).
    Record(&'a mut [Recording]),
    /// Replays each band's links, written down by an earlier pass: of one direction, or of
    /// several whose bands are the same (one after the other on each band, in walk order; see
    /// `outcore::solver`'s `gathered_together`), each band's decoded in `scratch` in turn.
    Replay(&'a mut [Replaying], &'a mut LinkScratch),
}

/// Where a band's links are read and decoded, one band at a time: shared by the directions
/// replayed together, so that their memory is one band's links whatever their number.
#[derive(Default)]
pub struct LinkScratch {
    buffer: Vec<u8>,
    links: DirectionLinks,
}

/// A direction's links being written.
pub struct Recording {
    path: PathBuf,
    out: BufWriter<File>,
    written: u64,
    /// Bytes this direction may take.
    allowance: u64,
    /// Given up: over the allowance, or a write failed (the direction is searched again).
    abandoned: bool,
    buffer: Vec<u8>,
}

impl Recording {
    /// Writes down the links of a band of `surfels` surfels.
    pub fn band(
        &mut self,
        surfels: usize,
        links: &DirectionLinks,
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        if self.abandoned {
            return Ok(());
        }
        self.buffer.clear();
        self.buffer
            .extend_from_slice(&(surfels as u64).to_le_bytes());
        self.buffer
            .extend_from_slice(&(links.encoded_len() as u64).to_le_bytes());
        links.encode(&mut self.buffer);
        if self.written + self.buffer.len() as u64 > self.allowance {
            self.abandoned = true;
            return Ok(());
        }
        match self.out.write_all(&self.buffer) {
            Ok(()) => {
                self.written += self.buffer.len() as u64;
                io.written += self.buffer.len() as u64;
            }
            Err(e) => {
                tracing::warn!(
                    file = %self.path.display(),
                    error = %e,
                    "could not write partner links; this direction searches them again in \
                     every iteration"
                );
                self.abandoned = true;
            }
        }
        Ok(())
    }
}

/// A direction's links being read back.
pub struct Replaying {
    path: PathBuf,
    input: BufReader<File>,
}

impl Replaying {
    /// The links of the next band, which holds `surfels` surfels, read into `scratch`.
    pub fn band<'s>(
        &mut self,
        surfels: usize,
        scratch: &'s mut LinkScratch,
        io: &mut IoCounters,
    ) -> Result<&'s DirectionLinks, OocError> {
        let LinkScratch { buffer, links } = scratch;
        let mut head = [0u8; 16];
        self.input
            .read_exact(&mut head)
            .map_err(|e| OocError::io(&self.path, "read", e))?;
        let word = |k: usize| u64::from_le_bytes(head[8 * k..8 * k + 8].try_into().expect("8"));
        let (count, len) = (word(0), word(1));
        // A work file of this solve that does not read back as written: not the user's input
        // (exit status 1, as any other failed read of a work file).
        let bad = |what: String| {
            OocError::io(
                &self.path,
                "read",
                std::io::Error::new(std::io::ErrorKind::InvalidData, what),
            )
        };
        if count != surfels as u64 || len > 1 << 40 {
            return Err(bad(format!(
                "a band of the links file holds {count} surfels where the solve has {surfels}: \
                 the work files changed under the solve"
            )));
        }
        buffer.resize(len as usize, 0);
        self.input
            .read_exact(buffer)
            .map_err(|e| OocError::io(&self.path, "read", e))?;
        io.read += 16 + len;
        links
            .decode(buffer)
            .ok_or_else(|| bad("a band's links are damaged".to_string()))?;
        if links.surfels_named() > surfels {
            return Err(bad(
                "a band's links name surfels beyond the band".to_string()
            ));
        }
        Ok(links)
    }
}

/// The links files of one solve, one per direction.
pub struct LinkStore {
    dir: PathBuf,
    /// Bytes the files may still take.
    allowance: u64,
    /// Per direction: the bytes of its file, once written whole.
    kept: Vec<Option<u64>>,
    /// Per direction: whether this process ever gathered it.
    tried: Vec<bool>,
    buffer_bytes: usize,
    current: Option<Current>,
    scratch: LinkScratch,
    /// Surfels of the scene (for the bytes per surfel-direction).
    surfels: u64,
}

enum Current {
    /// The directions recorded, and their recordings.
    Record(Vec<usize>, Vec<Recording>),
    /// One direction's links, or several replayed together ([`LinkStore::begin_together`]).
    Replay(Vec<Replaying>),
}

impl LinkStore {
    /// A store of `directions` links files under `dir`, taking at most `allowance` bytes.
    pub fn new(
        dir: &Path,
        directions: usize,
        allowance: u64,
        surfels: u64,
        buffer_bytes: usize,
    ) -> Self {
        LinkStore {
            dir: dir.to_path_buf(),
            allowance,
            kept: vec![None; directions],
            tried: vec![false; directions],
            buffer_bytes: buffer_bytes.max(4 << 10),
            current: None,
            scratch: LinkScratch::default(),
            surfels,
        }
    }

    fn path(&self, d: usize) -> PathBuf {
        self.dir.join(format!("links-{d}.bin"))
    }

    /// Opens direction `d`'s links: replayed when kept, recorded while the allowance lasts.
    pub fn begin(&mut self, d: usize) -> Result<(), OocError> {
        self.begin_together(&[d])
    }

    /// Whether direction `d`'s links are kept (its passes replay them).
    pub fn is_kept(&self, d: usize) -> bool {
        self.kept[d].is_some()
    }

    /// Opens the links of directions `ds`, gathered in one pass band by band (see
    /// `DirectionPass::run_together`): all kept and replayed, or none kept and recorded while
    /// the allowance lasts, each then allowed its share of it. Their files' buffers share the
    /// one direction's room.
    pub fn begin_together(&mut self, ds: &[usize]) -> Result<(), OocError> {
        self.current = None;
        let share = ds.len().max(1);
        let capacity = (self.buffer_bytes / share).max(4 << 10);
        for &d in ds {
            self.tried[d] = true;
        }
        let kept = ds.iter().filter(|&&d| self.is_kept(d)).count();
        assert!(
            kept == 0 || kept == ds.len(),
            "directions gathered together are all kept or none"
        );
        if kept > 0 {
            let readers = ds
                .iter()
                .map(|&d| self.open(d, capacity))
                .collect::<Result<_, _>>()?;
            self.current = Some(Current::Replay(readers));
        } else if self.allowance > 0 {
            let mut recordings = Vec::with_capacity(ds.len());
            for &d in ds {
                let path = self.path(d);
                match File::create(&path) {
                    Ok(file) => recordings.push(Recording {
                        out: BufWriter::with_capacity(capacity, file),
                        path,
                        written: 0,
                        allowance: self.allowance / share as u64,
                        abandoned: false,
                        buffer: Vec::new(),
                    }),
                    Err(e) => {
                        tracing::warn!(file = %path.display(), error = %e,
                            "could not create a partner links file; directions search them again");
                        self.allowance = 0;
                        for r in recordings {
                            let _ = std::fs::remove_file(&r.path);
                        }
                        return Ok(());
                    }
                }
            }
            self.current = Some(Current::Record(ds.to_vec(), recordings));
        }
        Ok(())
    }

    /// Direction `d`'s kept links, read through a buffer of `capacity` bytes.
    fn open(&self, d: usize, capacity: usize) -> Result<Replaying, OocError> {
        let path = self.path(d);
        let file = File::open(&path).map_err(|e| OocError::io(&path, "open", e))?;
        Ok(Replaying {
            input: BufReader::with_capacity(capacity, file),
            path,
        })
    }

    /// What the pass of the direction begun does with its bands' links.
    pub fn band_links(&mut self) -> BandLinks<'_> {
        match &mut self.current {
            None => BandLinks::Search,
            Some(Current::Record(_, recordings)) => BandLinks::Record(recordings),
            Some(Current::Replay(readers)) => BandLinks::Replay(readers, &mut self.scratch),
        }
    }

    /// Ends the direction begun; `whole`: its pass ran over every band (not stopped by a
    /// signal), so that a recorded file can be kept.
    pub fn end(&mut self, whole: bool) {
        let Some(Current::Record(ds, recordings)) = self.current.take() else {
            return;
        };
        for (d, recording) in ds.into_iter().zip(recordings) {
            let Recording {
                path,
                out,
                written,
                abandoned,
                ..
            } = recording;
            let flushed = out.into_inner().map_err(|e| e.into_error()).is_ok();
            if whole && flushed && !abandoned {
                self.kept[d] = Some(written);
                self.allowance = self.allowance.saturating_sub(written);
            } else {
                let _ = std::fs::remove_file(&path);
                if abandoned || !flushed {
                    // The next directions are about as large: stop trying.
                    self.allowance = 0;
                }
            }
        }
    }

    /// What the stores of the processes of `comm` keep, for the report: a direction counts as
    /// kept when every process that gathers it keeps its part; the bytes are summed.
    /// Collective on `comm`.
    pub fn stats(&self, comm: &dyn crate::comm::Comm) -> LinkStats {
        let directions = self.kept.len();
        let mut sums: Vec<f64> = (0..directions)
            .map(|d| (self.tried[d] && self.kept[d].is_none()) as u8 as f64)
            .chain(self.tried.iter().map(|&t| t as u8 as f64))
            .chain([self.kept.iter().flatten().sum::<u64>() as f64])
            .collect();
        comm.sum_in_place(&mut sums);
        let kept_directions = (0..directions)
            .filter(|&d| sums[d] == 0.0 && sums[directions + d] > 0.0)
            .count();
        let bytes = sums[2 * directions];
        let per = self.surfels as f64 * kept_directions as f64;
        LinkStats {
            kept_directions,
            directions,
            bytes: bytes as u64,
            bytes_per_surfel_direction: if per > 0.0 { bytes / per } else { 0.0 },
            kept_in: if kept_directions > 0 { "files" } else { "none" }.to_string(),
        }
    }
}

/// The allowance of the links files of one of `sharers` ranks whose work files share the disk
/// of `dir`: `asked` (`--links-disk`) or by default half of what is free there once the work
/// files' growth still to come, `still_needed` bytes a rank, is set aside (files made at their
/// full length take their blocks only as they are written), divided among the sharers.
/// An allowance asked for is cut to what is free beyond that growth: links written into it
/// made the next gathered file find the disk full, and the solve fail. Nothing by default
/// where the free space cannot be read; what was asked for, then.
pub fn allowance(dir: &Path, asked: Option<u64>, still_needed: u64, sharers: u64) -> u64 {
    let free = super::workset::free_bytes(dir);
    let sharers = sharers.max(1);
    let room = free.map(|f| f.saturating_sub(still_needed.saturating_mul(sharers)) / sharers);
    match (asked, room) {
        (None, room) => room.unwrap_or(0) / 2,
        (Some(asked), Some(room)) if asked > room => {
            tracing::warn!(
                asked = super::budget::format_bytes(asked),
                kept = super::budget::format_bytes(room),
                "--links-disk is more than the disk has beyond the work files' growth: the \
                 links keep to what it has"
            );
            room
        }
        (Some(asked), _) => asked,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_direction_over_its_allowance_is_not_kept_and_stops_the_recording() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = LinkStore::new(dir.path(), 2, 56, 10, 4096);
        let mut io = IoCounters::default();
        store.begin(0).unwrap();
        let links = DirectionLinks::default();
        match store.band_links() {
            BandLinks::Record([r]) => {
                // 16 bytes of head and 32 of empty links: fits; a second band does not.
                r.band(5, &links, &mut io).unwrap();
                r.band(5, &links, &mut io).unwrap();
            }
            _ => panic!("the first direction records"),
        }
        store.end(true);
        assert!(store.kept[0].is_none());
        assert!(!dir.path().join("links-0.bin").exists());
        store.begin(1).unwrap();
        assert!(matches!(store.band_links(), BandLinks::Search));
    }

    #[test]
    fn recorded_bands_are_read_back_in_order_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = LinkStore::new(dir.path(), 1, 1 << 20, 10, 4096);
        let mut io = IoCounters::default();
        store.begin(0).unwrap();
        if let BandLinks::Record([r]) = store.band_links() {
            r.band(5, &DirectionLinks::default(), &mut io).unwrap();
            r.band(7, &DirectionLinks::default(), &mut io).unwrap();
        }
        store.end(true);
        let stats = store.stats(&crate::comm::SingleProcess);
        assert_eq!(
            (stats.kept_directions, stats.kept_in.as_str()),
            (1, "files")
        );
        store.begin(0).unwrap();
        let BandLinks::Replay(readers, scratch) = store.band_links() else {
            panic!("a kept direction replays")
        };
        let [r] = readers else {
            panic!("one direction begun, one reader")
        };
        r.band(5, scratch, &mut io).unwrap();
        let e = r.band(6, scratch, &mut io).unwrap_err();
        assert!(e.to_string().contains("7 surfels"), "{e}");
    }

    /// Directions gathered in one pass record side by side, each within its share of the
    /// allowance, and are read back side by side, band by band.
    #[test]
    fn directions_recorded_together_are_kept_and_read_back_together() {
        let empty = DirectionLinks::default();
        let mut io = IoCounters::default();
        // 48 bytes a band (see above); an allowance of 200 bytes, 100 for each of two.
        let record = |bands: &[usize], io: &mut IoCounters| {
            let dir = tempfile::tempdir().unwrap();
            let mut store = LinkStore::new(dir.path(), 2, 200, 10, 4096);
            store.begin_together(&[0, 1]).unwrap();
            let BandLinks::Record(recordings) = store.band_links() else {
                panic!("directions not kept record")
            };
            assert_eq!(recordings.len(), 2);
            for r in recordings.iter_mut() {
                for &n in bands {
                    r.band(n, &empty, io).unwrap();
                }
            }
            store.end(true);
            (dir, store)
        };
        // Three bands (144 bytes) would fit the allowance alone, not a share of it.
        let (_dir, store) = record(&[5, 6, 7], &mut io);
        assert!(!store.is_kept(0) && !store.is_kept(1));
        let (_dir, mut store) = record(&[5, 6], &mut io);
        assert!(store.is_kept(0) && store.is_kept(1));
        store.begin_together(&[0, 1]).unwrap();
        let BandLinks::Replay(readers, scratch) = store.band_links() else {
            panic!("kept directions replay")
        };
        for n in [5, 6] {
            for r in readers.iter_mut() {
                r.band(n, scratch, &mut io).unwrap();
            }
        }
    }

    #[test]
    fn a_direction_stopped_by_a_signal_is_not_kept() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = LinkStore::new(dir.path(), 1, 1 << 20, 10, 4096);
        store.begin(0).unwrap();
        store.end(false);
        assert!(store.kept[0].is_none());
        store.begin(0).unwrap();
        assert!(matches!(store.band_links(), BandLinks::Record(_)));
    }
}
