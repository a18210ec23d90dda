//! `voxrad render` and `voxrad probe`: read a solve's results and turn them into a picture or
//! into values at given points; the previews a solve writes.

use super::*;

/// The PLY and the picture.
pub(super) fn write_previews(
    out: &Path,
    set: &SurfelSet,
    solution: &Solution,
    size: (u32, u32),
) -> Result<(), AppError> {
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    ply::write_ply(&out.join(crate::output::PLY_FILE), set, solution).map_err(fail)?;
    let camera = auto_camera(set, solution);
    render_png(
        &out.join(RENDER_FILE),
        set,
        solution,
        &camera,
        size.0,
        size.1,
    )
    .map_err(fail)?;
    Ok(())
}

/// Rebuilds a surfel set and solution from a results file, for rendering.
pub(super) fn from_results(results: &Results) -> (SurfelSet, Solution) {
    let surfels = results
        .records
        .iter()
        .map(|r| Surfel {
            voxel: r.voxel,
            point: r.point,
            normal: r.normal,
            normal_id: 0,
            group: 0,
            area: r.area,
            material: [0, 0],
            extent: [[0.0; 3], [1.0; 3]],
        })
        .collect();
    let radiosity = results.records.iter().map(|r| r.radiosity).collect();
    let set = SurfelSet {
        grid: results.grid,
        surfels,
        normals: Vec::new(),
        materials: Vec::new(),
    };
    (
        set,
        Solution {
            radiosity,
            stats: Default::default(),
        },
    )
}

pub(super) fn load_results(dir: &Path) -> Result<Results, AppError> {
    let path = dir.join(crate::output::RESULTS_FILE);
    if !path.exists() {
        return Err(AppError::BadInput(format!(
            "{}: no results file; is {} the --out directory of a finished `voxrad solve`?",
            path.display(),
            dir.display()
        )));
    }
    read_results(&path).map_err(|e| AppError::BadInput(e.to_string()))
}

/// `voxrad render DIR --out IMG [--camera ...]`.
pub fn run_render(
    dir: &Path,
    out: &Path,
    camera: Option<&str>,
    size: (u32, u32),
) -> Result<(), AppError> {
    let results = load_results(dir)?;
    let (set, solution) = from_results(&results);
    let camera = match camera {
        Some(text) => Camera::parse(text).map_err(|e| AppError::BadInput(e.to_string()))?,
        None => auto_camera(&set, &solution),
    };
    render_png(out, &set, &solution, &camera, size.0, size.1)
        .map_err(|e| AppError::Failure(e.to_string()))
}

/// `voxrad probe DIR --points P.csv`: rows on standard output (or into `out`).
pub fn run_probe(dir: &Path, points: &Path, out: Option<&Path>) -> Result<(), AppError> {
    let results = load_results(dir)?;
    let rows = probe::probe(&results, points).map_err(|e| AppError::BadInput(e.to_string()))?;
    match out {
        Some(path) => {
            probe::write_probe_csv(path, &rows).map_err(|e| AppError::Failure(e.to_string()))
        }
        None => {
            let stdout = std::io::stdout();
            let mut lock = stdout.lock();
            probe::write_rows(&mut lock, &rows)
                .map_err(|e| AppError::Failure(format!("cannot write to standard output: {e}")))
        }
    }
}
