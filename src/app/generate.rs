//! `voxrad generate` (scenes, their probes and surfaces) and `voxrad study`.

use super::*;

/// A scene the `generate` command can write.
#[derive(Clone, Copy, Debug)]
pub enum GenerateScene {
    Cornell,
    Room {
        furniture: usize,
        seed: u64,
    },
    Building {
        rooms: (usize, usize, usize),
        seed: u64,
    },
    SealedRooms,
    Furnace,
    /// Two facing unit squares at distance 1 (emitter `E` = 1, receiver `rho` = 0.5).
    ParallelSquares,
    Office,
    WindowRoom,
    Corridor,
    ThinSlab {
        /// Thickness in voxels at resolution 128.
        thickness: f64,
        /// Degrees about y and about x.
        tilt: [f64; 2],
        light: crate::gen::SlabLight,
    },
    /// A twin of a furnace hard case under light from one place.
    HardTwin(crate::gen::HardTwin),
}

/// The scene and its probes: the generator's own for the interiors, else 300 points from
/// [`crate::study::probe_points`] (seed `0x5eed`, labelled with their material's name).
pub(super) fn generated(which: GenerateScene) -> crate::gen::Interior {
    let scene = match which {
        GenerateScene::Cornell => crate::gen::cornell_box(),
        GenerateScene::Room { furniture, seed } => crate::gen::room(5.0, seed, furniture),
        GenerateScene::Building {
            rooms: (x, z, floors),
            seed,
        } => crate::gen::building(x, z, floors, seed),
        GenerateScene::SealedRooms => crate::gen::sealed_rooms(),
        GenerateScene::Furnace => crate::gen::furnace(1.0, 0.5),
        GenerateScene::ParallelSquares => {
            crate::gen::parallel_squares_reflecting(1.0, 1.0, 1.0, 0.5)
        }
        GenerateScene::Office => return crate::gen::office(),
        GenerateScene::WindowRoom => return crate::gen::window_room(),
        GenerateScene::Corridor => return crate::gen::corridor(),
        GenerateScene::ThinSlab {
            thickness,
            tilt,
            light,
        } => return crate::gen::thin_slab(thickness, tilt, light),
        GenerateScene::HardTwin(which) => return crate::gen::hard_twin(which),
    };
    let probes = crate::study::probe_points(&scene, 300, 0x5eed)
        .into_iter()
        .map(|(point, normal)| {
            // The material of the triangle the point was drawn on (the closest coplanar one).
            let surface = scene
                .triangles
                .iter()
                .filter(|t| {
                    let n = t.cross().normalize();
                    n.dot(normal) > 1.0 - 1e-9 && (point - t.vertices[0]).dot(n).abs() < 1e-9
                })
                .map(|t| scene.materials[t.material as usize].name.clone())
                .next()
                .unwrap_or_default();
            crate::gen::Probe {
                point,
                normal,
                surface,
            }
        })
        .collect();
    crate::gen::Interior { scene, probes }
}

pub(super) fn write_text(path: &Path, text: &str) -> Result<(), AppError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    crate::gen::obj_writer::write_atomically(&dir, path, |w| {
        std::io::Write::write_all(w, text.as_bytes())
    })
    .map_err(|e| AppError::Failure(format!("cannot write {}: {e}", path.display())))
}

/// `voxrad generate KIND --out FILE.obj [--probes P.csv] [--surfaces S.csv]`: writes the scene,
/// optionally its probe points (`x,y,z,nx,ny,nz`) and their surface labels (`probe,surface`),
/// and returns the triangle count.
pub fn run_generate(
    which: GenerateScene,
    out: &Path,
    probes: Option<&Path>,
    surfaces: Option<&Path>,
) -> Result<usize, AppError> {
    if out
        .extension()
        .is_none_or(|e| !e.eq_ignore_ascii_case("obj"))
    {
        return Err(AppError::BadInput(format!(
            "{}: the output must be an .obj file",
            out.display()
        )));
    }
    let crate::gen::Interior {
        scene,
        probes: points,
    } = generated(which);
    crate::gen::write_obj(&scene, out)
        .map_err(|e| AppError::Failure(format!("cannot write {}: {e}", out.display())))?;
    if let Some(path) = probes {
        write_text(path, &crate::gen::interiors::probes_csv(&points))?;
    }
    if let Some(path) = surfaces {
        write_text(path, &crate::gen::interiors::surfaces_csv(&points))?;
    }
    Ok(scene.triangles.len())
}

/// `voxrad study SCENE --out DIR [--quick | --presets]`: SCENE is a built-in name (`furnace`,
/// `cornell`), an .obj file, or a directory of reference data (`scene.obj`, `reference.csv`).
/// Writes `study.csv`, `study.md` and `study.png` and returns the study.
pub fn run_study(
    scene: &str,
    out: &Path,
    quick: bool,
    presets: bool,
    threads: usize,
) -> Result<crate::study::Study, AppError> {
    use crate::study::{Plan, StudyScene};
    let load = |path: &Path| {
        load_obj(path).map_err(|e| {
            if e.is_bad_input() {
                AppError::BadInput(e.to_string())
            } else {
                AppError::Failure(e.to_string())
            }
        })
    };
    let path = Path::new(scene);
    let studied = match StudyScene::builtin(scene) {
        Some(s) => s,
        None if path.is_dir() => {
            let reference = crate::study::reference::Reference::load(path)
                .map_err(|e| AppError::BadInput(e.to_string()))?;
            StudyScene {
                name: scene.to_string(),
                scene: load(&path.join("scene.obj"))?,
                analytic: None,
                path_traced: Some(reference),
            }
        }
        None if path.exists() => StudyScene {
            name: scene.to_string(),
            scene: load(path)?,
            analytic: None,
            path_traced: None,
        },
        None => {
            return Err(AppError::BadInput(format!(
                "{scene}: neither a built-in scene (furnace, cornell), an existing .obj file nor \
                 a directory of reference data"
            )))
        }
    };
    let mut plan = if quick {
        Plan::quick()
    } else if presets {
        Plan::presets_only()
    } else {
        Plan::full()
    };
    plan.threads = threads;
    let study = crate::study::run(&studied, &plan, |r| {
        tracing::info!(
            knob = r.knob,
            resolution = r.settings.resolution,
            directions = r.directions_used,
            tolerance = r.settings.tolerance,
            iterations = r.iterations,
            seconds = format!("{:.2}", r.seconds),
            mean_error = format!("{:.2e}", r.mean_error),
            gathered_mean_error = format!("{:.2e}", r.gathered_mean_error),
            "study run"
        );
    })
    .map_err(|e| AppError::BadInput(format!("{scene}: {e}")))?;
    crate::study::write(&study, out).map_err(AppError::Failure)?;
    Ok(study)
}
