//! The per-voxel results file, `surfels.bin`: every surfel with its radiosity on both sides.
//!
//! Binary, little-endian, fixed-size records so a reader can check the length from the header
//! alone and seek to record `k` at `HEADER_LEN + k * RECORD_LEN`.
//!
//! ```text
//! header (72 bytes)
//!   0  magic         8 bytes  "VXRSURF\0"
//!   8  version       u32      1
//!  12  record_len    u32      64
//!  16  count         u64      number of records
//!  24  grid.origin   f64 x 3  world position of voxel (0,0,0)'s low corner
//!  48  grid.voxel_size f64
//!  56  grid.dims     u32 x 3
//!  68  reserved      u32      0
//! records (count x 64 bytes), in the solver's surfel order
//!   0  voxel         i32 x 3  integer voxel coordinates
//!  12  point         f32 x 3  surface point inside the voxel, voxel units in [0, 1]
//!                             (world = origin + (voxel + point) * voxel_size; kept relative so
//!                             huge scenes do not lose precision to f32)
//!  24  normal        f32 x 3  unit normal of the front side
//!  36  area          f32      surface area inside the voxel, in voxel_size^2 (0: only touched)
//!  40  B front       f32 x 3  radiosity of side 0 (facing along normal), RGB, units of Ke
//!  52  B back        f32 x 3  radiosity of side 1 (facing along -normal)
//! footer (20 bytes)
//!   0  count         u64      the header's count again
//!   8  crc32         u32      CRC-32 (IEEE) of every byte before the footer
//!  12  end magic     8 bytes  "VXREND\0\0"
//! ```
//!
//! A file is written to a temporary name and renamed only by [`ResultsWriter::finish`], after
//! the footer is written and synced, so a file under the real name is always complete. The reader
//! checks, in order: magic, version (and record length), file length against the header's count
//! (and the footer), checksum; each error names the file and what is wrong.

use super::{atomic, check_pair, OutputError};
use crate::solve::Solution;
use crate::voxel::{Grid, Surfel, SurfelSet, BACK, FRONT};
use glam::DVec3;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use tempfile::NamedTempFile;

pub const MAGIC: [u8; 8] = *b"VXRSURF\0";
pub const END_MAGIC: [u8; 8] = *b"VXREND\0\0";
pub const VERSION: u32 = 1;
pub const HEADER_LEN: u64 = 72;
pub const RECORD_LEN: u64 = 64;
pub const FOOTER_LEN: u64 = 20;

/// One surfel and its radiosity, as stored.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Record {
    pub voxel: [i32; 3],
    pub point: [f32; 3],
    pub normal: [f32; 3],
    pub area: f32,
    /// `radiosity[side][channel]`, side `FRONT` or `BACK`.
    pub radiosity: [[f32; 3]; 2],
}

impl Record {
    pub fn from_surfel(s: &Surfel, radiosity: [[f32; 3]; 2]) -> Self {
        Record {
            voxel: s.voxel,
            point: s.point,
            normal: s.normal,
            area: s.area,
            radiosity,
        }
    }

    /// Surface point in voxel units (absolute).
    pub fn position(&self) -> DVec3 {
        crate::voxel::absolute_position(self.voxel, self.point)
    }

    /// Unit normal of side `side` (`FRONT` or `BACK`).
    pub fn side_normal(&self, side: usize) -> DVec3 {
        crate::voxel::oriented_normal(self.normal, side)
    }

    /// Whether side `side` is worth exporting: it has surface, or it carries light.
    pub fn side_is_present(&self, side: usize) -> bool {
        self.area > 0.0 || self.radiosity[side].iter().any(|&b| b != 0.0)
    }

    fn encode(&self) -> [u8; RECORD_LEN as usize] {
        let mut b = [0u8; RECORD_LEN as usize];
        let mut at = 0;
        let mut put = |bytes: [u8; 4]| {
            b[at..at + 4].copy_from_slice(&bytes);
            at += 4;
        };
        self.voxel.iter().for_each(|v| put(v.to_le_bytes()));
        self.point.iter().for_each(|v| put(v.to_le_bytes()));
        self.normal.iter().for_each(|v| put(v.to_le_bytes()));
        put(self.area.to_le_bytes());
        self.radiosity
            .iter()
            .flatten()
            .for_each(|v| put(v.to_le_bytes()));
        b
    }

    fn decode(b: &[u8; RECORD_LEN as usize]) -> Self {
        let word = |i: usize| [b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]];
        let f = |i: usize| f32::from_le_bytes(word(i));
        Record {
            voxel: [0, 1, 2].map(|i| i32::from_le_bytes(word(i))),
            point: [f(3), f(4), f(5)],
            normal: [f(6), f(7), f(8)],
            area: f(9),
            radiosity: [[f(10), f(11), f(12)], [f(13), f(14), f(15)]],
        }
    }
}

/// A whole results file in memory.
#[derive(Clone, Debug, PartialEq)]
pub struct Results {
    pub grid: Grid,
    pub records: Vec<Record>,
}

impl Results {
    /// The records of a solve, without going through a file.
    pub fn from_solution(set: &SurfelSet, solution: &Solution) -> Result<Results, OutputError> {
        check_pair(Path::new("<results>"), set, solution)?;
        Ok(Results {
            grid: set.grid,
            records: set
                .surfels
                .iter()
                .zip(&solution.radiosity)
                .map(|(s, b)| Record::from_surfel(s, *b))
                .collect(),
        })
    }

    /// World position of record `r`'s surface point.
    pub fn world_position(&self, r: &Record) -> DVec3 {
        self.grid.to_world(r.position())
    }
}

fn encode_header(grid: &Grid, count: u64) -> [u8; HEADER_LEN as usize] {
    let mut h = Vec::with_capacity(HEADER_LEN as usize);
    h.extend_from_slice(&MAGIC);
    h.extend_from_slice(&VERSION.to_le_bytes());
    h.extend_from_slice(&(RECORD_LEN as u32).to_le_bytes());
    h.extend_from_slice(&count.to_le_bytes());
    grid.origin
        .iter()
        .for_each(|v| h.extend_from_slice(&v.to_le_bytes()));
    h.extend_from_slice(&grid.voxel_size.to_le_bytes());
    grid.dims
        .iter()
        .for_each(|v| h.extend_from_slice(&v.to_le_bytes()));
    h.extend_from_slice(&0u32.to_le_bytes());
    let mut out = [0u8; HEADER_LEN as usize];
    out.copy_from_slice(&h);
    out
}

/// Streams records into a results file. Nothing appears under the real name until
/// [`ResultsWriter::finish`] succeeds; dropping the writer earlier deletes the temporary file.
pub struct ResultsWriter {
    path: PathBuf,
    out: BufWriter<NamedTempFile>,
    hasher: crc32fast::Hasher,
    declared: u64,
    written: u64,
}

impl ResultsWriter {
    /// Starts a file that will hold exactly `count` records.
    pub fn create(path: &Path, grid: &Grid, count: u64) -> Result<Self, OutputError> {
        let tmp = atomic::temp_beside(path)?;
        let mut w = ResultsWriter {
            path: path.to_path_buf(),
            out: BufWriter::with_capacity(1 << 20, tmp),
            hasher: crc32fast::Hasher::new(),
            declared: count,
            written: 0,
        };
        w.put(&encode_header(grid, count))?;
        Ok(w)
    }

    fn put(&mut self, bytes: &[u8]) -> Result<(), OutputError> {
        self.hasher.update(bytes);
        self.out
            .write_all(bytes)
            .map_err(|e| OutputError::io(&self.path, e))
    }

    pub fn push(&mut self, record: &Record) -> Result<(), OutputError> {
        if self.written == self.declared {
            return Err(OutputError::invalid(
                &self.path,
                format!("more records than the {} declared", self.declared),
            ));
        }
        self.put(&record.encode())?;
        self.written += 1;
        Ok(())
    }

    /// Writes the footer, syncs and renames the file into place.
    pub fn finish(mut self) -> Result<(), OutputError> {
        if self.written != self.declared {
            return Err(OutputError::invalid(
                &self.path,
                format!(
                    "{} records declared but only {} written",
                    self.declared, self.written
                ),
            ));
        }
        let crc = self.hasher.clone().finalize();
        let mut footer = Vec::with_capacity(FOOTER_LEN as usize);
        footer.extend_from_slice(&self.written.to_le_bytes());
        footer.extend_from_slice(&crc.to_le_bytes());
        footer.extend_from_slice(&END_MAGIC);
        let path = self.path;
        self.out
            .write_all(&footer)
            .map_err(|e| OutputError::io(&path, e))?;
        let tmp = self
            .out
            .into_inner()
            .map_err(|e| OutputError::io(&path, e.into_error()))?;
        atomic::commit(tmp, &path)
    }
}

/// Writes the results of a solve to `path` and returns the number of records.
pub fn write_results(
    path: &Path,
    set: &SurfelSet,
    solution: &Solution,
) -> Result<u64, OutputError> {
    check_pair(path, set, solution)?;
    let count = set.surfels.len() as u64;
    let mut w = ResultsWriter::create(path, &set.grid, count)?;
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        w.push(&Record::from_surfel(s, *b))?;
    }
    w.finish()?;
    Ok(count)
}

/// Why a results file cannot be read. Every case names the file.
#[derive(Debug, thiserror::Error)]
pub enum ResultsError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{} is not a voxrad results file: it starts with {found:?}, expected {expected:?}",
        path.display()
    )]
    BadMagic {
        path: PathBuf,
        found: Vec<u8>,
        expected: Vec<u8>,
    },
    #[error(
        "{} has results format version {found}; this build reads version {expected}",
        path.display()
    )]
    UnsupportedVersion {
        path: PathBuf,
        found: u32,
        expected: u32,
    },
    #[error("{} has an invalid header: {what}", path.display())]
    BadHeader { path: PathBuf, what: String },
    #[error("{} is truncated or has extra bytes: {what}", path.display())]
    BadLength { path: PathBuf, what: String },
    #[error(
        "{} is corrupted: checksum {computed:#010x} of its contents does not match the stored \
         {stored:#010x}",
        path.display()
    )]
    ChecksumMismatch {
        path: PathBuf,
        stored: u32,
        computed: u32,
    },
}

impl ResultsError {
    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            ResultsError::Io { path, .. }
            | ResultsError::BadMagic { path, .. }
            | ResultsError::UnsupportedVersion { path, .. }
            | ResultsError::BadHeader { path, .. }
            | ResultsError::BadLength { path, .. }
            | ResultsError::ChecksumMismatch { path, .. } => path,
        }
    }
}

/// Reads and verifies a whole results file (see the module header for the checks and order).
pub fn read_results(path: &Path) -> Result<Results, ResultsError> {
    let reader = ResultsReader::open(path)?;
    // The count is checked against the real file length by `open`, so the collection is bounded
    // by the file size; the last item of the iterator is the checksum's verdict.
    let records = reader.records(1 << 20)?.collect::<Result<Vec<_>, _>>()?;
    Ok(Results {
        grid: reader.grid,
        records,
    })
}

/// A results file whose header, length and footer have been checked, read as a stream: for
/// files too large to hold. The checksum is checked by [`ResultsReader::check_checksum`] (a pass
/// over the file) and again at the end of every [`ResultsReader::records`] pass, so a caller that
/// must not act on unverified data checks first, then streams.
#[derive(Clone, Debug)]
pub struct ResultsReader {
    path: PathBuf,
    grid: Grid,
    count: u64,
    stored: u32,
    header: [u8; HEADER_LEN as usize],
}

impl ResultsReader {
    /// Opens `path` and checks, in order, magic, version, record length, file length against the
    /// header's count, and the footer.
    pub fn open(path: &Path) -> Result<Self, ResultsError> {
        let io = |source| ResultsError::Io {
            path: path.to_path_buf(),
            source,
        };
        let bad_length = |what: String| ResultsError::BadLength {
            path: path.to_path_buf(),
            what,
        };
        let mut file = File::open(path).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();

        // Read as much of the header as exists, so a short file still gets its magic checked
        // first.
        let mut header = [0u8; HEADER_LEN as usize];
        let got = read_up_to(&mut file, &mut header).map_err(io)?;
        if got < MAGIC.len() || header[..8] != MAGIC {
            return Err(ResultsError::BadMagic {
                path: path.to_path_buf(),
                found: header[..got.min(8)].to_vec(),
                expected: MAGIC.to_vec(),
            });
        }
        if got < 12 {
            return Err(bad_length(format!(
                "{len} bytes, shorter than the {HEADER_LEN}-byte header"
            )));
        }
        let u32_at = |b: &[u8], i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let bytes8 = |b: &[u8], i: usize| {
            let mut w = [0u8; 8];
            w.copy_from_slice(&b[i..i + 8]);
            w
        };
        let u64_at = |b: &[u8], i: usize| u64::from_le_bytes(bytes8(b, i));
        let f64_at = |b: &[u8], i: usize| f64::from_le_bytes(bytes8(b, i));
        let version = u32_at(&header, 8);
        if version != VERSION {
            return Err(ResultsError::UnsupportedVersion {
                path: path.to_path_buf(),
                found: version,
                expected: VERSION,
            });
        }
        if got < HEADER_LEN as usize {
            return Err(bad_length(format!(
                "{len} bytes, shorter than the {HEADER_LEN}-byte header"
            )));
        }
        let record_len = u32_at(&header, 12);
        if record_len as u64 != RECORD_LEN {
            return Err(ResultsError::BadHeader {
                path: path.to_path_buf(),
                what: format!("record length {record_len}, expected {RECORD_LEN}"),
            });
        }
        let count = u64_at(&header, 16);
        let expected = count
            .checked_mul(RECORD_LEN)
            .and_then(|r| r.checked_add(HEADER_LEN + FOOTER_LEN));
        if expected != Some(len) {
            return Err(bad_length(format!(
                "the header announces {count} records ({} bytes in all) but the file has {len} \
                 bytes",
                expected.map_or_else(|| "an impossible number of".to_string(), |e| e.to_string())
            )));
        }
        let body_len = len - FOOTER_LEN;
        file.seek(SeekFrom::Start(body_len)).map_err(io)?;
        let mut footer = [0u8; FOOTER_LEN as usize];
        file.read_exact(&mut footer).map_err(io)?;
        let footer_count = u64_at(&footer, 0);
        let stored = u32_at(&footer, 8);
        if footer[12..] != END_MAGIC {
            return Err(bad_length(
                "the footer's end marker is missing (the file was not finished)".to_string(),
            ));
        }
        if footer_count != count {
            return Err(bad_length(format!(
                "the header announces {count} records but the footer {footer_count}"
            )));
        }
        let grid = Grid {
            origin: [0, 1, 2].map(|i| f64_at(&header, 24 + 8 * i)),
            voxel_size: f64_at(&header, 48),
            dims: [0, 1, 2].map(|i| u32_at(&header, 56 + 4 * i)),
        };
        Ok(ResultsReader {
            path: path.to_path_buf(),
            grid,
            count,
            stored,
            header,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Number of records.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// The records in file order through a buffer of `buffer_bytes`. After the last record,
    /// yields a [`ResultsError::ChecksumMismatch`] if the bytes read do not match the footer.
    pub fn records(&self, buffer_bytes: usize) -> Result<ResultsRecords, ResultsError> {
        let io = |source| ResultsError::Io {
            path: self.path.clone(),
            source,
        };
        let mut file = File::open(&self.path).map_err(io)?;
        file.seek(SeekFrom::Start(HEADER_LEN)).map_err(io)?;
        let mut hasher = crc32fast::Hasher::new();
        hasher.update(&self.header);
        Ok(ResultsRecords {
            reader: self.clone(),
            file: BufReader::with_capacity(buffer_bytes.max(RECORD_LEN as usize), file),
            hasher,
            left: self.count,
            done: false,
        })
    }

    /// Reads the whole file once and compares its checksum with the footer's.
    pub fn check_checksum(&self) -> Result<(), ResultsError> {
        for r in self.records(1 << 20)? {
            r?;
        }
        Ok(())
    }
}

/// Iterator over a results file's records (see [`ResultsReader::records`]).
pub struct ResultsRecords {
    reader: ResultsReader,
    file: BufReader<File>,
    hasher: crc32fast::Hasher,
    left: u64,
    done: bool,
}

impl Iterator for ResultsRecords {
    type Item = Result<Record, ResultsError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        if self.left == 0 {
            self.done = true;
            let computed = self.hasher.clone().finalize();
            return (computed != self.reader.stored).then(|| {
                Err(ResultsError::ChecksumMismatch {
                    path: self.reader.path.clone(),
                    stored: self.reader.stored,
                    computed,
                })
            });
        }
        let mut buf = [0u8; RECORD_LEN as usize];
        if let Err(source) = self.file.read_exact(&mut buf) {
            self.done = true;
            return Some(Err(ResultsError::Io {
                path: self.reader.path.clone(),
                source,
            }));
        }
        self.hasher.update(&buf);
        self.left -= 1;
        Some(Ok(Record::decode(&buf)))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.left as usize;
        (left, Some(left + 1))
    }
}

/// Fills `buf` as far as the reader allows; returns how many bytes were read. (A short read is
/// not an error here: readers of checked files report short files as length errors.)
pub(crate) fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// The first line of a CSV export.
pub const CSV_HEADER: &str = "x,y,z,nx,ny,nz,B_r,B_g,B_b";

/// Writes the CSV rows of one record (one per present side, see [`write_csv`]); returns how many.
pub fn write_csv_record(w: &mut dyn Write, grid: &Grid, r: &Record) -> std::io::Result<u64> {
    let p = grid.to_world(r.position());
    let mut rows = 0;
    for side in [FRONT, BACK] {
        if !r.side_is_present(side) {
            continue;
        }
        let n = r.side_normal(side);
        let b = r.radiosity[side];
        writeln!(
            w,
            "{},{},{},{},{},{},{},{},{}",
            p.x, p.y, p.z, n.x as f32, n.y as f32, n.z as f32, b[0], b[1], b[2]
        )?;
        rows += 1;
    }
    Ok(rows)
}

/// Writes one CSV row per present surfel side (area > 0 or any radiosity): world position, the
/// side's unit normal and its radiosity, `x,y,z,nx,ny,nz,B_r,B_g,B_b`, after a header line.
/// Meant for small scenes (`voxrad-shard export` streams large ones); returns the number of rows.
pub fn write_csv(path: &Path, results: &Results) -> Result<u64, OutputError> {
    let mut rows = 0u64;
    atomic::write_atomically(path, |w| {
        writeln!(w, "{CSV_HEADER}")?;
        for r in &results.records {
            rows += write_csv_record(w, &results.grid, r)?;
        }
        Ok(())
    })?;
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::testutil;

    fn written() -> (tempfile::TempDir, PathBuf, Results) {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.bin");
        let (set, solution) = testutil::lit_square(5);
        assert_eq!(write_results(&path, &set, &solution).unwrap(), 25);
        let expected = Results::from_solution(&set, &solution).unwrap();
        (dir, path, expected)
    }

    #[test]
    fn round_trip() {
        let (dir, path, expected) = written();
        let back = read_results(&path).unwrap();
        assert_eq!(back, expected);
        let len = std::fs::metadata(&path).unwrap().len();
        assert_eq!(len, HEADER_LEN + 25 * RECORD_LEN + FOOTER_LEN);
        // Only the finished file is left: no temporary beside it.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    fn corrupt(path: &Path, f: impl FnOnce(&mut Vec<u8>)) {
        let mut bytes = std::fs::read(path).unwrap();
        f(&mut bytes);
        std::fs::write(path, bytes).unwrap();
    }

    fn names_file(e: &ResultsError, path: &Path) {
        assert_eq!(e.path(), path);
        assert!(e.to_string().contains(&path.display().to_string()), "{e}");
    }

    #[test]
    fn flipped_byte_is_a_checksum_error() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| {
            let mid = b.len() / 2;
            b[mid] ^= 0x40;
        });
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::ChecksumMismatch { .. }), "{e}");
        names_file(&e, &path);
    }

    #[test]
    fn truncation_is_a_length_error() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| b.truncate(b.len() - 30));
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadLength { .. }), "{e}");
        names_file(&e, &path);
        // Cut inside the header too.
        corrupt(&path, |b| b.truncate(40));
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadLength { .. }), "{e}");
    }

    #[test]
    fn wrong_magic_is_reported_first() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| {
            b[0] = b'X';
            b[8] = 99; // a bad version too: the magic is checked first
        });
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadMagic { .. }), "{e}");
        names_file(&e, &path);
        std::fs::write(&path, b"VX").unwrap();
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadMagic { .. }), "{e}");
    }

    #[test]
    fn wrong_version_is_reported_before_the_checksum() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| b[8..12].copy_from_slice(&7u32.to_le_bytes()));
        let e = read_results(&path).unwrap_err();
        match &e {
            ResultsError::UnsupportedVersion { found, .. } => assert_eq!(*found, 7),
            other => panic!("{other}"),
        }
        names_file(&e, &path);
    }

    #[test]
    fn missing_file_names_it() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("absent.bin");
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::Io { .. }));
        names_file(&e, &path);
    }

    #[test]
    fn unfinished_writer_leaves_nothing() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.bin");
        let (set, solution) = testutil::lit_square(2);
        let mut w = ResultsWriter::create(&path, &set.grid, 4).unwrap();
        w.push(&Record::from_surfel(&set.surfels[0], solution.radiosity[0]))
            .unwrap();
        let e = w.finish().unwrap_err();
        assert!(e.to_string().contains("surfels.bin"), "{e}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn csv_has_present_sides_in_world_units() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.csv");
        let mut surfels = vec![
            testutil::surfel([1, 2, 3], [0.5, 0.5, 0.5], [0.0, 0.0, 1.0], 0.0),
            testutil::surfel([0, 0, 0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 0.0),
        ];
        surfels[1].area = 0.0;
        let set = testutil::set_of(surfels, 0.5);
        let solution = Solution {
            radiosity: vec![[[1.0, 2.0, 3.0], [0.0; 3]], [[0.0; 3]; 2]],
            stats: Default::default(),
        };
        let results = Results::from_solution(&set, &solution).unwrap();
        assert_eq!(write_csv(&path, &results).unwrap(), 1);
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "x,y,z,nx,ny,nz,B_r,B_g,B_b");
        // origin (-1, 2, 0.5) + (1.5, 2.5, 3.5) * 0.5
        assert_eq!(lines[1], "-0.25,3.25,2.25,0,0,1,1,2,3");
        assert_eq!(lines.len(), 2);
    }
}
