//! What a solve writes: `report.json`, per-voxel results, a coloured PLY, a PNG preview; probes.
//!
//! One file per concern:
//! - [`report`]: the run report (`report.json`) and the process's peak RSS.
//! - [`results`]: the per-voxel results file (`surfels.bin`, checksummed binary) and its reader,
//!   plus a CSV export for small scenes.
//! - [`ply`]: surfel sides as coloured points in a binary PLY.
//! - [`bake`]: the radiosity baked onto the scene's own triangles, cut where the light varies;
//!   [`glb`] writes that mesh as glTF 2.0 binary (`baked.glb`), [`mesh_ply`] as a PLY mesh
//!   (`baked.ply`).
//! - [`render`]: a tone-mapped PNG preview from an automatic or given camera; the tone mapping is
//!   shared with the PLY so both show the same colours.
//! - [`probe`]: radiosity at given points and normals, looked up in a results file.
//! - [`sensor`]: irradiance at sensor points anywhere, gathered from the results by casting
//!   rays; [`grid`] lays them out on a workplane and writes its CSV and false-colour picture.
//! - [`atomic`]: the temp-file, sync, rename discipline every writer here uses, so a crash or a
//!   full disk never leaves a half-written file under a real name.
//! - [`staging`]: a run's outputs written together into a hidden directory and moved into place
//!   only when all are complete, so a failure never mixes new files with earlier ones.
//!
//! Writers return [`OutputError`], which always names the file concerned. The results reader and
//! the probe have their own error types because their callers need to tell their cases apart
//! (corruption vs. I/O, and which CSV line is bad).

pub mod atomic;
pub mod bake;
pub mod glb;
pub mod grid;
pub mod mesh_ply;
pub mod ply;
pub mod probe;
pub mod render;
pub mod report;
pub mod results;
pub mod sensor;
pub mod staging;

pub use ply::write_ply;
pub use probe::{probe, ProbeError, ProbeIndex, ProbeRow};
pub use render::{auto_camera, render_png, Camera, CameraParseError, ToneMap};
pub use report::{peak_rss_bytes, Effect, Energy, Report, RunInfo};
pub use results::{read_results, write_csv, write_results, Record, Results, ResultsError};

use std::path::{Path, PathBuf};

/// File names the solver writes into its output directory.
pub const REPORT_FILE: &str = "report.json";
pub const RESULTS_FILE: &str = "surfels.bin";
pub const RENDER_FILE: &str = "render.png";
pub const RENDER_EXR_FILE: &str = "render.exr";
pub const PLY_FILE: &str = "surfels.ply";
pub const BAKED_GLB_FILE: &str = "baked.glb";
pub const BAKED_PLY_FILE: &str = "baked.ply";

/// Why an output file could not be written. Every case names the file.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error("cannot write {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot encode {} as JSON: {source}", path.display())]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("cannot write {}: {what}", path.display())]
    Invalid { path: PathBuf, what: String },
}

impl OutputError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        OutputError::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    pub(crate) fn invalid(path: &Path, what: impl Into<String>) -> Self {
        OutputError::Invalid {
            path: path.to_path_buf(),
            what: what.into(),
        }
    }

    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            OutputError::Io { path, .. }
            | OutputError::Json { path, .. }
            | OutputError::Invalid { path, .. } => path,
        }
    }
}

/// A solution belongs to one surfel set; writing a mismatched pair would silently attach the
/// wrong radiosity to surfels, so every writer checks it first.
pub(crate) fn check_pair(
    path: &Path,
    set: &crate::voxel::SurfelSet,
    solution: &crate::solve::Solution,
) -> Result<(), OutputError> {
    if set.surfels.len() != solution.radiosity.len() {
        return Err(OutputError::invalid(
            path,
            format!(
                "the solution has radiosity for {} surfels but the surfel set holds {}",
                solution.radiosity.len(),
                set.surfels.len()
            ),
        ));
    }
    Ok(())
}

/// Rec. 709 luminance of a linear RGB triple: the one scalar "brightness" used for tone mapping,
/// camera choice and the report.
pub fn luminance(rgb: [f32; 3]) -> f64 {
    0.2126 * rgb[0] as f64 + 0.7152 * rgb[1] as f64 + 0.0722 * rgb[2] as f64
}

#[cfg(test)]
pub(crate) mod testutil {
    //! Hand-built surfel sets shared by the tests of this module.
    use crate::solve::Solution;
    use crate::voxel::{Grid, Surfel, SurfelSet};

    pub fn surfel(voxel: [i32; 3], point: [f32; 3], normal: [f32; 3], area: f32) -> Surfel {
        Surfel {
            voxel,
            point,
            normal,
            normal_id: 0,
            group: 0,
            area,
            material: [0, 0],
            extent: [[0.0; 3], [1.0; 3]],
        }
    }

    pub fn set_of(surfels: Vec<Surfel>, voxel_size: f64) -> SurfelSet {
        SurfelSet {
            grid: Grid {
                origin: [-1.0, 2.0, 0.5],
                voxel_size,
                dims: [16, 16, 16],
            },
            surfels,
            normals: vec![[0.0, 0.0, 1.0]],
            materials: vec![crate::scene::Material::new("white", [0.5; 3], [0.0; 3])],
        }
    }

    /// An n x n square of surfels in the plane z = 0.5 (voxel units) facing +z, its front lit
    /// brighter towards the middle, its back dark.
    pub fn lit_square(n: i32) -> (SurfelSet, Solution) {
        let mut surfels = Vec::new();
        let mut radiosity = Vec::new();
        for x in 0..n {
            for y in 0..n {
                surfels.push(surfel([x, y, 0], [0.5, 0.5, 0.5], [0.0, 0.0, 1.0], 1.0));
                let b = 1.0 + (x.min(n - 1 - x).min(y).min(n - 1 - y)) as f32;
                radiosity.push([[b, b, b], [0.0; 3]]);
            }
        }
        (
            set_of(surfels, 0.25),
            Solution {
                radiosity,
                stats: Default::default(),
            },
        )
    }
}
