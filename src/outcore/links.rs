//! Partner links out of core: the links of each direction (`solve::links`) kept in a work file
//! of their own, so that the iterations after the first replay them instead of reading the
//! surfels' static records, dispatching the lines and searching partners again.
//!
//! A direction is solved band by band, and the bands of a direction hold the same surfels in the
//! same order in every iteration (they are cut from the copy's row histogram and the budget,
//! neither of which changes), so a band's links are numbered by place in its band, written down
//! one band after the other by the direction's first pass and read back in that order, a
//! sequential stream, by the later ones.
//!
//! ```text
//! band after band:
//!   surfels  u64 LE   the band's surfels, checked when read back
//!   head     u64 LE   bytes of the links' head, then the head (DirectionLinks::encode_head:
//!                     counts, factors, piece bounds)
//!   blocks            the links, PLANE_BLOCK_LINKS at a time (the last block may hold fewer),
//!                     each block's byte planes (DirectionLinks::encode_block) as
//!                     u32 LE bytes of an LZ4 block, then the block
//! ```
//!
//! **Compressed.** The links are most of what the iterations after the first read, and most of
//! the disk a large solve takes: 8 bytes a link as words. As byte planes of differences and
//! compressed with LZ4 (liblz4, as the static records' frames, `super::framed`), they take
//! about 2.5 bytes a link (`docs/out-of-core.md`), so that about three times as many directions
//! fit the disk allowance, and a replay reads less than a third of the bytes. Each block
//! stands alone: a band's blocks are compressed, and decompressed and put back, on the threads,
//! each thread holding one block's planes beside the band's links (and the band's compressed
//! bytes), not a band's planes.

use super::files::IoCounters;
use super::OocError;
use crate::solve::links::{DirectionLinks, PLANE_BLOCK_LINKS};
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
    /// A band's head, then its links' blocks as read, compressed.
    buffer: Vec<u8>,
    /// Where each block lies in `buffer`.
    places: Vec<std::ops::Range<usize>>,
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
    /// A band's links compressed, with their head.
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
        let head_at = self.buffer.len();
        self.buffer.extend_from_slice(&[0; 8]);
        links.encode_head(&mut self.buffer);
        let head = (self.buffer.len() - head_at - 8) as u64;
        self.buffer[head_at..head_at + 8].copy_from_slice(&head.to_le_bytes());
        // The blocks are compressed on the threads, each with its own room for one block's
        // planes (not kept between bands: directions recorded together each hold a recording),
        // and each kept at its compressed size until it is copied into the band's bytes.
        let blocks = links.encode_blocks(|planes| {
            let mut packed = Vec::new();
            compress_block(planes, &mut packed).map(|()| {
                packed.shrink_to_fit();
                packed
            })
        });
        for packed in blocks {
            let packed = packed.map_err(|e| OocError::io(&self.path, "compress", e))?;
            self.buffer.extend_from_slice(&packed);
        }
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

/// Appends `raw` (a block's byte planes) to `out` compressed: the bytes of its LZ4 block
/// (`u32` LE) and the block.
fn compress_block(raw: &[u8], out: &mut Vec<u8>) -> std::io::Result<()> {
    let bound = lz4::block::compress_bound(raw.len())?;
    let at = out.len();
    out.resize(at + 4 + bound, 0);
    let packed = lz4::block::compress_to_buffer(raw, None, false, &mut out[at + 4..])?;
    out[at..at + 4].copy_from_slice(&(packed as u32).to_le_bytes());
    out.truncate(at + 4 + packed);
    Ok(())
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
        let LinkScratch {
            buffer,
            places,
            links,
        } = scratch;
        let mut head = [0u8; 16];
        self.input
            .read_exact(&mut head)
            .map_err(|e| OocError::io(&self.path, "read", e))?;
        let word = |k: usize| u64::from_le_bytes(head[8 * k..8 * k + 8].try_into().expect("8"));
        let (count, head_len) = (word(0), word(1));
        // A work file of this solve that does not read back as written: not the user's input
        // (exit status 1, as any other failed read of a work file).
        let bad = |what: String| {
            OocError::io(
                &self.path,
                "read",
                std::io::Error::new(std::io::ErrorKind::InvalidData, what),
            )
        };
        if count != surfels as u64 || head_len > 1 << 32 {
            return Err(bad(format!(
                "a band of the links file holds {count} surfels where the solve has {surfels}: \
                 the work files changed under the solve"
            )));
        }
        let mut read = |bytes: &mut [u8]| {
            self.input
                .read_exact(bytes)
                .map_err(|e| OocError::io(&self.path, "read", e))
        };
        buffer.resize(head_len as usize, 0);
        read(buffer)?;
        io.read += 16 + head_len;
        links
            .decode_head(buffer)
            .ok_or_else(|| bad("a band's links are damaged".to_string()))?;
        // The blocks are read one after the other, then decompressed and put back on the
        // threads.
        let bound = lz4::block::compress_bound(PLANE_BLOCK_LINKS * 12).unwrap_or(0);
        buffer.clear();
        places.clear();
        for _ in 0..links.links_to_come().div_ceil(PLANE_BLOCK_LINKS) {
            let mut size = [0u8; 4];
            read(&mut size)?;
            let packed = u32::from_le_bytes(size) as usize;
            if packed > bound {
                return Err(bad("a band's links are damaged".to_string()));
            }
            let at = buffer.len();
            buffer.resize(at + packed, 0);
            read(&mut buffer[at..])?;
            places.push(at..at + packed);
            io.read += 4 + packed as u64;
        }
        let unpacked = links.decode_blocks(|block, planes| {
            let packed = &buffer[places[block].clone()];
            lz4::block::decompress_to_buffer(packed, Some(planes.len() as i32), planes)
                .is_ok_and(|got| got == planes.len())
        });
        if unpacked.is_none() {
            return Err(bad(
                "a band's links do not decompress or are damaged".to_string()
            ));
        }
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

    /// Bytes a band of `links` takes in a links file: its head and its compressed blocks.
    fn band_bytes(links: &DirectionLinks) -> u64 {
        let mut packed = Vec::new();
        links.encode_head(&mut packed);
        for block in 0..links.blocks() {
            let mut raw = Vec::new();
            links.encode_block(block, &mut raw);
            compress_block(&raw, &mut packed).unwrap();
        }
        16 + packed.len() as u64
    }

    /// The links' head and blocks as bytes, to compare two sets of links.
    fn bytes_of(links: &DirectionLinks) -> Vec<u8> {
        let mut bytes = Vec::new();
        links.encode_head(&mut bytes);
        for block in 0..links.blocks() {
            links.encode_block(block, &mut bytes);
        }
        bytes
    }

    #[test]
    fn a_direction_over_its_allowance_is_not_kept_and_stops_the_recording() {
        let dir = tempfile::tempdir().unwrap();
        let links = DirectionLinks::default();
        let band = band_bytes(&links);
        let mut store = LinkStore::new(dir.path(), 2, band + band / 2, 10, 4096);
        let mut io = IoCounters::default();
        store.begin(0).unwrap();
        match store.band_links() {
            BandLinks::Record([r]) => {
                // One band fits; a second does not.
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
        // An allowance of five bands, two and a half for each of two directions.
        let band = band_bytes(&empty);
        let record = |bands: &[usize], io: &mut IoCounters| {
            let dir = tempfile::tempdir().unwrap();
            let mut store = LinkStore::new(dir.path(), 2, 5 * band, 10, 4096);
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
        // Three bands would fit the allowance alone, not a share of it.
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

    /// Links as a line-by-line gather writes them: each side gathers from the next surfel of
    /// its line, lines of surfels a few strides apart, a few factors.
    fn line_links(count: u32) -> DirectionLinks {
        let triples: Vec<(u32, u32, u32)> = (0..count)
            .map(|k| {
                let (line, place) = (k / 40, k % 40);
                let surfel = line * 3 + place * (97 + line % 3);
                let partner = surfel + 97 + line % 3;
                (surfel << 1 | (k & 1), partner << 1 | (!k & 1), k % 3)
            })
            .collect();
        DirectionLinks::from_triples(&triples, vec![0.25, 0.5, 0.125])
    }

    #[test]
    fn links_come_back_from_their_compressed_blocks_and_take_less_than_words() {
        let dir = tempfile::tempdir().unwrap();
        // Enough links for several blocks in one band.
        let big = line_links((PLANE_BLOCK_LINKS * 2 + 1000) as u32);
        let small = line_links(5000);
        let surfels = [big.surfels_named(), small.surfels_named()];
        let mut store = LinkStore::new(dir.path(), 1, 1 << 30, 10, 4096);
        let mut io = IoCounters::default();
        store.begin(0).unwrap();
        if let BandLinks::Record([r]) = store.band_links() {
            r.band(surfels[0], &big, &mut io).unwrap();
            r.band(surfels[1], &small, &mut io).unwrap();
        }
        store.end(true);
        let file = std::fs::metadata(dir.path().join("links-0.bin"))
            .unwrap()
            .len();
        let words = 8 * (big.len() + small.len()) as u64;
        assert!(file * 2 < words, "{file} bytes for {words} bytes of words");
        assert_eq!(store.stats(&crate::comm::SingleProcess).bytes, file);
        store.begin(0).unwrap();
        let BandLinks::Replay([r], scratch) = store.band_links() else {
            panic!("a kept direction replays")
        };
        for (links, n) in [(&big, surfels[0]), (&small, surfels[1])] {
            let back = r.band(n, scratch, &mut io).unwrap();
            assert!(
                bytes_of(back) == bytes_of(links),
                "a band's links come back the same"
            );
        }
    }

    #[test]
    fn a_damaged_links_file_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let links = line_links(3000);
        let n = links.surfels_named();
        let path = dir.path().join("links-0.bin");
        let mut store = LinkStore::new(dir.path(), 1, 1 << 30, 10, 4096);
        let mut io = IoCounters::default();
        store.begin(0).unwrap();
        if let BandLinks::Record([r]) = store.band_links() {
            r.band(n, &links, &mut io).unwrap();
        }
        store.end(true);
        let good = std::fs::read(&path).unwrap();
        // A byte of a block changed, the file cut short, a block's size too large.
        let mut changed = good.clone();
        changed[good.len() / 2] ^= 0x5a;
        let mut sized = good.clone();
        sized[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        for bytes in [changed, good[..good.len() - 7].to_vec(), sized] {
            std::fs::write(&path, &bytes).unwrap();
            store.begin(0).unwrap();
            let BandLinks::Replay([r], scratch) = store.band_links() else {
                panic!("a kept direction replays")
            };
            match r.band(n, scratch, &mut io) {
                Err(e) => assert!(e.to_string().contains("links-0.bin"), "{e}"),
                // A changed byte may still decode to links within the band (LZ4 blocks carry
                // no checksum, as no work file does); they are then other links, not a panic.
                Ok(back) => assert!(back.surfels_named() <= n),
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
