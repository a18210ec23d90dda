//! Where the out-of-core solver's surfels come from: a shard set on disk (the normal case) or a
//! surfel set already in memory (for tests and for the OBJ path under a budget), read as one
//! stream in the *canonical order*, the order the solver's results come out in.
//!
//! The canonical order keeps the surfels of one voxel together (both a shard set's lexicographic
//! order and the voxelizer's Morton order do), which is what [`VoxelGroups`] relies on to give
//! each surfel its voxel-mates (for its coverage) without an index.
//!
//! Besides the stream, a source hands over the surfels of chosen voxels
//! ([`SurfelSource::pick_voxels`], for the direct-light pass's parts): by default from the
//! stream; a shard set sorted in the voxels' order searches its shards instead
//! (`outcore::pick`, which owns both ways).

use super::OocError;
use crate::scene::Material;
use crate::solve::enclosure::{Enclosure, Verdict};
use crate::storage::{Manifest, ShardEntry, ShardReader, WindowedRecords};
use crate::voxel::{Grid, Surfel, SurfelSet};
use std::path::{Path, PathBuf};

/// What every consumer of a source needs besides the surfels.
#[derive(Clone, Debug)]
pub struct SourceInfo {
    pub grid: Grid,
    pub normals: Vec<[f32; 3]>,
    pub materials: Vec<Material>,
    /// Number of surfels.
    pub count: u64,
}

pub type SurfelStream<'a> = Box<dyn Iterator<Item = Result<Surfel, OocError>> + 'a>;

/// A source of surfels in canonical order that can be read any number of times.
pub trait SurfelSource: Sync {
    fn info(&self) -> &SourceInfo;
    /// A fresh pass over all surfels. A shard set checks each shard's checksum at its end, so a
    /// consumer must not trust what it read if the stream ends with an error.
    fn stream(&self, window_bytes: u64) -> Result<SurfelStream<'_>, OocError>;
    /// A pass from about surfel `first` on: the stream and the canonical index of its first
    /// surfel, at most `first` (by default the whole stream, from 0). A shard set starts at the
    /// shard that holds `first`, so a rank of the data mode reads little more than its share.
    fn stream_from(
        &self,
        _first: u64,
        window_bytes: u64,
    ) -> Result<(SurfelStream<'_>, u64), OocError> {
        Ok((self.stream(window_bytes)?, 0))
    }
    /// Where each part of the source begins in the canonical stream (and the count at the
    /// end), where its parts are cut at voxel boundaries (a shard set that says so), else
    /// `None`. A rank of the data mode out of core whose slice is one part reads it alone.
    fn voxel_aligned_parts(&self) -> Option<Vec<u64>> {
        None
    }
    /// A pass over the parts holding surfels `first..end`, whole (so that a shard's checksum is
    /// checked at its end): the stream and the canonical index of its first surfel. By default
    /// [`Self::stream_from`], which goes on to the end.
    fn stream_between(
        &self,
        first: u64,
        _end: u64,
        window_bytes: u64,
    ) -> Result<(SurfelStream<'_>, u64), OocError> {
        self.stream_from(first, window_bytes)
    }
    /// The surfels of the voxels `keys` (sorted keys of `solve::direct::VoxelTable`: `z`, then
    /// `y`, then `x`), handed to `take` in canonical order with their canonical indices, until
    /// it says stop; returns the bytes read. By default a pass over the whole stream
    /// (`pick::by_stream`).
    fn pick_voxels(
        &self,
        keys: &[u64],
        window_bytes: u64,
        take: &mut super::pick::Take<'_>,
    ) -> Result<u64, OocError> {
        super::pick::by_stream(self.stream(window_bytes)?, keys, take)
    }
    /// What to call the source in messages.
    fn describe(&self) -> String;
    /// Whether the scene's light is sealed in (`solve::enclosure`), the check taking at most
    /// `max_bytes`. By default a pass over the surfels, which must come sorted by `z` first (a
    /// shard set's order).
    fn enclosure(
        &self,
        max_bytes: u64,
        window_bytes: u64,
        io: &mut super::files::IoCounters,
    ) -> Result<Verdict, OocError> {
        let info = self.info();
        let Some(mut enclosure) = Enclosure::new(info.grid.dims, max_bytes) else {
            return Ok(Verdict::too_large());
        };
        for s in self.stream(window_bytes)? {
            let s = s?;
            let emits = s
                .material
                .map(|m| info.materials[m as usize].emission.iter().any(|&e| e > 0.0));
            enclosure.add(s.voxel, s.normal, emits);
            io.read += crate::storage::RECORD_LEN as u64;
        }
        Ok(enclosure.verdict())
    }
    /// A CRC-32 of everything of the source that the radiosity depends on (it names the run in
    /// a checkpoint). By default a pass over the surfels; a source that knows checksums of its
    /// contents gives one made from them.
    fn checksum(&self, window_bytes: u64) -> Result<u32, OocError> {
        let info = self.info();
        let mut failure = None;
        let crc =
            crate::checkpoint::scene_checksum(&info.grid, &info.normals, &info.materials, |h| {
                let stream = match self.stream(window_bytes) {
                    Ok(s) => s,
                    Err(e) => return failure = Some(e),
                };
                for s in stream {
                    match s {
                        Ok(s) => crate::checkpoint::hash_surfel(h, &s),
                        Err(e) => return failure = Some(e),
                    }
                }
            });
        failure.map_or(Ok(crc), Err)
    }
}

/// A surfel set held in memory.
pub struct InMemorySource<'a> {
    set: &'a SurfelSet,
    info: SourceInfo,
}

impl<'a> InMemorySource<'a> {
    pub fn new(set: &'a SurfelSet) -> Self {
        InMemorySource {
            set,
            info: SourceInfo {
                grid: set.grid,
                normals: set.normals.clone(),
                materials: set.materials.clone(),
                count: set.surfels.len() as u64,
            },
        }
    }
}

impl SurfelSource for InMemorySource<'_> {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn stream(&self, _window_bytes: u64) -> Result<SurfelStream<'_>, OocError> {
        Ok(Box::new(self.set.surfels.iter().map(|s| Ok(*s))))
    }

    fn describe(&self) -> String {
        "the voxelized scene".to_string()
    }

    /// The set is in memory already (in Morton order): checked as the in-memory solvers check
    /// it, whatever the budget.
    fn enclosure(
        &self,
        _max_bytes: u64,
        _window_bytes: u64,
        _io: &mut super::files::IoCounters,
    ) -> Result<Verdict, OocError> {
        Ok(Enclosure::verdict_of_set(self.set))
    }
}

/// A shard set directory: its shards, in manifest order, are the canonical order.
pub struct ShardSetSource {
    dir: PathBuf,
    /// Every shard's reader, in manifest order; `None` for a shard not in `dir` (opened with
    /// [`ShardSetSource::open_present`]), with its manifest entry.
    readers: Vec<(Option<ShardReader>, ShardEntry)>,
    /// The manifest's order (the shards' key order).
    order: usize,
    /// The manifest says no voxel is split over two shards.
    voxel_aligned: bool,
    info: SourceInfo,
}

impl ShardSetSource {
    /// Opens the shard set `dir`: reads and validates the manifest, and checks every shard's
    /// header, length and footer against it (checksums are checked as the shards are streamed).
    pub fn open(dir: &Path) -> Result<Self, OocError> {
        Self::open_with(dir, false)
    }

    /// As [`ShardSetSource::open`], but shards whose files are not in `dir` are allowed: a rank
    /// of the data mode out of core other than rank 0 reads only its slice, so its node may hold
    /// only the shards that slice touches (staged on a node-local disk). The shards that are
    /// there are checked as by `open`; reading a missing one fails with a message naming it.
    pub fn open_present(dir: &Path) -> Result<Self, OocError> {
        Self::open_with(dir, true)
    }

    fn open_with(dir: &Path, allow_missing: bool) -> Result<Self, OocError> {
        let manifest = Manifest::read_dir(dir)?;
        let readers = manifest
            .check_present_shards(dir, allow_missing)?
            .into_iter()
            .zip(manifest.shards.iter().cloned())
            .collect();
        let count = manifest.records();
        Ok(ShardSetSource {
            dir: dir.to_path_buf(),
            readers,
            order: manifest.order,
            voxel_aligned: manifest.voxel_aligned,
            info: SourceInfo {
                grid: manifest.grid,
                normals: manifest.normals.clone(),
                materials: manifest.materials(),
                count,
            },
        })
    }
}

impl SurfelSource for ShardSetSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn stream(&self, window_bytes: u64) -> Result<SurfelStream<'_>, OocError> {
        Ok(self.stream_from(0, window_bytes)?.0)
    }

    fn voxel_aligned_parts(&self) -> Option<Vec<u64>> {
        self.voxel_aligned.then(|| {
            let mut starts = vec![0u64];
            for (_, entry) in &self.readers {
                starts.push(starts.last().expect("a first start") + entry.records);
            }
            starts
        })
    }

    fn stream_from(
        &self,
        first: u64,
        window_bytes: u64,
    ) -> Result<(SurfelStream<'_>, u64), OocError> {
        self.stream_between(first, u64::MAX, window_bytes)
    }

    fn stream_between(
        &self,
        first: u64,
        end: u64,
        window_bytes: u64,
    ) -> Result<(SurfelStream<'_>, u64), OocError> {
        // Whole shards before `first` are not read at all; the shard holding it is read from its
        // start, so that its checksum is still checked at its end. Shards from `end` on are not
        // read either.
        let mut start = 0u64;
        let mut skip = 0;
        for (_, entry) in &self.readers {
            let count = entry.records;
            // From the start, every shard is read (even an empty one: its checksum is checked).
            if first == 0 || start + count > first {
                break;
            }
            start += count;
            skip += 1;
        }
        let mut parts: Vec<SurfelStream<'_>> = Vec::with_capacity(self.readers.len());
        let mut at = start;
        for (reader, entry) in &self.readers[skip..] {
            if at >= end {
                break;
            }
            at += entry.records;
            let Some(reader) = reader else {
                // Not on this node: an error if the stream gets this far.
                let path = Manifest::shard_path(&self.dir, entry);
                parts.push(Box::new(std::iter::once(Err(OocError::BadData {
                    source_name: path.display().to_string(),
                    what: "is not on this node, and this rank's part of the scene lies in it: \
                           copy it there from the shard set (rank 0 reads every shard)"
                        .to_string(),
                }))));
                continue;
            };
            let path = reader.path();
            let records = WindowedRecords::new(reader, window_bytes)?;
            // The checksum is known only at a shard's end, but the solver acts on each record as
            // it comes: a damaged record must not reach an index or the grid first, and the
            // message must name the file that holds it.
            parts.push(Box::new(records.enumerate().map(move |(index, r)| {
                let s = r?;
                match check_record(&self.info, &s) {
                    Ok(()) => Ok(s),
                    Err(what) => Err(OocError::BadData {
                        source_name: path.display().to_string(),
                        what: format!(
                            "record {index} {what}: the file is damaged; restore it from a copy \
                             or make the shard set again with `voxrad-shard convert`"
                        ),
                    }),
                }
            })));
        }
        Ok((Box::new(parts.into_iter().flatten()), start))
    }

    fn describe(&self) -> String {
        format!("the shard set {}", self.dir.display())
    }

    /// A set sorted in the voxels' order (order 0) with every shard here is searched, reading
    /// only the records of the voxels wanted (`pick::from_sorted_shards`); any other, streamed.
    fn pick_voxels(
        &self,
        keys: &[u64],
        window_bytes: u64,
        take: &mut super::pick::Take<'_>,
    ) -> Result<u64, OocError> {
        let present: Option<Vec<(&ShardReader, u64)>> = self
            .readers
            .iter()
            .map(|(reader, entry)| reader.as_ref().map(|r| (r, entry.records)))
            .collect();
        match present {
            Some(shards) if self.order == 0 && super::pick::shards_in_key_order(&shards)? => {
                let shards = shards.into_iter();
                super::pick::from_sorted_shards(shards, &self.info, keys, window_bytes, take)
            }
            _ => super::pick::by_stream(self.stream(window_bytes)?, keys, take),
        }
    }

    /// From the shards' own checksums (checked against the data as it is streamed), without
    /// reading the shards.
    fn checksum(&self, _window_bytes: u64) -> Result<u32, OocError> {
        let info = &self.info;
        Ok(crate::checkpoint::scene_checksum(
            &info.grid,
            &info.normals,
            &info.materials,
            |h| {
                // From the manifest, which every shard present was checked against: the same
                // sum on a node that holds only some of them.
                for (_, entry) in &self.readers {
                    h.update(&(self.order as u64).to_le_bytes());
                    h.update(&entry.records.to_le_bytes());
                    h.update(&entry.crc32.to_le_bytes());
                }
            },
        ))
    }
}

/// Whether a record read from a shard can be used with the set's manifest: its voxel inside the
/// grid, its normal and materials in the manifest's tables, its numbers finite. A set written by
/// `voxrad-shard convert` always passes; a damaged or hand-made one must fail here, with a
/// message, rather than index out of bounds or spread NaN through the solve.
pub fn check_record(info: &SourceInfo, s: &Surfel) -> Result<(), String> {
    let dims = info.grid.dims;
    if !(0..3).all(|k| s.voxel[k] >= 0 && (s.voxel[k] as u64) < dims[k] as u64) {
        return Err(format!(
            "lies in voxel {:?}, outside the grid of {dims:?} voxels",
            s.voxel
        ));
    }
    if s.normal_id as usize >= info.normals.len() {
        return Err(format!(
            "has normal {} but the manifest lists {} normals",
            s.normal_id,
            info.normals.len()
        ));
    }
    if let Some(m) = s
        .material
        .iter()
        .find(|&&m| m as usize >= info.materials.len())
    {
        return Err(format!(
            "has material {m} but the manifest lists {} materials",
            info.materials.len()
        ));
    }
    let floats = s
        .point
        .iter()
        .chain(&s.normal)
        .chain([&s.area])
        .chain(s.extent.iter().flatten());
    if !floats.into_iter().all(|v| v.is_finite()) {
        return Err("has a number that is not finite".to_string());
    }
    Ok(())
}

/// Reads a stream voxel by voxel: each call to [`VoxelGroups::next_group`] fills `group` with
/// the surfels of the next voxel.
pub struct VoxelGroups<'a> {
    stream: SurfelStream<'a>,
    pending: Option<Surfel>,
    done: bool,
}

impl<'a> VoxelGroups<'a> {
    pub fn new(stream: SurfelStream<'a>) -> Self {
        VoxelGroups {
            stream,
            pending: None,
            done: false,
        }
    }

    /// Fills `group` with the next voxel's surfels; false at the end of the stream.
    pub fn next_group(&mut self, group: &mut Vec<Surfel>) -> Result<bool, OocError> {
        group.clear();
        if let Some(s) = self.pending.take() {
            group.push(s);
        }
        while !self.done {
            match self.stream.next() {
                None => self.done = true,
                Some(Err(e)) => return Err(e),
                Some(Ok(s)) => {
                    if group.first().is_some_and(|g| g.voxel != s.voxel) {
                        self.pending = Some(s);
                        return Ok(true);
                    }
                    group.push(s);
                }
            }
        }
        Ok(!group.is_empty())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::voxel::voxelize::{voxelize, GridSpec};

    /// A rank that reads its own shard alone (`stream_between`) still finds a damaged record by
    /// the shard's checksum at its end, and reads nothing of the next shard (here not on its
    /// node).
    #[test]
    fn a_shard_read_alone_is_checked_and_the_next_is_not_read() {
        let dir = tempfile::tempdir().unwrap();
        let set = voxelize(&crate::gen::cornell_box(), GridSpec::Resolution(16)).unwrap();
        crate::storage::write_shard_set(&set, dir.path(), 2, 0).unwrap();
        let manifest = Manifest::read_dir(dir.path()).unwrap();
        let first = manifest.shards[0].records;
        std::fs::remove_file(Manifest::shard_path(dir.path(), &manifest.shards[1])).unwrap();
        let source = ShardSetSource::open_present(dir.path()).unwrap();
        let read = |source: &ShardSetSource| -> Result<u64, OocError> {
            let (stream, start) = source.stream_between(0, first, 1 << 16)?;
            assert_eq!(start, 0);
            let mut count = 0;
            for s in stream {
                s?;
                count += 1;
            }
            Ok(count)
        };
        assert_eq!(read(&source).unwrap(), first);
        // The lowest bit of a record's byte flipped: a value still plausible, the checksum not.
        let path = Manifest::shard_path(dir.path(), &manifest.shards[0]);
        let mut bytes = std::fs::read(&path).unwrap();
        let record_3 = crate::storage::shard::HEADER_LEN as usize + 3 * crate::storage::RECORD_LEN;
        bytes[record_3 + 13] ^= 1;
        std::fs::write(&path, bytes).unwrap();
        let source = ShardSetSource::open_present(dir.path()).unwrap();
        let e = read(&source).unwrap_err().to_string();
        assert!(e.contains("shard-00000"), "{e}");
    }
}
