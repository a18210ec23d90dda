//! The OBJ + MTL reader: turns a Wavefront `.obj` file and the `.mtl` libraries it names into a
//! validated [`Scene`], or into a [`LoadError`] that names the file and line to fix.
//!
//! What is read:
//! - OBJ: `v` (with an optional `w`, which divides x, y, z; vertex colours are ignored), `f`
//!   (`v`, `v/vt`, `v//vn`, `v/vt/vn`, negative indices count back from the latest vertex),
//!   `o`/`g` groups, `usemtl` and `mtllib` (one name, or several separated by spaces). Texture
//!   coordinates and normals are ignored: a triangle's front side is given by its winding.
//!   Faces are fan-triangulated; faces with fewer than three vertices, `l` and `p` are dropped.
//! - MTL: `newmtl`, `Kd` (reflectance `rho` per RGB channel) and `Ke` (emitted radiosity `E` per
//!   channel, not radiance). `Kd r` alone means `Kd r r r`, as in the MTL specification. Every
//!   other statement (`Ka`, `Ks`, `Km`, `refl`, `disp`, `Pr`, `map_*`, ...) is ignored.
//! - Defaults: a material without `Kd` reflects [`DEFAULT_REFLECTANCE`] (0.5 grey) and one
//!   without `Ke` emits nothing; faces before any `usemtl` get the material [`DEFAULT_MATERIAL`]
//!   (0.5 grey, no emission).
//!
//! How: `tobj` groups faces by object and material and triangulates them, but it parses
//! coordinates in single precision, panics on some malformed MTL statements (`Kd 0.5`) and on
//! some face indices, and its errors carry no line numbers. So this module first scans the text
//! itself, line by line: every statement that matters is checked here and reported with its line,
//! MTL files are read here, and `tobj` is handed a cleaned text (vertices, faces with position
//! indices only, groups, `usemtl`) that it cannot fail on. Each vertex is handed to `tobj` as its
//! index (three 24-bit digits, exact in `f32`) rather than its coordinates, and the coordinates
//! are read back from this module's own `f64` parse, so no precision is lost. The `tobj` call is
//! still wrapped in `catch_unwind` as a last resort. Material value checks (reflectance in
//! `[0, 1)`, finite non-negative emission) are done by [`Scene::validate`] on the materials the
//! faces use, and mapped back to the `Kd`/`Ke` line.

use super::{Material, Scene, SceneProblem, Triangle};
use glam::DVec3;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::io;
use std::path::{Path, PathBuf};

/// Reflectance of a material that has no `Kd` statement, and of the default material.
pub const DEFAULT_REFLECTANCE: [f64; 3] = [0.5, 0.5, 0.5];

/// Name of the material given to faces that come before any `usemtl`.
pub const DEFAULT_MATERIAL: &str = "(default grey)";

/// Why an OBJ scene could not be loaded. Every variant names the file the problem is in and,
/// where there is one, the 1-based line; see [`LoadError::path`] and [`LoadError::line`].
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The OBJ file itself cannot be read.
    #[error("{}: cannot read the OBJ file: {source}; {}", path.display(), io_advice(source))]
    Read {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    /// An `mtllib` statement names a material library that cannot be read.
    #[error(
        "{} line {line}: {statement}: cannot read the material library {}: {source}; \
         put the MTL file next to the OBJ file, fix the name, or remove the mtllib line",
        path.display(), mtl.display()
    )]
    MtlRead {
        /// The OBJ file holding the `mtllib` line.
        path: PathBuf,
        line: usize,
        statement: String,
        /// The library as it was looked for (relative names are taken from the OBJ's directory).
        mtl: PathBuf,
        #[source]
        source: io::Error,
    },
    /// A statement that does not parse (OBJ or MTL file).
    #[error("{} line {line}: {statement}: {reason}", path.display())]
    Malformed {
        path: PathBuf,
        line: usize,
        statement: String,
        reason: String,
    },
    /// A statement that parses but whose value cannot be used: a non-finite coordinate, a face
    /// index out of range, an unknown material, a reflectance outside `[0, 1)`, a bad emission.
    #[error("{} line {line}: {statement}: {reason}", path.display())]
    Invalid {
        path: PathBuf,
        line: usize,
        statement: String,
        reason: String,
    },
    /// The file has nothing to light: no face with a non-zero area.
    #[error("{}: the scene has no surfaces: {reason}", path.display())]
    NoSurfaces { path: PathBuf, reason: String },
    /// `tobj` refused or panicked on a file this module's checks let through.
    #[error("{}: the OBJ reader could not read this file ({reason}); check that it is a \
             well-formed Wavefront OBJ file", path.display())]
    Reader { path: PathBuf, reason: String },
    /// [`Scene::validate`] failed in a way no line can be given for.
    #[error("{}: {problem}", path.display())]
    Scene {
        path: PathBuf,
        problem: SceneProblem,
    },
}

impl LoadError {
    /// True when the user's files are at fault (exit status 2): malformed or invalid content,
    /// and files that are missing, unreadable for lack of permission, or directories. False for
    /// other I/O failures and internal inconsistencies (exit status 1).
    pub fn is_bad_input(&self) -> bool {
        match self {
            LoadError::Read { source, .. } | LoadError::MtlRead { source, .. } => {
                is_user_io_error(source)
            }
            LoadError::Scene { problem, .. } => {
                !matches!(problem, SceneProblem::MaterialOutOfRange { .. })
            }
            LoadError::Malformed { .. }
            | LoadError::Invalid { .. }
            | LoadError::NoSurfaces { .. }
            | LoadError::Reader { .. } => true,
        }
    }

    /// The file the problem is in (for [`LoadError::MtlRead`], the OBJ holding the `mtllib`).
    pub fn path(&self) -> &Path {
        match self {
            LoadError::Read { path, .. }
            | LoadError::MtlRead { path, .. }
            | LoadError::Malformed { path, .. }
            | LoadError::Invalid { path, .. }
            | LoadError::NoSurfaces { path, .. }
            | LoadError::Reader { path, .. }
            | LoadError::Scene { path, .. } => path,
        }
    }

    /// The 1-based line in [`LoadError::path`], where there is one.
    pub fn line(&self) -> Option<usize> {
        match self {
            LoadError::MtlRead { line, .. }
            | LoadError::Malformed { line, .. }
            | LoadError::Invalid { line, .. } => Some(*line),
            _ => None,
        }
    }
}

fn is_user_io_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::NotFound
            | io::ErrorKind::PermissionDenied
            | io::ErrorKind::IsADirectory
            | io::ErrorKind::InvalidInput
    )
}

/// Reads a whole OBJ or MTL file. Only regular files: a device or a pipe named by mistake (an
/// `mtllib /dev/zero`) would otherwise be read until memory runs out.
fn read_file(path: &Path) -> io::Result<Vec<u8>> {
    let meta = std::fs::metadata(path)?;
    if meta.is_dir() {
        return Err(io::Error::new(
            io::ErrorKind::IsADirectory,
            "is a directory",
        ));
    }
    if !meta.is_file() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "not a regular file (a device or a pipe)",
        ));
    }
    std::fs::read(path)
}

fn io_advice(e: &io::Error) -> &'static str {
    match e.kind() {
        io::ErrorKind::NotFound => "check the path",
        io::ErrorKind::PermissionDenied => "check the file's permissions",
        io::ErrorKind::IsADirectory => "give the path of an .obj file, not a directory",
        io::ErrorKind::InvalidInput => "give the path of an ordinary file",
        _ => "check the disk or file system and try again",
    }
}

/// Reads `path` (an `.obj` file) and the MTL libraries it names into a validated [`Scene`].
/// All objects and groups are merged into one scene; see the module header for what is read.
pub fn load_obj(path: &Path) -> Result<Scene, LoadError> {
    let bytes = read_file(path).map_err(|source| LoadError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let text = decode_text(&bytes);
    drop(bytes);
    let scan = scan_obj(path, &text)?;
    drop(text);
    let models = run_tobj(path, &scan)?;
    build_scene(path, &scan, &models)
}

// ---------------------------------------------------------------------------------------------
// Text handling shared by OBJ and MTL.

/// Decodes a text file. UTF-16 files (with a byte-order mark) occur in the wild; anything else is
/// taken as UTF-8, with invalid bytes replaced: they can only matter in comments and names, and a
/// replaced name still matches the same replaced name in the MTL file.
fn decode_text(bytes: &[u8]) -> String {
    let utf16 = |big_endian: bool| {
        let units = bytes[2..].chunks_exact(2).map(|c| {
            if big_endian {
                u16::from_be_bytes([c[0], c[1]])
            } else {
                u16::from_le_bytes([c[0], c[1]])
            }
        });
        char::decode_utf16(units)
            .map(|c| c.unwrap_or(char::REPLACEMENT_CHARACTER))
            .collect::<String>()
    };
    match bytes {
        [0xFE, 0xFF, ..] => utf16(true),
        [0xFF, 0xFE, ..] => utf16(false),
        [0xEF, 0xBB, 0xBF, rest @ ..] => String::from_utf8_lossy(rest).into_owned(),
        _ => String::from_utf8_lossy(bytes).into_owned(),
    }
}

/// Lines with their 1-based numbers. `\n` and `\r\n` end lines; a file using only `\r` (old Mac
/// style) is split on `\r`, since otherwise it would read as one long comment.
fn numbered_lines(text: &str) -> Box<dyn Iterator<Item = (usize, &str)> + '_> {
    if !text.contains('\n') && text.contains('\r') {
        Box::new(text.split('\r').enumerate().map(|(i, l)| (i + 1, l)))
    } else {
        Box::new(
            text.split('\n')
                .enumerate()
                .map(|(i, l)| (i + 1, l.strip_suffix('\r').unwrap_or(l))),
        )
    }
}

/// Cuts a `#` comment off a line. A `#` only starts a comment at the start of the line or after
/// white space, so that a `#` inside a material name survives.
fn strip_comment(line: &str) -> &str {
    let mut prev_space = true;
    for (i, c) in line.char_indices() {
        if c == '#' && prev_space {
            return &line[..i];
        }
        prev_space = c.is_whitespace();
    }
    line
}

/// The statement as shown in messages: trimmed, and shortened if very long.
fn shown(line: &str) -> String {
    const MAX: usize = 80;
    let line = line.trim();
    match line.char_indices().nth(MAX) {
        Some((i, _)) => format!("{}...", &line[..i]),
        None => line.to_string(),
    }
}

/// The keyword and the rest of the line (trimmed), e.g. `("usemtl", "Red plastic")`.
fn split_keyword(line: &str) -> Option<(&str, &str)> {
    let line = line.trim();
    if line.is_empty() {
        return None;
    }
    match line.find(char::is_whitespace) {
        Some(i) => Some((&line[..i], line[i..].trim())),
        None => Some((line, "")),
    }
}

fn parse_number(token: &str) -> Option<f64> {
    token.parse::<f64>().ok()
}

// ---------------------------------------------------------------------------------------------
// MTL files.

/// A colour statement (`Kd` or `Ke`) and where it was.
#[derive(Clone, Debug)]
struct ColourAt {
    value: [f64; 3],
    line: usize,
    statement: String,
}

/// One `newmtl` block of one MTL file.
#[derive(Clone, Debug)]
struct MtlMaterial {
    name: String,
    /// Index into [`ObjScan::mtl_paths`].
    file: usize,
    kd: Option<ColourAt>,
    ke: Option<ColourAt>,
}

impl MtlMaterial {
    fn to_material(&self) -> Material {
        Material::new(
            &self.name,
            self.kd.as_ref().map_or(DEFAULT_REFLECTANCE, |c| c.value),
            self.ke.as_ref().map_or([0.0; 3], |c| c.value),
        )
    }
}

/// Parses one MTL file's `newmtl`, `Kd` and `Ke` statements; only their syntax is checked here
/// (values are checked on the materials actually used, see [`build_scene`]).
fn parse_mtl(path: &Path, file: usize, text: &str) -> Result<Vec<MtlMaterial>, LoadError> {
    let mut materials: Vec<MtlMaterial> = Vec::new();
    for (line, raw) in numbered_lines(text) {
        let Some((keyword, rest)) = split_keyword(strip_comment(raw)) else {
            continue;
        };
        let malformed = |reason: String| LoadError::Malformed {
            path: path.to_path_buf(),
            line,
            statement: shown(raw),
            reason,
        };
        match keyword {
            // An empty name is a material named "" (Blender writes these), not an error.
            "newmtl" => {
                materials.push(MtlMaterial {
                    name: rest.to_string(),
                    file,
                    kd: None,
                    ke: None,
                });
            }
            "Kd" | "Ke" => {
                let value = parse_rgb(keyword, rest).map_err(malformed)?;
                let colour = ColourAt {
                    value,
                    line,
                    statement: shown(raw),
                };
                // A colour before the first `newmtl` belongs to no material; like other readers,
                // ignore it. A repeated statement replaces the earlier one.
                if let Some(m) = materials.last_mut() {
                    if keyword == "Kd" {
                        m.kd = Some(colour);
                    } else {
                        m.ke = Some(colour);
                    }
                }
            }
            _ => {}
        }
    }
    Ok(materials)
}

/// Parses the arguments of `Kd`/`Ke`: three numbers, or one for grey.
fn parse_rgb(keyword: &str, rest: &str) -> Result<[f64; 3], String> {
    let tokens: Vec<&str> = rest.split_whitespace().collect();
    if let Some(&form @ ("spectral" | "xyz")) = tokens.first() {
        return Err(format!(
            "`{keyword} {form}` colours are not supported; give `{keyword} r g b` with three numbers"
        ));
    }
    let mut values = Vec::with_capacity(3);
    for t in &tokens {
        match parse_number(t) {
            Some(v) => values.push(v),
            None => {
                return Err(format!(
                    "'{t}' is not a number; write `{keyword} r g b` with three numbers"
                ))
            }
        }
    }
    match values[..] {
        [g] => Ok([g, g, g]),
        [r, g, b] => Ok([r, g, b]),
        _ => Err(format!(
            "expected three numbers `{keyword} r g b` (or one, for grey), found {}",
            values.len()
        )),
    }
}

// ---------------------------------------------------------------------------------------------
// The OBJ scan.

/// What the scan of an OBJ file found, and the cleaned text handed to `tobj`.
struct ObjScan {
    /// Vertex positions in file order, in `f64`.
    positions: Vec<DVec3>,
    /// MTL files read, in the order of first reference.
    mtl_paths: Vec<PathBuf>,
    /// Every `newmtl` block of every MTL file, in reading order.
    materials: Vec<MtlMaterial>,
    /// For each distinct `usemtl` name, in order of first use, the index into `materials` it
    /// resolves to (`None`: the file names no library, so the default material is used). `tobj`
    /// sees the k-th name as `u{k}`, so odd names (empty, spaces, tabs) cannot trip it up.
    used_materials: Vec<Option<usize>>,
    /// Cleaned text for `tobj`.
    tobj_text: String,
    /// `f` statements with three or more vertices.
    faces: usize,
    /// `f` statements with fewer than three vertices, and `l`/`p` statements.
    dropped: usize,
}

/// Vertices are handed to `tobj` as their index written in three base-2^24 digits: each digit
/// is an integer below 2^24, exact in `f32`, and three digits cover any file that fits in memory.
const DIGIT: u64 = 1 << 24;

fn encode_vertex(index: usize) -> [u64; 3] {
    let k = index as u64;
    [k % DIGIT, (k / DIGIT) % DIGIT, k / (DIGIT * DIGIT)]
}

fn decode_vertex(p: [f64; 3]) -> Option<usize> {
    let mut k: u64 = 0;
    for d in p.iter().rev() {
        if !(0.0..DIGIT as f64).contains(d) || d.fract() != 0.0 {
            return None;
        }
        k = k.checked_mul(DIGIT)?.checked_add(*d as u64)?;
    }
    usize::try_from(k).ok()
}

/// Why a face-vertex index cannot be used: it does not parse, or it names nothing.
enum IndexError {
    Malformed(String),
    Invalid(String),
}

/// Resolves one face-vertex index (1-based, or negative counting back) against `count` elements
/// defined so far, and returns it 0-based.
fn resolve_index(token: &str, count: usize, what: &str, whats: &str) -> Result<usize, IndexError> {
    let i: i64 = token.parse().map_err(|_| {
        IndexError::Malformed(format!(
            "'{token}' is not a valid {what} index; face vertices are written v, v/vt, v//vn or v/vt/vn"
        ))
    })?;
    let resolved = if i > 0 {
        usize::try_from(i - 1).ok().filter(|&k| k < count)
    } else if i < 0 {
        usize::try_from(i.unsigned_abs())
            .ok()
            .and_then(|back| count.checked_sub(back))
    } else {
        return Err(IndexError::Invalid(format!(
            "{what} index 0 is invalid: OBJ indices start at 1 (or count back from -1)"
        )));
    };
    resolved.ok_or_else(|| {
        IndexError::Invalid(format!(
            "{what} index {i} is out of range: only {count} {} defined before this line",
            if count == 1 {
                format!("{what} is")
            } else {
                format!("{whats} are")
            }
        ))
    })
}

fn scan_obj(path: &Path, text: &str) -> Result<ObjScan, LoadError> {
    let obj_dir = path.parent().unwrap_or(Path::new(""));
    let mut scan = ObjScan {
        positions: Vec::new(),
        mtl_paths: Vec::new(),
        materials: Vec::new(),
        used_materials: Vec::new(),
        tobj_text: String::new(),
        faces: 0,
        dropped: 0,
    };
    let mut texcoords = 0usize;
    let mut normals = 0usize;
    // `usemtl` names with the line of their first use; checked once every library is read,
    // because `mtllib` may come after `usemtl`.
    let mut used: Vec<(String, usize, String)> = Vec::new();
    let mut used_index: HashMap<String, usize> = HashMap::new();
    let mut body = String::new();

    for (line, raw) in numbered_lines(text) {
        let Some((keyword, rest)) = split_keyword(strip_comment(raw)) else {
            continue;
        };
        let malformed = |reason: String| LoadError::Malformed {
            path: path.to_path_buf(),
            line,
            statement: shown(raw),
            reason,
        };
        let invalid = |reason: String| LoadError::Invalid {
            path: path.to_path_buf(),
            line,
            statement: shown(raw),
            reason,
        };
        match keyword {
            "v" => {
                let tokens: Vec<&str> = rest.split_whitespace().collect();
                // x y z, x y z w, or x y z r g b (colours are ignored).
                if !matches!(tokens.len(), 3 | 4 | 6) {
                    return Err(malformed(format!(
                        "a vertex is `v x y z` (optionally with w, or with r g b), found {} values",
                        tokens.len()
                    )));
                }
                let mut xyz = [0.0; 3];
                for (k, t) in tokens.iter().take(3).enumerate() {
                    xyz[k] = parse_number(t).ok_or_else(|| {
                        malformed(format!("'{t}' is not a number; write `v x y z`"))
                    })?;
                }
                if tokens.len() == 4 {
                    let t = tokens[3];
                    let w = parse_number(t).ok_or_else(|| {
                        malformed(format!("'{t}' (the w component) is not a number"))
                    })?;
                    if w == 0.0 || !w.is_finite() {
                        return Err(invalid(format!(
                            "the w component is {w}; it divides x, y and z and must be a non-zero \
                             finite number (usually 1, or leave it out)"
                        )));
                    }
                    xyz = xyz.map(|c| c / w);
                }
                if let Some(k) = xyz.iter().position(|c| !c.is_finite()) {
                    return Err(invalid(format!(
                        "the {} coordinate is {}; every coordinate must be a finite number",
                        ["x", "y", "z"][k],
                        xyz[k]
                    )));
                }
                let [a, b, c] = encode_vertex(scan.positions.len());
                // Writing to a String cannot fail.
                let _ = writeln!(body, "v {a} {b} {c}");
                scan.positions.push(DVec3::from_array(xyz));
            }
            // Only counted, so that face indices into them can be checked.
            "vt" => texcoords += 1,
            "vn" => normals += 1,
            "f" => {
                if rest.is_empty() {
                    return Err(malformed(
                        "a face needs at least three vertex indices, e.g. `f 1 2 3`".into(),
                    ));
                }
                let mut indices = Vec::new();
                for token in rest.split_whitespace() {
                    let parts: Vec<&str> = token.split('/').collect();
                    if parts.len() > 3 || parts[0].is_empty() {
                        return Err(malformed(format!(
                            "'{token}' is not a face vertex; write v, v/vt, v//vn or v/vt/vn"
                        )));
                    }
                    let check = |r: Result<usize, IndexError>| {
                        r.map_err(|e| match e {
                            IndexError::Malformed(reason) => malformed(reason),
                            IndexError::Invalid(reason) => invalid(reason),
                        })
                    };
                    indices.push(check(resolve_index(
                        parts[0],
                        scan.positions.len(),
                        "vertex",
                        "vertices",
                    ))?);
                    if let Some(vt) = parts.get(1).filter(|s| !s.is_empty()) {
                        check(resolve_index(
                            vt,
                            texcoords,
                            "texture coordinate",
                            "texture coordinates",
                        ))?;
                    }
                    if let Some(vn) = parts.get(2).filter(|s| !s.is_empty()) {
                        check(resolve_index(vn, normals, "normal", "normals"))?;
                    }
                }
                if indices.len() < 3 {
                    scan.dropped += 1;
                    continue;
                }
                scan.faces += 1;
                // Absolute position indices only: tobj never sees texture or normal indices.
                body.push('f');
                for i in indices {
                    let _ = write!(body, " {}", i + 1);
                }
                body.push('\n');
            }
            "l" | "p" => scan.dropped += 1,
            "o" | "g" => {
                body.push_str(keyword);
                if !rest.is_empty() {
                    body.push(' ');
                    body.push_str(rest);
                }
                body.push('\n');
            }
            "usemtl" => {
                // An empty name is accepted: Blender writes `newmtl`/`usemtl` without one for
                // an unnamed material.
                let k = *used_index.entry(rest.to_string()).or_insert_with(|| {
                    used.push((rest.to_string(), line, shown(raw)));
                    used.len() - 1
                });
                let _ = writeln!(body, "usemtl u{k}");
            }
            "mtllib" => {
                if rest.is_empty() {
                    return Err(malformed(
                        "mtllib needs a file name; write `mtllib NAME.mtl`".into(),
                    ));
                }
                for name in mtllib_names(obj_dir, rest) {
                    let mtl = obj_dir.join(name);
                    if scan.mtl_paths.contains(&mtl) {
                        continue;
                    }
                    let bytes = read_file(&mtl).map_err(|source| LoadError::MtlRead {
                        path: path.to_path_buf(),
                        line,
                        statement: shown(raw),
                        mtl: mtl.clone(),
                        source,
                    })?;
                    let file = scan.mtl_paths.len();
                    let mut materials = parse_mtl(&mtl, file, &decode_text(&bytes))?;
                    scan.mtl_paths.push(mtl);
                    scan.materials.append(&mut materials);
                }
            }
            // s, mg, vp, curves and surfaces, and anything unknown: nothing to light.
            _ => {}
        }
    }

    let names = material_ids(&scan.materials);
    for (name, line, statement) in &used {
        if let Some(&id) = names.get(name) {
            scan.used_materials.push(Some(id));
            continue;
        }
        if scan.mtl_paths.is_empty() {
            // No library at all: the materials were never exported, which is common and not a
            // mistake the user can have made by a typo. Light the faces with the default grey.
            tracing::warn!(
                "{} line {line}: {statement}: the file names no material library; \
                 using the default grey material",
                path.display()
            );
            scan.used_materials.push(None);
            continue;
        }
        let libs: Vec<String> = scan
            .mtl_paths
            .iter()
            .map(|p| p.display().to_string())
            .collect();
        let reason = if name.is_empty() {
            format!(
                "usemtl without a name, and no unnamed material (newmtl without a name) in {}; \
                 give the material's name",
                libs.join(", ")
            )
        } else {
            format!(
                "no material named '{name}' in {}; define it with `newmtl {name}` or fix the name",
                libs.join(", ")
            )
        };
        return Err(LoadError::Invalid {
            path: path.to_path_buf(),
            line: *line,
            statement: statement.clone(),
            reason,
        });
    }

    // One virtual library holding the used names, named at the top: tobj looks materials up
    // when it meets `usemtl`, so a library named later in the file would be missed.
    if !used.is_empty() {
        scan.tobj_text.push_str("mtllib voxrad-materials\n");
    }
    scan.tobj_text.push_str(&body);
    Ok(scan)
}

/// The file names of an `mtllib` statement. The specification separates several names by
/// spaces, but names with spaces occur too: the whole rest is taken as one name if such a file
/// exists, else it is split. A missing file is then reported under the name it was looked for.
fn mtllib_names<'a>(obj_dir: &Path, rest: &'a str) -> Vec<&'a str> {
    let tokens: Vec<&str> = rest.split_whitespace().collect();
    if tokens.len() == 1 || obj_dir.join(rest).is_file() {
        return vec![rest];
    }
    if tokens.iter().any(|t| obj_dir.join(t).is_file()) {
        tokens
    } else {
        // None exists either way: report the name as written.
        vec![rest]
    }
}

/// Material name -> index into the material list; a later definition of a name wins, as in
/// `tobj` (the two must agree, since `tobj` resolves `usemtl` with the same list).
fn material_ids(materials: &[MtlMaterial]) -> HashMap<String, usize> {
    materials
        .iter()
        .enumerate()
        .map(|(i, m)| (m.name.clone(), i))
        .collect()
}

// ---------------------------------------------------------------------------------------------
// tobj and the scene.

fn run_tobj(path: &Path, scan: &ObjScan) -> Result<Vec<tobj::Model>, LoadError> {
    // `LoadOptions` gains fields with tobj's `merging`/`reordering` features; keep their defaults.
    #[allow(clippy::needless_update)]
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
        ..Default::default()
    };
    let load = || {
        let mut reader = io::Cursor::new(scan.tobj_text.as_bytes());
        tobj::load_obj_buf(&mut reader, &options, |_virtual_library| {
            let names: Vec<String> = (0..scan.used_materials.len())
                .map(|k| format!("u{k}"))
                .collect();
            let materials = names
                .iter()
                .map(|name| tobj::Material {
                    name: name.clone(),
                    ..Default::default()
                })
                .collect();
            // Collected rather than named: tobj's map type depends on its features.
            let ids = names.into_iter().enumerate().map(|(k, n)| (n, k)).collect();
            Ok((materials, ids))
        })
    };
    // The scan above should leave tobj nothing to fail or panic on; if it does, the user still
    // gets an error naming the file instead of a crash.
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(load));
    match result {
        Ok(Ok((models, _materials))) => Ok(models),
        Ok(Err(e)) => Err(LoadError::Reader {
            path: path.to_path_buf(),
            reason: e.to_string(),
        }),
        Err(panic) => {
            let message = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown cause".to_string());
            Err(LoadError::Reader {
                path: path.to_path_buf(),
                reason: format!("it panicked: {message}"),
            })
        }
    }
}

fn build_scene(path: &Path, scan: &ObjScan, models: &[tobj::Model]) -> Result<Scene, LoadError> {
    let reader_error = |reason: &str| LoadError::Reader {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    };
    let mut scene = Scene {
        source: path.to_path_buf(),
        ..Default::default()
    };
    // MTL material (None: the default) -> scene material; each material is added once, and
    // only if a face uses it.
    let mut scene_material: HashMap<Option<usize>, u32> = HashMap::new();
    // Scene material -> its MTL block, to point value errors at their line.
    let mut origin: Vec<Option<usize>> = Vec::new();

    for model in models {
        let mesh = &model.mesh;
        let id = match mesh.material_id {
            None => None,
            Some(k) => *scan
                .used_materials
                .get(k)
                .ok_or_else(|| reader_error("material id out of range"))?,
        };
        let material = match scene_material.get(&id) {
            Some(&m) => m,
            None => {
                let m = match id {
                    None => Material::new(DEFAULT_MATERIAL, DEFAULT_REFLECTANCE, [0.0; 3]),
                    Some(i) => scan
                        .materials
                        .get(i)
                        .ok_or_else(|| reader_error("material id out of range"))?
                        .to_material(),
                };
                let index = scene.add_material(m);
                origin.push(id);
                scene_material.insert(id, index);
                index
            }
        };
        let vertex = |i: u32| -> Result<DVec3, LoadError> {
            let i = i as usize;
            let p = mesh
                .positions
                .get(3 * i..3 * i + 3)
                .ok_or_else(|| reader_error("vertex index out of range"))?;
            let k = decode_vertex([f64::from(p[0]), f64::from(p[1]), f64::from(p[2])])
                .ok_or_else(|| reader_error("unexpected vertex"))?;
            scan.positions
                .get(k)
                .copied()
                .ok_or_else(|| reader_error("unexpected vertex"))
        };
        for t in mesh.indices.chunks_exact(3) {
            scene.triangles.push(Triangle {
                vertices: [vertex(t[0])?, vertex(t[1])?, vertex(t[2])?],
                material,
            });
        }
    }

    match scene.validate() {
        Ok(()) => Ok(scene),
        Err(SceneProblem::Empty) => Err(LoadError::NoSurfaces {
            path: path.to_path_buf(),
            reason: if scan.faces == 0 {
                format!(
                    "it has no faces (f statements with three or more vertices){}; \
                     add faces, or check that this is the right file",
                    if scan.dropped > 0 {
                        format!(", only {} points or lines", scan.dropped)
                    } else {
                        String::new()
                    }
                )
            } else {
                format!(
                    "all {} faces have zero area (their vertices coincide or lie on a line); \
                     check the vertex coordinates",
                    scan.faces
                )
            },
        }),
        Err(problem) => Err(locate_problem(path, scan, &scene, &origin, problem)),
    }
}

/// Points a material problem found by [`Scene::validate`] at its `Kd`/`Ke` line.
fn locate_problem(
    path: &Path,
    scan: &ObjScan,
    scene: &Scene,
    origin: &[Option<usize>],
    problem: SceneProblem,
) -> LoadError {
    const CHANNELS: [&str; 3] = ["red", "green", "blue"];
    let same = |a: f64, b: f64| a == b || (a.is_nan() && b.is_nan());
    // validate() checks materials in scene order, so the first match is the one it reported.
    let find = |name: &str, pick: &dyn Fn(&Material) -> [f64; 3], channel: usize, value: f64| {
        scene
            .materials
            .iter()
            .zip(origin)
            .find(|(m, _)| m.name == name && same(pick(m)[channel], value))
            .and_then(|(_, o)| o.and_then(|i| scan.materials.get(i)))
    };
    match &problem {
        SceneProblem::BadReflectance {
            name,
            channel,
            value,
        } => {
            let m = find(name, &|m| m.reflectance, *channel, *value);
            if let Some((m, kd)) = m.and_then(|m| m.kd.as_ref().map(|kd| (m, kd))) {
                let ch = CHANNELS[*channel];
                let reason = if value.is_nan() {
                    format!("the {ch} reflectance is not a number; give three numbers in [0, 1)")
                } else if *value < 0.0 {
                    format!(
                        "reflectance must be in [0, 1) but the {ch} channel is {value}; \
                         use 0 for a black surface"
                    )
                } else {
                    format!(
                        "reflectance must be in [0, 1) (a value of 1 or more creates energy) \
                         but the {ch} channel is {value}; lower it"
                    )
                };
                return LoadError::Invalid {
                    path: scan.mtl_paths[m.file].clone(),
                    line: kd.line,
                    statement: kd.statement.clone(),
                    reason: format!("material '{}': {reason}", m.name),
                };
            }
        }
        SceneProblem::BadEmission {
            name,
            channel,
            value,
        } => {
            let m = find(name, &|m| m.emission, *channel, *value);
            if let Some((m, ke)) = m.and_then(|m| m.ke.as_ref().map(|ke| (m, ke))) {
                let ch = CHANNELS[*channel];
                let reason = if value.is_finite() {
                    format!(
                        "emission cannot be negative but the {ch} channel is {value}; \
                         use 0 for a surface that emits nothing"
                    )
                } else {
                    format!(
                        "the {ch} emission is {value}; Ke is the emitted radiosity \
                         (power per area) and must be a finite number, 0 or more"
                    )
                };
                return LoadError::Invalid {
                    path: scan.mtl_paths[m.file].clone(),
                    line: ke.line,
                    statement: ke.statement.clone(),
                    reason: format!("material '{}': {reason}", m.name),
                };
            }
        }
        _ => {}
    }
    LoadError::Scene {
        path: path.to_path_buf(),
        problem,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vertex_encoding_round_trips_through_f32() {
        for k in [0usize, 1, 12345, (1 << 24) - 1, 1 << 24, (1 << 40) + 7] {
            let d = encode_vertex(k).map(|x| f64::from(x as f32));
            assert_eq!(decode_vertex(d), Some(k));
        }
        assert_eq!(decode_vertex([0.5, 0.0, 0.0]), None);
        assert_eq!(decode_vertex([-1.0, 0.0, 0.0]), None);
    }

    #[test]
    fn comments_only_start_after_space() {
        assert_eq!(strip_comment("v 1 2 3 # c"), "v 1 2 3 ");
        assert_eq!(strip_comment("usemtl a#b"), "usemtl a#b");
        assert_eq!(strip_comment("# all"), "");
    }

    #[test]
    fn indices_resolve() {
        assert!(matches!(resolve_index("1", 3, "vertex", "vertices"), Ok(0)));
        assert!(matches!(
            resolve_index("-1", 3, "vertex", "vertices"),
            Ok(2)
        ));
        assert!(resolve_index("-4", 3, "vertex", "vertices").is_err());
        assert!(resolve_index("4", 3, "vertex", "vertices").is_err());
        assert!(resolve_index("0", 3, "vertex", "vertices").is_err());
        assert!(matches!(
            resolve_index("99999999999999999999", 3, "vertex", "vertices"),
            Err(IndexError::Malformed(_))
        ));
    }
}
