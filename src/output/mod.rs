//! What a solve writes: `report.json`, per-voxel results, a coloured PLY, a PNG preview; probes.
