//! `voxrad render`, `voxrad probe` and `voxrad bake`: read a solve's results and turn them into
//! a picture, into values at given points, or into the scene's mesh with its light baked on; the
//! previews and baked meshes a solve writes.

use super::*;
use glam::DVec3;
use rayon::prelude::*;

/// The PLY and the pictures (`render.png`, `render.exr`): drawn from the baked mesh where there
/// is one (smooth), else from the surfels.
pub(super) fn write_previews(
    out: &Path,
    set: &SurfelSet,
    solution: &Solution,
    mesh: Option<&bake::BakedMesh>,
    size: (u32, u32),
) -> Result<(), AppError> {
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    ply::write_ply(&out.join(crate::output::PLY_FILE), set, solution).map_err(fail)?;
    let camera = auto_camera(set, solution);
    let (png, exr) = (
        out.join(RENDER_FILE),
        out.join(crate::output::RENDER_EXR_FILE),
    );
    let drawn = match mesh {
        Some(mesh) => Drawn::Mesh(mesh),
        None => Drawn::Surfels(set, solution),
    };
    render_pictures(&png, Some(&exr), drawn, &camera, size.0, size.1).map_err(fail)
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
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    // Smooth, from the baked mesh, where the scene the report names is still there (as the
    // solve's own preview); else the surfels.
    match scene_of_report(dir).ok().filter(|p| p.is_file()) {
        Some(scene_path) => {
            let scene = load_scene_for_baking(&scene_path)?;
            let mesh = bake::bake(&scene, &results, &bake::BakeOptions::default());
            let drawn = Drawn::Mesh(&mesh);
            render_pictures(out, None, drawn, &camera, size.0, size.1).map_err(fail)
        }
        None => render_png(out, &set, &solution, &camera, size.0, size.1).map_err(fail),
    }
}

/// `voxrad probe DIR --points P.csv [--gather [N]]`: rows on standard output (or into `out`);
/// with `gather`, each answered by gathering along about that many directions (without a
/// count, as many as `sensor::directions_for` the solve's grid).
pub fn run_probe(
    dir: &Path,
    points: &Path,
    out: Option<&Path>,
    gather: Option<Option<usize>>,
) -> Result<(), AppError> {
    let results = load_results(dir)?;
    let mut rows = probe::probe(&results, points).map_err(|e| AppError::BadInput(e.to_string()))?;
    if let Some(directions) = gather {
        if results.materials.is_empty() {
            return Err(AppError::BadInput(format!(
                "{}: results written before version 2 of the format do not say which surfaces \
                 emit; solve again to gather",
                dir.join(crate::output::RESULTS_FILE).display()
            )));
        }
        let directions =
            directions.unwrap_or_else(|| crate::output::sensor::directions_for(results.grid.dims));
        let field = crate::output::sensor::SensorField::new(&results, directions);
        rows = rows.par_iter().map(|row| field.gather_row(row)).collect();
    }
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

/// Bakes `results` onto `scene`, writes `baked.glb` and `baked.ply` into `out` and returns the
/// mesh.
pub(super) fn write_baked(
    out: &Path,
    scene: &crate::scene::Scene,
    results: &Results,
) -> Result<bake::BakedMesh, AppError> {
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    let t = Instant::now();
    let mesh = bake::bake(scene, results, &bake::BakeOptions::default());
    glb::write_glb(&out.join(crate::output::BAKED_GLB_FILE), &mesh).map_err(fail)?;
    mesh_ply::write_mesh_ply(&out.join(crate::output::BAKED_PLY_FILE), &mesh).map_err(fail)?;
    tracing::info!(
        triangles = mesh.triangle_count(),
        vertices = mesh.positions.len(),
        seconds = t.elapsed().as_secs_f64(),
        "baked onto the scene's triangles"
    );
    Ok(mesh)
}

/// Reads the OBJ scene at `path` for baking.
pub(super) fn load_scene_for_baking(path: &Path) -> Result<crate::scene::Scene, AppError> {
    load_obj(path).map_err(|e| {
        if e.is_bad_input() {
            AppError::BadInput(e.to_string())
        } else {
            AppError::Failure(e.to_string())
        }
    })
}

/// `voxrad bake DIR [--scene SCENE.obj] --out FILE.glb|FILE.ply`: the results of a solve baked
/// onto the triangles of its scene (by default the scene `report.json` names).
pub fn run_bake(dir: &Path, scene: Option<&Path>, out: &Path) -> Result<(), AppError> {
    let results = load_results(dir)?;
    let scene_path = match scene {
        Some(path) => path.to_path_buf(),
        None => scene_of_report(dir)?,
    };
    if scene_path.is_dir() {
        return Err(AppError::BadInput(format!(
            "{}: a shard set holds voxels, not the scene's triangles; give the OBJ scene with \
             --scene",
            scene_path.display()
        )));
    }
    let scene = load_scene_for_baking(&scene_path)?;
    let mesh = bake::bake(&scene, &results, &bake::BakeOptions::default());
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    match out.extension().and_then(|e| e.to_str()) {
        Some(e) if e.eq_ignore_ascii_case("glb") => {
            glb::write_glb(out, &mesh).map_err(fail)?;
        }
        Some(e) if e.eq_ignore_ascii_case("ply") => {
            mesh_ply::write_mesh_ply(out, &mesh).map_err(fail)?;
        }
        _ => {
            return Err(AppError::BadInput(format!(
                "{}: the baked mesh is written as .glb (glTF binary) or .ply",
                out.display()
            )))
        }
    }
    Ok(())
}

/// The scene path `DIR/report.json` names.
fn scene_of_report(dir: &Path) -> Result<PathBuf, AppError> {
    let path = dir.join(crate::output::REPORT_FILE);
    let text = std::fs::read_to_string(&path).map_err(|e| {
        AppError::BadInput(format!(
            "{}: {e}; give the scene with --scene",
            path.display()
        ))
    })?;
    let json: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| AppError::BadInput(format!("{}: {e}", path.display())))?;
    json.get("scene")
        .and_then(|s| s.as_str())
        .map(PathBuf::from)
        .ok_or_else(|| {
            AppError::BadInput(format!(
                "{}: no \"scene\" key; give the scene with --scene",
                path.display()
            ))
        })
}

/// `voxrad grid DIR --height H --spacing S --out PREFIX`: irradiance sensors on a workplane,
/// written to `PREFIX.csv` and `PREFIX.png`; the figures go to standard output.
pub fn run_grid(
    dir: &Path,
    spec: &crate::output::grid::GridSpec,
    directions: usize,
    prefix: &Path,
) -> Result<(), AppError> {
    let results = load_results(dir)?;
    if results.materials.is_empty() {
        return Err(AppError::BadInput(format!(
            "{}: results written before version 2 of the format do not say which surfaces \
             emit; solve again to gather irradiance",
            dir.join(crate::output::RESULTS_FILE).display()
        )));
    }
    let (mut low, mut high) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for r in &results.records {
        let p = results.world_position(r);
        low = low.min(p);
        high = high.max(p);
    }
    let t = Instant::now();
    let field = crate::output::sensor::SensorField::new(&results, directions);
    let grid = crate::output::grid::GridResult::gather(&field, spec, [low, high])
        .map_err(AppError::BadInput)?;
    let with = |ext: &str| {
        let mut name = prefix.as_os_str().to_owned();
        name.push(ext);
        PathBuf::from(name)
    };
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    grid.write_csv(&with(".csv")).map_err(fail)?;
    grid.write_png(&with(".png")).map_err(fail)?;
    let f = grid.figures();
    println!(
        "{} x {} sensors at {} = {} ({} directions and {} emitting sides each, {:.1} s): \
         irradiance min {:.6}, mean {:.6}, max {:.6} (units of Ke), uniformity U0 = min/mean {:.4}",
        grid.counts[0],
        grid.counts[1],
        ["x", "y", "z"][spec.up],
        spec.height,
        field.direction_count(),
        field.emitter_count(),
        t.elapsed().as_secs_f64(),
        f.min,
        f.mean,
        f.max,
        f.uniformity
    );
    Ok(())
}
