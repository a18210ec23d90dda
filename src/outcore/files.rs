//! The solver's private work files: fixed-size records read and written sequentially (buffered;
//! a sequential writer leaves whole blocks of zeros as holes) or at positions
//! (`pread`/`pwrite`), and the byte layouts of what they hold.
//!
//! Work files live in a temporary directory of one solve and are never read by another program,
//! so they carry no header or checksum (the shard set they are made from is checked as it is
//! read). Band reads copy exactly the records a band needs into the band's own arrays; a memory
//! map would save no copy here, so positioned reads keep the address space flat instead.
//!
//! ```text
//! static record (72 bytes), one per surfel, in a copy's order (an axis copy keeps them in
//!                          compressed frames, super::framed; a rank's held files in the
//!                          data mode, end to end)
//!   0 voxel    i32 x 3     see crate::voxel::Surfel; below 2^24, so the top bytes hold
//!                          PropSurfel::rank (in x) and PropSurfel::mate_sides (low byte in y,
//!                          high byte in z)
//!  12 point    f32 x 3     in [0, 1]; the sign bit of x set where the surfel has no area
//!                          (PropSurfel::no_area)
//!  24 normal   f32 x 3
//!  36 extent   f32 x 6
//!  60 group    u32
//!  64 coverage f32         see solve::coverage; its sign bit set where the back side lies
//!                          inside a closed solid (PropSurfel::inside_back)
//!  68 id       u32         index of the surfel in the canonical (shard set) order
//! radiosity (24 bytes): f32 x 6, side-major (front RGB, back RGB)
//! gathered light (48 bytes): f64 x 6, side-major: light as a checkpoint holds it (the work
//!                          files' f32 light is written there as f64 and read back exactly)
//! light in f32 (24 bytes): f32 x 6, side-major: the light of a main axis's directions so far
//!                          (an axis light record), the canonical sum of an iteration's axes
//!                          (rounded at each fold) and the direct light (rounded once)
//! ```
//!
//! **The axis light in f32.** A band sums the light of its axis's directions in f32, each
//! link's light added in f64 and the sum rounded at once (`solve::light_sum`), and its file
//! holds those sums as they are: half the bytes of f64 (the two files of an axis's light took 96
//! bytes a surfel of the work files' peak, and every pass read and wrote 48 bytes a surfel of
//! each). Every path adds a surfel's links in the same order, so the sums do not depend on where
//! passes begin and end: the one-process solver and the data mode cut them differently and
//! still agree to the bit. Over an axis's directions (a few hundred at most) the sum stays
//! within about `links * 2^-24` of the f64 sum, relatively; the in-memory solver keeps f64
//! throughout. The canonical sum adds the axes in one order in every out-of-core path
//! (`solver::fold_gathered`, `distribute::ooc::fold_axis`), rounded to f32 at each fold.

use super::OocError;
use crate::solve::propagate::PropSurfel;
use std::fs::{File, OpenOptions};
use std::io::{BufReader, Read};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

pub const STATIC_LEN: usize = 72;
pub const RADIOSITY_LEN: usize = 24;
pub const GATHER_LEN: usize = 48;
pub const LIGHT32_LEN: usize = 24;

pub type Radiosity = [[f32; 3]; 2];
pub type Gathered = [[f64; 3]; 2];
/// An axis light record: see the module header.
pub type AxisLight = [[f32; 3]; 2];

/// A surfel as the bands need it, with its canonical index.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StaticRecord {
    pub prop: PropSurfel,
    pub id: u32,
}

fn put(out: &mut [u8], at: &mut usize, word: [u8; 4]) {
    out[*at..*at + 4].copy_from_slice(&word);
    *at += 4;
}

pub fn encode_static(r: &StaticRecord, out: &mut [u8; STATIC_LEN]) {
    let p = &r.prop;
    let mut at = 0;
    // Voxel coordinates stay below 2^24: the top bytes carry the rank in the voxel and the
    // sides of the voxel-mates' planes, so the record keeps its size.
    const _: () = assert!(crate::voxel::voxelize::MAX_GRID_EDGE <= 1 << 24);
    let sides = [
        p.rank as u32,
        p.mate_sides as u32 & 0xff,
        p.mate_sides as u32 >> 8,
    ];
    for (v, side) in p.voxel.into_iter().zip(sides) {
        put(out, &mut at, (v as u32 | side << 24).to_le_bytes());
    }
    // The point lies in [0, 1]: the sign bit of its x carries the flag.
    let mut point = p.point.map(f32::abs);
    if p.no_area {
        point[0] = -point[0];
    }
    for v in point
        .iter()
        .chain(&p.normal)
        .chain(p.extent.iter().flatten())
    {
        put(out, &mut at, v.to_le_bytes());
    }
    put(out, &mut at, p.group.to_le_bytes());
    // Coverage is positive: its sign bit carries the flag, so the record keeps its size.
    let coverage = if p.inside_back {
        -p.coverage.abs()
    } else {
        p.coverage.abs()
    };
    put(out, &mut at, coverage.to_le_bytes());
    put(out, &mut at, r.id.to_le_bytes());
    debug_assert_eq!(at, STATIC_LEN);
}

#[inline]
fn word(bytes: &[u8], k: usize) -> [u8; 4] {
    [
        bytes[4 * k],
        bytes[4 * k + 1],
        bytes[4 * k + 2],
        bytes[4 * k + 3],
    ]
}

/// One voxel coordinate of an encoded static record, from its 4 bytes (without the top byte
/// that [`encode_static`] fills).
pub fn static_coordinate(bytes: [u8; 4]) -> i32 {
    i32::from_le_bytes(bytes) & 0xff_ffff
}

/// The voxel of an encoded static record.
pub fn static_voxel(bytes: &[u8]) -> [i32; 3] {
    [0, 1, 2].map(|k| static_coordinate(word(bytes, k)))
}

pub fn decode_static(bytes: &[u8]) -> StaticRecord {
    let f = |k: usize| f32::from_le_bytes(word(bytes, k));
    let u = |k: usize| u32::from_le_bytes(word(bytes, k));
    StaticRecord {
        prop: PropSurfel {
            voxel: static_voxel(bytes),
            point: [f(3).abs(), f(4), f(5)],
            normal: [f(6), f(7), f(8)],
            extent: [[f(9), f(10), f(11)], [f(12), f(13), f(14)]],
            group: u(15),
            coverage: f(16).abs(),
            inside_back: f(16).is_sign_negative(),
            no_area: f(3).is_sign_negative(),
            rank: (u(0) >> 24) as u8,
            mate_sides: (u(1) >> 24 | u(2) >> 24 << 8) as u16,
        },
        id: u(17),
    }
}

// The light records (`Radiosity`, `AxisLight`, `Gathered`) are little-endian f32 and f64, the
// in-memory layout of those arrays on the machines voxrad builds for, so a band reads and writes
// them as the arrays' own bytes (`band`); a big-endian build is refused here rather than reading
// them wrong.
const _: () = {
    assert!(
        cfg!(target_endian = "little"),
        "voxrad's work files are little-endian"
    );
    assert!(std::mem::size_of::<Radiosity>() == RADIOSITY_LEN);
    assert!(std::mem::size_of::<Gathered>() == GATHER_LEN);
    assert!(std::mem::size_of::<AxisLight>() == LIGHT32_LEN);
};

pub fn encode_radiosity(b: &Radiosity, out: &mut [u8]) {
    for (k, v) in b.iter().flatten().enumerate() {
        out[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
    }
}

pub fn decode_radiosity(bytes: &[u8]) -> Radiosity {
    let f = |k: usize| f32::from_le_bytes(word(bytes, k));
    [[f(0), f(1), f(2)], [f(3), f(4), f(5)]]
}

pub fn encode_gathered(h: &Gathered, out: &mut [u8]) {
    for (k, v) in h.iter().flatten().enumerate() {
        out[8 * k..8 * k + 8].copy_from_slice(&v.to_le_bytes());
    }
}

pub fn decode_gathered(bytes: &[u8]) -> Gathered {
    let f = |k: usize| {
        let mut w = [0u8; 8];
        w.copy_from_slice(&bytes[8 * k..8 * k + 8]);
        f64::from_le_bytes(w)
    };
    [[f(0), f(1), f(2)], [f(3), f(4), f(5)]]
}

/// Writes a light record in f32 (an axis light record, or the direct light), laid out as a
/// radiosity record: `h` rounded to f32, exactly where `h` came from such a record.
pub fn encode_light32(h: &Gathered, out: &mut [u8]) {
    encode_radiosity(&h.map(|side| side.map(|v| v as f32)), out);
}

pub fn decode_light32(bytes: &[u8]) -> Gathered {
    decode_radiosity(bytes).map(|side| side.map(f64::from))
}

/// Bytes moved through work files, for the report.
#[derive(Clone, Copy, Debug, Default)]
pub struct IoCounters {
    pub read: u64,
    pub written: u64,
}

/// A work file opened for positioned reads and writes: one file's bytes, or bytes laid
/// end to end from pieces of several files ([`RecordFile::pieced`]).
pub struct RecordFile {
    path: PathBuf,
    file: File,
    /// Where the bytes are when pieced (empty: `file`'s own).
    pieces: Vec<Piece>,
    others: Vec<(PathBuf, File)>,
}

/// Bytes `start..start + len` of a pieced [`RecordFile`] are bytes `at..at + len` of file
/// `file` (0: the first one, else `others[file - 1]`).
#[derive(Clone, Copy, Debug)]
struct Piece {
    start: u64,
    len: u64,
    file: usize,
    at: u64,
}

impl RecordFile {
    pub fn create(path: &Path) -> Result<Self, OocError> {
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(path)
            .map_err(|e| OocError::io(path, "create", e))?;
        Ok(RecordFile {
            path: path.to_path_buf(),
            file,
            pieces: Vec::new(),
            others: Vec::new(),
        })
    }

    pub fn open(path: &Path) -> Result<Self, OocError> {
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(|e| OocError::io(path, "open", e))?;
        Ok(RecordFile {
            path: path.to_path_buf(),
            file,
            pieces: Vec::new(),
            others: Vec::new(),
        })
    }

    /// The bytes of `pieces`, `(file, first byte, bytes)` of `paths`, end to end: a file whose
    /// parts lie in several files, read and written in place.
    pub fn pieced(paths: &[&Path], pieces: &[(usize, u64, u64)]) -> Result<Self, OocError> {
        let mut files = paths.iter().map(|&p| RecordFile::open(p));
        let Some(first) = files.next() else {
            return Err(OocError::io(
                Path::new(""),
                "open",
                std::io::Error::other("no file"),
            ));
        };
        let mut file = first?;
        file.others = files
            .map(|f| f.map(|f| (f.path, f.file)))
            .collect::<Result<_, _>>()?;
        let mut start = 0;
        for &(index, at, len) in pieces.iter().filter(|p| p.2 > 0) {
            file.pieces.push(Piece {
                start,
                len,
                file: index,
                at,
            });
            start += len;
        }
        Ok(file)
    }

    /// The file and the offset in it of byte `offset`, and the bytes from there on in that
    /// file that belong to this one (all, when not pieced).
    fn locate(&self, offset: u64) -> Result<(&Path, &File, u64, u64), OocError> {
        if self.pieces.is_empty() && self.others.is_empty() {
            return Ok((&self.path, &self.file, offset, u64::MAX));
        }
        let k = self.pieces.partition_point(|p| p.start + p.len <= offset);
        let Some(p) = self.pieces.get(k) else {
            return Err(OocError::io(
                &self.path,
                "read",
                std::io::Error::from(std::io::ErrorKind::UnexpectedEof),
            ));
        };
        let (path, file) = match p.file {
            0 => (self.path.as_path(), &self.file),
            i => (self.others[i - 1].0.as_path(), &self.others[i - 1].1),
        };
        let inside = offset - p.start;
        Ok((path, file, p.at + inside, p.len - inside))
    }

    pub fn read_at(
        &self,
        offset: u64,
        buf: &mut [u8],
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        let mut done = 0;
        while done < buf.len() {
            let (path, file, at, left) = self.locate(offset + done as u64)?;
            let n = (buf.len() - done).min(left.min(usize::MAX as u64) as usize);
            file.read_exact_at(&mut buf[done..done + n], at)
                .map_err(|e| OocError::io(path, "read", e))?;
            done += n;
        }
        io.read += buf.len() as u64;
        Ok(())
    }

    pub fn write_at(&self, offset: u64, buf: &[u8], io: &mut IoCounters) -> Result<(), OocError> {
        let mut done = 0;
        while done < buf.len() {
            let (path, file, at, left) = self.locate(offset + done as u64)?;
            let n = (buf.len() - done).min(left.min(usize::MAX as u64) as usize);
            file.write_all_at(&buf[done..done + n], at)
                .map_err(|e| OocError::io(path, "write", e))?;
            done += n;
        }
        io.written += buf.len() as u64;
        Ok(())
    }
}

/// Sequential, buffered writing of a work file.
///
/// Whole blocks of zeros ([`HOLE_BLOCK`] bytes at aligned offsets) are not written but left as
/// holes: the file is new, so they read back as zeros. Light cleared at the start of an axis
/// or the end of an iteration is such zeros, and then costs neither writes nor disk until it
/// is filled. With a buffer under two blocks every byte is written.
pub struct SeqWriter {
    path: PathBuf,
    file: File,
    buffer: Vec<u8>,
    capacity: usize,
    /// The file offset of `buffer[0]`.
    at: u64,
    /// Bytes written to the file (holes left out).
    written: u64,
}

/// The size of a hole [`SeqWriter`] leaves for zeros, and the alignment of its holes: a file
/// system block, the unit in which holes give disk back.
pub const HOLE_BLOCK: usize = 4096;

impl SeqWriter {
    pub fn create(path: &Path, buffer_bytes: usize) -> Result<Self, OocError> {
        let file = File::create(path).map_err(|e| OocError::io(path, "create", e))?;
        let capacity = buffer_bytes.max(64);
        Ok(SeqWriter {
            path: path.to_path_buf(),
            file,
            buffer: Vec::with_capacity(capacity),
            capacity,
            at: 0,
            written: 0,
        })
    }

    pub fn write(&mut self, mut bytes: &[u8]) -> Result<(), OocError> {
        while !bytes.is_empty() {
            let take = (self.capacity - self.buffer.len()).min(bytes.len());
            self.buffer.extend_from_slice(&bytes[..take]);
            bytes = &bytes[take..];
            if self.buffer.len() == self.capacity {
                self.flush(false)?;
            }
        }
        Ok(())
    }

    /// Writes the buffer out: all of it (`all`), or up to the last block boundary when holes
    /// are made, so that a block of zeros split between two fillings is still found.
    fn flush(&mut self, all: bool) -> Result<(), OocError> {
        let block = HOLE_BLOCK as u64;
        let sparse = self.capacity >= 2 * HOLE_BLOCK;
        let end = self.at + self.buffer.len() as u64;
        let upto = if all || !sparse {
            end
        } else {
            end / block * block
        };
        if upto <= self.at {
            return Ok(());
        }
        let n = (upto - self.at) as usize;
        // Pieces between block boundaries; a whole block of zeros is skipped, the runs of
        // other pieces are written at once.
        let (mut k, mut run_start) = (0usize, 0usize);
        while k < n {
            let offset = self.at + k as u64;
            let piece = ((offset / block + 1) * block - offset).min((n - k) as u64) as usize;
            let hole =
                sparse && piece == HOLE_BLOCK && self.buffer[k..k + piece].iter().all(|&b| b == 0);
            if hole {
                self.write_at_offset(run_start, k)?;
                run_start = k + piece;
            }
            k += piece;
        }
        self.write_at_offset(run_start, n)?;
        self.buffer.drain(..n);
        self.at = upto;
        Ok(())
    }

    /// Writes `buffer[from..to]` where it belongs in the file.
    fn write_at_offset(&mut self, from: usize, to: usize) -> Result<(), OocError> {
        if from < to {
            self.file
                .write_all_at(&self.buffer[from..to], self.at + from as u64)
                .map_err(|e| OocError::io(&self.path, "write", e))?;
            self.written += (to - from) as u64;
        }
        Ok(())
    }

    /// Writes what is left and closes; returns the bytes written (holes left out).
    pub fn finish(mut self) -> Result<u64, OocError> {
        self.flush(true)?;
        // A hole at the end is not in the file until its length says so.
        self.file
            .set_len(self.at)
            .map_err(|e| OocError::io(&self.path, "write", e))?;
        Ok(self.written)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for SeqWriter {
    /// A writer dropped unfinished (on an error path) still leaves its bytes in the file, as a
    /// buffered writer would. Best effort: errors here have no one to go to.
    fn drop(&mut self) {
        if !self.buffer.is_empty() && self.flush(true).is_ok() {
            let _ = self.file.set_len(self.at);
        }
    }
}

/// Sequential, buffered reading of a work file of `LEN`-byte records.
pub struct SeqReader<const LEN: usize> {
    path: PathBuf,
    input: BufReader<File>,
    left: u64,
}

impl<const LEN: usize> SeqReader<LEN> {
    /// Opens `path` holding `count` records, reading from record `first` on.
    pub fn open(path: &Path, buffer_bytes: usize) -> Result<Self, OocError> {
        let file = File::open(path).map_err(|e| OocError::io(path, "open", e))?;
        let len = file
            .metadata()
            .map_err(|e| OocError::io(path, "read", e))?
            .len();
        Ok(SeqReader {
            path: path.to_path_buf(),
            input: BufReader::with_capacity(buffer_bytes.max(LEN), file),
            left: len / LEN as u64,
        })
    }

    /// The next record, or `None` at the end.
    pub fn next_record(&mut self) -> Result<Option<[u8; LEN]>, OocError> {
        if self.left == 0 {
            return Ok(None);
        }
        let mut buf = [0u8; LEN];
        self.input
            .read_exact(&mut buf)
            .map_err(|e| OocError::io(&self.path, "read", e))?;
        self.left -= 1;
        Ok(Some(buf))
    }

    /// The next record, which must exist.
    pub fn expect_record(&mut self) -> Result<[u8; LEN], OocError> {
        self.next_record()?.ok_or_else(|| {
            OocError::io(
                &self.path,
                "read",
                std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "work file ended early"),
            )
        })
    }
}

impl RecordFile {
    /// Sets the file's length (new bytes read as zero).
    pub fn set_len(&self, len: u64) -> Result<(), OocError> {
        self.file
            .set_len(len)
            .map_err(|e| OocError::io(&self.path, "resize", e))
    }
}

/// Gives the disk blocks under bytes `offset..offset + len` of `file` back to the file system:
/// a hole, which reads as zeros, the file keeping its length. For work files whose records
/// nothing reads again while the file itself still serves the others. Best effort: `false`
/// where the system or the file system cannot (the bytes then stay until the file goes).
pub fn punch_hole(file: &File, offset: u64, len: u64) -> bool {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let (Ok(offset), Ok(len)) = (libc::off_t::try_from(offset), libc::off_t::try_from(len))
        else {
            return false;
        };
        if len == 0 {
            return true;
        }
        // SAFETY: a plain system call on a descriptor `file` owns; it reads no memory of ours.
        let mode = libc::FALLOC_FL_PUNCH_HOLE | libc::FALLOC_FL_KEEP_SIZE;
        unsafe { libc::fallocate(file.as_raw_fd(), mode, offset, len) == 0 }
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = (file, offset, len);
        false
    }
}

/// Removes everything in the work directory `dir` but the file `keep`, once a solve is over and
/// its outputs need only that file (the answer in canonical order) and the source. Best effort:
/// what cannot be removed now goes with the directory when it is dropped.
pub fn remove_all_but(dir: &Path, keep: Option<&Path>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if Some(path.as_path()) == keep {
            continue;
        }
        let removed = if path.is_dir() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        if let Err(e) = removed {
            tracing::debug!(path = %path.display(), error = %e, "work file left to the end");
        }
    }
}

/// The disk blocks the files directly in `dir` hold now, in bytes (a file made at its full
/// length holds none until written).
pub fn allocated_bytes(dir: &Path) -> u64 {
    use std::os::unix::fs::MetadataExt;
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .filter_map(|entry| entry.metadata().ok())
        .filter(|m| m.is_file())
        // `st_blocks` counts 512-byte units whatever the filesystem's block size.
        .map(|m| m.blocks() * 512)
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sequential_writer_leaves_whole_blocks_of_zeros_as_holes() {
        let dir = tempfile::tempdir().unwrap();
        // Data, then zeros over several blocks from an unaligned offset, data, and zeros to
        // the end: written in pieces that fall on no boundary.
        let block = HOLE_BLOCK;
        let mut expected = vec![7u8; block + 100];
        expected.extend(vec![0u8; 5 * block + 37]);
        expected.extend(vec![9u8; 3 * block]);
        expected.extend(vec![0u8; 4 * block]);
        for buffer in [64, 3 * block + 5, 1 << 20] {
            let path = dir.path().join(format!("w-{buffer}"));
            let mut w = SeqWriter::create(&path, buffer).unwrap();
            for piece in expected.chunks(777) {
                w.write(piece).unwrap();
            }
            let written = w.finish().unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), expected, "buffer {buffer}");
            // Whole aligned blocks of zeros: 4 in the middle (the run begins 100 bytes into a
            // block and ends 137 bytes into one) and 3 at the end (from 137 bytes into a block
            // on; the last 137 bytes are a part of a block, written).
            let holes = if buffer >= 2 * block { 7 * block } else { 0 };
            assert_eq!(written as usize, expected.len() - holes, "buffer {buffer}");
            #[cfg(target_os = "linux")]
            {
                use std::os::unix::fs::MetadataExt;
                let allocated = std::fs::metadata(&path).unwrap().blocks() * 512;
                if holes > 0 {
                    // On a file system that keeps holes (tmpfs and ext4 do), they take no disk.
                    assert!(
                        allocated as usize <= expected.len().div_ceil(block) * block - holes,
                        "{allocated} bytes allocated"
                    );
                }
            }
        }
        // A writer dropped unfinished still leaves its bytes.
        let path = dir.path().join("dropped");
        let mut w = SeqWriter::create(&path, 1 << 20).unwrap();
        w.write(&expected).unwrap();
        drop(w);
        assert_eq!(std::fs::read(&path).unwrap(), expected);
    }

    #[test]
    fn static_records_read_back_with_their_flags_and_mate_sides() {
        let cases = [
            (1.0, false, false),
            (1.0, true, true),
            (0.25, false, true),
            (0.25, true, false),
        ];
        for (coverage, inside_back, no_area) in cases {
            let r = StaticRecord {
                prop: PropSurfel {
                    voxel: [3, 7, (1 << 20) - 1],
                    group: 12,
                    point: [if no_area { 0.0 } else { 0.1 }, 0.5, 0.9],
                    normal: [0.0, 0.6, 0.8],
                    extent: [[0.0, 0.25, 0.5], [1.0, 0.75, 0.5]],
                    coverage,
                    inside_back,
                    no_area,
                    rank: if no_area { 200 } else { 3 },
                    mate_sides: if inside_back { 0xb1e4 } else { 0x00ff },
                },
                id: 99,
            };
            let mut bytes = [0u8; STATIC_LEN];
            encode_static(&r, &mut bytes);
            assert_eq!(decode_static(&bytes), r);
        }
    }
}
