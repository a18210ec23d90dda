//! Writes a [`Scene`] as a Wavefront OBJ file plus its MTL file beside it, so generated scenes can
//! go through the same path as user files (`voxrad solve scene.obj`) and be inspected in any viewer.
//!
//! Format choices: vertices are shared only when bit-identical (exact, no tolerance: a tolerance
//! could weld vertices the scene keeps apart); numbers use Rust's shortest round-trip formatting,
//! so reading the file back gives the very same `f64`s; faces keep the scene's triangle order and
//! winding; a `usemtl` line appears whenever the material changes. `Kd` is the reflectance and
//! `Ke` the emitted radiosity, as in the brief. Both files are written to temporary names in the
//! target directory and renamed into place, so a failure never leaves a half-written file behind.

use crate::scene::Scene;
use std::collections::HashMap;
use std::io::{self, BufWriter, Write};
use std::path::Path;

/// Writes `scene` to `obj_path` and its materials to the same path with the extension `.mtl`.
///
/// Errors: `InvalidInput` if `obj_path` has no file name, or if a triangle names a material that
/// does not exist (an OBJ cannot refer to it); otherwise the I/O error that occurred.
pub fn write_obj(scene: &Scene, obj_path: &Path) -> io::Result<()> {
    let file_name = obj_path.file_name().ok_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{}: not a file path", obj_path.display()),
        )
    })?;
    if let Some((i, t)) = scene
        .triangles
        .iter()
        .enumerate()
        .find(|(_, t)| t.material as usize >= scene.materials.len())
    {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "triangle {i} names material {}, but the scene has {} materials",
                t.material,
                scene.materials.len()
            ),
        ));
    }
    let mtl_path = obj_path.with_extension("mtl");
    let mtl_name = mtl_path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let names = material_names(scene);

    let dir = match obj_path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };

    write_atomically(&dir, &mtl_path, |w| write_mtl(scene, &names, w))?;
    write_atomically(&dir, obj_path, |w| {
        write_obj_body(scene, &names, &mtl_name, &file_name.to_string_lossy(), w)
    })
}

/// MTL names must be single tokens and distinct, or a reader would merge or mis-split them.
fn material_names(scene: &Scene) -> Vec<String> {
    let mut seen = HashMap::new();
    scene
        .materials
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let mut name: String = m
                .name
                .chars()
                .map(|c| {
                    if c.is_whitespace() || c == '#' {
                        '_'
                    } else {
                        c
                    }
                })
                .collect();
            if name.is_empty() {
                name = format!("material_{i}");
            }
            if seen.contains_key(&name) {
                name = format!("{name}_{i}");
            }
            seen.insert(name.clone(), i);
            name
        })
        .collect()
}

fn write_mtl(scene: &Scene, names: &[String], w: &mut dyn Write) -> io::Result<()> {
    writeln!(w, "# voxrad materials for {}", scene.source.display())?;
    writeln!(
        w,
        "# Kd = diffuse reflectance, Ke = emitted radiosity E (= pi * radiance)"
    )?;
    for (m, name) in scene.materials.iter().zip(names) {
        writeln!(w)?;
        writeln!(w, "newmtl {name}")?;
        let [r, g, b] = m.reflectance;
        writeln!(w, "Kd {r} {g} {b}")?;
        let [r, g, b] = m.emission;
        writeln!(w, "Ke {r} {g} {b}")?;
    }
    Ok(())
}

fn write_obj_body(
    scene: &Scene,
    names: &[String],
    mtl_name: &str,
    obj_name: &str,
    w: &mut dyn Write,
) -> io::Result<()> {
    writeln!(
        w,
        "# {obj_name}: written by voxrad from {}",
        scene.source.display()
    )?;
    writeln!(w, "mtllib {mtl_name}")?;
    // Exact deduplication: key on the bit patterns (with -0.0 folded into 0.0 so they weld).
    let key = |v: glam::DVec3| [v.x, v.y, v.z].map(|c| (c + 0.0).to_bits());
    let mut index: HashMap<[u64; 3], usize> = HashMap::new();
    let mut corners = Vec::with_capacity(scene.triangles.len());
    for t in &scene.triangles {
        let mut ids = [0usize; 3];
        for (k, v) in t.vertices.iter().enumerate() {
            let next = index.len() + 1;
            let id = *index.entry(key(*v)).or_insert_with(|| {
                // First sighting: emit the vertex now so its number is its line order.
                next
            });
            if id == next {
                writeln!(w, "v {} {} {}", v.x, v.y, v.z)?;
            }
            ids[k] = id;
        }
        corners.push(ids);
    }
    let mut current = None;
    for (t, ids) in scene.triangles.iter().zip(&corners) {
        if current != Some(t.material) {
            writeln!(w, "usemtl {}", names[t.material as usize])?;
            current = Some(t.material);
        }
        writeln!(w, "f {} {} {}", ids[0], ids[1], ids[2])?;
    }
    Ok(())
}

pub(crate) fn write_atomically(
    dir: &Path,
    target: &Path,
    body: impl FnOnce(&mut dyn Write) -> io::Result<()>,
) -> io::Result<()> {
    // A plain file (not `tempfile`, whose files are private 0600) so the result gets the usual
    // permissions; the name is hidden and unique per process, and removed on any failure.
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let result = (|| {
        let file = std::fs::File::create(&tmp)?;
        let mut w = BufWriter::new(&file);
        body(&mut w)?;
        w.flush()?;
        drop(w);
        file.sync_all()?;
        std::fs::rename(&tmp, target)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gen::{cornell_box, furnace};
    use crate::scene::{Material, Triangle};
    use glam::DVec3;
    use std::collections::HashSet;

    fn count(text: &str, prefix: &str) -> usize {
        text.lines().filter(|l| l.starts_with(prefix)).count()
    }

    #[test]
    fn counts_of_vertices_faces_and_materials() {
        let dir = tempfile::tempdir().unwrap();
        for scene in [cornell_box(), furnace(1.0, 0.5)] {
            let path = dir.path().join("scene.obj");
            write_obj(&scene, &path).unwrap();
            let obj = std::fs::read_to_string(&path).unwrap();
            let mtl = std::fs::read_to_string(dir.path().join("scene.mtl")).unwrap();
            let distinct: HashSet<[u64; 3]> = scene
                .triangles
                .iter()
                .flat_map(|t| t.vertices)
                .map(|v| [v.x, v.y, v.z].map(|c| (c + 0.0).to_bits()))
                .collect();
            assert_eq!(count(&obj, "v "), distinct.len());
            assert_eq!(count(&obj, "f "), scene.triangles.len());
            assert_eq!(count(&obj, "mtllib scene.mtl"), 1);
            assert_eq!(count(&mtl, "newmtl "), scene.materials.len());
            assert_eq!(count(&mtl, "Kd "), scene.materials.len());
            assert_eq!(count(&mtl, "Ke "), scene.materials.len());
            // No stray temporary files.
            assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
        }
    }

    /// Parses our own output back (a minimal reader, independent of the crate's OBJ loader) and
    /// checks every triangle and material survives exactly.
    #[test]
    fn round_trips_exactly() {
        let scene = cornell_box();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.obj");
        write_obj(&scene, &path).unwrap();
        let obj = std::fs::read_to_string(&path).unwrap();
        let mtl = std::fs::read_to_string(dir.path().join("c.mtl")).unwrap();
        let nums = |l: &str| -> Vec<f64> {
            l.split_whitespace()
                .skip(1)
                .map(|x| x.parse().unwrap())
                .collect()
        };
        let mut mats: Vec<(String, Vec<f64>, Vec<f64>)> = Vec::new();
        for l in mtl.lines() {
            if let Some(n) = l.strip_prefix("newmtl ") {
                mats.push((n.to_string(), vec![], vec![]));
            } else if l.starts_with("Kd ") {
                mats.last_mut().unwrap().1 = nums(l);
            } else if l.starts_with("Ke ") {
                mats.last_mut().unwrap().2 = nums(l);
            }
        }
        for (m, (n, kd, ke)) in scene.materials.iter().zip(&mats) {
            assert_eq!(&m.name, n);
            assert_eq!(m.reflectance.to_vec(), *kd);
            assert_eq!(m.emission.to_vec(), *ke);
        }
        let mut vs = Vec::new();
        let mut tris = Vec::new();
        let mut cur = 0;
        for l in obj.lines() {
            if l.starts_with("v ") {
                let c = nums(l);
                vs.push(DVec3::new(c[0], c[1], c[2]));
            } else if let Some(n) = l.strip_prefix("usemtl ") {
                cur = mats.iter().position(|m| m.0 == n).unwrap() as u32;
            } else if l.starts_with("f ") {
                let i: Vec<usize> = l
                    .split_whitespace()
                    .skip(1)
                    .map(|x| x.parse().unwrap())
                    .collect();
                tris.push(Triangle {
                    vertices: [vs[i[0] - 1], vs[i[1] - 1], vs[i[2] - 1]],
                    material: cur,
                });
            }
        }
        assert_eq!(tris, scene.triangles);
    }

    /// The crate's reader is built on tobj; the files must load there with every triangle and
    /// the `Kd` / `Ke` values intact.
    #[test]
    fn tobj_reads_the_output() {
        let scene = cornell_box();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.obj");
        write_obj(&scene, &path).unwrap();
        let (models, materials) = tobj::load_obj(
            &path,
            &tobj::LoadOptions {
                triangulate: true,
                single_index: true,
                ..Default::default()
            },
        )
        .unwrap();
        let materials = materials.unwrap();
        assert_eq!(materials.len(), scene.materials.len());
        let faces: usize = models.iter().map(|m| m.mesh.indices.len() / 3).sum();
        assert_eq!(faces, scene.triangles.len());
        for (ours, theirs) in scene.materials.iter().zip(&materials) {
            assert_eq!(ours.name, theirs.name);
            let kd = theirs.diffuse.unwrap();
            let ke = theirs.emissive.unwrap();
            for c in 0..3 {
                assert!((kd[c] as f64 - ours.reflectance[c]).abs() < 1e-6);
                assert!((ke[c] as f64 - ours.emission[c]).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn awkward_material_names_stay_distinct_tokens() {
        let mut s = Scene::default();
        s.add_material(Material::new("a b", [0.1; 3], [0.0; 3]));
        s.add_material(Material::new("a_b", [0.2; 3], [0.0; 3]));
        s.add_material(Material::new("", [0.3; 3], [0.0; 3]));
        let names = material_names(&s);
        assert_eq!(names, ["a_b", "a_b_1", "material_2"]);
    }

    #[test]
    fn bad_material_index_and_bad_path_are_errors_not_panics() {
        let mut s = Scene::default();
        s.add_material(Material::new("m", [0.5; 3], [0.0; 3]));
        s.triangles.push(Triangle {
            vertices: [DVec3::ZERO, DVec3::X, DVec3::Y],
            material: 3,
        });
        let dir = tempfile::tempdir().unwrap();
        let err = write_obj(&s, &dir.path().join("x.obj")).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::InvalidInput);
        s.triangles[0].material = 0;
        let err = write_obj(&s, Path::new("/")).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::InvalidInput);
        let err = write_obj(&s, &dir.path().join("missing/dir/x.obj")).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::NotFound);
    }

    /// The committed example files are exactly what the generator writes today.
    #[test]
    fn committed_examples_are_up_to_date() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
        let dir = tempfile::tempdir().unwrap();
        write_obj(&cornell_box(), &dir.path().join("cornell_box.obj")).unwrap();
        write_obj(&crate::gen::office().scene, &dir.path().join("office.obj")).unwrap();
        for name in [
            "cornell_box.obj",
            "cornell_box.mtl",
            "office.obj",
            "office.mtl",
        ] {
            let fresh = std::fs::read_to_string(dir.path().join(name)).unwrap();
            let committed = std::fs::read_to_string(root.join(name)).unwrap_or_default();
            assert!(
                fresh == committed,
                "examples/{name} is stale: regenerate with `cargo run --example write_examples`"
            );
        }
    }
}
