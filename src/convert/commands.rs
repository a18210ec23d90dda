//! The subcommands of `voxrad-shard` as library functions of parsed options: each validates what
//! the parser cannot, runs, logs with `tracing`, and returns a summary for the binary to print.

use super::pieces::{PiecePlan, PieceStats};
use super::shardset::{self, records_of, shard_file_name, verify_set, Digest, Staging};
use super::stream::{stream_voxelize, StreamOptions};
use super::ConvertError;
use crate::scene::obj::load_obj;
use crate::scene::Scene;
use crate::storage::merge::{self, KWayMerge};
use crate::storage::shard::{self, ShardInfo, ShardReader, ShardWriter, WriteOptions, ORDERS};
use crate::storage::{Manifest, ShardEntry, RECORD_LEN};
use crate::voxel::voxelize::GridSpec;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Options of `voxrad-shard convert`.
#[derive(Clone, Debug)]
pub struct ConvertOptions {
    pub scene: PathBuf,
    pub out: PathBuf,
    pub spec: GridSpec,
    pub ranks: usize,
    /// The memory budget in bytes.
    pub memory: u64,
    pub order: usize,
    /// Worker threads; 0 for all cores, 1 for none besides the main thread.
    pub threads: usize,
}

/// What a conversion did.
#[derive(Clone, Debug)]
pub struct ConvertSummary {
    pub surfels: u64,
    pub shards: Vec<ShardInfo>,
    pub sort: PieceStats,
    pub plan: PiecePlan,
    pub seconds: f64,
}

fn check_ranks(ranks: usize) -> Result<(), ConvertError> {
    if ranks == 0 {
        return Err(ConvertError::BadInput(
            "--ranks 0: a shard set needs at least one shard".into(),
        ));
    }
    Ok(())
}

fn load_scene(path: &Path) -> Result<Scene, ConvertError> {
    load_obj(path).map_err(|e| {
        if e.is_bad_input() {
            ConvertError::BadInput(e.to_string())
        } else {
            ConvertError::Failure(e.to_string())
        }
    })
}

/// Runs `f` on a pool of `threads` threads (0: rayon's global pool); returns whether sorting
/// in parallel is worth it.
fn with_threads<T>(
    threads: usize,
    f: impl FnOnce(bool) -> Result<T, ConvertError> + Send,
) -> Result<T, ConvertError>
where
    T: Send,
{
    match threads {
        // One thread: no pool at all, so that nothing but the main thread runs (and allocates).
        1 => f(false),
        0 => f(true),
        n => rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .map_err(|e| ConvertError::Failure(format!("cannot start {n} threads: {e}")))?
            .install(|| f(true)),
    }
}

/// `voxrad-shard convert`: OBJ scene -> shard set (see `stream` and `shardset`).
pub fn convert(o: &ConvertOptions) -> Result<ConvertSummary, ConvertError> {
    let started = Instant::now();
    check_ranks(o.ranks)?;
    if o.order >= ORDERS {
        return Err(ConvertError::BadInput(format!(
            "--order {}: orders are 0 to {}",
            o.order,
            ORDERS - 1
        )));
    }
    let plan = PiecePlan::new(o.memory)?;
    if let GridSpec::Resolution(n) = o.spec {
        if n < 2 {
            return Err(ConvertError::BadInput(format!(
                "--resolution {n}: use at least 2 voxels along the longest side"
            )));
        }
    }
    // The output is checked before the scene is read, which may take a while.
    let staging = Staging::new(&o.out)?;
    let scene = load_scene(&o.scene)?;
    tracing::info!(
        triangles = scene.triangles.len(),
        materials = scene.materials.len(),
        "scene read"
    );
    // The only bad input the voxelization itself can find is about the scene (its grid, its
    // size); everything else in this stage concerns files this command writes.
    let scene_err = |e: ConvertError| match e {
        ConvertError::BadInput(m) => ConvertError::BadInput(format!("{}: {m}", o.scene.display())),
        other => other,
    };
    let scratch_err = |e: ConvertError| ConvertError::Failure(e.to_string());
    let (streamed, infos) = with_threads(o.threads, |parallel| {
        let options = StreamOptions {
            spec: o.spec,
            order: o.order,
            plan,
            parallel,
        };
        let write = WriteOptions {
            buffer_bytes: plan.out_bytes as usize,
            sync: o.ranks == 1,
        };
        // One rank: straight into the final shard. More: the count per shard is known only at
        // the end, so into one sorted scratch file first, then split.
        let first = if o.ranks == 1 {
            staging.path().join(shard_file_name(0))
        } else {
            staging.path().join("sorted.scratch")
        };
        let mut w = ShardWriter::create_with(&first, o.order, write)?;
        let streamed = stream_voxelize(&scene, &options, staging.path(), |s| Ok(w.push(s)?))
            .map_err(scene_err)?;
        let info = w.finish()?;
        if o.ranks == 1 {
            return Ok((streamed, vec![info]));
        }
        let reader = ShardReader::open_lazy(&first).map_err(|e| scratch_err(e.into()))?;
        let records = records_of(std::slice::from_ref(&reader), plan.io_bytes as usize)
            .map_err(scratch_err)?;
        let infos = shardset::write_split(
            records,
            info.count,
            o.ranks,
            staging.path(),
            o.order,
            plan.out_bytes as usize,
        )
        .map_err(scratch_err)?;
        std::fs::remove_file(&first).map_err(|e| {
            ConvertError::Failure(format!("cannot remove {}: {e}", first.display()))
        })?;
        Ok((streamed, infos))
    })?;
    let entries = infos
        .iter()
        .map(ShardEntry::from_info)
        .collect::<Result<Vec<_>, _>>()?;
    let mut manifest = Manifest::new(
        streamed.grid,
        &streamed.materials,
        streamed.normals,
        o.order,
        entries,
    );
    // One shard, or `write_split`'s cuts.
    manifest.voxel_aligned = true;
    manifest.write(staging.path())?;
    staging.commit()?;
    let summary = ConvertSummary {
        surfels: streamed.surfels,
        shards: infos
            .into_iter()
            .map(|mut i| {
                i.path = o.out.join(i.path.file_name().unwrap_or_default());
                i
            })
            .collect(),
        sort: streamed.sort,
        plan,
        seconds: started.elapsed().as_secs_f64(),
    };
    tracing::info!(
        surfels = summary.surfels,
        shards = summary.shards.len(),
        runs = summary.sort.runs,
        seconds = summary.seconds,
        "converted"
    );
    Ok(summary)
}

/// `voxrad-shard inspect`: the manifest, described.
pub fn inspect(set: &Path) -> Result<String, ConvertError> {
    if !set.is_dir() {
        return Err(ConvertError::BadInput(format!(
            "{}: not a directory (a shard set is a directory with a manifest.json)",
            set.display()
        )));
    }
    let m = Manifest::read_dir(set)?;
    Ok(shardset::describe(set, &m))
}

/// `voxrad-shard verify`: every file checked; a report of the good shards, or every problem.
pub fn verify(set: &Path) -> Result<String, ConvertError> {
    let (m, v) = verify_set(set)?;
    if !v.problems.is_empty() {
        return Err(ConvertError::BadInput(format!(
            "{} of the {} shards of {} failed verification:\n  {}",
            v.problems.len(),
            m.shards.len(),
            set.display(),
            v.problems.join("\n  ")
        )));
    }
    let bytes: u64 = v.good.iter().map(|i| i.bytes).sum();
    let mut report = format!(
        "{}: {} shards, {} records, {} bytes: all magic numbers, versions, lengths, checksums \
         and orders are correct and match {}",
        set.display(),
        v.good.len(),
        m.records(),
        bytes,
        crate::storage::MANIFEST_FILE
    );
    if !v.unlisted.is_empty() {
        report.push_str(&format!(
            "\nnote: not listed in {}, so not part of the set: {}",
            crate::storage::MANIFEST_FILE,
            v.unlisted.join(", ")
        ));
    }
    Ok(report)
}

/// What a re-shard did.
#[derive(Clone, Debug)]
pub struct ReshardSummary {
    pub records: u64,
    pub shards: Vec<ShardInfo>,
}

fn same_place(a: &Path, b: &Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

/// `voxrad-shard reshard`: the records of `set` re-split into `ranks` shards at `out`, by a
/// streaming merge of the old shards; the new set is verified and compared with the old records
/// (count and digest, in order) before it is moved into place.
pub fn reshard(
    set: &Path,
    ranks: usize,
    out: &Path,
    memory: u64,
) -> Result<ReshardSummary, ConvertError> {
    check_ranks(ranks)?;
    if same_place(set, out) {
        return Err(ConvertError::BadInput(format!(
            "{}: --out is the input set; give another directory",
            out.display()
        )));
    }
    let manifest = Manifest::read_dir(set)?;
    let readers = manifest.check_shards(set)?;
    // Budget: one read buffer per old shard, one write buffer, the merge heap.
    let head = merge::head_bytes::<(i64, i64, i64), usize, crate::voxel::Surfel>() as u64;
    let sources = readers.len() as u64 + 1;
    let share = memory / sources;
    let buffer =
        (share.saturating_sub(head) / RECORD_LEN as u64 * RECORD_LEN as u64).min(256 << 10);
    if memory < PiecePlan::MIN_BUDGET_BYTES || buffer < RECORD_LEN as u64 {
        return Err(ConvertError::BadInput(format!(
            "--memory {memory} bytes is too small to merge {} shards: give at least {} bytes",
            readers.len(),
            (sources * (RECORD_LEN as u64 + head)).max(PiecePlan::MIN_BUDGET_BYTES)
        )));
    }
    let order = manifest.order;
    let staging = Staging::new(out)?;
    let mut before = Digest::default();
    let iters = readers
        .iter()
        .map(|r| r.records(buffer as usize))
        .collect::<Result<Vec<_>, _>>()?;
    let merged = KWayMerge::new(iters, move |s| shard::key(order, s), merge::by_source)
        .map(|r| r.map_err(ConvertError::from))
        .inspect(|r| {
            if let Ok(s) = r {
                before.add(s)
            }
        });
    let progress = crate::progress::bar(manifest.records(), "reshard");
    let merged = merged.inspect(|_| progress.inc(1));
    let infos = shardset::write_split(
        merged,
        manifest.records(),
        ranks,
        staging.path(),
        order,
        buffer as usize,
    )?;
    progress.finish_and_clear();
    let entries = infos
        .iter()
        .map(ShardEntry::from_info)
        .collect::<Result<Vec<_>, _>>()?;
    let mut new = manifest.clone();
    new.format_version = crate::storage::manifest::VERSION;
    new.shards = entries;
    new.voxel_aligned = true;
    new.write(staging.path())?;

    // The new set must verify and hold the same records in the same order.
    // Problems found in the new set are this command's failures, not the user's input.
    let ours = |e: ConvertError| ConvertError::Failure(e.to_string());
    let (new_manifest, v) = verify_set(staging.path()).map_err(ours)?;
    if !v.problems.is_empty() {
        return Err(ConvertError::Failure(format!(
            "the new set failed verification: {}",
            v.problems.join("; ")
        )));
    }
    let new_readers = new_manifest
        .check_shards(staging.path())
        .map_err(|e| ours(e.into()))?;
    let mut after = Digest::default();
    for s in records_of(&new_readers, buffer as usize).map_err(ours)? {
        after.add(&s.map_err(ours)?);
    }
    if after.value() != before.value() {
        return Err(ConvertError::Failure(format!(
            "the new set's records differ from those of {} ({:?} vs {:?}); nothing was written",
            set.display(),
            after.value(),
            before.value()
        )));
    }
    staging.commit()?;
    tracing::info!(records = after.count, shards = ranks, "resharded");
    Ok(ReshardSummary {
        records: after.count,
        shards: infos,
    })
}
