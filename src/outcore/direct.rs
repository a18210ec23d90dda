//! The direct-light pass out of core: the emitters' light gathered once along the dense
//! directions (`solve::direct`), with the scene in its source and the light in a work file.
//!
//! The in-memory pass walks, per dense direction, only the lines through emitting surfels; a
//! line reads its surfels from a table of the whole scene. Out of core the scene does not fit,
//! but the pass never reads more than the surfels on its emitters' lines. So:
//!
//! 1. One pass over the source finds the emitting surfels and an occupancy map: one bit per
//!    brick of `e x e x e` voxels over the whole grid, `e` the smallest power of two whose map
//!    takes at most an eighth of the budget (`e = 1`, one bit a voxel, on most grids).
//! 2. The dense directions are taken in *parts* of whole groups (a sender's balance is settled
//!    over a group, `solve::direct`): for each direction of a part, its emitters' lines are
//!    walked through the occupancy map and the voxels of occupied bricks on them listed; a part
//!    takes as many groups as the budget holds the surfels of those voxels for (estimated from
//!    the scene's surfels per brick voxel; a part whose surfels turn out too many is taken again
//!    with half its groups).
//! 3. One pass over the source picks these surfels, in canonical order: a small scene of its
//!    own, on which `solve::direct::gather_groups` runs unchanged. Every line it walks is whole
//!    there, so it finds the links the whole scene gives.
//! 4. The light and weight shifts of the part's surfels are added to the running sums, kept by
//!    canonical index in a work file ([`SUM_LEN`] bytes a surfel), starting from the sums of the
//!    parts before: each surfel adds its contributions in direction order, exactly as the
//!    in-memory pass adds them, so the answer is that pass's bit for bit.
//! 5. A last pass divides each side's light by `S_dense(n)` plus its shift into the direct-light
//!    file ([`LIGHT32_LEN`] bytes a surfel, canonical order, rounded once to f32: the data mode
//!    carries it in its records, and both read the same values), which every update reads.
//!
//! **Memory.** The occupancy map and the emitters' voxels stay for the whole pass; a part holds
//! its voxels' keys and its surfels (about [`PART_BYTES_PER_SURFEL`] each with the tables the
//! gathering builds). A single group that does not fit is refused with what it needs.

use super::budget::{format_bytes, MemoryPlan};
use super::files::{encode_light32, IoCounters, RecordFile, SeqReader, SeqWriter, LIGHT32_LEN};
use super::source::SurfelSource;
use super::OocError;
use crate::geometry::directions::DirectionSet;
use crate::geometry::lines::LineFrame;
use crate::solve::direct::{
    emits, emitting, for_each_voxel_on_line, gather_groups, DirectStats, SenderBalance, Sums,
    DIRECTIONS_PER_GROUP,
};
use crate::solve::normalize::cosine_sums;
use crate::solve::propagate::prop_surfels;
use crate::voxel::SurfelSet;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Bytes of one surfel's running sums: light by side and channel (f64 x 6), then each side's
/// shift of its gathered weights (f64 x 2).
pub const SUM_LEN: usize = 64;

/// Bytes a part holds per surfel: the surfel and its propagation data, emission, the voxel
/// table's entry, the sums and the canonical index, with room for the per-direction lists.
pub const PART_BYTES_PER_SURFEL: u64 = 320;

/// The direct light, out of core: a work file of [`LIGHT32_LEN`] bytes per surfel in canonical
/// order (`H_dense(E) / S_dense(n)` by side and channel), and what the pass did.
pub struct DirectFile {
    pub path: PathBuf,
    pub stats: DirectStats,
}

/// Bricks of `edge`^3 voxels holding a surfel, one bit each over the whole grid.
struct Occupancy {
    /// log2 of the brick edge.
    shift: u32,
    /// Bricks along each axis.
    bricks: [u64; 3],
    bits: Vec<u64>,
}

impl Occupancy {
    /// The finest map of a grid of `dims` that takes at most `bytes`.
    fn new(dims: [u32; 3], bytes: u64) -> Self {
        let mut shift = 0;
        loop {
            let bricks = dims.map(|d| (d as u64).div_ceil(1 << shift));
            let count = bricks[0] * bricks[1] * bricks[2];
            if count.div_ceil(8) <= bytes || shift >= 20 {
                return Occupancy {
                    shift,
                    bricks,
                    bits: vec![0; count.div_ceil(64) as usize],
                };
            }
            shift += 1;
        }
    }

    fn at(&self, voxel: [i32; 3]) -> u64 {
        let b = voxel.map(|c| (c as u64) >> self.shift);
        (b[2] * self.bricks[1] + b[1]) * self.bricks[0] + b[0]
    }

    fn insert(&mut self, voxel: [i32; 3]) {
        let at = self.at(voxel);
        self.bits[(at / 64) as usize] |= 1 << (at % 64);
    }

    fn contains(&self, voxel: [i32; 3]) -> bool {
        let at = self.at(voxel);
        self.bits[(at / 64) as usize] & (1 << (at % 64)) != 0
    }

    fn bytes(&self) -> u64 {
        self.bits.len() as u64 * 8
    }

    /// Voxels in the bricks that hold a surfel.
    fn voxels_marked(&self) -> u64 {
        let ones: u64 = self.bits.iter().map(|w| w.count_ones() as u64).sum();
        ones << (3 * self.shift)
    }
}

/// The refusal of a budget whose room for a part (`room` bytes) cannot hold one group's
/// `needed` bytes (`voxels` listed voxels of `directions` dense directions).
fn too_small(
    plan: &MemoryPlan,
    room: u64,
    needed: u64,
    voxels: usize,
    directions: usize,
) -> OocError {
    OocError::BudgetTooSmall {
        budget: plan.budget,
        needed: plan.budget - room + needed,
        what: format!(
            "the direct-light pass (the surfels of {voxels} voxels on the emitters' lines of \
             {directions} dense directions; --direct-directions 0 turns the pass off)"
        ),
    }
}

/// A voxel as one sortable number: the key of the in-memory pass's voxel table.
fn voxel_key(voxel: [i32; 3]) -> u64 {
    crate::solve::direct::VoxelTable::key(voxel)
}

/// Runs the pass over `source` along `dense` within `plan`, writing its files into `dir`.
pub fn gather_direct_out_of_core(
    source: &dyn SurfelSource,
    dense: &DirectionSet,
    plan: &MemoryPlan,
    pool: &rayon::ThreadPool,
    dir: &Path,
    io: &mut IoCounters,
) -> Result<DirectFile, OocError> {
    let started = Instant::now();
    let info = source.info();
    let n = info.count;
    let emission_of = |material: [u32; 2]| {
        material.map(|m| info.materials[m as usize].emission.map(|e| e as f32))
    };
    // 1. Emitters and occupancy.
    let mut occupancy = Occupancy::new(info.grid.dims, plan.working / 8);
    let mut emitter_voxels: Vec<[i32; 3]> = Vec::new();
    for s in source.stream(plan.io_bytes as u64)? {
        let s = s?;
        occupancy.insert(s.voxel);
        if emits(&emission_of(s.material)) {
            emitter_voxels.push(s.voxel);
        }
    }
    io.read += n * crate::storage::RECORD_LEN as u64;
    // Surfels per voxel of the marked bricks: what a part's listed voxels hold on average.
    let density = n as f64 / occupancy.voxels_marked().max(1) as f64;
    let fixed = occupancy.bytes() + emitter_voxels.len() as u64 * 12;
    let voxels: u64 = info.grid.dims.iter().map(|&d| d as u64).product();
    let room = plan
        .working
        .saturating_sub(fixed + 2 * plan.io_bytes as u64);
    // The gathering's voxel table may keep a bit per voxel where that takes a small share.
    let bitmap_bytes = crate::solve::direct::bitmap_bytes(voxels);
    let bitmap = voxels <= crate::solve::direct::MAX_BITMAP_VOXELS && bitmap_bytes <= room / 8;
    let room = room - if bitmap { bitmap_bytes } else { 0 };
    // A part's surfels and its listed voxels' keys (8 bytes each).
    let part_bytes = |keys: usize, surfels: f64| {
        keys as u64 * 8 + (surfels * PART_BYTES_PER_SURFEL as f64) as u64
    };
    let cosine_sum = cosine_sums(&info.normals, dense);

    let sum_path = dir.join("direct-sums.bin");
    let sums_file = RecordFile::create(&sum_path)?;
    sums_file.set_len(n * SUM_LEN as u64)?;
    let mut stats = DirectStats {
        directions: dense.len(),
        emitting_surfels: emitter_voxels.len(),
        ..Default::default()
    };
    let groups: Vec<Vec<usize>> = (0..dense.len())
        .collect::<Vec<_>>()
        .chunks(DIRECTIONS_PER_GROUP)
        .map(<[usize]>::to_vec)
        .collect();
    let progress = crate::progress::bar(dense.len() as u64, "direct light");
    let mut parts = 0u64;
    let mut next = 0;
    // At most this many groups per part (halved when a part's surfels did not fit).
    let mut most = groups.len();
    while next < groups.len() {
        // 2. The groups of this part and the voxels of occupied bricks on their emitters' lines.
        let mut keys: Vec<u64> = Vec::new();
        let mut which: Vec<usize> = Vec::new();
        let mut taken = 0;
        while next + taken < groups.len() && taken < most {
            let group = &groups[next + taken];
            let mut merged = line_voxels(
                group,
                dense,
                info.grid.dims,
                &emitter_voxels,
                &occupancy,
                pool,
            );
            merged.extend_from_slice(&keys);
            merged.sort_unstable();
            merged.dedup();
            let needed = part_bytes(merged.len(), merged.len() as f64 * density);
            if needed > room {
                if taken == 0 {
                    return Err(too_small(plan, room, needed, merged.len(), group.len()));
                }
                break;
            }
            keys = merged;
            which.extend_from_slice(group);
            taken += 1;
        }
        // 3. The part's surfels, in canonical order; too many for the estimate: fewer groups.
        let cap = (room.saturating_sub(keys.len() as u64 * 8) / PART_BYTES_PER_SURFEL) as usize;
        let mut part = SurfelSet {
            grid: info.grid,
            surfels: Vec::new(),
            normals: info.normals.clone(),
            materials: info.materials.clone(),
        };
        let mut ids: Vec<u64> = Vec::new();
        let mut overflow = false;
        for (id, s) in source.stream(plan.io_bytes as u64)?.enumerate() {
            let s = s?;
            if keys.binary_search(&voxel_key(s.voxel)).is_ok() {
                if part.surfels.len() >= cap {
                    overflow = true;
                    break;
                }
                part.surfels.push(s);
                ids.push(id as u64);
            }
        }
        io.read += n * crate::storage::RECORD_LEN as u64;
        if overflow {
            if taken == 1 {
                let needed = part_bytes(keys.len(), cap as f64 * 2.0);
                return Err(too_small(plan, room, needed, keys.len(), which.len()));
            }
            most = taken / 2;
            tracing::debug!(
                groups = most,
                "direct-light pass: a part's surfels did not fit, fewer groups"
            );
            continue;
        }
        drop(keys);
        next += taken;
        // 4. Its sums so far, the part's light added, written back.
        let mut light = vec![[[0f64; 3]; 2]; ids.len()];
        let mut rescaled = vec![[0f64; 2]; ids.len()];
        let mut bytes = [0u8; SUM_LEN];
        if parts > 0 {
            for (k, &id) in ids.iter().enumerate() {
                sums_file.read_at(id * SUM_LEN as u64, &mut bytes, io)?;
                (light[k], rescaled[k]) = decode_sum(&bytes);
            }
        }
        let emission: Vec<[[f32; 3]; 2]> = part
            .surfels
            .iter()
            .map(|s| emission_of(s.material))
            .collect();
        let emitters = emitting(&emission);
        let surfels = prop_surfels(&part);
        gather_groups(
            &part,
            &surfels,
            &emission,
            &emitters,
            &cosine_sum,
            dense,
            &which,
            SenderBalance::PerDirection,
            pool,
            bitmap,
            &progress,
            Sums {
                light: &mut light,
                rescaled: &mut rescaled,
                stats: &mut stats,
            },
        );
        for (k, &id) in ids.iter().enumerate() {
            encode_sum(&light[k], &rescaled[k], &mut bytes);
            sums_file.write_at(id * SUM_LEN as u64, &bytes, io)?;
        }
        parts += 1;
        tracing::debug!(
            part = parts,
            directions = which.len(),
            surfels = ids.len(),
            "direct-light pass: part gathered"
        );
    }
    progress.finish_and_clear();
    // 5. Each side's light over `S + shift`, in canonical order.
    let path = dir.join("direct.bin");
    let mut out = SeqWriter::create(&path, plan.io_bytes)?;
    let mut sums = SeqReader::<SUM_LEN>::open(&sum_path, plan.io_bytes)?;
    let mut record = [0u8; LIGHT32_LEN];
    for s in source.stream(plan.io_bytes as u64)? {
        let s = s?;
        let (mut light, shift) = decode_sum(&sums.expect_record()?);
        let norm = cosine_sum[s.normal_id as usize];
        for side in 0..2 {
            light[side]
                .iter_mut()
                .for_each(|v| *v /= norm + shift[side]);
        }
        encode_light32(&light, &mut record);
        out.write(&record)?;
    }
    io.read += n * (crate::storage::RECORD_LEN + SUM_LEN) as u64;
    io.written += out.finish()?;
    drop(sums);
    std::fs::remove_file(&sum_path).map_err(|e| OocError::io(&sum_path, "remove", e))?;
    stats.seconds = started.elapsed().as_secs_f64();
    stats.parts = parts;
    tracing::info!(
        directions = dense.len(),
        parts,
        map = format_bytes(fixed),
        seconds = format!("{:.1}", stats.seconds),
        "direct-light pass done out of core"
    );
    Ok(DirectFile { path, stats })
}

/// The occupied voxels on the lines through the emitters (at `emitter_voxels`) along the dense
/// directions `which`, sorted, each once.
fn line_voxels(
    which: &[usize],
    dense: &DirectionSet,
    dims: [u32; 3],
    emitter_voxels: &[[i32; 3]],
    occupancy: &Occupancy,
    pool: &rayon::ThreadPool,
) -> Vec<u64> {
    let mut keys: Vec<u64> = pool.install(|| {
        which
            .par_iter()
            .flat_map_iter(|&k| {
                let vector = dense.directions[k].vector;
                let frame = LineFrame::new(vector, dims);
                let mut lines: Vec<u64> = emitter_voxels
                    .iter()
                    .map(|&v| frame.line_index(v))
                    .collect();
                lines.sort_unstable();
                lines.dedup();
                let mut found = Vec::new();
                for line in lines {
                    for_each_voxel_on_line(&frame, dims, vector, line, |voxel| {
                        if occupancy.contains(voxel) {
                            found.push(voxel_key(voxel));
                        }
                    });
                }
                found
            })
            .collect()
    });
    keys.sort_unstable();
    keys.dedup();
    keys
}

fn encode_sum(light: &[[f64; 3]; 2], shift: &[f64; 2], out: &mut [u8; SUM_LEN]) {
    for (slot, v) in out
        .chunks_exact_mut(8)
        .zip(light.iter().flatten().chain(shift))
    {
        slot.copy_from_slice(&v.to_le_bytes());
    }
}

fn decode_sum(bytes: &[u8; SUM_LEN]) -> ([[f64; 3]; 2], [f64; 2]) {
    let v = |k: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[8 * k..8 * k + 8]);
        f64::from_le_bytes(b)
    };
    ([[v(0), v(1), v(2)], [v(3), v(4), v(5)]], [v(6), v(7)])
}
