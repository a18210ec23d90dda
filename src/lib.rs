//! voxrad: diffuse global illumination (radiosity) of very large scenes by the discrete,
//! voxel-based method of Chatelier and Malgouyres, parallelised as in Zrour et al.
//!
//! The pipeline, one module each: `scene` (read or generate triangles and materials) ->
//! `voxel` (tunnel-free voxelization into surfels) -> `geometry` (integer directions, discrete
//! lines, lexicographic orders) -> `solve` (dispatch into lines, propagate, Jacobi iterations) ->
//! `output` (report, per-voxel results, PLY, picture, probes). `gen` makes test and example scenes.
//! `storage` keeps surfels out of core: sorted shard files, bounded memory-map windows, k-way
//! merges and an external sort under a memory budget. `outcore` solves from a shard set with
//! every array that grows with the scene in files, under a `--memory` budget. `convert` is the
//! library of the `voxrad-shard` tool: scenes into shard sets out of core, sets verified,
//! re-split, results exported. `study` measures what accuracy costs in time; `quality` holds
//! the presets chosen from it. `checkpoint` saves a solve at iteration boundaries and resumes it
//! bit for bit; `interrupt` turns SIGTERM and SIGINT into a clean stop.

pub mod app;
pub mod checkpoint;
pub mod comm;
pub mod convert;
pub mod distribute;
pub mod gen;
pub mod geometry;
pub mod interrupt;
pub mod outcore;
pub mod output;
pub mod progress;
pub mod quality;
pub mod scene;
pub mod solve;
pub mod storage;
pub mod study;
pub mod voxel;
