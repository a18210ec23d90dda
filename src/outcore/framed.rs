//! An axis copy's static records in compressed frames: runs of [`FRAME_RECORDS`] records, each
//! run stored as byte planes (byte `b` of every record of the frame, then byte `b + 1` ...)
//! and compressed on its own as an LZ4 block, and the byte offset of every frame kept in an index
//! file beside, so that a band reads any range of records by reading and decompressing only the
//! frames that hold it. The data mode's held files keep their static records the same way, in
//! several files whose runs of records [`FramedRuns`] reads as one; its run files use the same
//! byte planes ([`planes_of_records`]) for their longer records.
//!
//! Why: the static records are three of the largest work files (72 bytes a surfel in each of the
//! three copies), and neighbours in a copy's order are alike (the same plane, normal, material
//! and box, coordinates one apart). Cut into pieces of 4.6 and 18 KB, the 80-byte records of
//! shard sets (a generated building, the office and the Cornell box at resolution 256) became
//! 5.2 to 8.1 and 6.5 to 9.3 times smaller with LZ4, 9 to 14 and 12 to 19 times with zstd at
//! level 1; but zstd rebuilds its entropy tables for every small frame, and decompressing took
//! longer than the reads it saved while the work files stayed in the page cache. LZ4 has no
//! entropy stage and decompresses at memory speed. The records come back bit for bit, so the
//! answers do not change; only the disk taken and the bytes read do.
//!
//! The frames are LZ4 blocks as the reference library (liblz4, through the `lz4` crate) writes
//! and reads them. A pure-Rust decoder tried first (`lz4_flex`) copies a match that overlaps
//! its own output a byte at a time, and byte planes are made of such matches (a run of one
//! byte repeated): the first iteration of the out-of-core bench read its bands in 13 s with
//! it against 8 s with liblz4.
//!
//! Why byte planes: alike neighbours differ in a few low bytes of a few fields, which LZ4, whose
//! matches are whole runs of equal bytes, finds only as short matches record after record. In
//! planes, the bytes that do not change from record to record (high bytes, normals, materials)
//! form long runs. On a generated building of 6,964,850 surfels the three copies' frames took
//! 41.4 bytes a surfel as records and 18.9 as planes.
//!
//! ```text
//! static-M.bin         frame after frame: LZ4 blocks of FRAME_RECORDS records (the last may
//!                      hold fewer), each the byte planes of its 72-byte static records
//! static-index-M.bin   u64 little-endian, one a frame: the byte offset where it starts in
//!                      static-M.bin; then one more, the file's length
//! ```
//!
//! Frames are small so that a band's range in one layer (tens of records in a large sparse
//! grid) decompresses little beyond itself: at most one frame's worth at each end. Like the
//! other work files they carry no checksum (`super::files`); a frame that does not decompress
//! to its records' length is an error.

use super::files::{IoCounters, RecordFile, SeqWriter, STATIC_LEN};
use super::OocError;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// Records a frame holds (the last one of a file may hold fewer).
pub const FRAME_RECORDS: u64 = 128;

const FRAME_BYTES: usize = FRAME_RECORDS as usize * STATIC_LEN;

/// Bytes the readers of `copies` copies of `records` records hold: their indexes, and the
/// buffers they share ([`FrameBuffers`]): the frames of one read (the records of at most
/// `io_bytes` and a frame at each end) and one frame decompressed.
pub fn readers_bytes(copies: u64, records: u64, io_bytes: usize) -> u64 {
    let index = (records.div_ceil(FRAME_RECORDS) + 1) * 8;
    copies * index + (io_bytes + 3 * FRAME_BYTES) as u64
}

/// Writes static records (or other records of a whole number of 8-byte words), in order, into
/// frames and their index.
pub struct FramedWriter {
    out: SeqWriter,
    index: SeqWriter,
    /// Bytes of a whole frame.
    frame_bytes: usize,
    record_len: usize,
    pending: Vec<u8>,
    planes: Vec<u8>,
    packed: Vec<u8>,
    /// Bytes of frames written so far: where the next frame starts.
    offset: u64,
}

impl FramedWriter {
    /// A writer of the frames to `path` and their index to `index`, each through a buffer of
    /// `buffer_bytes`.
    pub fn create(path: &Path, index: &Path, buffer_bytes: usize) -> Result<Self, OocError> {
        Self::with_records(path, index, buffer_bytes, STATIC_LEN)
    }

    /// As [`FramedWriter::create`], for records of `record_len` bytes (a multiple of 8).
    pub fn with_records(
        path: &Path,
        index: &Path,
        buffer_bytes: usize,
        record_len: usize,
    ) -> Result<Self, OocError> {
        assert!(
            record_len > 0 && record_len % 8 == 0,
            "records of whole words"
        );
        let frame_bytes = FRAME_RECORDS as usize * record_len;
        Ok(FramedWriter {
            out: SeqWriter::create(path, buffer_bytes)?,
            index: SeqWriter::create(index, buffer_bytes)?,
            frame_bytes,
            record_len,
            pending: Vec::with_capacity(frame_bytes),
            planes: vec![0; frame_bytes],
            packed: vec![0; packed_bound(frame_bytes)],
            offset: 0,
        })
    }

    /// Appends `bytes`: records, or pieces of records in order (a frame is cut only after a
    /// whole frame's bytes).
    pub fn write(&mut self, mut bytes: &[u8]) -> Result<(), OocError> {
        while !bytes.is_empty() {
            let take = (self.frame_bytes - self.pending.len()).min(bytes.len());
            self.pending.extend_from_slice(&bytes[..take]);
            bytes = &bytes[take..];
            if self.pending.len() == self.frame_bytes {
                self.flush_frame()?;
            }
        }
        Ok(())
    }

    fn flush_frame(&mut self) -> Result<(), OocError> {
        debug_assert_eq!(self.pending.len() % self.record_len, 0, "whole records");
        let len = compress_frame(
            &self.pending,
            self.record_len,
            &mut self.planes,
            &mut self.packed,
        )
        .map_err(|e| OocError::io(self.out.path(), "compress", e))?;
        self.index.write(&self.offset.to_le_bytes())?;
        self.out.write(&self.packed[..len])?;
        self.offset += len as u64;
        self.pending.clear();
        Ok(())
    }

    /// Writes the last frame and the index's end; returns the bytes written to both files.
    pub fn finish(mut self) -> Result<u64, OocError> {
        if !self.pending.is_empty() {
            self.flush_frame()?;
        }
        self.index.write(&self.offset.to_le_bytes())?;
        Ok(self.out.finish()? + self.index.finish()?)
    }
}

/// LZ4's bound on the compressed size of `bytes` bytes (a frame at most).
fn packed_bound(bytes: usize) -> usize {
    lz4::block::compress_bound(bytes).expect("a frame is far below LZ4's limit")
}

/// Compresses one frame's records, as byte planes (`planes`, of a frame's length, is scratch),
/// into `packed` (of LZ4's bound for a frame); returns its length.
fn compress_frame(
    records: &[u8],
    record_len: usize,
    planes: &mut [u8],
    packed: &mut [u8],
) -> std::io::Result<usize> {
    let planes = &mut planes[..records.len()];
    planes_of_records(records, record_len, planes);
    lz4::block::compress_to_buffer(planes, None, false, packed)
}

/// Records of `record_len` bytes as byte planes (byte 0 of every record, then byte 1, ...):
/// `planes` is as long as `records`. Also the run files of the data mode
/// (`distribute::ooc::held`), whose records are longer.
pub fn planes_of_records(records: &[u8], record_len: usize, planes: &mut [u8]) {
    let n = records.len() / record_len;
    for (r, record) in records.chunks_exact(record_len).enumerate() {
        for (b, &byte) in record.iter().enumerate() {
            planes[b * n + r] = byte;
        }
    }
}

/// The inverse of [`planes_of_records`], a byte at a time (the frames of static records are
/// read back faster, eight records at a time, by `records_of_planes`).
pub fn records_of_byte_planes(planes: &[u8], record_len: usize, records: &mut [u8]) {
    let n = planes.len() / record_len;
    for (b, plane) in planes.chunks_exact(n.max(1)).enumerate().take(record_len) {
        for (r, &byte) in plane.iter().enumerate() {
            records[r * record_len + b] = byte;
        }
    }
}

/// Records `lo..hi` of a frame of `n` records of `len` bytes (a multiple of 8) held as byte
/// planes, into `out` as records.
///
/// Eight records at a time, as 8 x 8 blocks of bytes (eight bytes of eight planes) turned
/// in registers: a byte at a time, this took longer than the decompression itself.
fn records_of_planes(
    planes: &[u8],
    n: usize,
    (lo, hi): (usize, usize),
    len: usize,
    out: &mut [u8],
) {
    let words = len / 8;
    let whole = (hi - lo) / 8 * 8;
    for k in (0..whole).step_by(8) {
        let r = lo + k;
        let block = &mut out[k * len..(k + 8) * len];
        for w in 0..words {
            let mut rows = [0u64; 8];
            for (i, row) in rows.iter_mut().enumerate() {
                let at = (8 * w + i) * n + r;
                *row = u64::from_le_bytes(planes[at..at + 8].try_into().expect("8 bytes"));
            }
            for (j, word) in transpose_bytes(rows).iter().enumerate() {
                let at = j * len + 8 * w;
                block[at..at + 8].copy_from_slice(&word.to_le_bytes());
            }
        }
    }
    let rest = &mut out[whole * len..(hi - lo) * len];
    for (b, plane) in planes.chunks_exact(n).enumerate() {
        for (record, &byte) in rest.chunks_exact_mut(len).zip(&plane[lo + whole..hi]) {
            record[b] = byte;
        }
    }
}

/// The 8 x 8 matrix of bytes whose row `i` is `rows[i]` (byte `j` its column `j`, little-endian),
/// transposed: byte `i` of the result's word `j` is byte `j` of `rows[i]`. Three rounds of
/// swapping blocks across the diagonal: of 4 x 4 bytes, then 2 x 2, then single bytes.
fn transpose_bytes(mut x: [u64; 8]) -> [u64; 8] {
    for (half, mask, pairs) in [
        (32, 0x0000_0000_ffff_ffff_u64, [0, 1, 2, 3]),
        (16, 0x0000_ffff_0000_ffff, [0, 1, 4, 5]),
        (8, 0x00ff_00ff_00ff_00ff, [0, 2, 4, 6]),
    ] {
        let step = half / 8;
        for i in pairs {
            let t = ((x[i] >> half) ^ x[i + step]) & mask;
            x[i] ^= t << half;
            x[i + step] ^= t;
        }
    }
    x
}

/// Counts the bytes that records would take in frames, without writing them: what
/// [`FramedWriter`] writes of the same records in the same order, less the index.
pub struct FrameSizer {
    pending: Vec<u8>,
    planes: Vec<u8>,
    packed: Vec<u8>,
    bytes: u64,
}

impl Default for FrameSizer {
    fn default() -> Self {
        FrameSizer {
            pending: Vec::with_capacity(FRAME_BYTES),
            planes: vec![0; FRAME_BYTES],
            packed: vec![0; packed_bound(FRAME_BYTES)],
            bytes: 0,
        }
    }
}

impl FrameSizer {
    pub fn add(&mut self, record: &[u8; STATIC_LEN]) -> std::io::Result<()> {
        self.pending.extend_from_slice(record);
        if self.pending.len() == FRAME_BYTES {
            self.size_frame()?;
        }
        Ok(())
    }

    /// Counts the pending records' frame.
    fn size_frame(&mut self) -> std::io::Result<()> {
        let (planes, packed) = (&mut self.planes, &mut self.packed);
        self.bytes += compress_frame(&self.pending, STATIC_LEN, planes, packed)? as u64;
        self.pending.clear();
        Ok(())
    }

    /// The bytes of the frames of the records added.
    pub fn finish(mut self) -> std::io::Result<u64> {
        if !self.pending.is_empty() {
            self.size_frame()?;
        }
        Ok(self.bytes)
    }
}

/// The frames of one copy opened for reading ranges of records (static records, or the
/// records [`FramedStatics::open_records`] is given the length of).
pub struct FramedStatics {
    file: RecordFile,
    path: PathBuf,
    record_len: usize,
    /// Where each frame starts, then the file's length.
    index: Vec<u64>,
    records: u64,
    /// Tells this reader's frames from those of the others sharing `buffers`.
    id: usize,
    buffers: Arc<Mutex<FrameBuffers>>,
}

/// The buffers of the readers of a solve's copies, shared (the copies are read one at a time):
/// the frames read, the one decompressed, and which frame of which reader that is.
pub struct FrameBuffers {
    packed: Vec<u8>,
    frame: Vec<u8>,
    held: Option<(usize, u64)>,
}

impl FrameBuffers {
    pub fn shared() -> Arc<Mutex<FrameBuffers>> {
        Arc::new(Mutex::new(FrameBuffers {
            packed: Vec::new(),
            // Grown for longer records by their first read.
            frame: vec![0; FRAME_BYTES],
            held: None,
        }))
    }
}

/// Numbers the readers, for [`FrameBuffers::held`].
static READERS: AtomicUsize = AtomicUsize::new(0);

impl FramedStatics {
    /// Opens the frames at `path` of `records` records, loading their index from `index`, to
    /// be read through `buffers`.
    pub fn open(
        path: &Path,
        index: &Path,
        records: u64,
        buffers: &Arc<Mutex<FrameBuffers>>,
    ) -> Result<Self, OocError> {
        Self::open_records(path, index, (records, STATIC_LEN), buffers)
    }

    /// As [`FramedStatics::open`], for `records` records of `record_len` bytes (a multiple of
    /// 8), as [`FramedWriter::with_records`] writes them.
    pub fn open_records(
        path: &Path,
        index: &Path,
        (records, record_len): (u64, usize),
        buffers: &Arc<Mutex<FrameBuffers>>,
    ) -> Result<Self, OocError> {
        assert!(
            record_len > 0 && record_len % 8 == 0,
            "records of whole words"
        );
        let bytes = std::fs::read(index).map_err(|e| OocError::io(index, "read", e))?;
        let index: Vec<u64> = bytes
            .chunks_exact(8)
            .map(|w| u64::from_le_bytes(w.try_into().expect("8 bytes")))
            .collect();
        if index.len() as u64 != records.div_ceil(FRAME_RECORDS) + 1
            || index.windows(2).any(|w| w[0] > w[1])
        {
            return Err(Self::damaged(path));
        }
        Ok(FramedStatics {
            file: RecordFile::open(path)?,
            path: path.to_path_buf(),
            record_len,
            index,
            records,
            id: READERS.fetch_add(1, Ordering::Relaxed),
            buffers: buffers.clone(),
        })
    }

    fn damaged(path: &Path) -> OocError {
        OocError::io(
            path,
            "read",
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "a work file's frames do not match their index",
            ),
        )
    }

    /// Fills `out` (a whole number of records) with the records from `start` on.
    pub fn read(&self, start: u64, out: &mut [u8], io: &mut IoCounters) -> Result<(), OocError> {
        let len = self.record_len;
        let count = (out.len() / len) as u64;
        if count == 0 {
            return Ok(());
        }
        if start + count > self.records {
            return Err(Self::damaged(&self.path));
        }
        let mut buffers = self.buffers.lock().unwrap_or_else(|e| e.into_inner());
        let FrameBuffers {
            packed,
            frame,
            held,
        } = &mut *buffers;
        let frame_bytes = FRAME_RECORDS as usize * len;
        if frame.len() < frame_bytes {
            frame.resize(frame_bytes, 0);
        }
        // The frame held, if it is one of this reader's.
        let mut mine = held.filter(|&(id, _)| id == self.id).map(|(_, f)| f);
        // Set again at the end: a read that fails leaves no frame held.
        *held = None;
        let (first, last) = (start / FRAME_RECORDS, (start + count - 1) / FRAME_RECORDS);
        // The first frame may be the one held already (a binary search reads one record at a
        // time): read the frames after it only.
        let from = if mine == Some(first) && first < last {
            first + 1
        } else {
            first
        };
        let (begin, end) = (self.index[from as usize], self.index[last as usize + 1]);
        if mine != Some(first) || first < last {
            packed.resize((end - begin) as usize, 0);
            self.file.read_at(begin, packed, io)?;
        }
        let mut written = 0;
        for f in first..=last {
            let records = FRAME_RECORDS.min(self.records - f * FRAME_RECORDS) as usize;
            // This frame's part of the range, in records from the frame's start.
            let lo = (start.max(f * FRAME_RECORDS) - f * FRAME_RECORDS) as usize;
            let hi = ((start + count).min((f + 1) * FRAME_RECORDS) - f * FRAME_RECORDS) as usize;
            let wanted = (hi - lo) * len;
            let planes = &mut frame[..records * len];
            if mine != Some(f) {
                let at = (self.index[f as usize] - begin) as usize;
                let bytes = (self.index[f as usize + 1] - self.index[f as usize]) as usize;
                // The frame decompressed is kept: the next read may want the rest of it.
                let size = Some(planes.len() as i32);
                let got = lz4::block::decompress_to_buffer(&packed[at..at + bytes], size, planes)
                    .map_err(|_| Self::damaged(&self.path))?;
                if got != records * len {
                    return Err(Self::damaged(&self.path));
                }
                mine = Some(f);
            }
            let into = &mut out[written..written + wanted];
            records_of_planes(planes, records, (lo, hi), len, into);
            written += wanted;
        }
        *held = mine.map(|f| (self.id, f));
        Ok(())
    }
}

/// Static records laid end to end from runs of records of several framed files (a rank's held
/// files in the data mode out of core, `distribute::ooc::held`): run `k` is records
/// `first..first + count` of file `set`.
pub struct FramedRuns {
    files: Vec<FramedStatics>,
    /// Per run: its file, its first record there, and its first record in the whole.
    runs: Vec<(usize, u64, u64)>,
    records: u64,
}

impl FramedRuns {
    /// `files` (each read through `buffers`) and the runs `(file, first, count)` in order.
    pub fn new(files: Vec<FramedStatics>, runs: &[(usize, u64, u64)]) -> Self {
        let mut at = 0;
        let runs = runs
            .iter()
            .map(|&(set, first, count)| {
                let run = (set, first, at);
                at += count;
                run
            })
            .collect();
        FramedRuns {
            files,
            runs,
            records: at,
        }
    }

    /// Fills `out` (a whole number of records) with the records from `start` on.
    pub fn read(&self, start: u64, out: &mut [u8], io: &mut IoCounters) -> Result<(), OocError> {
        let len = self.files.first().map_or(STATIC_LEN, |f| f.record_len);
        let count = (out.len() / len) as u64;
        if start + count > self.records {
            let path = self
                .files
                .first()
                .map_or(Path::new(""), |f| f.path.as_path());
            return Err(FramedStatics::damaged(path));
        }
        // The run holding `start`: the last that begins at or before it.
        let mut k = self
            .runs
            .partition_point(|r| r.2 <= start)
            .saturating_sub(1);
        let (mut at, end) = (start, start + count);
        while at < end {
            let (set, first, begins) = self.runs[k];
            let run_end = self.runs.get(k + 1).map_or(self.records, |r| r.2);
            let take = run_end.min(end) - at;
            let from = (at - start) as usize * len;
            let part = &mut out[from..from + take as usize * len];
            self.files[set].read(first + (at - begins), part, io)?;
            at += take;
            k += 1;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(k: u32) -> [u8; STATIC_LEN] {
        let mut r = [0u8; STATIC_LEN];
        // Alike neighbours, as in a copy, with every record distinct.
        r[..4].copy_from_slice(&k.to_le_bytes());
        r[4..8].copy_from_slice(&(k / 7).to_le_bytes());
        r[68..].copy_from_slice(&(k ^ 0x5a5a).to_le_bytes());
        r
    }

    /// Runs of records of two framed files, read as one: any range, across runs.
    #[test]
    fn runs_of_several_files_read_back_in_their_order() {
        let dir = tempfile::tempdir().unwrap();
        let buffers = FrameBuffers::shared();
        let counts = [3 * FRAME_RECORDS + 5, 2 * FRAME_RECORDS];
        let files: Vec<FramedStatics> = counts
            .iter()
            .enumerate()
            .map(|(f, &n)| {
                let path = dir.path().join(format!("s{f}.bin"));
                let index = dir.path().join(format!("i{f}.bin"));
                let mut w = FramedWriter::create(&path, &index, 4096).unwrap();
                for k in 0..n as u32 {
                    w.write(&record(k + 1_000_000 * f as u32)).unwrap();
                }
                w.finish().unwrap();
                FramedStatics::open(&path, &index, n, &buffers).unwrap()
            })
            .collect();
        // File 1's records 7..200, file 0's 100..389, an empty run, file 1's 0..7.
        let runs = [(1, 7, 193), (0, 100, 289), (0, 5, 0), (1, 0, 7)];
        let expected: Vec<u8> = runs
            .iter()
            .flat_map(|&(f, first, n)| {
                (first..first + n).flat_map(move |k| record(k as u32 + 1_000_000 * f as u32))
            })
            .collect();
        let whole = FramedRuns::new(files, &runs);
        let total = (expected.len() / STATIC_LEN) as u64;
        let mut io = IoCounters::default();
        for (start, n) in [
            (0, total),
            (190, 10),
            (192, 1),
            (482, 7),
            (5, 300),
            (total - 1, 1),
        ] {
            let mut out = vec![0u8; n as usize * STATIC_LEN];
            whole.read(start, &mut out, &mut io).unwrap();
            let at = start as usize * STATIC_LEN;
            assert!(out == expected[at..at + out.len()], "{start} {n}");
        }
        let mut beyond = vec![0u8; 2 * STATIC_LEN];
        assert!(whole.read(total - 1, &mut beyond, &mut io).is_err());
    }

    #[test]
    fn any_range_reads_back_the_records_written() {
        let dir = tempfile::tempdir().unwrap();
        let (path, index) = (dir.path().join("s.bin"), dir.path().join("i.bin"));
        // Frames full and one short at the end.
        let records = 5 * FRAME_RECORDS as u32 + 17;
        let mut w = FramedWriter::create(&path, &index, 4096).unwrap();
        for k in 0..records {
            w.write(&record(k)).unwrap();
        }
        w.finish().unwrap();
        let packed = std::fs::metadata(&path).unwrap().len();
        let mut sizer = FrameSizer::default();
        for k in 0..records {
            sizer.add(&record(k)).unwrap();
        }
        assert_eq!(sizer.finish().unwrap(), packed);
        assert!(
            packed * 4 < records as u64 * STATIC_LEN as u64,
            "{packed} bytes"
        );
        // A second copy, of other records, read through the same buffers.
        let (path2, index2) = (dir.path().join("s2.bin"), dir.path().join("i2.bin"));
        let mut w = FramedWriter::create(&path2, &index2, 4096).unwrap();
        for k in 0..records {
            w.write(&record(k + 1_000_000)).unwrap();
        }
        w.finish().unwrap();
        let buffers = FrameBuffers::shared();
        let r = FramedStatics::open(&path, &index, records as u64, &buffers).unwrap();
        let other = FramedStatics::open(&path2, &index2, records as u64, &buffers).unwrap();
        let mut io = IoCounters::default();
        let n = records as u64;
        for (start, count) in [
            (0, 1),
            (0, n),
            (63, 2),
            (64, 64),
            (100, 200),
            (n - 1, 1),
            (5, 0),
        ] {
            let mut out = vec![0u8; count as usize * STATIC_LEN];
            r.read(start, &mut out, &mut io).unwrap();
            for (k, got) in out.chunks_exact(STATIC_LEN).enumerate() {
                assert_eq!(got, record(start as u32 + k as u32), "{start} + {k}");
            }
        }
        // One record at a time, as a binary search reads them, in any order, the two copies in
        // turn: each reads its own frames, not the one the other left in the buffers.
        for k in [300u64, 2, 301, 64, 63, 63, n - 1] {
            let mut out = [0u8; STATIC_LEN];
            r.read(k, &mut out, &mut io).unwrap();
            assert_eq!(out, record(k as u32));
            other.read(k, &mut out, &mut io).unwrap();
            assert_eq!(out, record(k as u32 + 1_000_000));
        }
        let mut past = [0u8; STATIC_LEN];
        assert!(r.read(n, &mut past, &mut io).is_err());
    }

    #[test]
    fn records_come_back_from_planes_at_any_range() {
        // The static records, and the data mode's held rest records with and without the
        // direct light.
        for (n, rec) in [1usize, 7, 8, 9, 100, FRAME_RECORDS as usize]
            .into_iter()
            .flat_map(|n| [(n, STATIC_LEN), (n, 88), (n, 112)])
        {
            let records: Vec<u8> = (0..n * rec).map(|k| (k * 31 + k / 7) as u8).collect();
            let mut planes = vec![0u8; records.len()];
            let mut packed = vec![0u8; packed_bound(records.len())];
            let len = compress_frame(&records, rec, &mut planes, &mut packed).unwrap();
            let mut unpacked = vec![0u8; records.len()];
            let size = Some(unpacked.len() as i32);
            lz4::block::decompress_to_buffer(&packed[..len], size, &mut unpacked).unwrap();
            assert_eq!(unpacked, planes);
            for lo in 0..n.min(10) {
                for hi in [lo, lo + 1, (lo + 8).min(n), (lo + 17).min(n), n] {
                    let mut out = vec![0u8; (hi - lo) * rec];
                    records_of_planes(&planes, n, (lo, hi), rec, &mut out);
                    assert_eq!(out, records[lo * rec..hi * rec], "{n} x {rec}: {lo}..{hi}");
                }
            }
        }
    }

    #[test]
    fn a_short_file_or_a_wrong_index_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let (path, index) = (dir.path().join("s.bin"), dir.path().join("i.bin"));
        let records = 3 * FRAME_RECORDS as u32;
        let mut w = FramedWriter::create(&path, &index, 4096).unwrap();
        for k in 0..records {
            w.write(&record(k)).unwrap();
        }
        w.finish().unwrap();
        let buffers = FrameBuffers::shared();
        assert!(FramedStatics::open(&path, &index, records as u64 + 1000, &buffers).is_err());
        // A frame cut short (a full disk's write, a file truncated by hand).
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let r =
            FramedStatics::open(&path, &index, records as u64, &FrameBuffers::shared()).unwrap();
        let mut out = vec![0u8; records as usize * STATIC_LEN];
        assert!(r.read(0, &mut out, &mut IoCounters::default()).is_err());
    }
}
