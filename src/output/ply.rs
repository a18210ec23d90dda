//! The solution as a coloured point cloud: a binary little-endian PLY of surfel sides.
//!
//! One vertex per surfel side that has surface (area > 0) or light (non-zero radiosity); the two
//! sides of a surfel share the position and differ in normal, so a viewer that culls by normal
//! shows the side facing it. Layout per vertex (27 bytes):
//!
//! ```text
//! float x, y, z        world position of the surfel's surface point
//! float nx, ny, nz     unit normal of the side
//! uchar red, green, blue  radiosity after the render's tone mapping (sRGB)
//! ```
//!
//! The colours use [`ToneMap::for_solution`] unless a tone map is given, so the cloud and the
//! PNG preview look alike. Written atomically (see [`super::atomic`]).

use super::render::ToneMap;
use super::results::Record;
use super::{atomic, check_pair, OutputError};
use crate::solve::Solution;
use crate::voxel::{Grid, SurfelSet, BACK, FRONT};
use std::io::Write;
use std::path::Path;

/// Bytes per vertex record.
pub const VERTEX_LEN: usize = 6 * 4 + 3;

fn side_present(area: f32, b: &[f32; 3]) -> bool {
    area > 0.0 || b.iter().any(|&v| v != 0.0)
}

/// Writes the PLY with the solution's own tone map; returns the number of vertices.
pub fn write_ply(path: &Path, set: &SurfelSet, solution: &Solution) -> Result<u64, OutputError> {
    check_pair(path, set, solution)?;
    write_ply_with(path, set, solution, &ToneMap::for_solution(set, solution))
}

/// Writes the PLY with a given tone map; returns the number of vertices.
pub fn write_ply_with(
    path: &Path,
    set: &SurfelSet,
    solution: &Solution,
    tone: &ToneMap,
) -> Result<u64, OutputError> {
    check_pair(path, set, solution)?;
    let records = || {
        set.surfels
            .iter()
            .zip(&solution.radiosity)
            .map(|(s, b)| Record::from_surfel(s, *b))
    };
    // The header needs the count before the first vertex; counting is cheap next to writing.
    let count: u64 = records().map(|r| vertices_of(&r)).sum();
    atomic::write_atomically(path, |w| {
        write_header(w, count)?;
        for r in records() {
            write_vertices(w, &set.grid, &r, tone)?;
        }
        Ok(())
    })?;
    Ok(count)
}

/// Number of vertices a record contributes: one per side with surface or light.
pub fn vertices_of(r: &Record) -> u64 {
    [FRONT, BACK]
        .iter()
        .filter(|&&k| side_present(r.area, &r.radiosity[k]))
        .count() as u64
}

/// The PLY header for `count` vertices.
pub fn write_header(w: &mut dyn Write, count: u64) -> std::io::Result<()> {
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\n\
         comment voxrad surfel sides; colour is tone-mapped radiosity (sRGB)\n\
         element vertex {count}\n\
         property float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         end_header\n"
    )
}

/// The vertices of one record (see [`vertices_of`]), in the layout of the module header.
pub fn write_vertices(
    w: &mut dyn Write,
    grid: &Grid,
    r: &Record,
    tone: &ToneMap,
) -> std::io::Result<()> {
    let mut rec = [0u8; VERTEX_LEN];
    let p = grid.to_world(r.position());
    for side in [FRONT, BACK] {
        if !side_present(r.area, &r.radiosity[side]) {
            continue;
        }
        let n = r.side_normal(side);
        let floats = [p.x, p.y, p.z, n.x, n.y, n.z].map(|v| v as f32);
        for (i, f) in floats.iter().enumerate() {
            rec[4 * i..4 * i + 4].copy_from_slice(&f.to_le_bytes());
        }
        rec[24..27].copy_from_slice(&tone.map(r.radiosity[side]));
        w.write_all(&rec)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::testutil;

    #[test]
    fn header_and_vertex_count() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.ply");
        let (mut set, mut solution) = testutil::lit_square(3);
        // One touched surfel without light: no vertex. One touched with a lit back: one vertex.
        set.surfels
            .push(testutil::surfel([0, 0, 1], [0.0; 3], [0.0, 0.0, 1.0], 0.0));
        solution.radiosity.push([[0.0; 3]; 2]);
        set.surfels
            .push(testutil::surfel([1, 0, 1], [0.0; 3], [0.0, 0.0, 1.0], 0.0));
        solution.radiosity.push([[0.0; 3], [0.0, 2.0, 0.0]]);
        // 9 square surfels with area: both sides each.
        let expected = 9 * 2 + 1;
        assert_eq!(write_ply(&path, &set, &solution).unwrap(), expected);

        let bytes = std::fs::read(&path).unwrap();
        let end = b"end_header\n";
        let at = bytes
            .windows(end.len())
            .position(|w| w == end)
            .expect("header end")
            + end.len();
        let header = std::str::from_utf8(&bytes[..at]).unwrap();
        let lines: Vec<&str> = header.lines().collect();
        assert_eq!(lines[0], "ply");
        assert_eq!(lines[1], "format binary_little_endian 1.0");
        assert!(lines.contains(&format!("element vertex {expected}").as_str()));
        let props: Vec<&str> = lines
            .iter()
            .filter(|l| l.starts_with("property"))
            .copied()
            .collect();
        assert_eq!(
            props,
            [
                "property float x",
                "property float y",
                "property float z",
                "property float nx",
                "property float ny",
                "property float nz",
                "property uchar red",
                "property uchar green",
                "property uchar blue"
            ]
        );
        assert_eq!(bytes.len() - at, expected as usize * VERTEX_LEN);

        // First vertex: surfel (0,0,0) front, world (-1,2,0.5) + 0.5 * 0.25, normal +z, lit.
        let v = &bytes[at..at + VERTEX_LEN];
        let f = |i: usize| f32::from_le_bytes(v[4 * i..4 * i + 4].try_into().unwrap());
        assert_eq!([f(0), f(1), f(2)], [-0.875, 2.125, 0.625]);
        assert_eq!([f(3), f(4), f(5)], [0.0, 0.0, 1.0]);
        assert!(v[24] > 0);
        // Its back side: normal -z, black.
        let v = &bytes[at + VERTEX_LEN..at + 2 * VERTEX_LEN];
        assert_eq!(f32::from_le_bytes(v[20..24].try_into().unwrap()), -1.0);
        assert_eq!(&v[24..27], &[0, 0, 0]);
    }

    #[test]
    fn mismatched_solution_is_refused() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.ply");
        let (set, mut solution) = testutil::lit_square(2);
        solution.radiosity.clear();
        let e = write_ply(&path, &set, &solution).unwrap_err();
        assert!(e.to_string().contains("surfels.ply"), "{e}");
        assert!(!path.exists());
    }
}
