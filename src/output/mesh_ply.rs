//! A [`BakedMesh`] as a binary little-endian PLY mesh (`baked.ply`), for MeshLab and scientific
//! tools: the same vertices and triangles as `baked.glb`.
//!
//! ```text
//! element vertex N
//!   float x, y, z                            world position
//!   float nx, ny, nz                         unit normal of the side baked
//!   float radiosity_r, radiosity_g, radiosity_b   linear radiosity B (units of Ke)
//!   uchar red, green, blue                   display colour (the preview's tone map, sRGB)
//! element face M
//!   list uchar uint vertex_indices           three indices, counter-clockwise seen from the normal
//! ```

use super::bake::BakedMesh;
use super::{atomic, OutputError};
use std::path::Path;

/// Bytes of one vertex record.
const VERTEX_LEN: usize = 9 * 4 + 3;

/// Writes `mesh` to `path`; returns the number of triangles.
pub fn write_mesh_ply(path: &Path, mesh: &BakedMesh) -> Result<u64, OutputError> {
    let vertices = mesh.positions.len();
    if u32::try_from(vertices).is_err() {
        return Err(OutputError::invalid(
            path,
            format!("{vertices} vertices is more than 32-bit indices can name"),
        ));
    }
    let faces = mesh.triangle_count();
    atomic::write_atomically(path, |w| {
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\n\
             comment voxrad: radiosity baked onto the scene's triangles\n\
             comment radiosity_*: linear radiosity B in the units of Ke; red/green/blue: \
             tone-mapped sRGB\n\
             element vertex {vertices}\n\
             property float x\nproperty float y\nproperty float z\n\
             property float nx\nproperty float ny\nproperty float nz\n\
             property float radiosity_r\nproperty float radiosity_g\nproperty float radiosity_b\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\n\
             element face {faces}\n\
             property list uchar uint vertex_indices\n\
             end_header\n"
        )?;
        let mut record = [0u8; VERTEX_LEN];
        for v in 0..vertices {
            let floats = mesh.positions[v]
                .iter()
                .chain(&mesh.normals[v])
                .chain(&mesh.radiosity[v]);
            for (i, f) in floats.enumerate() {
                record[4 * i..4 * i + 4].copy_from_slice(&f.to_le_bytes());
            }
            record[36..39].copy_from_slice(&mesh.srgb_colour(v));
            w.write_all(&record)?;
        }
        let mut face = [0u8; 13];
        face[0] = 3;
        for t in mesh.indices.chunks_exact(3) {
            for (k, &i) in t.iter().enumerate() {
                face[1 + 4 * k..5 + 4 * k].copy_from_slice(&i.to_le_bytes());
            }
            w.write_all(&face)?;
        }
        Ok(())
    })?;
    Ok(faces as u64)
}
