//! The solver's working copies of the surfels: three copies sorted by axis (see the `outcore`
//! module header), each with its row histogram, its canonical indices, and where each canonical
//! surfel sits in it.
//!
//! A copy is made by a distribution sort that never holds more than one bucket: a first pass
//! over the source counts the surfels of every row `(x_m, x_v)` (the histogram the bands are cut
//! from later); consecutive rows are grouped into buckets that fit the budget; a second pass
//! appends each surfel, with its coverage (from its voxel-mates, adjacent in the source), to its
//! bucket's file; then each bucket is sorted in memory and appended to the copy. Buckets are
//! ranges of rows, so the copy comes out sorted by `(x_m, x_v, x_u, canonical index)`.

use super::budget::MemoryPlan;
use super::files::{
    encode_static, IoCounters, RecordFile, SeqReader, SeqWriter, StaticRecord, LIGHT32_LEN,
    RADIOSITY_LEN, STATIC_LEN,
};
use super::framed::{FrameSizer, FramedWriter};
use super::packed_index::IndexWriter;
use super::scatter::Scatter;
use super::source::{SurfelSource, VoxelGroups};
use super::OocError;
use crate::solve::propagate::PropSurfel;
use std::path::{Path, PathBuf};
use tempfile::TempDir;

/// One axis copy.
pub struct AxisCopy {
    /// Main axis and the two others (`u = main + 1`, `v = main + 2`, modulo 3).
    pub main: usize,
    pub u: usize,
    pub v: usize,
    /// Layers (voxels along the main axis) and rows per layer (voxels along `v`).
    pub layers: usize,
    pub rows: usize,
    /// Static records, in copy order, in compressed frames (`super::framed`).
    pub statics: PathBuf,
    /// Where each frame of `statics` starts.
    pub statics_index: PathBuf,
    /// What the lines carry of the current radiosity, in copy order. One file serves the three
    /// copies in turn: it is written for a copy just before that copy's directions are solved
    /// (`solver::OutOfCore::step`), which saves two copies' worth of it on disk (48 bytes a
    /// surfel).
    pub radiosity: PathBuf,
    /// Canonical index of each record, in copy order (u32).
    pub ids: PathBuf,
    /// Position in this copy of each canonical surfel, in canonical order (u32).
    pub positions: PathBuf,
    /// Surfels per row, `layers x rows` u32 values, layer-major.
    pub histogram: PathBuf,
    /// Index of the first record of each layer, and the total.
    pub layer_start: Vec<u64>,
}

impl AxisCopy {
    /// Loads the row histogram (held while this copy's directions are solved).
    pub fn load_histogram(&self, plan: &MemoryPlan) -> Result<Vec<u32>, OocError> {
        let mut reader = SeqReader::<4>::open(&self.histogram, plan.io_bytes)?;
        let mut h = Vec::with_capacity(self.layers * self.rows);
        while let Some(w) = reader.next_record()? {
            h.push(u32::from_le_bytes(w));
        }
        Ok(h)
    }
}

/// The working copies of one solve, in a temporary directory removed when dropped.
pub struct WorkSet {
    pub dir: TempDir,
    pub copies: Vec<AxisCopy>,
    /// Radiosity in canonical order.
    pub canonical_radiosity: PathBuf,
    /// Light gathered by the directions of the axis being solved, in that copy's order (the
    /// files serve the three copies in turn): a pass over an axis's copy (one direction, or
    /// several gathered together) reads the light of the directions before it from one file
    /// and writes it with its own to the other (the axis's first pass writes file 0), so the
    /// light of the directions done is whole on disk between any two passes.
    pub gathered: [PathBuf; 2],
    /// Light gathered this iteration by the axes done so far, in canonical order.
    pub canonical_gathered: PathBuf,
    /// Surfels and distinct voxels.
    pub count: u64,
    pub voxels: u64,
}

impl WorkSet {
    /// Removes every work file but the canonical radiosity, once the solve is over: the
    /// outputs are written from that file and the source alone, and the files they make would
    /// otherwise be added to the work files' peak on the disk (on a building of 7 million
    /// surfels the results file, 96 bytes a surfel, was written beside 261 bytes a surfel of
    /// files no longer read).
    pub fn keep_only_the_answer(&self) {
        super::files::remove_all_but(self.dir.path(), Some(&self.canonical_radiosity));
    }

    /// Bytes the work files will still take on the disk beyond what they take now, at their
    /// peak, with `also_per_surfel` of the solve's own files: the peak of
    /// [`DISK_BYTES_PER_SURFEL`] with the static records at the size they were written, less
    /// the blocks every file of the work directory holds now (files made at their full length
    /// hold none until written).
    pub fn disk_still_needed(&self, also_per_surfel: u64) -> u64 {
        let statics: u64 = self
            .copies
            .iter()
            .flat_map(|c| [&c.statics, &c.statics_index])
            .filter_map(|path| std::fs::metadata(path).ok())
            .map(|m| m.len())
            .sum();
        let peak = self.count * (DISK_BYTES_PER_SURFEL - 3 * STATIC_LEN as u64 + also_per_surfel)
            + statics;
        peak.saturating_sub(super::files::allocated_bytes(self.dir.path()))
    }
}

/// Bytes a surfel of the files the solve adds to the work set's own during the iterations:
/// the radiosity before each update, kept for the tail extrapolation, and with the direct-light
/// pass its light, in canonical order, and the reflected part the lines carry (`solver`).
pub fn solve_files_per_surfel(extrapolate: bool, direct: bool) -> u64 {
    let previous = if extrapolate { RADIOSITY_LEN } else { 0 };
    let direct = if direct {
        LIGHT32_LEN + RADIOSITY_LEN
    } else {
        0
    };
    (previous + direct) as u64
}

/// Key of a voxel in copy order: `(x_m, x_v, x_u)` packed (each below 2^21).
#[inline]
fn row_of(copy: &AxisCopy, voxel: [i32; 3]) -> u64 {
    voxel[copy.main] as u64 * copy.rows as u64 + voxel[copy.v] as u64
}

/// Builds the three copies of `source` in a new temporary directory under `parent`.
/// `also_per_surfel` is what the solve's own files add to the work set's peak, a surfel
/// ([`solve_files_per_surfel`]): the disk must hold both.
pub fn build(
    source: &dyn SurfelSource,
    plan: &MemoryPlan,
    parent: &Path,
    also_per_surfel: u64,
    io: &mut IoCounters,
) -> Result<WorkSet, OocError> {
    check_disk(parent, source.info().count, also_per_surfel, || {
        static_bytes_in_frames(source, plan)
    })?;
    let dir = tempfile::Builder::new()
        .prefix(".voxrad-work-")
        .tempdir_in(parent)
        .map_err(|e| OocError::io(parent, "create a work directory in", e))?;
    let info = source.info();
    let dims = info.grid.dims.map(|d| d as usize);
    let count = info.count;
    let mut copies = Vec::with_capacity(3);
    let mut voxels = 0;
    let copy_radiosity = dir.path().join("radiosity-axis.bin");
    RecordFile::create(&copy_radiosity)?.set_len(count * RADIOSITY_LEN as u64)?;
    for main in 0..3 {
        let (u, v) = ((main + 1) % 3, (main + 2) % 3);
        let name = |what: &str| dir.path().join(format!("{what}-{main}.bin"));
        let mut copy = AxisCopy {
            main,
            u,
            v,
            layers: dims[main],
            rows: dims[v],
            statics: name("static"),
            statics_index: name("static-index"),
            radiosity: copy_radiosity.clone(),
            ids: name("ids"),
            positions: name("positions"),
            histogram: name("histogram"),
            layer_start: Vec::new(),
        };
        // Pass 1: the row histogram (and, once, the voxel count).
        let mut histogram = vec![0u32; copy.layers * copy.rows];
        let mut seen = 0u64;
        let mut last_voxel = None;
        for s in source.stream(plan.io_bytes as u64)? {
            let s = s?;
            check_voxel(source, &s.voxel, info.grid.dims)?;
            histogram[row_of(&copy, s.voxel) as usize] += 1;
            if main == 0 && last_voxel != Some(s.voxel) {
                voxels += 1;
                last_voxel = Some(s.voxel);
            }
            seen += 1;
        }
        io.read += seen * crate::storage::RECORD_LEN as u64;
        let mut out = SeqWriter::create(&copy.histogram, plan.io_bytes)?;
        for h in &histogram {
            out.write(&h.to_le_bytes())?;
        }
        io.written += out.finish()?;
        let mut start = 0u64;
        copy.layer_start.push(0);
        for layer in histogram.chunks(copy.rows.max(1)).take(copy.layers) {
            start += layer.iter().map(|&h| h as u64).sum::<u64>();
            copy.layer_start.push(start);
        }
        // Buckets: runs of consecutive rows that fit the budget.
        let mut bucket_rows = vec![0u64];
        let mut bucket_sizes = vec![0u64];
        let mut filled = 0u64;
        for (row, &h) in histogram.iter().enumerate() {
            let h = h as u64;
            if h > plan.sort_records {
                return Err(OocError::BudgetTooSmall {
                    budget: plan.budget,
                    needed: plan.budget - plan.working
                        + 2 * h * super::budget::SORT_BYTES_PER_RECORD,
                    what: format!("sorting a row of {h} surfels along axis {u}"),
                });
            }
            if filled + h > plan.sort_records {
                bucket_rows.push(row as u64);
                bucket_sizes.push(0);
                filled = 0;
            }
            filled += h;
            *bucket_sizes.last_mut().expect("one bucket at least") += h;
        }
        drop(histogram);
        // Pass 2: distribute into bucket files.
        let buffer = plan.bucket_buffer(bucket_rows.len() as u64);
        let mut buckets = Vec::with_capacity(bucket_rows.len());
        for b in 0..bucket_rows.len() {
            buckets.push(SeqWriter::create(
                &dir.path().join(format!("bucket-{main}-{b}.tmp")),
                buffer,
            )?);
        }
        let records = for_each_static_record(source, plan, |voxel, record| {
            let row = row_of(&copy, voxel);
            let b = bucket_rows.partition_point(|&first| first <= row) - 1;
            buckets[b].write(record)
        })?;
        io.read += records * crate::storage::RECORD_LEN as u64;
        let bucket_paths: Vec<PathBuf> = buckets.iter().map(|b| b.path().to_path_buf()).collect();
        for b in buckets {
            io.written += b.finish()?;
        }
        // Sort each bucket, append it to the copy, and note where each surfel went.
        let mut statics = FramedWriter::create(&copy.statics, &copy.statics_index, plan.io_bytes)?;
        let mut ids = IndexWriter::create(&copy.ids, plan.io_bytes)?;
        let chunks = count.div_ceil(plan.chunk_surfels.max(1));
        let mut positions = Scatter::<4>::new(
            dir.path(),
            &format!("positions-{main}"),
            count,
            plan.chunk_surfels,
            plan.bucket_buffer(chunks),
        )?;
        let mut entries: Vec<(u64, u32, [u8; STATIC_LEN])> = Vec::new();
        let mut position = 0u64;
        for (path, &size) in bucket_paths.iter().zip(&bucket_sizes) {
            entries.clear();
            // Exactly the bucket's size: growth by doubling could overshoot the budget.
            entries.reserve_exact(size as usize);
            let mut reader = SeqReader::<STATIC_LEN>::open(path, plan.io_bytes)?;
            while let Some(bytes) = reader.next_record()? {
                let r = super::files::decode_static(&bytes);
                let key = row_of(&copy, r.prop.voxel) * dims[u] as u64 + r.prop.voxel[u] as u64;
                entries.push((key, r.id, bytes));
            }
            io.read += entries.len() as u64 * STATIC_LEN as u64;
            entries.sort_unstable_by_key(|e| (e.0, e.1));
            for (_, id, bytes) in &entries {
                statics.write(bytes)?;
                ids.push(*id)?;
                positions.push(*id as u64, &(position as u32).to_le_bytes())?;
                position += 1;
            }
            std::fs::remove_file(path).map_err(|e| OocError::io(path, "remove", e))?;
        }
        drop(entries);
        io.written += statics.finish()? + ids.finish()?;
        let mut chunks = positions.into_chunks()?;
        let mut out = IndexWriter::create(&copy.positions, plan.io_bytes)?;
        let mut chunk = Vec::new();
        while let Some((_, len)) = {
            chunk.clear();
            chunk.resize(plan.chunk_surfels.min(count) as usize, 0u32);
            chunks.next_chunk(|at, value| chunk[at] = u32::from_le_bytes(*value))?
        } {
            for &p in &chunk[..len as usize] {
                out.push(p)?;
            }
        }
        io.written += out.finish()? + chunks.written;
        io.read += chunks.read;
        copies.push(copy);
    }
    let canonical_radiosity = dir.path().join("radiosity-canonical.bin");
    RecordFile::create(&canonical_radiosity)?.set_len(count * RADIOSITY_LEN as u64)?;
    let gathered = [0, 1].map(|k| dir.path().join(format!("gathered-{k}.bin")));
    for path in &gathered {
        RecordFile::create(path)?.set_len(count * LIGHT32_LEN as u64)?;
    }
    let canonical_gathered = dir.path().join("gathered-canonical.bin");
    RecordFile::create(&canonical_gathered)?.set_len(count * LIGHT32_LEN as u64)?;
    Ok(WorkSet {
        dir,
        copies,
        canonical_radiosity,
        gathered,
        canonical_gathered,
        count,
        voxels,
    })
}

/// A surfel outside the grid would index past the histogram: refuse it by name.
fn check_voxel(
    source: &dyn SurfelSource,
    voxel: &[i32; 3],
    dims: [u32; 3],
) -> Result<(), OocError> {
    if (0..3).all(|k| voxel[k] >= 0 && (voxel[k] as u64) < dims[k] as u64) {
        return Ok(());
    }
    Err(OocError::BadData {
        source_name: source.describe(),
        what: format!("a surfel lies in voxel {voxel:?}, outside the grid of {dims:?} voxels"),
    })
}

/// Bytes of work files per surfel at their peak, with the static records at their full size:
/// the three copies' static records, indices and positions, the radiosity file they share, the
/// canonical radiosity, the canonical sum, and then whichever is larger of a pass over an axis
/// (its two files of axis light) and a fold or a checkpoint inside an axis (the one file of axis
/// light that holds the light and the buckets of one permutation of it: the other is empty
/// between passes). Compressed (`super::framed`) the static records take about a tenth of
/// their full size; `check_disk` counts them so only where the files would not fit otherwise.
pub const DISK_BYTES_PER_SURFEL: u64 = 3 * (STATIC_LEN as u64 + 8)
    + 2 * RADIOSITY_LEN as u64
    + LIGHT32_LEN as u64
    + LIGHT32_LEN as u64
    + (8 + LIGHT32_LEN as u64);

/// Refuses to start when the work files of `surfels` surfels, with `also_per_surfel` bytes a
/// surfel of the solve's own files, cannot fit on the disk of `parent`: a long solve must not
/// find out hours later. Where they would not fit with their
/// static records at full size, `static_bytes` is asked what those records take compressed in
/// one order (the source's), and each copy is counted at half as much again: the copies' orders
/// put other neighbours side by side (measured on a building of 7 million surfels: the copies
/// took 1.00 to 1.35 times the source order's bytes in byte planes, 0.94 to 1.24 as records).
fn check_disk(
    parent: &Path,
    surfels: u64,
    also_per_surfel: u64,
    static_bytes: impl FnOnce() -> Result<u64, OocError>,
) -> Result<(), OocError> {
    let Some(free) = free_bytes(parent) else {
        return Ok(());
    };
    let per_surfel = DISK_BYTES_PER_SURFEL + also_per_surfel;
    if free >= surfels * per_surfel {
        return Ok(());
    }
    let statics = static_bytes()?;
    let needed = surfels * (per_surfel - 3 * STATIC_LEN as u64) + 3 * (statics * 3 / 2);
    tracing::info!(
        static_bytes_per_surfel = statics as f64 / surfels.max(1) as f64,
        needed = super::budget::format_bytes(needed),
        free = super::budget::format_bytes(free),
        "work files counted with their static records compressed"
    );
    check_free_space(parent, needed)
}

/// The bytes the static records of `source` take in frames, in its own order: one pass over it,
/// compressing without writing.
fn static_bytes_in_frames(source: &dyn SurfelSource, plan: &MemoryPlan) -> Result<u64, OocError> {
    let failed = |e| OocError::io(Path::new(&source.describe()), "compress", e);
    let mut sizer = FrameSizer::default();
    for_each_static_record(source, plan, |_, record| sizer.add(record).map_err(failed))?;
    sizer.finish().map_err(failed)
}

/// Hands `f` the static record of every surfel of `source`, in its order, with its voxel (the
/// coverage and the sides of its voxel-mates found from the voxel's surfels, adjacent in a
/// source); returns the number of records.
fn for_each_static_record(
    source: &dyn SurfelSource,
    plan: &MemoryPlan,
    mut f: impl FnMut([i32; 3], &[u8; STATIC_LEN]) -> Result<(), OocError>,
) -> Result<u64, OocError> {
    let mut groups = VoxelGroups::new(source.stream(plan.io_bytes as u64)?);
    let mut group = Vec::new();
    let mut id = 0u32;
    let mut record = [0u8; STATIC_LEN];
    while groups.next_group(&mut group)? {
        let props = PropSurfel::of_voxel(&group, &source.info().materials);
        for (s, prop) in group.iter().zip(props) {
            encode_static(&StaticRecord { prop, id }, &mut record);
            f(s.voxel, &record)?;
            id += 1;
        }
    }
    Ok(id as u64)
}

/// Bytes an out-of-core checkpoint takes per surfel at most with `sum_arrays` arrays of
/// partial sums: its radiosity and the one before (Chebyshev), and the sums (`checkpoint::file`;
/// f32 since format version 7). One process keeps two arrays, the light gathered so far and
/// that of the axis in progress (96 bytes a surfel in all, 144 before the f32 sums); the data
/// and hybrid modes two a group.
pub(crate) fn checkpoint_bytes_per_surfel(sum_arrays: u64) -> u64 {
    2 * crate::checkpoint::file::RADIOSITY_LEN as u64
        + sum_arrays * crate::checkpoint::file::PARTIAL32_LEN as u64
}

/// The disk that the checkpoints at `checkpoint` of a solve of `count` surfels, `per_surfel`
/// bytes each ([`checkpoint_bytes_per_surfel`]), may still take on the file system of
/// `work_dir`: two copies (the new one is written beside the old, then renamed over it) less
/// the one already there; 0 where they lie on another file system.
pub(crate) fn checkpoint_growth(
    checkpoint: &Path,
    work_dir: &Path,
    count: u64,
    per_surfel: u64,
) -> u64 {
    use std::os::unix::fs::MetadataExt;
    let device = |p: &Path| std::fs::metadata(p).ok().map(|m| m.dev());
    let out = checkpoint.parent().unwrap_or(Path::new("."));
    match (device(out), device(work_dir)) {
        (Some(a), Some(b)) if a == b => {
            let there = std::fs::metadata(checkpoint).map_or(0, |m| m.len());
            (2 * count * per_surfel).saturating_sub(there)
        }
        _ => 0,
    }
}

/// Refuses to start when `needed` bytes of work files cannot fit on the disk of `parent`.
pub(crate) fn check_free_space(parent: &Path, needed: u64) -> Result<(), OocError> {
    match free_bytes(parent) {
        Some(free) if free < needed => Err(OocError::DiskTooSmall {
            path: parent.to_path_buf(),
            needed,
            free,
        }),
        _ => Ok(()),
    }
}

/// Bytes available to this user on the filesystem of `dir` (`None` if the system will not say).
pub(crate) fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::fd::AsRawFd;
    let file = std::fs::File::open(dir).ok()?;
    // SAFETY: a zeroed statvfs is a valid value for fstatvfs to fill; the descriptor is open for
    // the duration of the call.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::fstatvfs(file.as_raw_fd(), &mut st) } != 0 {
        return None;
    }
    Some(st.f_bavail as u64 * st.f_frsize as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checkpoints_on_the_work_disk_take_two_copies_less_the_one_there() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let work = dir.path().join("work");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&work).unwrap();
        let checkpoint = out.join("checkpoint.bin");
        // One process: the radiosity, the one before and two arrays of sums, in f32.
        let per = checkpoint_bytes_per_surfel(2);
        assert_eq!(per, 96);
        let two = 2 * 1000 * per;
        assert_eq!(checkpoint_growth(&checkpoint, &work, 1000, per), two);
        std::fs::write(&checkpoint, vec![0u8; 5000]).unwrap();
        assert_eq!(checkpoint_growth(&checkpoint, &work, 1000, per), two - 5000);
        // Where the file system cannot be told, nothing is set aside.
        let gone = dir.path().join("nowhere").join("checkpoint.bin");
        assert_eq!(checkpoint_growth(&gone, &work, 1000, per), 0);
    }

    #[test]
    fn work_files_that_cannot_fit_are_refused_up_front() {
        let dir = tempfile::tempdir().unwrap();
        let free = free_bytes(dir.path()).expect("statvfs of a temporary directory");
        assert!(free > 0);
        let unasked = || -> Result<u64, OocError> { panic!("the records' size asked for") };
        assert!(check_disk(dir.path(), 1000, 0, unasked).is_ok());
        // Twice what is free: other tests running beside this one create and delete files, and
        // one more surfel than fits was refused or not by a few hundred bytes freed meanwhile.
        let too_many = 2 * (free / DISK_BYTES_PER_SURFEL + 1);
        let full_size = Ok(too_many * STATIC_LEN as u64);
        let e = check_disk(dir.path(), too_many, 0, || full_size).unwrap_err();
        assert!(e.to_string().contains("free"), "{e}");
        // The records compressed to nothing: the rest of the files, for twice as many surfels
        // as they alone would fit, are refused.
        let bare = DISK_BYTES_PER_SURFEL - 3 * STATIC_LEN as u64;
        let too_many = 2 * (free / bare + 1);
        let e = check_disk(dir.path(), too_many, 0, || Ok(0)).unwrap_err();
        assert!(e.to_string().contains("free"), "{e}");
        // Admitted with the records compressed where they would not fit at full size: as many
        // surfels as fit in four fifths of the free space with 20 bytes of records a surfel in
        // each copy.
        let compressed = 20;
        let per_surfel = DISK_BYTES_PER_SURFEL - 3 * STATIC_LEN as u64 + 3 * compressed * 3 / 2;
        let surfels = free / 5 * 4 / per_surfel;
        assert!(
            surfels * DISK_BYTES_PER_SURFEL > free,
            "free space too small to tell"
        );
        let statics = Ok(surfels * compressed);
        assert!(check_disk(dir.path(), surfels, 0, || statics).is_ok());
    }

    #[test]
    fn the_solves_own_files_are_counted_with_the_work_set() {
        let dir = tempfile::tempdir().unwrap();
        let free = free_bytes(dir.path()).expect("statvfs of a temporary directory");
        // Surfels whose work set fits in nine tenths of the free space, and whose tail
        // extrapolation and direct-light files (72 bytes a surfel) make it a tenth too large.
        let also = solve_files_per_surfel(true, true);
        assert_eq!(also, 72);
        let surfels = free / (DISK_BYTES_PER_SURFEL + also / 2);
        let unasked = || -> Result<u64, OocError> { panic!("the records' size asked for") };
        assert!(check_disk(dir.path(), surfels, 0, unasked).is_ok());
        let full_size = Ok(surfels * STATIC_LEN as u64);
        let e = check_disk(dir.path(), surfels, also, || full_size).unwrap_err();
        assert!(e.to_string().contains("free"), "{e}");
    }
}
