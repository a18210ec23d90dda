//! Out-of-core voxelization: exactly the surfels of `voxel::voxelize`, produced in shard order
//! while holding only the scene and a bounded buffer.
//!
//! The in-memory voxelizer makes every piece (one triangle's share of one voxel), sorts them and
//! merges each run of one (voxel, plane group, facing) into a surfel. Here the same pieces are
//! made triangle by triangle, one voxel at a time (`PlaneGroups::triangle_pieces`), and fed to the
//! external piece sort (`pieces`), whose output comes back in shard order; each voxel's pieces
//! are then merged into its surfels by the very function the in-memory path uses
//! (`voxelize::merge_voxel`). The
//! pieces of a surfel arrive in the same order in both paths (the sort key ends in the
//! triangle's index, so it is unique), hence the floating-point sums and the surfels are equal
//! bit for bit; only the order of the surfels differs (Morton order in memory, shard order here).
//!
//! What needs the whole scene, and how it stays bounded:
//! - plane groups and their normals are assigned in triangle order before any piece is made;
//!   they grow with the triangles, which this path holds anyway;
//! - the flipped normals of back-facing surfels and the unlit back sides of emitters
//!   (`voxelize::Tables`) are numbered from facts known before the merge: one flag per group
//!   normal, set while the pieces are made, and the scene's materials. The in-memory path
//!   numbers them the same way (it used to number them in the order surfels were met, which an
//!   out-of-core pass in another order cannot reproduce without a second pass over the data);
//! - a voxel's pieces are held while its surfels are merged (faces pressed together are cut by
//!   each other there): as many as there are triangles in one voxel, a handful except for
//!   finely tessellated surfaces.
//!
//! Disk: the runs hold every piece once (132 bytes each, about 1.05 to 1.1 pieces per surfel, so
//! about 1.8 times the shard set); an intermediate merge pass, needed only when the runs
//! outnumber what one merge takes, holds them twice for a moment. They live in the output's
//! staging directory, on the output's file system, and are deleted as soon as they are merged.

use super::pieces::{PiecePlan, PieceSorter, PieceStats};
use super::ConvertError;
use crate::scene::{Material, Scene};
use crate::voxel::voxelize::{grid_for, merge_voxel, GridSpec, Piece, PlaneGroups, Tables};
use crate::voxel::{Grid, Surfel, BACK};
use std::path::Path;

/// How a streamed voxelization runs.
#[derive(Clone, Copy, Debug)]
pub struct StreamOptions {
    pub spec: GridSpec,
    /// The lexicographic order (0..4) surfels come out in.
    pub order: usize,
    pub plan: PiecePlan,
    /// Sort runs with rayon's pool.
    pub parallel: bool,
}

/// What a streamed voxelization produced besides the surfels.
#[derive(Clone, Debug)]
pub struct Streamed {
    pub grid: Grid,
    pub normals: Vec<[f32; 3]>,
    pub materials: Vec<Material>,
    pub surfels: u64,
    pub sort: PieceStats,
}

/// Voxelizes `scene` (validated) and hands every surfel to `sink`, in order `options.order`,
/// with scratch files under `scratch`.
pub fn stream_voxelize(
    scene: &Scene,
    options: &StreamOptions,
    scratch: &Path,
    mut sink: impl FnMut(&Surfel) -> Result<(), ConvertError>,
) -> Result<Streamed, ConvertError> {
    let grid = grid_for(scene, options.spec).map_err(|e| ConvertError::BadInput(e.to_string()))?;
    let groups = PlaneGroups::new(scene, grid);
    let mut sorter = PieceSorter::new(options.order, options.plan, scratch, options.parallel)?;
    let mut back_facing = vec![false; groups.normal_count()];

    let progress = crate::progress::bar(scene.triangles.len() as u64, "pieces");
    for index in 0..scene.triangles.len() {
        groups.triangle_pieces(scene, index, &mut |p: Piece| {
            if p.side as usize == BACK {
                back_facing[groups.normal_of(&p) as usize] = true;
            }
            sorter.push(p)
        })?;
        progress.inc(1);
    }
    progress.finish_and_clear();
    let tables = Tables::new(scene, &groups, &back_facing);

    let sorted = sorter.finish()?;
    let sort = *sorted.stats();
    tracing::info!(
        pieces = sort.pieces,
        runs = sort.runs,
        spilled_bytes = sort.bytes_spilled,
        "pieces sorted into runs"
    );
    let progress = crate::progress::bar(sort.pieces, "surfels");
    let mut run: Vec<Piece> = Vec::new();
    let mut surfels: u64 = 0;
    let mut emit = |run: &mut Vec<Piece>| -> Result<(), ConvertError> {
        if !run.is_empty() {
            for surfel in merge_voxel(run, &tables, &groups, scene) {
                sink(&surfel)?;
                surfels += 1;
            }
            progress.inc(run.len() as u64);
            run.clear();
        }
        Ok(())
    };
    for p in sorted {
        let p = p?;
        if run.last().is_some_and(|last| last.voxel != p.voxel) {
            emit(&mut run)?;
        }
        run.push(p);
    }
    emit(&mut run)?;
    progress.finish_and_clear();
    if surfels > u32::MAX as u64 {
        return Err(ConvertError::BadInput(format!(
            "the scene produced {surfels} surfels; at most 4294967295 are supported in one set \
             (lower --resolution)"
        )));
    }
    Ok(Streamed {
        grid,
        normals: tables.normals,
        materials: tables.materials,
        surfels,
        sort,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::shard;
    use crate::voxel::voxelize::voxelize;

    /// Equal as sets: both sorted by every field's bits.
    pub(crate) fn canonical(mut v: Vec<Surfel>) -> Vec<Surfel> {
        let bits = |s: &Surfel| crate::storage::record::encode(s);
        v.sort_by_key(bits);
        v
    }

    fn check(scene: &Scene, spec: GridSpec, budget: u64) -> PieceStats {
        let dir = tempfile::TempDir::new().unwrap();
        let expected = voxelize(scene, spec).unwrap();
        let options = StreamOptions {
            spec,
            order: 1,
            plan: PiecePlan::new(budget).unwrap(),
            parallel: false,
        };
        let mut got = Vec::new();
        let streamed = stream_voxelize(scene, &options, dir.path(), |s| {
            got.push(*s);
            Ok(())
        })
        .unwrap();
        assert!(got.is_sorted_by_key(|s| shard::key(1, s)), "shard order");
        assert_eq!(streamed.surfels, got.len() as u64);
        assert_eq!(streamed.grid, expected.grid);
        assert_eq!(streamed.normals, expected.normals);
        assert_eq!(streamed.materials, expected.materials);
        assert_eq!(canonical(got), canonical(expected.surfels));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        // The budget: the run buffer (its peak, in pieces) and one write buffer.
        let plan = options.plan;
        let held = streamed.sort.peak_buffered * std::mem::size_of::<Piece>() as u64;
        assert!(
            held + plan.io_bytes <= budget,
            "{:?} {plan:?}",
            streamed.sort
        );
        if streamed.sort.pieces > plan.run_pieces {
            assert_eq!(
                streamed.sort.runs,
                streamed.sort.pieces.div_ceil(plan.run_pieces),
                "runs of the full buffer size"
            );
        }
        streamed.sort
    }

    #[test]
    fn same_surfels_as_in_memory() {
        let cornell = crate::gen::cornell_box();
        let stats = check(&cornell, GridSpec::Resolution(24), 64 << 10);
        assert!(stats.runs > 1, "{stats:?}");
        check(&cornell, GridSpec::Resolution(17), 1 << 30);
        let building = crate::gen::building(2, 1, 2, 3);
        let stats = check(&building, GridSpec::Resolution(40), 128 << 10);
        assert!(stats.runs > 1, "{stats:?}");
    }
}
