//! Integration tests of the OBJ + MTL reader (`voxrad::scene::obj`): valid scenes load with the
//! right triangles and materials, every kind of bad input gives a `LoadError` naming the file and
//! line, and no OBJ file of Debian's `assimp-testmodels` makes the reader panic.

use std::path::{Path, PathBuf};
use voxrad::scene::obj::{load_obj, LoadError, DEFAULT_MATERIAL, DEFAULT_REFLECTANCE};
use voxrad::scene::Scene;

fn write(dir: &Path, name: &str, content: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, content).expect("write test file");
    path
}

fn load_ok(dir: &Path, obj: &str) -> Scene {
    let path = dir.join(obj);
    match load_obj(&path) {
        Ok(scene) => scene,
        Err(e) => panic!("{} should load, got: {e}", path.display()),
    }
}

/// Loads a file that must be rejected and checks the error is bad input, names `file` and
/// carries `line`. Returns the message for further checks.
fn load_bad(dir: &Path, obj: &str, file: &str, line: Option<usize>) -> String {
    let path = dir.join(obj);
    let err = match load_obj(&path) {
        Ok(scene) => panic!(
            "{} should be rejected, loaded {} triangles",
            path.display(),
            scene.triangles.len()
        ),
        Err(e) => e,
    };
    let msg = err.to_string();
    assert!(err.is_bad_input(), "not bad input: {msg}");
    assert!(msg.contains(file), "message does not name {file}: {msg}");
    assert_eq!(
        err.path().file_name().and_then(|f| f.to_str()),
        Some(file),
        "{msg}"
    );
    assert_eq!(err.line(), line, "wrong line in: {msg}");
    if let Some(l) = line {
        assert!(msg.contains(&format!("line {l}:")), "no line {l} in: {msg}");
    }
    msg
}

fn total_area(scene: &Scene) -> f64 {
    scene.triangles.iter().map(|t| t.area()).sum()
}

fn material_area(scene: &Scene, name: &str) -> f64 {
    let Some(m) = scene.materials.iter().position(|m| m.name == name) else {
        panic!("no material {name}");
    };
    scene
        .triangles
        .iter()
        .filter(|t| t.material as usize == m)
        .map(|t| t.area())
        .sum()
}

const TWO_MATERIALS_MTL: &str = "\
newmtl wall
Kd 0.8 0.1 0.1
Ka 1 1 1
newmtl lamp
Kd 0 0 0
Ke 10 20 30
";

#[test]
fn two_material_scene_with_quads() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(dir.path(), "scene.mtl", TWO_MATERIALS_MTL);
    // A 2 x 3 wall quad, a 1 x 1 lamp quad, and a pentagon of area 2 x 2 - 0.5 in the wall material.
    write(
        dir.path(),
        "scene.obj",
        "mtllib scene.mtl\n\
         v 0 0 0\nv 2 0 0\nv 2 3 0\nv 0 3 0\n\
         v 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n\
         v 0 0 5\nv 2 0 5\nv 2 1 5\nv 1 2 5\nv 0 2 5\n\
         usemtl wall\nf 1 2 3 4\n\
         usemtl lamp\nf 5 6 7 8\n\
         usemtl wall\nf 9 10 11 12 13\n",
    );
    let scene = load_ok(dir.path(), "scene.obj");
    assert_eq!(scene.triangles.len(), 2 + 2 + 3);
    assert_eq!(scene.materials.len(), 2, "materials are deduplicated");
    assert!((total_area(&scene) - (6.0 + 1.0 + 3.5)).abs() < 1e-12);
    assert!((material_area(&scene, "wall") - 9.5).abs() < 1e-12);
    assert!((material_area(&scene, "lamp") - 1.0).abs() < 1e-12);
    let lamp = scene.materials.iter().find(|m| m.name == "lamp").unwrap();
    assert_eq!(lamp.emission, [10.0, 20.0, 30.0]);
    assert_eq!(lamp.reflectance, [0.0, 0.0, 0.0]);
    assert!(lamp.is_emitter());
    let wall = scene.materials.iter().find(|m| m.name == "wall").unwrap();
    assert_eq!(wall.reflectance, [0.8, 0.1, 0.1]);
    assert_eq!(wall.emission, [0.0; 3]);
    assert_eq!(scene.source, dir.path().join("scene.obj"));
    // Winding gives the front side: the first quad is counter-clockwise seen from +z.
    assert!(scene.triangles[0].cross().z > 0.0);
}

#[test]
fn groups_vertex_forms_negative_indices_and_comments() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(dir.path(), "m.mtl", TWO_MATERIALS_MTL);
    write(
        dir.path(),
        "groups.obj",
        "# a comment\n\
         \n\
         mtllib m.mtl\n\
         o first\n\
         v 0 0 0\nv 1 0 0\nv 1 1 0 # trailing comment\n\
         vt 0 0\nvt 1 0\nvt 1 1\n\
         vn 0 0 1\n\
         g part_a\n\
         usemtl wall\n\
         f 1/1/1 2/2/1 3/3/1\n\
         g part_b\n\
         \t  \n\
         v 0 0 2\nv 1 0 2\nv 1 1 2\n\
         f -3//1 -2//1 -1//1\n\
         o second\n\
         usemtl lamp\n\
         v 0 0 4\nv 2 0 4\nv 0 2 4\n\
         f 7/1 8/2 9/3\n\
         s off\n\
         f -1 -2 -3\n",
    );
    let scene = load_ok(dir.path(), "groups.obj");
    assert_eq!(scene.triangles.len(), 4);
    assert!((total_area(&scene) - (0.5 + 0.5 + 2.0 + 2.0)).abs() < 1e-12);
    assert_eq!(scene.materials.len(), 2);
    // The negative indices named the second triangle's own vertices.
    let t = scene.triangles[1];
    assert_eq!(t.vertices[0].z, 2.0);
    assert_eq!(t.vertices[2].x, 1.0);
    // `f -1 -2 -3` reverses the winding of `f 7 8 9`.
    assert!(scene.triangles[2].cross().z > 0.0);
    assert!(scene.triangles[3].cross().z < 0.0);
}

#[test]
fn crlf_line_endings() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(
        dir.path(),
        "c.mtl",
        &TWO_MATERIALS_MTL.replace('\n', "\r\n"),
    );
    write(
        dir.path(),
        "crlf.obj",
        "mtllib c.mtl\r\nv 0 0 0\r\nv 1 0 0\r\nv 1 1 0\r\nv 0 1 0\r\nusemtl lamp\r\nf 1 2 3 4\r\n",
    );
    let scene = load_ok(dir.path(), "crlf.obj");
    assert_eq!(scene.triangles.len(), 2);
    assert_eq!(scene.materials[0].name, "lamp");
    assert_eq!(scene.materials[0].emission, [10.0, 20.0, 30.0]);
    // An error's line number counts CRLF lines too.
    write(
        dir.path(),
        "bad.obj",
        "v 0 0 0\r\nv 1 0 0\r\nv 1 nan 0\r\nf 1 2 3\r\n",
    );
    load_bad(dir.path(), "bad.obj", "bad.obj", Some(3));
}

#[test]
fn defaults_and_ignored_mtl_statements() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(
        dir.path(),
        "d.mtl",
        "Kd 0.9 0.9 0.9\n\
         newmtl bare\n\
         Km 0.1\nrefl -type sphere chrome.rgb\ndisp -mm 0 1 bump.png\nPr 0.5\nPm 1\n\
         map_Kd wood.png\nmap_Bump -bm 2 n.png\nbump\nillum 2\nNs 10\nd 1\nTf 1 1 1\n\
         Ka spectral x.rfl\nsomething_unknown 1 2\n\
         newmtl grey\n\
         Kd 0.3\n",
    );
    write(
        dir.path(),
        "d.obj",
        "mtllib d.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\n\
         f 1 2 3\nusemtl bare\nf 1 2 3\nusemtl grey\nf 1 2 3\n",
    );
    let scene = load_ok(dir.path(), "d.obj");
    assert_eq!(scene.materials.len(), 3);
    assert_eq!(scene.materials[0].name, DEFAULT_MATERIAL);
    assert_eq!(scene.materials[0].reflectance, DEFAULT_REFLECTANCE);
    assert_eq!(scene.materials[1].name, "bare");
    assert_eq!(scene.materials[1].reflectance, [0.5; 3]);
    assert_eq!(scene.materials[1].emission, [0.0; 3]);
    assert_eq!(scene.materials[2].reflectance, [0.3; 3]);
    // A file without any material statement gets the default grey.
    write(
        dir.path(),
        "plain.obj",
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    );
    let plain = load_ok(dir.path(), "plain.obj");
    assert_eq!(plain.materials.len(), 1);
    assert!(!plain.materials[0].is_emitter());
}

#[test]
fn mtllib_after_usemtl_spaces_in_names_and_several_libraries() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(dir.path(), "a.mtl", "newmtl red paint\nKd 0.7 0 0\n");
    write(dir.path(), "b.mtl", "newmtl light\nKe 1 1 1\nKd 0 0 0\n");
    write(dir.path(), "my lib.mtl", "newmtl spaced\nKd 0.2 0.2 0.2\n");
    write(
        dir.path(),
        "late.obj",
        "v 0 0 0\nv 1 0 0\nv 0 1 0\n\
         usemtl red paint\nf 1 2 3\nusemtl light\nf 1 3 2\nusemtl spaced\nf 2 3 1\n\
         mtllib a.mtl b.mtl\nmtllib my lib.mtl\n",
    );
    let scene = load_ok(dir.path(), "late.obj");
    let names: Vec<&str> = scene.materials.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["red paint", "light", "spaced"]);
    assert_eq!(scene.materials[1].emission, [1.0; 3]);
}

#[test]
fn coordinates_keep_double_precision_and_w_divides() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(
        dir.path(),
        "p.obj",
        "v 12345678.001 0.1 -7.25\nv 12345679.001 0.1 -7.25\nv 4 2 6 2\nf 1 2 3\n",
    );
    let scene = load_ok(dir.path(), "p.obj");
    let t = scene.triangles[0];
    assert_eq!(t.vertices[0].x, 12345678.001);
    assert_eq!(t.vertices[0].y, 0.1);
    assert_eq!(t.vertices[1].x, 12345679.001);
    assert_eq!(t.vertices[2].to_array(), [2.0, 1.0, 3.0]);
}

#[test]
fn utf16_and_bom_files_load() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = "v 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nf 1 2 3\r\n";
    let mut utf16 = vec![0xFE, 0xFF];
    for u in text.encode_utf16() {
        utf16.extend_from_slice(&u.to_be_bytes());
    }
    std::fs::write(dir.path().join("u16.obj"), utf16).unwrap();
    assert_eq!(load_ok(dir.path(), "u16.obj").triangles.len(), 1);
    let mut bom = vec![0xEF, 0xBB, 0xBF];
    bom.extend_from_slice(text.as_bytes());
    std::fs::write(dir.path().join("bom.obj"), bom).unwrap();
    assert_eq!(load_ok(dir.path(), "bom.obj").triangles.len(), 1);
}

// ---------------------------------------------------------------------------------------------
// Bad input.

const TRI: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";

#[test]
fn missing_and_unreadable_files() {
    let dir = tempfile::tempdir().expect("tempdir");
    let msg = load_bad(dir.path(), "nothere.obj", "nothere.obj", None);
    assert!(msg.contains("check the path"), "{msg}");

    std::fs::create_dir(dir.path().join("adir.obj")).unwrap();
    load_bad(dir.path(), "adir.obj", "adir.obj", None);

    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let path = write(dir.path(), "secret.obj", TRI);
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o000)).unwrap();
        // Root reads anything; only check where the permission really denies reading.
        if std::fs::read(&path).is_err() {
            load_bad(dir.path(), "secret.obj", "secret.obj", None);
        }
    }
}

#[test]
fn missing_mtl_names_the_library_and_the_obj_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(
        dir.path(),
        "scene.obj",
        &format!("# header\n{TRI}mtllib gone.mtl\nf 1 2 3\n"),
    );
    let msg = load_bad(dir.path(), "scene.obj", "scene.obj", Some(5));
    assert!(msg.contains("gone.mtl"), "{msg}");
    // One of several libraries missing: the missing one is named.
    write(dir.path(), "here.mtl", "newmtl x\n");
    write(
        dir.path(),
        "two.obj",
        &format!("{TRI}mtllib here.mtl gone2.mtl\nf 1 2 3\n"),
    );
    let msg = load_bad(dir.path(), "two.obj", "two.obj", Some(4));
    assert!(msg.contains("gone2.mtl"), "{msg}");
}

#[test]
fn malformed_obj_statements() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cases: &[(&str, usize)] = &[
        ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", 2),
        ("v 0 0 0\nv 1 0 0\nv 0 abc 0\nf 1 2 3\n", 3),
        ("v 0 0 0\nv 1 0 0\nv 0 3.1+e2 0\nf 1 2 3\n", 3),
        ("v 0 0 0 1 1\n", 1),
        (&format!("{TRI}f 1 2 x\n"), 4),
        (&format!("{TRI}f 1/1/1/1 2 3\n"), 4),
        (&format!("{TRI}f /1 2 3\n"), 4),
        (&format!("{TRI}\n\nf\n"), 6),
        ("v 0 0 0 1 1 1 1\n", 1),
        (&format!("{TRI}mtllib\nf 1 2 3\n"), 4),
    ];
    for (i, (text, line)) in cases.iter().enumerate() {
        let name = format!("m{i}.obj");
        write(dir.path(), &name, text);
        load_bad(dir.path(), &name, &name, Some(*line));
    }
}

#[test]
fn non_finite_coordinates() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cases: &[(&str, usize)] = &[
        ("v 0 0 0\nv 1 0 0\nv NaN 1 0\nf 1 2 3\n", 3),
        ("v 0 0 0\nv inf 0 0\nv 0 1 0\nf 1 2 3\n", 2),
        ("v 0 0 0\nv 1 0 0\nv 0 1 -infinity\nf 1 2 3\n", 3),
        ("v 1e400 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", 1),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0 0\nf 1 2 3\n", 3),
        ("v 0 0 0\nv 1 0 0\nv 1e300 1 0 1e-300\nf 1 2 3\n", 3),
    ];
    for (i, (text, line)) in cases.iter().enumerate() {
        let name = format!("n{i}.obj");
        write(dir.path(), &name, text);
        let msg = load_bad(dir.path(), &name, &name, Some(*line));
        assert!(msg.contains("finite"), "{msg}");
    }
}

#[test]
fn face_indices_out_of_range() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cases: &[(&str, usize)] = &[
        (&format!("{TRI}f 1 2 4\n"), 4),
        (&format!("{TRI}f 1 2 0\n"), 4),
        (&format!("{TRI}f -4 -2 -1\n"), 4),
        (&format!("{TRI}f 1 2 99999999999999999999\n"), 4),
        // A vertex defined after the face does not count.
        ("v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n", 3),
        (&format!("{TRI}vt 0 0\nf 1/2 2/1 3/1\n"), 5),
        (&format!("{TRI}vn 0 0 1\nf 1//1 2//0 3//1\n"), 5),
        (&format!("{TRI}f 1/1 2/1 3/1\n"), 4),
    ];
    for (i, (text, line)) in cases.iter().enumerate() {
        let name = format!("i{i}.obj");
        write(dir.path(), &name, text);
        load_bad(dir.path(), &name, &name, Some(*line));
    }
    // assimp's malformed.obj: out-of-range indices inside a larger file.
    write(
        dir.path(),
        "box.obj",
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 4 12 2 1\n",
    );
    let msg = load_bad(dir.path(), "box.obj", "box.obj", Some(5));
    assert!(msg.contains("12"), "{msg}");
}

#[test]
fn unknown_material() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(dir.path(), "m.mtl", "newmtl known\nKd 0.5 0.5 0.5\n");
    write(
        dir.path(),
        "u.obj",
        &format!("mtllib m.mtl\n{TRI}usemtl known\nf 1 2 3\nusemtl typo\nf 1 2 3\n"),
    );
    let msg = load_bad(dir.path(), "u.obj", "u.obj", Some(7));
    assert!(msg.contains("typo") && msg.contains("m.mtl"), "{msg}");
    // `usemtl` without a name, when the library has no unnamed material.
    write(
        dir.path(),
        "noname.obj",
        &format!("mtllib m.mtl\n{TRI}usemtl\nf 1 2 3\n"),
    );
    let msg = load_bad(dir.path(), "noname.obj", "noname.obj", Some(5));
    assert!(msg.contains("without a name"), "{msg}");
}

#[test]
fn usemtl_without_any_library_uses_the_default() {
    let dir = tempfile::tempdir().expect("tempdir");
    write(
        dir.path(),
        "nolib.obj",
        &format!("{TRI}usemtl red\nf 1 2 3\nusemtl blue\nf 1 3 2\n"),
    );
    let scene = load_ok(dir.path(), "nolib.obj");
    assert_eq!(scene.triangles.len(), 2);
    assert_eq!(scene.materials.len(), 1);
    assert_eq!(scene.materials[0].reflectance, DEFAULT_REFLECTANCE);
}

#[test]
fn unnamed_blender_material() {
    // Blender writes `newmtl ` and `usemtl ` (with a trailing space) for an unnamed material.
    let dir = tempfile::tempdir().expect("tempdir");
    write(
        dir.path(),
        "b.mtl",
        "newmtl \nKd 0.8 0.8 0.8\nnewmtl other\n",
    );
    write(
        dir.path(),
        "b.obj",
        &format!("mtllib b.mtl\n{TRI}usemtl \nf 1 2 3\n"),
    );
    let scene = load_ok(dir.path(), "b.obj");
    assert_eq!(scene.materials.len(), 1);
    assert_eq!(scene.materials[0].name, "");
    assert_eq!(scene.materials[0].reflectance, [0.8; 3]);
}

/// Writes `scene.obj` using material `used` from an MTL with `mtl` as its text.
fn obj_with_mtl(dir: &Path, mtl: &str, used: &str) {
    write(dir, "scene.mtl", mtl);
    write(
        dir,
        "scene.obj",
        &format!("mtllib scene.mtl\n{TRI}usemtl {used}\nf 1 2 3\n"),
    );
}

#[test]
fn bad_reflectance() {
    let dir = tempfile::tempdir().expect("tempdir");
    let head = "# materials\nnewmtl ok\nKd 0.5 0.5 0.5\n\nnewmtl bad\nKs 1 1 1\n";
    for (kd, word) in [
        ("Kd 1.2 0.5 0.5", "lower it"),
        ("Kd 0.5 1 0.5", "lower it"),
        ("Kd 1", "lower it"),
        ("Kd 0.5 0.5 -0.1", "black"),
        ("Kd 0.5 nan 0.5", "not a number"),
        ("Kd 0.5 0.5 inf", "lower it"),
    ] {
        obj_with_mtl(dir.path(), &format!("{head}{kd}\nNs 3\n"), "bad");
        let msg = load_bad(dir.path(), "scene.obj", "scene.mtl", Some(7));
        assert!(msg.contains(kd) && msg.contains(word), "{msg}");
        assert!(msg.contains("[0, 1)"), "{msg}");
    }
    // The same value in a material no face uses is not an error.
    obj_with_mtl(dir.path(), &format!("{head}Kd 1.2 1 1\n"), "ok");
    load_ok(dir.path(), "scene.obj");
}

#[test]
fn bad_emission() {
    let dir = tempfile::tempdir().expect("tempdir");
    let head = "newmtl lamp\nKd 0 0 0\n";
    for ke in ["Ke 1 -2 1", "Ke inf 1 1", "Ke 1 1 nan"] {
        obj_with_mtl(dir.path(), &format!("{head}{ke}\n"), "lamp");
        let msg = load_bad(dir.path(), "scene.obj", "scene.mtl", Some(3));
        assert!(msg.contains(ke), "{msg}");
    }
}

#[test]
fn malformed_mtl_statements() {
    let dir = tempfile::tempdir().expect("tempdir");
    // `Kd 0.5 0.5` makes tobj 4 panic; here it is an error with its line.
    for (mtl, line) in [
        ("newmtl a\nKd 0.5 0.5\n", 2),
        ("newmtl a\n\nKd 0.5 x 0.5\n", 3),
        ("newmtl a\nKd\n", 2),
        ("newmtl a\nKd 0.1 0.2 0.3 0.4\n", 2),
        ("newmtl a\nKd spectral file.rfl\n", 2),
        ("newmtl a\nKe 1 2\n", 2),
        ("newmtl a\nKe one 1 1\n", 2),
    ] {
        obj_with_mtl(dir.path(), mtl, "a");
        load_bad(dir.path(), "scene.obj", "scene.mtl", Some(line));
    }
}

#[test]
fn scenes_without_surfaces() {
    let dir = tempfile::tempdir().expect("tempdir");
    for (name, text) in [
        ("empty.obj", ""),
        ("comments.obj", "# nothing\n\n"),
        ("vertices.obj", TRI),
        ("points.obj", &format!("{TRI}p 1 2 3\nl 1 2 3\nf 1 2\n")),
        (
            "flat.obj",
            "v 0 0 0\nv 1 1 1\nv 2 2 2\nv 5 5 5\nf 1 2 3\nf 1 1 4\n",
        ),
    ] {
        write(dir.path(), name, text);
        let msg = load_bad(dir.path(), name, name, None);
        assert!(msg.contains("no surfaces"), "{msg}");
    }
}

// ---------------------------------------------------------------------------------------------
// Real files.

/// Where Debian's `assimp-testmodels` puts its models (`dpkg -L assimp-testmodels`).
const ASSIMP_MODELS: &str = "/usr/share/assimp/models";

fn obj_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            obj_files(&path, out);
        } else if path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("obj"))
        {
            out.push(path);
        }
    }
}

#[test]
fn assimp_test_models_never_panic() {
    let root = Path::new(ASSIMP_MODELS);
    if !root.is_dir() {
        if std::env::var_os("CI").is_some() {
            panic!(
                "{ASSIMP_MODELS} is missing: .ci/run must install the Debian package \
                 assimp-testmodels (apt-get install -y assimp-testmodels)"
            );
        }
        eprintln!("note: {ASSIMP_MODELS} not found (install assimp-testmodels); skipping");
        return;
    }
    let mut files = Vec::new();
    obj_files(root, &mut files);
    files.sort();
    assert!(!files.is_empty(), "no .obj files under {ASSIMP_MODELS}");

    let mut loaded = Vec::new();
    let mut rejected = Vec::new();
    let mut panicked = Vec::new();
    for file in &files {
        match std::panic::catch_unwind(|| load_obj(file)) {
            Ok(Ok(scene)) => loaded.push(format!(
                "{} ({} triangles)",
                file.display(),
                scene.triangles.len()
            )),
            Ok(Err(e)) => {
                let e: LoadError = e;
                assert!(
                    e.to_string().contains(&*e.path().to_string_lossy()),
                    "error does not name its file: {e}"
                );
                rejected.push(format!("{e}"));
            }
            Err(_) => panicked.push(file.display().to_string()),
        }
    }
    println!(
        "assimp-testmodels: loaded {}, rejected {}, panicked {}",
        loaded.len(),
        rejected.len(),
        panicked.len()
    );
    for l in &loaded {
        println!("  loaded: {l}");
    }
    for r in &rejected {
        println!("  rejected: {}", r.lines().next().unwrap_or(""));
    }
    assert!(panicked.is_empty(), "load_obj panicked on: {panicked:#?}");
    assert!(!loaded.is_empty(), "no assimp model loaded at all");
}
