//! The surfels one rank holds in the data mode out of core: four work files in one order (or
//! runs of records of a few such sets of files, [`Held`]), the record layout they travel in
//! between ranks, and the sorted merge and external sort that put them back in order.
//!
//! The four files are what the band machinery of `outcore::band` reads and writes (static
//! records, the radiosity the lines carry, the light gathered by the directions of the current
//! main axis), plus one file the rest of the loop needs (the light of the earlier axes of this
//! iteration, what the update of `B` takes from the scene's tables, the radiosity `B` itself and
//! the direct light). Between ranks and in run files a surfel is the four records one after
//! another:
//!
//! ```text
//! wire record (232 bytes)
//!   0 static       72 bytes   outcore::files layout (voxel, ..., canonical id at 68)
//!  72 carried      24 bytes   f32 x 6, what the lines carry: B, or B - E with the direct pass
//!  96 gathered     24 bytes   f32 x 6, this axis's directions so far (an axis light record,
//!                             summed in f32 as `outcore::files` says)
//! 120 earlier      24 bytes   f32 x 6, the earlier axes of this iteration (rounded at each
//!                             fold, as the one-process solver's canonical sum)
//! 144 normal id    u32
//! 148 area         f32
//! 152 materials    u32 x 2    front, back
//! 160 radiosity    24 bytes   f32 x 6, B
//! 184 direct       24 bytes   f32 x 6, the direct light H_dense / S_dense (0 without the pass),
//!                             as the one-process out-of-core pass writes it
//! 208 older        24 bytes   f32 x 6, the radiosity the last update replaced (the tail
//!                             extrapolation's, and the Chebyshev semi-iteration's `B_{k-1}`)
//! ```
//!
//! On disk the fourth file leaves the direct light out in a solve without the direct-light
//! pass, where it is zero (`Held::direct`): 88 bytes a record instead of 112.
//!
//! `B` travels beside what the lines carry, as the one-process out-of-core solver keeps its
//! canonical radiosity beside the axis copies' `B - E`: the update reads `B` and writes both,
//! and the answer stays that solver's bit for bit.
//!
//! **The static and rest records in frames.** A set's static and rest records are written
//! once, from start to end, and then only read (by ranges: a band's rows, the records that
//! leave, a copy; the bands write only the other two files, in place), so each set keeps them
//! as the one-process solver keeps an axis copy's static records (`outcore::framed`: frames of
//! byte planes under LZ4, with an index file beside, `held-G-static.index` and
//! `held-G-rest.index`). The held order is a copy order, whose neighbours are alike: 72 bytes
//! of static record become a few; in the rest, the scene data repeats, the light of the
//! earlier axes is zero in an iteration's first axis, the radiosity before last without the
//! extrapolation, and the back sides of walls are dark (see `docs/cluster.md`). The rest file
//! is rewritten at every change of main axis and every update, so what it saves is saved
//! there each time. Run files ([`RunWriter`]), which also go between ranks as they are, keep
//! whole wire records in frames of their own.
//!
//! **Disk given back as it goes.** Records that nothing reads again (those that left the rank,
//! those copied into new files, a set read for the last time by a consuming [`HeldReader`]) are
//! released: holes punched in the two files of whole records, which keep their length
//! ([`Held::release`]), so that a rank's old and new files do not both lie whole on the disk.
//! (The frames stay until their set is removed: a few bytes a record.)

use crate::outcore::files::{
    IoCounters, RecordFile, SeqWriter, LIGHT32_LEN, RADIOSITY_LEN, STATIC_LEN,
};
use crate::outcore::framed::{
    planes_of_records, records_of_byte_planes, FrameBuffers, FramedRuns, FramedStatics,
    FramedWriter,
};
use crate::outcore::OocError;
use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Bytes of the fourth file's record: earlier axes' light, the update's scene data, `B`, the
/// direct light and the radiosity the last update replaced.
pub const REST_LEN: usize = LIGHT32_LEN + 16 + RADIOSITY_LEN + LIGHT32_LEN + RADIOSITY_LEN;
pub const WIRE_LEN: usize = STATIC_LEN + RADIOSITY_LEN + LIGHT32_LEN + REST_LEN;
pub type Wire = [u8; WIRE_LEN];

/// What the lines carry (the file the bands read).
pub const CARRIED_AT: usize = STATIC_LEN;
pub const GATHERED_AT: usize = CARRIED_AT + RADIOSITY_LEN;
pub const EARLIER_AT: usize = GATHERED_AT + LIGHT32_LEN;
pub const SCENE_AT: usize = EARLIER_AT + LIGHT32_LEN;
/// The radiosity `B`.
pub const RADIOSITY_AT: usize = SCENE_AT + 16;
pub const DIRECT_AT: usize = RADIOSITY_AT + RADIOSITY_LEN;
/// The radiosity the last update replaced.
pub const OLDER_AT: usize = DIRECT_AT + LIGHT32_LEN;
const _: () = assert!(OLDER_AT + RADIOSITY_LEN == WIRE_LEN);
const OFFSETS: [usize; 4] = [0, CARRIED_AT, GATHERED_AT, EARLIER_AT];

/// Bytes of each file's record in held files with the direct light (`direct`) or without: a
/// solve without the direct-light pass has none, and its rest file leaves those 24 bytes out
/// (they read back as zeros).
const fn lengths(direct: bool) -> [usize; 4] {
    let rest = if direct {
        REST_LEN
    } else {
        REST_LEN - LIGHT32_LEN
    };
    [STATIC_LEN, RADIOSITY_LEN, LIGHT32_LEN, rest]
}

/// The rest of wire record `w` as the rest file keeps it (`direct`: with the direct light), in
/// one or two pieces.
fn rest_pieces(w: &Wire, direct: bool) -> [&[u8]; 2] {
    if direct {
        [&w[EARLIER_AT..], &[]]
    } else {
        [&w[EARLIER_AT..DIRECT_AT], &w[DIRECT_AT + LIGHT32_LEN..]]
    }
}

/// Puts `rest`, one record of a rest file (`direct`: with the direct light), into wire record
/// `w`; the direct light is zero where the file leaves it out.
fn place_rest(w: &mut [u8], rest: &[u8], direct: bool) {
    if direct {
        w[EARLIER_AT..].copy_from_slice(rest);
    } else {
        let split = DIRECT_AT - EARLIER_AT;
        w[EARLIER_AT..DIRECT_AT].copy_from_slice(&rest[..split]);
        w[DIRECT_AT..DIRECT_AT + LIGHT32_LEN].fill(0);
        w[DIRECT_AT + LIGHT32_LEN..].copy_from_slice(&rest[split..]);
    }
}

fn word(w: &[u8], at: usize) -> [u8; 4] {
    [w[at], w[at + 1], w[at + 2], w[at + 3]]
}

pub fn voxel(w: &[u8]) -> [i32; 3] {
    crate::outcore::files::static_voxel(w)
}

pub fn id(w: &[u8]) -> u32 {
    u32::from_le_bytes(word(w, 68))
}

/// Normal id, area and the two materials.
pub fn scene_data(w: &[u8]) -> (u32, f32, [u32; 2]) {
    let u = |k: usize| u32::from_le_bytes(word(w, SCENE_AT + 4 * k));
    (u(0), f32::from_bits(u(1)), [u(2), u(3)])
}

pub fn encode_scene_data(normal_id: u32, area: f32, material: [u32; 2], out: &mut [u8]) {
    let words = [normal_id, area.to_bits(), material[0], material[1]];
    for (k, v) in words.iter().enumerate() {
        out[SCENE_AT + 4 * k..SCENE_AT + 4 * k + 4].copy_from_slice(&v.to_le_bytes());
    }
}

/// The order of the axis copy of main axis `main` (see the `outcore` module header):
/// `(x_m, x_v, x_u)`, then the canonical id.
#[derive(Clone, Copy, Debug)]
pub struct AxisKey {
    pub main: usize,
    pub u: usize,
    pub v: usize,
    dims: [u64; 3],
    /// The canonical order instead (by id alone; one row).
    canonical: bool,
}

impl AxisKey {
    pub fn new(main: usize, dims: [u32; 3]) -> Self {
        AxisKey {
            main,
            u: (main + 1) % 3,
            v: (main + 2) % 3,
            dims: dims.map(u64::from),
            canonical: false,
        }
    }

    /// The canonical order: by id (the hybrid mode's order at the end of an iteration).
    pub fn canonical() -> Self {
        AxisKey {
            main: 0,
            u: 1,
            v: 2,
            dims: [1; 3],
            canonical: true,
        }
    }

    pub fn layers(&self) -> usize {
        self.dims[self.main] as usize
    }

    pub fn rows(&self) -> usize {
        self.dims[self.v] as usize
    }

    /// Index of the record's row `(x_m, x_v)` in a layer-major histogram.
    #[inline]
    pub fn row(&self, v: [i32; 3]) -> usize {
        if self.canonical {
            return 0;
        }
        (v[self.main] as u64 * self.dims[self.v] + v[self.v] as u64) as usize
    }

    #[inline]
    pub fn key(&self, w: &[u8]) -> (u64, u32) {
        if self.canonical {
            return (0, id(w));
        }
        let v = voxel(w);
        let row = self.row(v) as u64;
        (row * self.dims[self.u] + v[self.u] as u64, id(w))
    }
}

/// A rank's held surfels: `count` records in one order, in four files (one per part of the
/// record), or laid end to end from runs of records of several such sets of four files.
///
/// A step inside an axis moves a few rows of every layer; rewriting the held files whole for
/// them cost each rank a read and a write of all its records at every change of slope. Instead
/// the received records are written to new files and the kept ones stay where they are
/// ([`HeldWriter::keep`]), up to [`MOST_SETS`] sets, after which the records are copied into
/// one set again.
#[derive(Clone)]
pub struct Held {
    /// Each set's four files, as [`HeldWriter`] names them.
    pub sets: Vec<[PathBuf; 4]>,
    /// The records in order: runs of `count` records of set `set` from record `first`.
    pub runs: Vec<HeldRun>,
    pub count: u64,
    /// Whether the rest files keep the direct light ([`lengths`]); the same in every set.
    pub direct: bool,
}

/// Records `first..first + count` of one set of held files.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeldRun {
    pub set: usize,
    pub first: u64,
    pub count: u64,
}

/// Sets of files a rank's held records may lie in before they are copied into one again (also
/// when the sets hold more than twice the records in use, so that the disk holds at most about
/// twice the rank's share). At 4 sets, the copies were two thirds of what the steps inside an
/// axis read and wrote: the Cornell box at resolution 64, 589 directions, one iteration on 2
/// ranks moved 45 MB a rank that way, and 15 MB at 16 sets (a rank's largest reads fell from
/// 1.35 to 1.17 times one process's share), in the same time (`docs/cluster.md`).
pub const MOST_SETS: usize = 16;

impl Held {
    /// The records of one set of four files, in their order.
    pub fn whole(paths: [PathBuf; 4], count: u64, direct: bool) -> Self {
        Held {
            sets: vec![paths],
            runs: vec![HeldRun {
                set: 0,
                first: 0,
                count,
            }],
            count,
            direct,
        }
    }

    /// The four files opened for positioned reads (and, but for the static records, writes),
    /// each as one file of records in the held order.
    pub fn open_files(&self) -> Result<HeldFiles, OocError> {
        let open = |k: usize| -> Result<RecordFile, OocError> {
            if self.sets.len() == 1 && self.runs.len() <= 1 && self.runs_from_start() {
                return RecordFile::open(&self.sets[0][k]);
            }
            let paths: Vec<&Path> = self.sets.iter().map(|set| set[k].as_path()).collect();
            let len = lengths(self.direct)[k] as u64;
            let pieces: Vec<(usize, u64, u64)> = self
                .runs
                .iter()
                .map(|r| (r.set, r.first * len, r.count * len))
                .collect();
            RecordFile::pieced(&paths, &pieces)
        };
        // One set of frame buffers for both framed parts: a reader reads them in turn.
        let buffers = FrameBuffers::shared();
        let runs: Vec<(usize, u64, u64)> = self
            .runs
            .iter()
            .map(|r| (r.set, r.first, r.count))
            .collect();
        let framed = |k: usize| -> Result<FramedRuns, OocError> {
            let files = self
                .sets
                .iter()
                .map(|set| {
                    let records = (set_records(set)?, lengths(self.direct)[k]);
                    FramedStatics::open_records(&set[k], &frame_index(&set[k]), records, &buffers)
                })
                .collect::<Result<Vec<_>, _>>()?;
            Ok(FramedRuns::new(files, &runs))
        };
        Ok(HeldFiles {
            statics: Arc::new(framed(0)?),
            radiosity: open(1)?,
            gathered: open(2)?,
            rest: framed(3)?,
            direct: self.direct,
        })
    }

    /// Records the files of every set hold, those no run reads (they left the rank) included.
    pub fn stored_records(&self) -> Result<u64, OocError> {
        let mut records = 0;
        for set in &self.sets {
            records += set_records(set)?;
        }
        Ok(records)
    }

    fn runs_from_start(&self) -> bool {
        self.runs.first().is_none_or(|r| r.first == 0)
    }

    /// The runs that hold records `first..first + count` of the held order.
    pub fn runs_of(&self, first: u64, count: u64) -> Vec<HeldRun> {
        let mut out = Vec::new();
        let (mut at, end) = (0u64, first + count);
        for r in &self.runs {
            let (lo, hi) = (at.max(first), (at + r.count).min(end));
            if lo < hi {
                out.push(HeldRun {
                    set: r.set,
                    first: r.first + (lo - at),
                    count: hi - lo,
                });
            }
            at += r.count;
            if at >= end {
                break;
            }
        }
        out
    }

    /// Gives back the disk under the records `ranges` (first, count) of the held order, which
    /// nothing reads again (they left the rank, or were copied into new files): holes punched in
    /// the files of whole records ([`crate::outcore::files::punch_hole`]), which keep their
    /// length, so every other record stays where it is. The static and rest records, a few
    /// bytes each in frames, stay. A rank's sets otherwise keep the records that left until they are copied
    /// into one set again (see [`MOST_SETS`]), and that copy wrote a whole share beside them.
    pub fn release(&self, ranges: &[(u64, u64)]) -> Result<(), OocError> {
        let mut files: Vec<Option<[std::fs::File; 2]>> = Vec::new();
        files.resize_with(self.sets.len(), || None);
        // Ranges that touch are joined: a hole gives back only the whole blocks inside it, and
        // the records that leave a rank above the kept rows of one layer and below those of the
        // next are one run of the held order.
        let mut joined: Vec<(u64, u64)> = Vec::with_capacity(ranges.len());
        for &(first, count) in ranges.iter().filter(|r| r.1 > 0) {
            match joined.last_mut() {
                Some(last) if last.0 + last.1 == first => last.1 += count,
                _ => joined.push((first, count)),
            }
        }
        for (first, count) in joined {
            for run in self.runs_of(first, count) {
                if files[run.set].is_none() {
                    let set = &self.sets[run.set];
                    let open = |k: usize| {
                        std::fs::OpenOptions::new()
                            .write(true)
                            .open(&set[k])
                            .map_err(|e| OocError::io(&set[k], "open", e))
                    };
                    files[run.set] = Some([open(1)?, open(2)?]);
                }
                let set_files = files[run.set].as_ref().expect("just opened");
                for (file, len) in set_files.iter().zip(&lengths(self.direct)[1..]) {
                    let len = *len as u64;
                    crate::outcore::files::punch_hole(file, run.first * len, run.count * len);
                }
            }
        }
        Ok(())
    }

    pub fn remove(self) -> Result<(), OocError> {
        for set in &self.sets {
            remove_set(set)?;
        }
        Ok(())
    }

    /// Removes the files of the sets no run reads any more, and numbers the others again.
    fn prune(mut self) -> Result<Self, OocError> {
        // Set 0 stays (a writer's own files, which an empty share still needs).
        let mut used = vec![false; self.sets.len()];
        used[0] = true;
        for r in &self.runs {
            used[r.set] = true;
        }
        let mut renumber = vec![usize::MAX; self.sets.len()];
        let mut sets = Vec::with_capacity(self.sets.len());
        for (k, set) in std::mem::take(&mut self.sets).into_iter().enumerate() {
            if used[k] {
                renumber[k] = sets.len();
                sets.push(set);
            } else {
                remove_set(&set)?;
            }
        }
        for r in &mut self.runs {
            r.set = renumber[r.set];
        }
        self.sets = sets;
        Ok(self)
    }
}

/// The held files opened for reading ([`Held::open_files`]): the static and rest records
/// through their frames, the other two as files of records (the bands write the radiosity and
/// gathered light in place).
pub struct HeldFiles {
    pub statics: Arc<FramedRuns>,
    pub radiosity: RecordFile,
    pub gathered: RecordFile,
    pub rest: FramedRuns,
    /// As [`Held::direct`].
    pub direct: bool,
}

impl HeldFiles {
    /// Fills `out` with records of part `part` (0 static, 1 radiosity, 2 gathered light, 3 the
    /// rest, as its file keeps it: [`lengths`]) from record `first` on.
    pub fn read(
        &self,
        part: usize,
        first: u64,
        out: &mut [u8],
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        let file = match part {
            0 => return self.statics.read(first, out, io),
            1 => &self.radiosity,
            2 => &self.gathered,
            _ => return self.rest.read(first, out, io),
        };
        file.read_at(first * lengths(self.direct)[part] as u64, out, io)
    }
}

/// The index of the frames of a set's static or rest records (`outcore::framed`).
fn frame_index(framed: &Path) -> PathBuf {
    framed.with_extension("index")
}

/// Records one set of held files holds: its radiosity file's records (the static records,
/// in frames, do not say).
fn set_records(set: &[PathBuf; 4]) -> Result<u64, OocError> {
    let meta = std::fs::metadata(&set[1]).map_err(|e| OocError::io(&set[1], "read", e))?;
    Ok(meta.len() / RADIOSITY_LEN as u64)
}

/// Removes one set of held files and the indexes of its frames.
fn remove_set(set: &[PathBuf; 4]) -> Result<(), OocError> {
    let indexes = [frame_index(&set[0]), frame_index(&set[3])];
    for p in set.iter().chain(&indexes) {
        std::fs::remove_file(p).map_err(|e| OocError::io(p, "remove", e))?;
    }
    Ok(())
}

/// Records a consuming [`HeldReader`] releases at once, at least: 1.3 MiB of whole records,
/// where the blocks a hole cannot give back (one at each end, in each file) are a few tenths of
/// a percent.
const RELEASE_RECORDS: u64 = 8192;

/// Reads held files record by record, in wire form, in the held order.
pub struct HeldReader {
    reader: HeldRangeReader,
    /// With [`HeldReader::consuming`]: the files, and the records handed out and not yet
    /// released (first, count).
    consumed: Option<(Held, (u64, u64))>,
}

impl HeldReader {
    pub fn open(held: &Held, buffer_bytes: usize) -> Result<Self, OocError> {
        let all = vec![(0, held.count)];
        Ok(HeldReader {
            reader: HeldRangeReader::open(held, all, buffer_bytes)?,
            consumed: None,
        })
    }

    /// As [`HeldReader::open`], for the last reading of `held` (its records rewritten into new
    /// files, which then replace it): the records read are released as it goes
    /// ([`Held::release`]), a buffer at a time, so that the old files and the new ones do not
    /// both lie whole on the disk. The update of every iteration did that: a rank's share twice.
    pub fn consuming(held: &Held, buffer_bytes: usize) -> Result<Self, OocError> {
        let mut reader = Self::open(held, buffer_bytes)?;
        reader.consumed = Some((held.clone(), (0, 0)));
        Ok(reader)
    }

    /// The next record, or `None` at the end.
    pub fn next(&mut self, io: &mut IoCounters) -> Result<Option<Wire>, OocError> {
        let next = self.reader.next(io)?;
        if let Some((held, (first, count))) = self.consumed.as_mut() {
            // The records handed out before the buffer is filled again are copies already.
            // Released in batches: a hole gives back only the whole blocks inside it.
            let at_end = next.is_none();
            *count += !at_end as u64;
            if (*count >= RELEASE_RECORDS || at_end) && self.reader.buffer_spent() && *count > 0 {
                held.release(&[(*first, *count)])?;
                (*first, *count) = (*first + *count, 0);
            }
        }
        Ok(next)
    }
}

/// Reads given ranges of records of held files, in wire form, in the order given: positioned
/// reads of at most about `buffer_bytes` at a time from each of the four files.
pub struct HeldRangeReader {
    files: HeldFiles,
    /// The ranges not read yet, as (first record, records), the next one last.
    ranges: Vec<(u64, u64)>,
    /// Records read ahead, in wire form, and how many of them were handed out.
    buffer: Vec<u8>,
    taken: usize,
    chunk: u64,
}

impl HeldRangeReader {
    pub fn open(
        held: &Held,
        mut ranges: Vec<(u64, u64)>,
        buffer_bytes: usize,
    ) -> Result<Self, OocError> {
        ranges.retain(|&(_, count)| count > 0);
        ranges.reverse();
        Ok(HeldRangeReader {
            files: held.open_files()?,
            ranges,
            buffer: Vec::new(),
            taken: 0,
            chunk: (buffer_bytes / WIRE_LEN).max(1) as u64,
        })
    }

    /// Whether every record read into the buffer has been handed out (the next call reads).
    fn buffer_spent(&self) -> bool {
        self.taken * WIRE_LEN >= self.buffer.len()
    }

    /// The next record, or `None` after the last range.
    pub fn next(&mut self, io: &mut IoCounters) -> Result<Option<Wire>, OocError> {
        if self.buffer_spent() {
            let Some(range) = self.ranges.last_mut() else {
                return Ok(None);
            };
            let (first, count) = (range.0, range.1.min(self.chunk));
            range.0 += count;
            range.1 -= count;
            if range.1 == 0 {
                self.ranges.pop();
            }
            let records = count as usize;
            self.buffer.resize(records * WIRE_LEN, 0);
            let mut part = Vec::new();
            let direct = self.files.direct;
            let lengths = lengths(direct);
            for k in 0..4 {
                part.resize(records * lengths[k], 0);
                self.files.read(k, first, &mut part, io)?;
                for (r, bytes) in part.chunks_exact(lengths[k]).enumerate() {
                    let at = r * WIRE_LEN + OFFSETS[k];
                    if k == 3 {
                        place_rest(
                            &mut self.buffer[r * WIRE_LEN..(r + 1) * WIRE_LEN],
                            bytes,
                            direct,
                        );
                    } else {
                        self.buffer[at..at + lengths[k]].copy_from_slice(bytes);
                    }
                }
            }
            self.taken = 0;
        }
        let at = self.taken * WIRE_LEN;
        self.taken += 1;
        Ok(Some(
            self.buffer[at..at + WIRE_LEN].try_into().expect("a record"),
        ))
    }
}

/// Writes held files (generation `generation` in `dir`), counting records per row of `key`'s
/// copy order when given one.
pub struct HeldWriter {
    /// The static records, in frames.
    statics: FramedWriter,
    /// What the lines carry, and the light of the current axis.
    writers: [SeqWriter; 2],
    /// The rest of the record, in frames.
    rest: FramedWriter,
    paths: [PathBuf; 4],
    count: u64,
    histogram: Option<(AxisKey, Vec<u32>)>,
    /// Records written to this writer's own files (set 0 of the result).
    written: u64,
    /// The sets of files taken over from earlier held files ([`HeldWriter::adopt`]): sets 1..
    /// of the result.
    adopted: Vec<[PathBuf; 4]>,
    /// The result's records in order.
    runs: Vec<HeldRun>,
    /// As [`Held::direct`].
    direct: bool,
}

impl HeldWriter {
    /// `direct`: the records carry the direct light, which the rest file then keeps
    /// ([`lengths`]); without, it must be zero.
    pub fn create(
        dir: &Path,
        generation: u64,
        buffer_bytes: usize,
        histogram: Option<(AxisKey, Vec<u32>)>,
        direct: bool,
    ) -> Result<Self, OocError> {
        let paths = ["static", "radiosity", "gathered", "rest"]
            .map(|name| dir.join(format!("held-{generation}-{name}.bin")));
        let statics = FramedWriter::create(&paths[0], &frame_index(&paths[0]), buffer_bytes)?;
        let writers = [
            SeqWriter::create(&paths[1], buffer_bytes)?,
            SeqWriter::create(&paths[2], buffer_bytes)?,
        ];
        let rest_len = lengths(direct)[3];
        let rest =
            FramedWriter::with_records(&paths[3], &frame_index(&paths[3]), buffer_bytes, rest_len)?;
        let histogram = histogram.map(|(key, mut h)| {
            h.clear();
            h.resize(key.layers() * key.rows(), 0);
            (key, h)
        });
        Ok(HeldWriter {
            statics,
            writers,
            rest,
            paths,
            count: 0,
            histogram,
            written: 0,
            adopted: Vec::new(),
            runs: Vec::new(),
            direct,
        })
    }

    pub fn write(&mut self, w: &Wire) -> Result<(), OocError> {
        self.statics.write(&w[..STATIC_LEN])?;
        let [radiosity, gathered] = &mut self.writers;
        radiosity.write(&w[CARRIED_AT..CARRIED_AT + RADIOSITY_LEN])?;
        gathered.write(&w[GATHERED_AT..GATHERED_AT + LIGHT32_LEN])?;
        debug_assert!(
            self.direct
                || w[DIRECT_AT..DIRECT_AT + LIGHT32_LEN]
                    .iter()
                    .all(|&b| b == 0),
            "direct light in held files made without it"
        );
        for piece in rest_pieces(w, self.direct) {
            self.rest.write(piece)?;
        }
        if let Some((key, h)) = self.histogram.as_mut() {
            h[key.row(voxel(w))] += 1;
        }
        self.push_run(HeldRun {
            set: 0,
            first: self.written,
            count: 1,
        });
        self.written += 1;
        self.count += 1;
        Ok(())
    }

    fn push_run(&mut self, run: HeldRun) {
        match self.runs.last_mut() {
            Some(last) if last.set == run.set && last.first + last.count == run.first => {
                last.count += run.count;
            }
            _ => self.runs.push(run),
        }
    }

    /// Takes over the files of `from`, whose records [`HeldWriter::keep`] can then put in
    /// place without copying them; the result removes them when it is removed. Returns the
    /// number `keep` is given for `from`.
    pub fn adopt(&mut self, from: &Held) -> usize {
        assert_eq!(from.direct, self.direct, "held files of one layout");
        let base = 1 + self.adopted.len();
        self.adopted.extend(from.sets.iter().cloned());
        base
    }

    /// Appends records `first..first + count` of `from` (adopted as `base`) where they lie,
    /// unchanged; they are not counted in the row histogram (the caller keeps it).
    pub fn keep(&mut self, from: &Held, base: usize, (first, count): (u64, u64)) {
        for run in from.runs_of(first, count) {
            self.push_run(HeldRun {
                set: base + run.set,
                ..run
            });
        }
        self.count += count;
    }

    /// Appends records `first..first + count` of the held files `from` unchanged, as bytes, in
    /// reads of at most `chunk` records (`buffer` reused); they are not counted in the row
    /// histogram (the caller keeps it).
    pub fn copy_records(
        &mut self,
        from: &HeldFiles,
        (first, count): (u64, u64),
        chunk: u64,
        buffer: &mut Vec<u8>,
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        assert_eq!(from.direct, self.direct, "held files of one layout");
        let (mut at, end) = (first, first + count);
        while at < end {
            let records = (end - at).min(chunk.max(1));
            for (k, &len) in lengths(self.direct).iter().enumerate() {
                buffer.resize(records as usize * len, 0);
                from.read(k, at, buffer, io)?;
                match k {
                    0 => self.statics.write(buffer)?,
                    3 => self.rest.write(buffer)?,
                    _ => self.writers[k - 1].write(buffer)?,
                }
            }
            at += records;
        }
        let first = self.written;
        self.push_run(HeldRun {
            set: 0,
            first,
            count,
        });
        self.written += count;
        self.count += count;
        Ok(())
    }

    /// Closes the files; returns them and the row histogram.
    pub fn finish(self, io: &mut IoCounters) -> Result<(Held, Option<Vec<u32>>), OocError> {
        io.written += self.statics.finish()? + self.rest.finish()?;
        for w in self.writers {
            io.written += w.finish()?;
        }
        let mut sets = vec![self.paths];
        sets.extend(self.adopted);
        let held = Held {
            sets,
            runs: self.runs,
            count: self.count,
            direct: self.direct,
        };
        Ok((held.prune()?, self.histogram.map(|(_, h)| h)))
    }
}

/// Records a frame of a run file holds (the last may hold fewer).
const RUN_FRAME_RECORDS: usize = 128;
const RUN_FRAME_BYTES: usize = RUN_FRAME_RECORDS * WIRE_LEN;

/// Appends wire records to a run file, in frames: each frame is `u32` LE records, `u32` LE
/// bytes of the LZ4 block that follows, and the block, the frame's records as byte planes
/// (byte 0 of every record, then byte 1, ...). Records of a run are in key order, neighbours in
/// a copy's order, whose static parts are alike (as `outcore::framed` keeps them). Run files
/// are read only from start to end, and the files of the exchange go between ranks as they are
/// (their receiver appends them whole, [`RunWriter::append_frames`]).
pub struct RunWriter {
    out: SeqWriter,
    pending: Vec<u8>,
    planes: Vec<u8>,
    packed: Vec<u8>,
    /// Records written through [`RunWriter::write`].
    pub count: u64,
    /// Bytes of frames appended whole.
    pub appended: u64,
}

impl RunWriter {
    pub fn create(path: &Path, buffer_bytes: usize) -> Result<Self, OocError> {
        Ok(RunWriter {
            out: SeqWriter::create(path, buffer_bytes)?,
            pending: Vec::new(),
            planes: Vec::new(),
            packed: Vec::new(),
            count: 0,
            appended: 0,
        })
    }

    /// Appends whole records (`bytes` holds a multiple of [`WIRE_LEN`]).
    pub fn write(&mut self, bytes: &[u8]) -> Result<(), OocError> {
        self.count += (bytes.len() / WIRE_LEN) as u64;
        self.pending.extend_from_slice(bytes);
        if self.pending.len() >= RUN_FRAME_BYTES {
            let whole = self.pending.len() / RUN_FRAME_BYTES * RUN_FRAME_BYTES;
            let pending = std::mem::take(&mut self.pending);
            for frame in pending[..whole].chunks_exact(RUN_FRAME_BYTES) {
                self.flush_frame(frame)?;
            }
            self.pending = pending;
            self.pending.drain(..whole);
        }
        Ok(())
    }

    /// Appends frames another run file holds, as they are (part of them, in order).
    pub fn append_frames(&mut self, bytes: &[u8]) -> Result<(), OocError> {
        self.appended += bytes.len() as u64;
        self.out.write(bytes)
    }

    fn flush_frame(&mut self, records: &[u8]) -> Result<(), OocError> {
        let n = records.len() / WIRE_LEN;
        self.planes.resize(records.len(), 0);
        planes_of_records(records, WIRE_LEN, &mut self.planes);
        let fail = |e| OocError::io(self.out.path(), "compress", e);
        let bound = lz4::block::compress_bound(records.len()).map_err(fail)?;
        self.packed.resize(bound, 0);
        let len = lz4::block::compress_to_buffer(&self.planes, None, false, &mut self.packed)
            .map_err(|e| OocError::io(self.out.path(), "compress", e))?;
        self.out.write(&(n as u32).to_le_bytes())?;
        self.out.write(&(len as u32).to_le_bytes())?;
        self.out.write(&self.packed[..len])
    }

    pub fn finish(mut self, io: &mut IoCounters) -> Result<PathBuf, OocError> {
        if !self.pending.is_empty() {
            let pending = std::mem::take(&mut self.pending);
            self.flush_frame(&pending)?;
        }
        let path = self.out.path().to_path_buf();
        io.written += self.out.finish()?;
        Ok(path)
    }
}

/// A stream of wire records (a run file, or the held files read through a filter). It counts
/// the bytes it reads from its files, as they lie on the disk (a run's compressed frames), in
/// the counters it is given.
pub type Source<'a> = Box<dyn FnMut(&mut IoCounters) -> Result<Option<Wire>, OocError> + 'a>;

/// A run file ([`RunWriter`]) as a [`Source`].
pub fn run_source<'a>(path: &Path, buffer_bytes: usize) -> Result<Source<'a>, OocError> {
    let file = std::fs::File::open(path).map_err(|e| OocError::io(path, "open", e))?;
    let mut input = std::io::BufReader::with_capacity(buffer_bytes.max(64), file);
    let path = path.to_path_buf();
    let (mut records, mut planes, mut packed) = (Vec::new(), Vec::new(), Vec::new());
    let mut next = 0usize;
    Ok(Box::new(move |io: &mut IoCounters| {
        use std::io::Read;
        if next * WIRE_LEN >= records.len() {
            let damaged = |what: &str| {
                OocError::io(
                    &path,
                    "read",
                    std::io::Error::new(std::io::ErrorKind::InvalidData, what.to_string()),
                )
            };
            let mut head = [0u8; 8];
            // The file's end is where a frame would begin; a signal may interrupt the read.
            loop {
                match input.read(&mut head[..1]) {
                    Ok(0) => return Ok(None),
                    Ok(_) => break,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(e) => return Err(OocError::io(&path, "read", e)),
                }
            }
            let fail = |e| OocError::io(&path, "read", e);
            input.read_exact(&mut head[1..]).map_err(fail)?;
            let word = |k: usize| u32::from_le_bytes(head[4 * k..4 * k + 4].try_into().expect("4"));
            let (n, len) = (word(0) as usize, word(1) as usize);
            let bound = lz4::block::compress_bound(RUN_FRAME_BYTES).unwrap_or(0);
            if n == 0 || n > RUN_FRAME_RECORDS || len > bound {
                return Err(damaged("a frame of a run file has a wrong header"));
            }
            packed.resize(len, 0);
            input.read_exact(&mut packed).map_err(fail)?;
            io.read += (head.len() + len) as u64;
            planes.resize(n * WIRE_LEN, 0);
            let got =
                lz4::block::decompress_to_buffer(&packed, Some(planes.len() as i32), &mut planes)
                    .map_err(|_| damaged("a frame of a run file does not decompress"))?;
            if got != planes.len() {
                return Err(damaged("a frame of a run file is short"));
            }
            records.resize(n * WIRE_LEN, 0);
            records_of_byte_planes(&planes, WIRE_LEN, &mut records);
            next = 0;
        }
        let at = next * WIRE_LEN;
        next += 1;
        Ok(Some(
            records[at..at + WIRE_LEN].try_into().expect("a record"),
        ))
    }))
}

/// Merges `first` (if any) and the run files `runs`, each sorted by `key`, into `sink` in that
/// order, `fan_in` sources at a time at most (earlier passes merge groups of runs into new runs
/// in `dir`). Removes the runs.
#[allow(clippy::too_many_arguments)]
pub fn merge_runs(
    first: Option<Source>,
    mut runs: Vec<PathBuf>,
    key: AxisKey,
    fan_in: usize,
    buffer_bytes: usize,
    dir: &Path,
    io: &mut IoCounters,
    sink: &mut dyn FnMut(&Wire) -> Result<(), OocError>,
) -> Result<(), OocError> {
    let fan_in = fan_in.max(2);
    let mut pass = 0;
    while runs.len() + first.is_some() as usize > fan_in {
        let mut next = Vec::new();
        for (g, group) in runs.chunks(fan_in).enumerate() {
            let path = dir.join(format!("merge-{pass}-{g}.run"));
            let mut out = RunWriter::create(&path, buffer_bytes)?;
            let sources = group
                .iter()
                .map(|p| run_source(p, buffer_bytes))
                .collect::<Result<Vec<_>, _>>()?;
            merge_sources(sources, key, io, &mut |w| out.write(w))?;
            next.push(out.finish(io)?);
            remove_all(group)?;
        }
        runs = next;
        pass += 1;
    }
    let mut sources: Vec<Source> = first.into_iter().collect();
    for p in &runs {
        sources.push(run_source(p, buffer_bytes)?);
    }
    merge_sources(sources, key, io, sink)?;
    remove_all(&runs)
}

fn remove_all(paths: &[PathBuf]) -> Result<(), OocError> {
    for p in paths {
        std::fs::remove_file(p).map_err(|e| OocError::io(p, "remove", e))?;
    }
    Ok(())
}

/// One k-way merge of sorted sources (keys are unique: they end with the canonical id).
fn merge_sources(
    mut sources: Vec<Source>,
    key: AxisKey,
    io: &mut IoCounters,
    sink: &mut dyn FnMut(&Wire) -> Result<(), OocError>,
) -> Result<(), OocError> {
    let mut heads: Vec<Wire> = Vec::with_capacity(sources.len());
    let mut heap = BinaryHeap::with_capacity(sources.len());
    for (k, source) in sources.iter_mut().enumerate() {
        let head = source(io)?;
        if let Some(w) = head {
            heap.push(Reverse((key.key(&w), k)));
        }
        heads.push(head.unwrap_or([0u8; WIRE_LEN]));
    }
    while let Some(Reverse((_, k))) = heap.pop() {
        sink(&heads[k])?;
        if let Some(w) = sources[k](io)? {
            heap.push(Reverse((key.key(&w), k)));
            heads[k] = w;
        }
    }
    Ok(())
}

/// Sorts the records of the run files `inputs` (in any order) by `key` into `sink`: pieces of
/// `chunk_records` sorted in memory into runs, then merged. The inputs are read one after the
/// other, and removed once every record is in a run, before the merge writes.
#[allow(clippy::too_many_arguments)]
pub fn sort_runs(
    inputs: Vec<PathBuf>,
    key: AxisKey,
    chunk_records: usize,
    fan_in: usize,
    buffer_bytes: usize,
    dir: &Path,
    io: &mut IoCounters,
    sink: &mut dyn FnMut(&Wire) -> Result<(), OocError>,
) -> Result<(), OocError> {
    let chunk_records = chunk_records.max(1);
    let mut runs = Vec::new();
    let mut piece: Vec<((u64, u32), Wire)> = Vec::new();
    let flush = |piece: &mut Vec<((u64, u32), Wire)>,
                 runs: &mut Vec<PathBuf>,
                 io: &mut IoCounters|
     -> Result<(), OocError> {
        if piece.is_empty() {
            return Ok(());
        }
        piece.sort_unstable_by_key(|e| e.0);
        let path = dir.join(format!("sorted-{}.run", runs.len()));
        let mut out = RunWriter::create(&path, buffer_bytes)?;
        for (_, w) in piece.iter() {
            out.write(w)?;
        }
        runs.push(out.finish(io)?);
        piece.clear();
        Ok(())
    };
    for p in &inputs {
        let mut source = run_source(p, buffer_bytes)?;
        while let Some(w) = source(io)? {
            if piece.is_empty() {
                // Exactly one piece: growth by doubling could overshoot the budget.
                piece.reserve_exact(chunk_records);
            }
            piece.push((key.key(&w), w));
            if piece.len() == chunk_records {
                flush(&mut piece, &mut runs, io)?;
            }
        }
    }
    remove_all(&inputs)?;
    flush(&mut piece, &mut runs, io)?;
    drop(piece);
    merge_runs(None, runs, key, fan_in, buffer_bytes, dir, io, sink)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(voxel: [i32; 3], id: u32) -> Wire {
        let mut w = [0u8; WIRE_LEN];
        for (k, v) in voxel.iter().enumerate() {
            w[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
        }
        w[68..72].copy_from_slice(&id.to_le_bytes());
        w[WIRE_LEN - 1] = id as u8;
        w
    }

    /// Held files of generation `generation` in `dir` holding `records`, in their order.
    fn written(dir: &Path, generation: u64, buffer: usize, records: &[Wire], direct: bool) -> Held {
        let mut writer = HeldWriter::create(dir, generation, buffer, None, direct).unwrap();
        for w in records {
            writer.write(w).unwrap();
        }
        writer.finish(&mut IoCounters::default()).unwrap().0
    }

    /// A run file of several frames reads back its records in order, takes fewer bytes than
    /// they do, and a damaged frame is an error naming the file.
    #[test]
    fn run_files_read_back_from_their_frames() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.run");
        let records: Vec<Wire> = (0..3 * RUN_FRAME_RECORDS as u32 + 9)
            .map(|k| record([k as i32 / 5, 3, (k % 5) as i32], k))
            .collect();
        let mut out = RunWriter::create(&path, 4096).unwrap();
        // Written in pieces that do not fall on frames.
        for piece in records.chunks(50) {
            out.write(&piece.concat()).unwrap();
        }
        let mut io = IoCounters::default();
        out.finish(&mut io).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(io.written, bytes.len() as u64);
        assert!(
            bytes.len() * 4 < records.len() * WIRE_LEN,
            "{} bytes",
            bytes.len()
        );
        let mut source = run_source(&path, 100).unwrap();
        // Reading counts the bytes on the disk, the compressed frames, not the records.
        let mut read = IoCounters::default();
        for (k, w) in records.iter().enumerate() {
            assert!(source(&mut read).unwrap().as_ref() == Some(w), "record {k}");
        }
        assert!(source(&mut read).unwrap().is_none());
        assert_eq!(read.read, bytes.len() as u64);
        // Appended whole elsewhere (as the exchange does, in pieces), the same records.
        let copy = dir.path().join("c.run");
        let mut appended = RunWriter::create(&copy, 64).unwrap();
        for piece in bytes.chunks(1000) {
            appended.append_frames(piece).unwrap();
        }
        appended.finish(&mut io).unwrap();
        assert_eq!(std::fs::read(&copy).unwrap(), bytes);
        let mut damaged = bytes.clone();
        damaged[0] = 0;
        std::fs::write(&path, &damaged).unwrap();
        let e = run_source(&path, 100).unwrap()(&mut read).unwrap_err();
        assert!(e.to_string().contains("r.run"), "{e}");
    }

    #[test]
    fn external_sort_gives_copy_order_with_small_pieces_and_fan_in() {
        let dir = tempfile::tempdir().unwrap();
        let key = AxisKey::new(1, [5, 6, 7]);
        let mut expected = Vec::new();
        let mut inputs = Vec::new();
        let mut io = IoCounters::default();
        for part in 0..3u32 {
            let path = dir.path().join(format!("in-{part}"));
            let mut out = RunWriter::create(&path, 4096).unwrap();
            for k in 0..50u32 {
                let id = part * 50 + k;
                let v = [(id * 7 % 5) as i32, (id * 3 % 6) as i32, (id % 7) as i32];
                let w = record(v, id);
                out.write(&w).unwrap();
                expected.push(w);
            }
            inputs.push(out.finish(&mut io).unwrap());
        }
        expected.sort_by_key(|w| key.key(w));
        let mut got = Vec::new();
        // The merge writes only once every input is read and removed.
        sort_runs(
            inputs.clone(),
            key,
            7,
            2,
            4096,
            dir.path(),
            &mut io,
            &mut |w| {
                assert!(
                    inputs.iter().all(|p| !p.exists()),
                    "every input read and removed before the merge writes"
                );
                got.push(*w);
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(got.len(), expected.len());
        assert!(got == expected);
        // Nothing left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn held_files_round_trip_and_count_rows() {
        let dir = tempfile::tempdir().unwrap();
        let key = AxisKey::new(0, [3, 4, 5]);
        let mut io = IoCounters::default();
        let mut writer =
            HeldWriter::create(dir.path(), 0, 4096, Some((key, Vec::new())), true).unwrap();
        let records: Vec<Wire> = (0..10u32)
            .map(|id| {
                let mut w = record([(id % 3) as i32, 1, (id % 5) as i32], id);
                encode_scene_data(id, 0.5, [1, 2], &mut w);
                w
            })
            .collect();
        for w in &records {
            writer.write(w).unwrap();
        }
        let (held, histogram) = writer.finish(&mut io).unwrap();
        let histogram = histogram.unwrap();
        assert_eq!(histogram.iter().sum::<u32>(), 10);
        assert_eq!(histogram[key.row([1, 0, 4])], 1);
        let mut reader = HeldReader::open(&held, 4096).unwrap();
        for w in &records {
            assert!(reader.next(&mut io).unwrap().unwrap() == *w);
            assert_eq!(scene_data(w).1, 0.5);
        }
        assert!(reader.next(&mut io).unwrap().is_none());
    }

    /// Held files that keep records of earlier ones where they are: read back in order,
    /// written in place through the pieced files, and the files no run reads removed.
    /// Released records read back as zeros in the two files of whole records (what the lines
    /// carry, the axis's light) and give their blocks back, across the sets a held order runs
    /// through; their static and rest parts, in frames, stay; every other record reads back
    /// unchanged. The files are those of a solve without the direct light, whose rest file
    /// leaves it out.
    #[test]
    fn released_records_give_their_disk_back_and_spare_the_others() {
        use std::os::unix::fs::MetadataExt;
        let dir = tempfile::tempdir().unwrap();
        let mut io = IoCounters::default();
        // Every byte past the static part set, so that a hole shows.
        let records: Vec<Wire> = (0..4020u32)
            .map(|id| {
                let mut w = record([id as i32, 1, 2], id);
                for (j, b) in w[STATIC_LEN..].iter_mut().enumerate() {
                    *b = (id as usize * 31 + j) as u8 | 1;
                }
                w[DIRECT_AT..DIRECT_AT + LIGHT32_LEN].fill(0);
                w
            })
            .collect();
        let a = written(dir.path(), 0, 4096, &records[..4000], false);
        let carried_len = RADIOSITY_LEN as u64;
        assert_eq!(
            std::fs::metadata(&a.sets[0][1]).unwrap().len(),
            4000 * carried_len
        );
        // Ten records of its own, records 100..3100 of `a` in place, ten more.
        let mut b = HeldWriter::create(dir.path(), 1, 4096, None, false).unwrap();
        let base = b.adopt(&a);
        for w in &records[4000..4010] {
            b.write(w).unwrap();
        }
        b.keep(&a, base, (100, 3000));
        for w in &records[4010..4020] {
            b.write(w).unwrap();
        }
        let (b, _) = b.finish(&mut io).unwrap();
        let order: Vec<usize> = (4000..4010).chain(100..3100).chain(4010..4020).collect();
        let carried_of_a = &b.sets[1][1];
        let blocks = || std::fs::metadata(carried_of_a).unwrap().blocks() * 512;
        let (before, length) = (blocks(), std::fs::metadata(carried_of_a).unwrap().len());
        // From `b`'s sixth record to its 3,016th: five of its own, then 3,000 of `a`'s, then one.
        let released = 5..3016;
        b.release(&[(
            released.start as u64,
            (released.end - released.start) as u64,
        )])
        .unwrap();
        let mut reader = HeldReader::open(&b, 4096).unwrap();
        for (k, &id) in order.iter().enumerate() {
            let w = reader.next(&mut io).unwrap().expect("a record");
            assert_eq!(w[..STATIC_LEN], records[id][..STATIC_LEN], "record {k}");
            if released.contains(&k) {
                assert!(
                    w[STATIC_LEN..EARLIER_AT].iter().all(|&b| b == 0),
                    "record {k}: a hole"
                );
                assert!(
                    w[EARLIER_AT..] == records[id][EARLIER_AT..],
                    "record {k}: framed"
                );
            } else {
                assert!(w == records[id], "record {k} unchanged");
            }
        }
        assert!(reader.next(&mut io).unwrap().is_none());
        assert_eq!(std::fs::metadata(carried_of_a).unwrap().len(), length);
        // 3,000 records of 24 bytes in the second file, less a block at each end.
        let freed = before - blocks();
        assert!(
            freed + 2 * 4096 >= 3000 * carried_len,
            "{freed} bytes given back of {before}"
        );
    }

    /// Records copied into new files and then released in the old ones (a rank's sets made one
    /// again, `route::merge_by_layers`) read back whole from the copy.
    #[test]
    fn a_copy_outlives_the_release_of_what_it_copied() {
        use std::os::unix::fs::MetadataExt;
        let dir = tempfile::tempdir().unwrap();
        let mut io = IoCounters::default();
        let records: Vec<Wire> = (0..5000u32)
            .map(|id| {
                let mut w = record([id as i32, 2, 0], id);
                w[STATIC_LEN..].fill(id as u8 | 1);
                w
            })
            .collect();
        let a = written(dir.path(), 0, 4096, &records, true);
        let from = a.open_files().unwrap();
        let mut b = HeldWriter::create(dir.path(), 1, 4096, None, true).unwrap();
        let mut buffer = Vec::new();
        for range in [(0, 2000), (2000, 3000)] {
            b.copy_records(&from, range, 300, &mut buffer, &mut io)
                .unwrap();
            a.release(&[range]).unwrap();
        }
        drop(from);
        let (b, _) = b.finish(&mut io).unwrap();
        // (The files of whole records; the static and rest frames stay with their set.)
        let carried = std::fs::metadata(&a.sets[0][1]).unwrap();
        assert!(
            carried.blocks() * 512 <= 2 * 4096,
            "the old file of what the lines carry is given back"
        );
        let mut reader = HeldReader::open(&b, 4096).unwrap();
        for (k, want) in records.iter().enumerate() {
            let got = reader.next(&mut io).unwrap().expect("a record");
            assert!(got == *want, "record {k}");
        }
        assert!(reader.next(&mut io).unwrap().is_none());
    }

    /// A consuming reader hands out every record as the plain one does, and the files hold
    /// none of them at the end (only the static frames stay).
    #[test]
    fn a_consuming_reader_gives_back_what_it_has_read() {
        use std::os::unix::fs::MetadataExt;
        let dir = tempfile::tempdir().unwrap();
        let mut io = IoCounters::default();
        let total = 3 * RELEASE_RECORDS as usize;
        let records: Vec<Wire> = (0..total as u32)
            .map(|id| {
                let mut w = record([id as i32, 0, 1], id);
                w[STATIC_LEN..].fill(id as u8 | 1);
                w
            })
            .collect();
        let held = written(dir.path(), 0, 4096, &records, true);
        // The files of whole records (the static and rest ones are in frames).
        let allocated = || {
            held.sets[0][1..3]
                .iter()
                .map(|p| std::fs::metadata(p).unwrap().blocks() * 512)
                .sum::<u64>()
        };
        let whole = allocated();
        assert!(whole >= (total * (RADIOSITY_LEN + LIGHT32_LEN)) as u64);
        // About 17 records a buffer: many refills.
        let mut reader = HeldReader::consuming(&held, 4096).unwrap();
        let mut got = Vec::new();
        while let Some(w) = reader.next(&mut io).unwrap() {
            got.push(w);
            // Two batches released once the buffer after them is read.
            if got.len() == 2 * RELEASE_RECORDS as usize + 100 {
                let left = allocated();
                assert!(
                    left < whole * 4 / 10,
                    "two thirds read: {left} of {whole} bytes left"
                );
            }
        }
        assert!(got == records);
        // A block at each end of each file at most.
        assert!(allocated() <= 2 * 2 * 4096, "{} bytes left", allocated());
    }

    #[test]
    fn kept_records_stay_in_their_files_and_read_back_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let files = || std::fs::read_dir(dir.path()).unwrap().count();
        let mut io = IoCounters::default();
        let records: Vec<Wire> = (0..20u32).map(|id| record([id as i32, 0, 0], id)).collect();
        let a = written(dir.path(), 0, 64, &records[..10], false);
        // New files: two records, records 3..7 of `a` kept in place, one more record.
        let mut b = HeldWriter::create(dir.path(), 1, 64, None, false).unwrap();
        let base = b.adopt(&a);
        b.write(&records[10]).unwrap();
        b.write(&records[11]).unwrap();
        b.keep(&a, base, (3, 4));
        b.write(&records[12]).unwrap();
        let (b, _) = b.finish(&mut io).unwrap();
        let expected: Vec<Wire> = [10, 11, 3, 4, 5, 6, 12].map(|k| records[k]).to_vec();
        assert_eq!((b.count, b.sets.len(), b.runs.len()), (7, 2, 3));
        // Four files a set and the indexes of its static and rest frames.
        assert_eq!(files(), 12);
        let read_all = |held: &Held| {
            let mut reader = HeldReader::open(held, 64).unwrap();
            let mut got = Vec::new();
            while let Some(w) = reader.next(&mut IoCounters::default()).unwrap() {
                got.push(w);
            }
            got
        };
        assert!(read_all(&b) == expected);
        // Positioned reads across the pieces, and a write in place: records 1..4 of `b` are
        // 11 (its own files) and 3, 4 (in `a`'s).
        let opened = b.open_files().unwrap();
        let mut gathered = vec![0u8; 3 * LIGHT32_LEN];
        opened
            .gathered
            .read_at(LIGHT32_LEN as u64, &mut gathered, &mut io)
            .unwrap();
        let expected_gathered: Vec<u8> = [11, 3, 4]
            .iter()
            .flat_map(|&k| records[k][GATHERED_AT..GATHERED_AT + LIGHT32_LEN].to_vec())
            .collect();
        assert_eq!(gathered, expected_gathered);
        let light = vec![7u8; 3 * LIGHT32_LEN];
        opened
            .gathered
            .write_at(LIGHT32_LEN as u64, &light, &mut io)
            .unwrap();
        drop(opened);
        let after = read_all(&b);
        for (k, w) in after.iter().enumerate() {
            let slot = &w[GATHERED_AT..GATHERED_AT + LIGHT32_LEN];
            assert_eq!(
                slot == &light[..LIGHT32_LEN],
                (1..4).contains(&k),
                "record {k}"
            );
        }
        // New files that keep nothing of `a`: its files go.
        let mut c = HeldWriter::create(dir.path(), 2, 64, None, false).unwrap();
        let base = c.adopt(&b);
        c.keep(&b, base, (0, 2));
        let (c, _) = c.finish(&mut io).unwrap();
        assert_eq!((c.count, c.sets.len()), (2, 2));
        assert!(read_all(&c) == after[..2]);
        assert!(a.sets[0].iter().all(|p| !p.exists()));
        assert!(c.sets[1] == b.sets[0] && b.sets[0].iter().all(|p| p.exists()));
        assert!(!frame_index(&a.sets[0][0]).exists() && !frame_index(&a.sets[0][3]).exists());
        assert_eq!(files(), 12);
        c.remove().unwrap();
        assert_eq!(files(), 0);
    }
}
