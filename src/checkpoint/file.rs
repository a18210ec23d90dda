//! The checkpoint file's byte layout, its durable writing and its checked reading.
//!
//! ```text
//!  0  magic         8 bytes  "VXRDCKPT"
//!  8  version       u32      FORMAT_VERSION (8; versions 1 to 7 are still read)
//! 12  header_len    u32      bytes of the header body that follows
//! 16  header body            Identity then State (see `encode_header`), little-endian;
//!                            version 2 ends it with the mid-iteration position, version 3
//!                            then with the layout of the partial sums (`State::data_groups`),
//!                            version 4 then with `State::axis_in_progress` (version 5
//!                            also with `data_groups`: the layout by groups out of core),
//!                            version 6 then with the Chebyshev semi-iteration's state
//!                            (present flag, ratio, updates: `solve::accelerate`) and
//!                            whether the run allows it (`Identity::chebyshev`), version 7
//!                            then with whether the partial sums are f32 (`State::sums_in_f32`);
//!                            version 8 has version 7's layout, its out-of-core partial sums
//!                            gathered in another walk (`State::walked_otherwise`)
//!  .  header_crc    u32      CRC-32 of bytes 0 .. 16 + header_len
//!  .  radiosity              surfels x 24 bytes: f32 x 6 per surfel, side-major (front RGB,
//!                            back RGB), in the solver's surfel order
//!  .  older radiosity        only while Chebyshev runs: the radiosity before the last
//!                            iteration's, surfels x 24 bytes alike
//!  .  partial sums           only in mid-iteration: ranks x surfels x 48 bytes, the light each
//!                            rank had gathered (f64 x 6 per surfel, side-major), rank 0 first
//!                            (24 bytes, f32 x 6, where `sums_in_f32`: the out-of-core solvers);
//!                            with `axis_in_progress`, one more array of surfels x 48 bytes
//!                            after them (out of core: the light of the main axis in progress);
//!                            by groups out of core (`data_groups` G and `axis_in_progress`),
//!                            G arrays of the axes each group has done, then G of each group's
//!                            axis in progress, all in canonical order
//!  .  payload_crc   u32      CRC-32 of the radiosity and partial-sum bytes
//! ```
//!
//! The header has its own checksum so that a run can be refused (wrong scene, damaged file)
//! before anything is read or computed; the payload's checksum is checked before a solver uses a
//! single value of it. The file's length is fixed by the header, so a truncated file is named as
//! such.
//!
//! Writing goes to `checkpoint.bin.partial` beside the real name, is synced, renamed over the
//! real name and the directory is synced: a kill at any moment leaves either the old checkpoint
//! or the new one, never a mixture. (A fixed temporary name, rather than a random one, so that
//! repeated kills do not pile up stray files; only one solve writes into an out directory.)

use super::{CheckpointError, ExtrapolationState, Header, Identity, Solver, State};
use std::fs::File;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

pub const MAGIC: [u8; 8] = *b"VXRDCKPT";
/// The version written; [`OLDEST_VERSION`] up to it are read.
pub const FORMAT_VERSION: u32 = 8;
/// Version 1: iteration boundaries only (no position, no partial sums).
pub const OLDEST_VERSION: u32 = 1;
/// Bytes per surfel of the radiosity payload.
pub const RADIOSITY_LEN: usize = 24;
/// Bytes per surfel of one rank's partial sums in f64 (what [`CheckpointFile`]'s readers hand
/// out, whatever the file holds).
pub const PARTIAL_LEN: usize = 48;
/// Bytes per surfel of one array of partial sums in f32 ([`State::sums_in_f32`]).
pub const PARTIAL32_LEN: usize = 24;
/// The fixed prefix: magic, version, header length.
const PREFIX_LEN: usize = 16;
/// A header never comes near this (its only variable part is a short list of change norms);
/// a larger stated length is damage, not a reason to allocate.
const MAX_HEADER_LEN: usize = 1 << 20;

pub type Radiosity = [[f32; 3]; 2];
/// The light gathered for one surfel, by side and channel, as the solver accumulates it.
pub type Gathered = [[f64; 3]; 2];

/// Where a checkpoint is written before it is renamed to `path`.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".partial");
    PathBuf::from(name)
}

pub fn encode_radiosity(b: &Radiosity, out: &mut [u8]) {
    for (k, v) in b.iter().flatten().enumerate() {
        out[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
    }
}

pub fn decode_radiosity(bytes: &[u8]) -> Radiosity {
    let f = |k: usize| {
        f32::from_le_bytes([
            bytes[4 * k],
            bytes[4 * k + 1],
            bytes[4 * k + 2],
            bytes[4 * k + 3],
        ])
    };
    [[f(0), f(1), f(2)], [f(3), f(4), f(5)]]
}

pub fn encode_gathered(g: &Gathered, out: &mut [u8]) {
    for (k, v) in g.iter().flatten().enumerate() {
        out[8 * k..8 * k + 8].copy_from_slice(&v.to_bits().to_le_bytes());
    }
}

/// One surfel's partial sums as the file of `header` holds them, in f64.
pub fn decode_partial(bytes: &[u8], header: &Header) -> Gathered {
    if header.state.sums_in_f32 {
        decode_radiosity(bytes).map(|side| side.map(f64::from))
    } else {
        decode_gathered(bytes)
    }
}

/// Pieces of f32 partial sums (`PARTIAL32_LEN` bytes a surfel) as the f64 records the readers
/// hand out (the same values), in `wide`.
fn widen(piece: &[u8], wide: &mut Vec<u8>) {
    wide.resize(piece.len() / PARTIAL32_LEN * PARTIAL_LEN, 0);
    for (narrow, out) in piece
        .chunks_exact(PARTIAL32_LEN)
        .zip(wide.chunks_exact_mut(PARTIAL_LEN))
    {
        encode_gathered(&decode_radiosity(narrow).map(|s| s.map(f64::from)), out);
    }
}

pub fn decode_gathered(bytes: &[u8]) -> Gathered {
    let f = |k: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[8 * k..8 * k + 8]);
        f64::from_bits(u64::from_le_bytes(b))
    };
    [[f(0), f(1), f(2)], [f(3), f(4), f(5)]]
}

/// Bytes of the payload (radiosity and partial sums) of a checkpoint with this header.
fn payload_len(header: &Header) -> Option<u64> {
    let per_surfel = header.radiosity_arrays() as u64 * RADIOSITY_LEN as u64
        + header.partial_arrays() as u64 * header.partial_len() as u64;
    header.identity.surfels.checked_mul(per_surfel)
}

/// The whole length of a checkpoint file with this header length and header.
fn file_len(header_len: usize, header: &Header) -> Option<u64> {
    payload_len(header)?.checked_add((PREFIX_LEN + header_len + 8) as u64)
}

fn encode_header(header: &Header) -> Vec<u8> {
    let mut b = Vec::with_capacity(128);
    let id = &header.identity;
    let state = &header.state;
    let u32s = |b: &mut Vec<u8>, v: u32| b.extend_from_slice(&v.to_le_bytes());
    let u64s = |b: &mut Vec<u8>, v: u64| b.extend_from_slice(&v.to_le_bytes());
    let opt = |b: &mut Vec<u8>, v: Option<f64>| {
        b.extend_from_slice(&(v.is_some() as u32).to_le_bytes());
        b.extend_from_slice(&v.unwrap_or(0.0).to_bits().to_le_bytes());
    };
    u32s(&mut b, id.solver as u32);
    u64s(&mut b, id.surfels);
    for d in id.dims {
        u32s(&mut b, d);
    }
    u64s(&mut b, id.voxel_size.to_bits());
    u32s(&mut b, id.directions);
    u32s(&mut b, id.directions_checksum);
    u32s(&mut b, id.channels);
    u32s(&mut b, id.accelerate as u32);
    u32s(&mut b, id.scene_checksum);
    u64s(&mut b, state.iteration);
    u32s(&mut b, state.ranks);
    opt(&mut b, state.previous_change);
    let (changes, count, last_ratio) = state.extrapolation.parts();
    u64s(&mut b, count as u64);
    opt(&mut b, last_ratio);
    u32s(&mut b, changes.len() as u32);
    for c in changes {
        u64s(&mut b, c.to_bits());
    }
    // Version 2: the mid-iteration position (present flag, directions done).
    u32s(&mut b, state.within.is_some() as u32);
    u64s(&mut b, state.within.unwrap_or(0));
    // Version 3: whose partial sums they are (by directions, or by held surfels, see `State`).
    u32s(&mut b, state.data_groups);
    // Version 4: whether the light of an out-of-core axis in progress follows the sums.
    u32s(&mut b, state.axis_in_progress as u32);
    // Version 6: the Chebyshev semi-iteration (present flag, ratio, updates).
    let (ratio, updates) = state.extrapolation.chebyshev.unwrap_or((0.0, 0));
    u32s(&mut b, state.extrapolation.chebyshev.is_some() as u32);
    u64s(&mut b, ratio.to_bits());
    u64s(&mut b, updates);
    u32s(&mut b, id.chebyshev as u32);
    // Version 7: whether the partial sums are f32.
    u32s(&mut b, state.sums_in_f32 as u32);
    b
}

/// Reads little-endian fields off a byte slice; running off its end is an error.
struct Fields<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Fields<'_> {
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let end = self.at.checked_add(N)?;
        let out = self.bytes.get(self.at..end)?.try_into().ok()?;
        self.at = end;
        Some(out)
    }
    fn u32(&mut self) -> Option<u32> {
        self.take().map(u32::from_le_bytes)
    }
    fn u64(&mut self) -> Option<u64> {
        self.take().map(u64::from_le_bytes)
    }
    fn f64(&mut self) -> Option<f64> {
        self.u64().map(f64::from_bits)
    }
    fn opt_f64(&mut self) -> Option<Option<f64>> {
        let present = self.u32()?;
        let v = self.f64()?;
        match present {
            0 => Some(None),
            1 => Some(Some(v)),
            _ => None,
        }
    }
}

fn decode_header(body: &[u8], version: u32) -> Option<Header> {
    let mut f = Fields { bytes: body, at: 0 };
    let solver = match f.u32()? {
        1 => Solver::InMemory,
        2 => Solver::OutOfCore,
        _ => return None,
    };
    let identity = Identity {
        solver,
        surfels: f.u64()?,
        dims: [f.u32()?, f.u32()?, f.u32()?],
        voxel_size: f.f64()?,
        directions: f.u32()?,
        directions_checksum: f.u32()?,
        channels: f.u32()?,
        accelerate: match f.u32()? {
            0 => false,
            1 => true,
            _ => return None,
        },
        // Read at the end of the header (version 6).
        chebyshev: false,
        scene_checksum: f.u32()?,
    };
    let iteration = f.u64()?;
    let ranks = f.u32()?;
    let previous_change = f.opt_f64()?;
    let count = f.u64()? as usize;
    let last_ratio = f.opt_f64()?;
    let len = f.u32()? as usize;
    if len > body.len() / 8 {
        return None;
    }
    let changes = (0..len).map(|_| f.f64()).collect::<Option<Vec<f64>>>()?;
    let within = if version >= 2 {
        let present = f.u32()?;
        let done = f.u64()?;
        match present {
            0 if done == 0 => None,
            // A position is never 0 (that is the boundary) and needs the ranks' sums.
            1 if done > 0 && ranks > 0 => Some(done),
            _ => return None,
        }
    } else {
        None
    };
    let data_groups = if version >= 3 { f.u32()? } else { 0 };
    let axis_in_progress = if version >= 4 {
        match f.u32()? {
            0 => false,
            // Only inside an iteration: in the layout by directions (out of core), or from
            // version 5 by groups out of core.
            1 if within.is_some() && (data_groups == 0 || version >= 5) => true,
            _ => return None,
        }
    } else {
        false
    };
    let (chebyshev, allowed) = if version >= 6 {
        let present = f.u32()?;
        let ratio = f.f64()?;
        let updates = f.u64()?;
        let allowed = match f.u32()? {
            0 => false,
            1 => true,
            _ => return None,
        };
        match present {
            0 => (None, allowed),
            1 if allowed && ratio > 0.0 && ratio < 1.0 => (Some((ratio, updates)), allowed),
            _ => return None,
        }
    } else {
        (None, false)
    };
    let sums_in_f32 = if version >= 7 {
        match f.u32()? {
            0 => false,
            1 => true,
            _ => return None,
        }
    } else {
        false
    };
    let identity = Identity {
        chebyshev: allowed,
        ..identity
    };
    if f.at != body.len() {
        return None;
    }
    Some(Header {
        identity,
        state: State {
            iteration,
            ranks,
            previous_change,
            extrapolation: ExtrapolationState {
                chebyshev,
                ..ExtrapolationState::from_parts(changes, count, last_ratio)
            },
            within,
            data_groups,
            axis_in_progress,
            sums_in_f32,
            walked_forwards: version < 8 && within.is_some(),
        },
    })
}

fn bad(path: &Path, what: impl Into<String>) -> CheckpointError {
    CheckpointError::Bad {
        path: path.to_path_buf(),
        what: what.into(),
    }
}

/// Checks the fixed prefix and the header (its checksum too); returns the header and the offset
/// of the radiosity. `bytes` must hold at least the prefix and the header.
fn parse_prefix(path: &Path, bytes: &[u8]) -> Result<(Header, usize), CheckpointError> {
    if bytes.len() < PREFIX_LEN {
        return Err(bad(
            path,
            format!(
                "not a voxrad checkpoint: only {} bytes (truncated)",
                bytes.len()
            ),
        ));
    }
    if bytes[..8] != MAGIC {
        return Err(bad(path, "not a voxrad checkpoint (wrong magic number)"));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap_or_default());
    if !(OLDEST_VERSION..=FORMAT_VERSION).contains(&version) {
        return Err(bad(
            path,
            format!(
                "checkpoint format version {version}; this voxrad reads versions \
                 {OLDEST_VERSION} to {FORMAT_VERSION}: finish that run with the voxrad that made \
                 it, or start afresh without --resume"
            ),
        ));
    }
    let header_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap_or_default()) as usize;
    if header_len > MAX_HEADER_LEN {
        return Err(bad(
            path,
            format!("damaged checkpoint: a header of {header_len} bytes"),
        ));
    }
    let end = PREFIX_LEN + header_len;
    if bytes.len() < end + 4 {
        return Err(bad(path, "truncated checkpoint (the header is incomplete)"));
    }
    let stored = u32::from_le_bytes(bytes[end..end + 4].try_into().unwrap_or_default());
    if crc32fast::hash(&bytes[..end]) != stored {
        return Err(bad(path, "damaged checkpoint (header checksum mismatch)"));
    }
    let header = decode_header(&bytes[PREFIX_LEN..end], version)
        .ok_or_else(|| bad(path, "damaged checkpoint (its header does not decode)"))?;
    Ok((header, end + 4))
}

/// What a checkpoint read whole into memory holds: its header, its radiosity and, in
/// mid-iteration, the partial sums of one rank.
#[derive(Debug)]
pub struct Parsed {
    pub header: Header,
    pub radiosity: Vec<Radiosity>,
    /// The radiosity before the last iteration's, while Chebyshev runs (see
    /// [`Header::radiosity_arrays`]).
    pub older: Option<Vec<Radiosity>>,
    /// The partial sums of the rank asked for (`None` at a boundary, or if the checkpoint has no
    /// sums for that rank).
    pub partial: Option<Vec<Gathered>>,
}

/// A checkpoint read whole into memory and checked; the partial sums of rank `rank` are kept.
pub fn parse(path: &Path, bytes: &[u8], rank: usize) -> Result<Parsed, CheckpointError> {
    let (header, at) = parse_prefix(path, bytes)?;
    let expected = file_len(at - PREFIX_LEN - 4, &header);
    if expected != Some(bytes.len() as u64) {
        return Err(length_error(path, expected, bytes.len() as u64));
    }
    let payload = &bytes[at..bytes.len() - 4];
    let stored = u32::from_le_bytes(bytes[bytes.len() - 4..].try_into().unwrap_or_default());
    if crc32fast::hash(payload) != stored {
        return Err(bad(path, "damaged checkpoint (payload checksum mismatch)"));
    }
    let surfels = header.identity.surfels as usize;
    let (arrays, sums) =
        payload.split_at(surfels * RADIOSITY_LEN * header.radiosity_arrays() as usize);
    let (radiosity, older) = decode_radiosity_arrays(arrays, surfels);
    let partial = (rank < header.partial_ranks() as usize).then(|| {
        let len = header.partial_len();
        let one = surfels * len;
        sums[rank * one..(rank + 1) * one]
            .chunks_exact(len)
            .map(|b| decode_partial(b, &header))
            .collect()
    });
    Ok(Parsed {
        header,
        radiosity,
        older,
        partial,
    })
}

/// The radiosity, and the older radiosity if `bytes` holds a second array of `surfels`.
fn decode_radiosity_arrays(
    bytes: &[u8],
    surfels: usize,
) -> (Vec<Radiosity>, Option<Vec<Radiosity>>) {
    let decode = |b: &[u8]| {
        b.chunks_exact(RADIOSITY_LEN)
            .map(decode_radiosity)
            .collect()
    };
    let (radiosity, older) = bytes.split_at((surfels * RADIOSITY_LEN).min(bytes.len()));
    (
        decode(radiosity),
        (!older.is_empty()).then(|| decode(older)),
    )
}

/// The file of a checked checkpoint up to the end of its radiosity and older radiosity (what
/// [`parse_head`] reads).
pub fn head<'a>(bytes: &'a [u8], header: &Header) -> &'a [u8] {
    &bytes[..radiosity_end(bytes, header)]
}

/// The partial sums of a checked checkpoint (every rank's, rank 0 first, then the axis in
/// progress's if it has one); empty at a boundary.
pub fn sums<'a>(bytes: &'a [u8], header: &Header) -> &'a [u8] {
    if bytes.is_empty() {
        return bytes;
    }
    &bytes[radiosity_end(bytes, header)..bytes.len() - 4]
}

fn radiosity_end(bytes: &[u8], header: &Header) -> usize {
    let header_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap_or_default()) as usize;
    PREFIX_LEN
        + header_len
        + 4
        + header.identity.surfels as usize * RADIOSITY_LEN * header.radiosity_arrays() as usize
}

/// The [`head`] of a checkpoint that rank 0 checked whole (its payload checksum too): the prefix
/// and the header are checked again, the radiosity decoded; no partial sums.
pub fn parse_head(path: &Path, head: &[u8]) -> Result<Parsed, CheckpointError> {
    let (header, at) = parse_prefix(path, head)?;
    let expected = (header.identity.surfels as usize)
        .checked_mul(RADIOSITY_LEN * header.radiosity_arrays() as usize)
        .and_then(|r| r.checked_add(at));
    if expected != Some(head.len()) {
        return Err(bad(
            path,
            "checkpoint damaged between the ranks (its length)",
        ));
    }
    let (radiosity, older) = decode_radiosity_arrays(&head[at..], header.identity.surfels as usize);
    Ok(Parsed {
        header,
        radiosity,
        older,
        partial: None,
    })
}

fn length_error(path: &Path, expected: Option<u64>, got: u64) -> CheckpointError {
    match expected {
        Some(e) if got < e => bad(
            path,
            format!("truncated checkpoint: {got} bytes where its header says {e}"),
        ),
        Some(e) => bad(
            path,
            format!("damaged checkpoint: {got} bytes where its header says {e}"),
        ),
        None => bad(path, "damaged checkpoint: an impossible surfel count"),
    }
}

/// A checkpoint file opened for streaming (the out-of-core solver): header checked, length
/// checked, radiosity read in pieces by [`CheckpointFile::read_radiosity`].
pub struct CheckpointFile {
    pub path: PathBuf,
    pub header: Header,
    payload_at: u64,
}

impl CheckpointFile {
    pub fn open(path: &Path) -> Result<Self, CheckpointError> {
        let io = |action, source| CheckpointError::Io {
            path: path.to_path_buf(),
            action,
            source,
        };
        let mut file = File::open(path).map_err(|e| io("open", e))?;
        let len = file.metadata().map_err(|e| io("read", e))?.len();
        let mut prefix = vec![0u8; PREFIX_LEN.min(len as usize)];
        file.read_exact(&mut prefix).map_err(|e| io("read", e))?;
        if prefix.len() == PREFIX_LEN && prefix[..8] == MAGIC {
            let header_len = u32::from_le_bytes(prefix[12..16].try_into().unwrap_or_default());
            let want = (header_len as usize).min(MAX_HEADER_LEN) + 4;
            let available = (len as usize).saturating_sub(PREFIX_LEN).min(want);
            let mut rest = vec![0u8; available];
            file.read_exact(&mut rest).map_err(|e| io("read", e))?;
            prefix.extend_from_slice(&rest);
        }
        let (header, at) = parse_prefix(path, &prefix)?;
        let expected = file_len(at - PREFIX_LEN - 4, &header);
        if expected != Some(len) {
            return Err(length_error(path, expected, len));
        }
        Ok(CheckpointFile {
            path: path.to_path_buf(),
            header,
            payload_at: at as u64,
        })
    }

    /// Hands the radiosity to `f` in pieces of whole surfels (at most `buffer_bytes` each, at
    /// least one surfel), then checks the checksum (reading through any partial sums): a caller
    /// must not keep what it was handed if this returns an error.
    pub fn read_radiosity<E: From<CheckpointError>>(
        &self,
        buffer_bytes: usize,
        f: impl FnMut(&[u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        self.read_payload(buffer_bytes, f, |_| Ok(()), |_| Ok(()), |_| Ok(()))
    }

    /// As [`CheckpointFile::read_radiosity`], then the older radiosity (while the Chebyshev
    /// semi-iteration runs, [`Header::radiosity_arrays`]) to `older`, then the partial sums to
    /// `sums` in pieces of whole surfels (every rank's in turn; the out-of-core solver writes
    /// one), then the light of the axis in progress (see [`State::axis_in_progress`]) to `axis`.
    pub fn read_payload<E: From<CheckpointError>>(
        &self,
        buffer_bytes: usize,
        mut radiosity: impl FnMut(&[u8]) -> Result<(), E>,
        mut older: impl FnMut(&[u8]) -> Result<(), E>,
        mut sums: impl FnMut(&[u8]) -> Result<(), E>,
        mut axis: impl FnMut(&[u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        let mut file = self.open_at(self.payload_at)?;
        let mut crc = crc32fast::Hasher::new();
        let surfels = self.header.identity.surfels;
        let sums_count = surfels * self.header.partial_ranks() as u64;
        let axis_count =
            surfels * (self.header.partial_arrays() - self.header.partial_ranks()) as u64;
        let mut read = |record, count, f: &mut dyn FnMut(&[u8]) -> Result<(), E>| {
            self.read_records(&mut file, (record, count), buffer_bytes, Some(&mut crc), f)
        };
        read(RADIOSITY_LEN, surfels, &mut radiosity)?;
        let older_count = surfels * (self.header.radiosity_arrays() as u64 - 1);
        read(RADIOSITY_LEN, older_count, &mut older)?;
        let len = self.header.partial_len();
        read(len, sums_count, &mut self.widening(&mut sums))?;
        read(len, axis_count, &mut self.widening(&mut axis))?;
        let mut stored = [0u8; 4];
        file.read_exact(&mut stored)
            .map_err(|e| self.io_error("read", e))?;
        if crc.finalize() != u32::from_le_bytes(stored) {
            return Err(bad(&self.path, "damaged checkpoint (payload checksum mismatch)").into());
        }
        Ok(())
    }

    /// Hands partial-sum array `index` (`0 .. partial_arrays`) to `f` in pieces of whole
    /// surfels (at most `buffer_bytes` each). Unchecked: only after a whole read
    /// ([`CheckpointFile::read_radiosity`]) has checked the payload's checksum.
    pub fn read_array<E: From<CheckpointError>>(
        &self,
        index: u32,
        buffer_bytes: usize,
        mut f: impl FnMut(&[u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        if index >= self.header.partial_arrays() {
            return Err(bad(&self.path, format!("it holds no partial-sum array {index}")).into());
        }
        let surfels = self.header.identity.surfels;
        let len = self.header.partial_len();
        let at = self.payload_at
            + surfels * RADIOSITY_LEN as u64 * self.header.radiosity_arrays() as u64
            + index as u64 * surfels * len as u64;
        let mut file = self.open_at(at)?;
        self.read_records(
            &mut file,
            (len, surfels),
            buffer_bytes,
            None,
            &mut self.widening(&mut f),
        )
    }

    /// `f`, handed partial sums as f64 records ([`PARTIAL_LEN`] bytes a surfel) whatever the
    /// file holds: pieces of f32 sums are widened first.
    fn widening<'f, E>(
        &self,
        f: &'f mut dyn FnMut(&[u8]) -> Result<(), E>,
    ) -> impl FnMut(&[u8]) -> Result<(), E> + 'f {
        let narrow = self.header.state.sums_in_f32;
        let mut wide = Vec::new();
        move |piece: &[u8]| {
            if narrow {
                widen(piece, &mut wide);
                f(&wide)
            } else {
                f(piece)
            }
        }
    }

    fn io_error(&self, action: &'static str, source: std::io::Error) -> CheckpointError {
        CheckpointError::Io {
            path: self.path.to_path_buf(),
            action,
            source,
        }
    }

    /// The file, open at byte `at`.
    fn open_at(&self, at: u64) -> Result<File, CheckpointError> {
        use std::io::{Seek, SeekFrom};
        let mut file = File::open(&self.path).map_err(|e| self.io_error("open", e))?;
        file.seek(SeekFrom::Start(at))
            .map_err(|e| self.io_error("read", e))?;
        Ok(file)
    }

    /// Reads `count` records of `record` bytes from `file` in pieces of whole records (at most
    /// `buffer_bytes`, at least one record), each added to `crc` if given and handed to `f`.
    fn read_records<E: From<CheckpointError>>(
        &self,
        file: &mut File,
        (record, count): (usize, u64),
        buffer_bytes: usize,
        mut crc: Option<&mut crc32fast::Hasher>,
        f: &mut dyn FnMut(&[u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        let piece = (buffer_bytes / record).max(1) * record;
        let mut buffer = vec![0u8; piece];
        let mut left = count * record as u64;
        while left > 0 {
            let len = (left as usize).min(piece);
            file.read_exact(&mut buffer[..len])
                .map_err(|e| self.io_error("read", e))?;
            if let Some(crc) = crc.as_deref_mut() {
                crc.update(&buffer[..len]);
            }
            f(&buffer[..len])?;
            left -= len as u64;
        }
        Ok(())
    }
}

/// A writer that checksums and counts what passes through it.
struct Summing<'a, W: Write> {
    inner: &'a mut W,
    crc: crc32fast::Hasher,
    bytes: u64,
}

impl<W: Write> Write for Summing<'_, W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(&buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// Writes a checkpoint at `path` durably (see the module header); `fill` writes the payload: the
/// radiosity of `header.identity.surfels` surfels, then in mid-iteration the partial sums of
/// every rank (and the axis in progress's, see [`State::axis_in_progress`]). On failure nothing is left under `path` but what was there.
pub fn write(
    path: &Path,
    header: &Header,
    buffer_bytes: usize,
    fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), CheckpointError> {
    let partial = partial_path(path);
    let result = write_partial(&partial, header, buffer_bytes, fill).and_then(|()| {
        std::fs::rename(&partial, path).map_err(|e| CheckpointError::Io {
            path: path.to_path_buf(),
            action: "rename a new checkpoint to",
            source: e,
        })
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&partial);
        return result;
    }
    // The rename is durable only once the directory is synced. Best effort, as for the other
    // outputs: the data itself is already on disk.
    // (A bare file name has an empty parent: the current directory.)
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty());
    if let Ok(dir) = File::open(parent.unwrap_or(Path::new("."))) {
        let _ = dir.sync_all();
    }
    Ok(())
}

fn write_partial(
    partial: &Path,
    header: &Header,
    buffer_bytes: usize,
    fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), CheckpointError> {
    let io = |action, source| CheckpointError::Io {
        path: partial.to_path_buf(),
        action,
        source,
    };
    let file = File::create(partial).map_err(|e| io("create", e))?;
    let mut out = BufWriter::with_capacity(buffer_bytes.max(4096), file);
    let body = encode_header(header);
    let mut prefix = Vec::with_capacity(PREFIX_LEN + body.len());
    prefix.extend_from_slice(&MAGIC);
    prefix.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    prefix.extend_from_slice(&(body.len() as u32).to_le_bytes());
    prefix.extend_from_slice(&body);
    let written = (|| {
        out.write_all(&prefix)?;
        out.write_all(&crc32fast::hash(&prefix).to_le_bytes())?;
        let mut summing = Summing {
            inner: &mut out,
            crc: crc32fast::Hasher::new(),
            bytes: 0,
        };
        fill(&mut summing)?;
        let (crc, bytes) = (summing.crc.finalize(), summing.bytes);
        if Some(bytes) != payload_len(header) {
            return Err(std::io::Error::other(format!(
                "internal error: {bytes} bytes of payload for {} surfels and {} array(s) of \
                 partial sums",
                header.identity.surfels,
                header.partial_arrays()
            )));
        }
        out.write_all(&crc.to_le_bytes())?;
        out.flush()
    })();
    written.map_err(|e| io("write", e))?;
    let file = out.into_inner().map_err(|e| io("write", e.into_error()))?;
    file.sync_all().map_err(|e| io("sync", e))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(surfels: u64, within: Option<u64>) -> Header {
        header_with(surfels, within, false)
    }

    /// An out-of-core header inside a main axis: one rank's sums and the axis's.
    fn axis_header(surfels: u64, within: u64) -> Header {
        let mut h = header_with(surfels, Some(within), true);
        h.identity.solver = Solver::OutOfCore;
        h.state.ranks = 1;
        h.state.data_groups = 0;
        h
    }

    /// The layout by groups out of core: 3 groups over 6 ranks.
    fn groups_header(surfels: u64, within: u64) -> Header {
        let mut h = header_with(surfels, Some(within), true);
        h.identity.solver = Solver::OutOfCore;
        h.state.ranks = 6;
        h.state.data_groups = 3;
        h
    }

    fn header_with(surfels: u64, within: Option<u64>, axis_in_progress: bool) -> Header {
        let mut observed = crate::solve::accelerate::Extrapolation::default();
        observed.observe(1.0, 0.5, 0.0);
        observed.observe(0.5, 0.25, 0.0);
        let extrapolation = ExtrapolationState::from(&observed);
        Header {
            identity: Identity {
                solver: Solver::InMemory,
                surfels,
                dims: [4, 5, 6],
                voxel_size: 0.25,
                directions: 49,
                directions_checksum: 7,
                channels: 3,
                accelerate: true,
                chebyshev: false,
                scene_checksum: 0xdead_beef,
            },
            state: State {
                iteration: 12,
                ranks: 2,
                previous_change: Some(0.125),
                extrapolation,
                within,
                data_groups: if within.is_some() { 2 } else { 0 },
                axis_in_progress,
                sums_in_f32: false,
                walked_forwards: false,
            },
        }
    }

    fn radiosity(n: usize) -> Vec<Radiosity> {
        (0..n)
            .map(|i| [[i as f32, 0.5, -0.0], [1e-30, f32::MAX, 3.25]])
            .collect()
    }

    /// Partial sums of rank `rank`: values whose every bit matters.
    fn sums(n: usize, rank: usize) -> Vec<Gathered> {
        (0..n)
            .map(|i| {
                let x = (i + 1) as f64 / 3.0 + rank as f64;
                [
                    [x, x * 1e-300, 0.0],
                    [x.next_up(), 1e300, f64::MIN_POSITIVE],
                ]
            })
            .collect()
    }

    /// The partial sums of array `rank` as a file of `header` keeps them: [`sums`], or in f32
    /// where its sums are (`State::sums_in_f32`).
    fn kept_sums(header: &Header, n: usize, rank: usize) -> Vec<Gathered> {
        let narrow = |g: Gathered| g.map(|side| side.map(|v| v as f32 as f64));
        match header.state.sums_in_f32 {
            true => sums(n, rank).into_iter().map(narrow).collect(),
            false => sums(n, rank),
        }
    }

    /// The older radiosity of a Chebyshev checkpoint: other values than [`radiosity`]'s.
    fn older(n: usize) -> Vec<Radiosity> {
        radiosity(n).iter().rev().map(|b| [b[1], b[0]]).collect()
    }

    fn write_one(path: &Path, header: &Header, values: &[Radiosity]) {
        write(path, header, 64, |w| {
            let mut bytes = [0u8; RADIOSITY_LEN];
            let older = older(values.len());
            let arrays = [values, &older[..]];
            for b in arrays[..header.radiosity_arrays() as usize]
                .iter()
                .copied()
                .flatten()
            {
                encode_radiosity(b, &mut bytes);
                w.write_all(&bytes)?;
            }
            let mut bytes = [0u8; PARTIAL_LEN];
            let len = header.partial_len();
            for rank in 0..header.partial_arrays() as usize {
                for g in kept_sums(header, values.len(), rank) {
                    match header.state.sums_in_f32 {
                        true => encode_radiosity(&g.map(|s| s.map(|v| v as f32)), &mut bytes),
                        false => encode_gathered(&g, &mut bytes),
                    }
                    w.write_all(&bytes[..len])?;
                }
            }
            Ok(())
        })
        .unwrap();
    }

    fn bits(v: &[Radiosity]) -> Vec<u32> {
        v.iter().flatten().flatten().map(|x| x.to_bits()).collect()
    }

    fn sum_bits(v: &[Gathered]) -> Vec<u64> {
        v.iter().flatten().flatten().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn round_trip_in_memory_and_streamed() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.bin");
        // The out-of-core layouts also with their sums in f32 (format version 7), which the
        // readers hand out in f64, the same values.
        let narrow = |mut h: Header| {
            h.state.sums_in_f32 = true;
            h
        };
        for h in [
            header(37, None),
            header(37, Some(17)),
            axis_header(37, 17),
            groups_header(37, 17),
            narrow(axis_header(37, 17)),
            narrow(groups_header(37, 17)),
        ] {
            let within = h.state.within;
            let values = radiosity(37);
            write_one(&path, &h, &values);
            assert!(!partial_path(&path).exists());
            let bytes = std::fs::read(&path).unwrap();
            for rank in 0..3 {
                let got = parse(&path, &bytes, rank).unwrap();
                assert_eq!(got.header, h);
                assert_eq!(bits(&got.radiosity), bits(&values));
                let ranks = h.partial_ranks() as usize;
                let want =
                    (within.is_some() && rank < ranks).then(|| sum_bits(&kept_sums(&h, 37, rank)));
                assert_eq!(got.partial.as_deref().map(sum_bits), want);
            }
            let file = CheckpointFile::open(&path).unwrap();
            assert_eq!(file.header, h);
            let mut streamed = Vec::new();
            file.read_radiosity::<CheckpointError>(50, |piece| {
                assert_eq!(piece.len() % RADIOSITY_LEN, 0);
                streamed.extend(piece.chunks_exact(RADIOSITY_LEN).map(decode_radiosity));
                Ok(())
            })
            .unwrap();
            assert_eq!(bits(&streamed), bits(&values));
            // Streamed whole: the ranks' sums, then the axis in progress's, each exactly.
            let (mut ranks, mut axis) = (Vec::new(), Vec::new());
            let take = |into: &mut Vec<Gathered>, piece: &[u8]| {
                assert_eq!(piece.len() % PARTIAL_LEN, 0);
                into.extend(piece.chunks_exact(PARTIAL_LEN).map(decode_gathered));
                Ok::<(), CheckpointError>(())
            };
            file.read_payload::<CheckpointError>(
                100,
                |_| Ok(()),
                |_| panic!("no older radiosity here"),
                |piece| take(&mut ranks, piece),
                |piece| take(&mut axis, piece),
            )
            .unwrap();
            let ranks_want: Vec<u64> = (0..h.partial_ranks() as usize)
                .flat_map(|rank| sum_bits(&kept_sums(&h, 37, rank)))
                .collect();
            assert_eq!(sum_bits(&ranks), ranks_want);
            let axis_want: Vec<u64> = (h.partial_ranks()..h.partial_arrays())
                .flat_map(|array| sum_bits(&kept_sums(&h, 37, array as usize)))
                .collect();
            assert_eq!(sum_bits(&axis), axis_want);
            // Each array alone, after the whole read checked the checksum.
            for array in 0..h.partial_arrays() {
                let mut one = Vec::new();
                file.read_array::<CheckpointError>(array, 100, |piece| take(&mut one, piece))
                    .unwrap();
                assert_eq!(sum_bits(&one), sum_bits(&kept_sums(&h, 37, array as usize)));
            }
            assert!(file
                .read_array::<CheckpointError>(h.partial_arrays(), 100, |_| Ok(()))
                .is_err());
        }
        let groups = groups_header(37, 17);
        assert_eq!((groups.partial_ranks(), groups.partial_arrays()), (3, 6));
        // f32 sums take half the bytes: the last file written above has them, against the
        // same layout in f64.
        let narrow_len = std::fs::metadata(&path).unwrap().len();
        write_one(&path, &groups, &radiosity(37));
        let wide_len = std::fs::metadata(&path).unwrap().len();
        assert_eq!(
            wide_len - narrow_len,
            37 * 6 * (PARTIAL_LEN - PARTIAL32_LEN) as u64
        );
    }

    /// An older file made from a current boundary one: the version, without the fields later
    /// versions added at the header's end (version 6 the precision of the sums, version 3
    /// also the axis in progress, version 2 also the layout of the sums, version 1 also the
    /// position), checksum redone.
    fn as_version(current: &[u8], version: u32) -> Vec<u8> {
        let header_len = u32::from_le_bytes(current[12..16].try_into().unwrap()) as usize;
        let end = PREFIX_LEN + header_len;
        // Version 6 added 24 bytes (the Chebyshev state and whether the run allows it),
        // version 7 four (whether the sums are f32).
        let cut = match version {
            1 => 48,
            2 => 36,
            3 => 32,
            4 | 5 => 28,
            6 => 4,
            _ => 0,
        };
        let mut old = current[..end - cut].to_vec();
        old[8..12].copy_from_slice(&version.to_le_bytes());
        old[12..16].copy_from_slice(&((header_len - cut) as u32).to_le_bytes());
        let crc = crc32fast::hash(&old);
        old.extend_from_slice(&crc.to_le_bytes());
        old.extend_from_slice(&current[end + 4..]);
        old
    }

    #[test]
    fn versions_1_to_7_are_read_and_an_unknown_version_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.bin");
        let h = header(5, None);
        write_one(&path, &h, &radiosity(5));
        let current = std::fs::read(&path).unwrap();
        for old in [1, 2, 3, 4, 5, 6, 7] {
            let bytes = as_version(&current, old);
            let got = parse(&path, &bytes, 0).unwrap();
            assert_eq!(got.header, h);
            assert_eq!(bits(&got.radiosity), bits(&radiosity(5)));
            std::fs::write(&path, &bytes).unwrap();
            assert_eq!(CheckpointFile::open(&path).unwrap().header, h);
        }
        // A mid-iteration file of version 3 (an out-of-core one between two main axes had this
        // layout): its sums are read as they were written.
        let mid = header(5, Some(2));
        write_one(&path, &mid, &radiosity(5));
        let v3 = as_version(&std::fs::read(&path).unwrap(), 3);
        let got = parse(&path, &v3, 1).unwrap();
        let mut walked = mid.clone();
        walked.state.walked_forwards = true;
        assert_eq!(got.header, walked);
        // Iteration 13 (12 done): an odd one, walked in the same order since version 8.
        assert!(!walked.state.walked_otherwise());
        walked.state.iteration = 13;
        assert!(walked.state.walked_otherwise());
        let mut v8 = walked.clone();
        v8.state.walked_forwards = false;
        assert!(!v8.state.walked_otherwise());
        assert_eq!(
            got.partial.as_deref().map(sum_bits),
            Some(sum_bits(&sums(5, 1)))
        );
        // The layout by groups out of core is version 5's: in a version 4 file it is damage.
        let groups = groups_header(5, 2);
        write_one(&path, &groups, &radiosity(5));
        let v4 = as_version(&std::fs::read(&path).unwrap(), 4);
        assert!(parse(&path, &v4, 0).unwrap_err().is_bad_input());
        let v1 = as_version(&current, 1);
        for version in [0u32, FORMAT_VERSION + 1, 99] {
            let mut b = v1.clone();
            b[8..12].copy_from_slice(&version.to_le_bytes());
            let err = parse(&path, &b, 0).unwrap_err();
            assert!(err.is_bad_input());
            let text = err.to_string();
            assert!(
                text.contains("checkpoint.bin") && text.contains(&format!("version {version}")),
                "{text}"
            );
        }
    }

    /// A Chebyshev semi-iteration's checkpoint (format version 6) holds the older radiosity
    /// after the radiosity, and its state in the header; whole reads give both back bit for
    /// bit, on one rank, handed between ranks (`head`) and streamed (the out-of-core solvers).
    #[test]
    fn a_chebyshev_checkpoint_keeps_the_older_radiosity() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.bin");
        for within in [None, Some(17)] {
            let mut h = header(37, within);
            h.identity.chebyshev = true;
            h.state.extrapolation.chebyshev = Some((0.625, 3));
            assert_eq!(h.radiosity_arrays(), 2);
            write_one(&path, &h, &radiosity(37));
            let bytes = std::fs::read(&path).unwrap();
            let got = parse(&path, &bytes, 1).unwrap();
            assert_eq!(got.header, h);
            assert_eq!(bits(&got.radiosity), bits(&radiosity(37)));
            assert_eq!(got.older.as_deref().map(bits), Some(bits(&older(37))));
            assert_eq!(
                got.partial.as_deref().map(sum_bits),
                within.map(|_| sum_bits(&sums(37, 1)))
            );
            let shared = parse_head(&path, head(&bytes, &h)).unwrap();
            assert_eq!(bits(&shared.radiosity), bits(&radiosity(37)));
            assert_eq!(shared.older.as_deref().map(bits), Some(bits(&older(37))));
            let file = CheckpointFile::open(&path).unwrap();
            let (mut first, mut second) = (Vec::new(), Vec::new());
            let take = |into: &mut Vec<Radiosity>, piece: &[u8]| {
                into.extend(piece.chunks_exact(RADIOSITY_LEN).map(decode_radiosity));
                Ok::<(), CheckpointError>(())
            };
            file.read_payload::<CheckpointError>(
                50,
                |piece| take(&mut first, piece),
                |piece| take(&mut second, piece),
                |_| Ok(()),
                |_| Ok(()),
            )
            .unwrap();
            assert_eq!(bits(&first), bits(&radiosity(37)));
            assert_eq!(bits(&second), bits(&older(37)));
            // The radiosity alone, the older array passed over (and checksummed).
            let mut alone = Vec::new();
            file.read_radiosity::<CheckpointError>(100, |piece| take(&mut alone, piece))
                .unwrap();
            assert_eq!(bits(&alone), bits(&radiosity(37)));
        }
        // A Chebyshev state in a run that does not allow it is damage, as is a ratio of 1.
        for (allowed, ratio) in [(false, 0.625), (true, 1.0)] {
            let mut h = header(5, None);
            h.identity.chebyshev = allowed;
            h.state.extrapolation.chebyshev = Some((ratio, 0));
            write_one(&path, &h, &radiosity(5));
            let err = parse(&path, &std::fs::read(&path).unwrap(), 0).unwrap_err();
            assert!(err.to_string().contains("does not decode"), "{err}");
        }
        // Without a running Chebyshev the file holds one radiosity array, as before.
        let mut h = header(5, None);
        h.identity.chebyshev = true;
        write_one(&path, &h, &radiosity(5));
        let got = parse(&path, &std::fs::read(&path).unwrap(), 0).unwrap();
        assert_eq!((got.header, got.older), (h, None));
    }

    #[test]
    fn every_damage_is_named_and_never_panics() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.bin");
        for h in [
            header(9, None),
            header(9, Some(3)),
            axis_header(9, 3),
            groups_header(9, 3),
        ] {
            write_one(&path, &h, &radiosity(9));
            let good = std::fs::read(&path).unwrap();
            // Every truncation and every single-byte flip is refused, by both readers.
            let mut cases: Vec<Vec<u8>> = (0..good.len()).map(|n| good[..n].to_vec()).collect();
            for at in 0..good.len() {
                let mut b = good.clone();
                b[at] ^= 0x10;
                cases.push(b);
            }
            let mut longer = good.clone();
            longer.push(0);
            cases.push(longer);
            for bytes in cases {
                let err = parse(&path, &bytes, 1).unwrap_err().to_string();
                assert!(err.contains("checkpoint.bin"), "{err}");
                std::fs::write(&path, &bytes).unwrap();
                let streamed = CheckpointFile::open(&path).and_then(|f| {
                    f.read_radiosity::<CheckpointError>(40, |_| Ok(()))?;
                    Ok(())
                });
                assert!(streamed.is_err(), "{} bytes accepted", bytes.len());
            }
        }
    }

    #[test]
    fn a_failed_write_keeps_the_earlier_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.bin");
        write_one(&path, &header(3, None), &radiosity(3));
        let before = std::fs::read(&path).unwrap();
        let err = write(&path, &header(3, Some(1)), 64, |w| {
            w.write_all(&[0u8; 30])?;
            Err(std::io::Error::other("disk full"))
        })
        .unwrap_err();
        assert!(err.to_string().contains("disk full"), "{err}");
        assert_eq!(std::fs::read(&path).unwrap(), before);
        assert!(!partial_path(&path).exists());
    }
}
