//! A tone-mapped PNG preview of the solution, and the tone mapping the PLY export shares.
//!
//! Rendering splats surfels, it does not ray-trace: every surfel's side that faces the camera is
//! drawn as a screen-space square the size of its projected voxel (a little larger, so that
//! neighbouring voxels leave no gaps), with a z-buffer so the nearest surfel wins each pixel. A
//! surfel whose camera-facing side is dark still hides what is behind it, so the back of a wall
//! is an opaque dark wall, as it should be.
//!
//! Tone mapping: linear radiosity times an exposure that maps the 99th percentile of the visible
//! (positive) luminance to white, clipped, then sRGB-encoded. A percentile rather than the maximum
//! keeps a small, very bright lamp from making the rest of the picture black.
//!
//! [`auto_camera`] frames the scene without help: it tries views from outside along the 6 axis
//! directions and the 8 diagonals, each fitted to the scene's bounding box, renders each into a
//! small buffer, and keeps the one that sees the most light (sum of visible luminance). A box open
//! on one side, like the Cornell box, is then seen through its open side.
//!
//! A camera can also be given as text, for a command-line option (see [`Camera::parse`]):
//! `eye=X,Y,Z;target=X,Y,Z[;up=X,Y,Z][;fov=DEGREES]`, items in any order, world units, `up`
//! defaulting to `0,1,0` and `fov` (vertical field of view) to 40 degrees.

use super::bake::BakedMesh;
use super::{atomic, check_pair, luminance, OutputError};
use crate::solve::Solution;
use crate::voxel::{SurfelSet, BACK, FRONT};
use glam::DVec3;
use rayon::prelude::*;
use std::path::Path;

/// Background of the preview: dark grey, so black (unlit) surfaces stay distinguishable.
pub const BACKGROUND: [u8; 3] = [40, 40, 40];
/// The luminance percentile mapped to white.
pub const EXPOSURE_PERCENTILE: f64 = 0.99;
/// Largest width or height accepted, to keep a typo from allocating gigabytes.
pub const MAX_SIDE: u32 = 16384;
const DEFAULT_FOV: f64 = 40.0;

/// A pinhole camera in world units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub eye: DVec3,
    pub target: DVec3,
    pub up: DVec3,
    pub vertical_fov_degrees: f64,
}

/// Why a camera description was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("bad camera '{text}': {what} (expected eye=X,Y,Z;target=X,Y,Z[;up=X,Y,Z][;fov=DEGREES])")]
pub struct CameraParseError {
    pub text: String,
    pub what: String,
}

impl Camera {
    /// Parses `eye=X,Y,Z;target=X,Y,Z[;up=X,Y,Z][;fov=DEGREES]` (see the module header).
    pub fn parse(text: &str) -> Result<Camera, CameraParseError> {
        let fail = |what: String| CameraParseError {
            text: text.to_string(),
            what,
        };
        let (mut eye, mut target, mut up, mut fov) = (None, None, None, None);
        for item in text.split(';').map(str::trim).filter(|s| !s.is_empty()) {
            let (key, value) = item
                .split_once('=')
                .ok_or_else(|| fail(format!("'{item}' is not KEY=VALUE")))?;
            let (key, value) = (key.trim(), value.trim());
            let slot = match key {
                "eye" => &mut eye,
                "target" => &mut target,
                "up" => &mut up,
                "fov" => {
                    let v = parse_number(value).map_err(|w| fail(format!("fov: {w}")))?;
                    if fov.replace(v).is_some() {
                        return Err(fail("fov is given twice".into()));
                    }
                    continue;
                }
                other => {
                    return Err(fail(format!(
                        "unknown key '{other}' (known: eye, target, up, fov)"
                    )))
                }
            };
            let v = parse_vector(value).map_err(|w| fail(format!("{key}: {w}")))?;
            if slot.replace(v).is_some() {
                return Err(fail(format!("{key} is given twice")));
            }
        }
        let camera = Camera {
            eye: eye.ok_or_else(|| fail("eye is missing".into()))?,
            target: target.ok_or_else(|| fail("target is missing".into()))?,
            up: up.unwrap_or(DVec3::Y),
            vertical_fov_degrees: fov.unwrap_or(DEFAULT_FOV),
        };
        camera.validate().map_err(fail)?;
        Ok(camera)
    }

    /// Checks that the camera defines a view: distinct eye and target, an up vector not along
    /// the view direction, a field of view strictly between 0 and 180 degrees.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.eye.is_finite() && self.target.is_finite() && self.up.is_finite()) {
            return Err("eye, target and up must be finite".into());
        }
        let forward = self.target - self.eye;
        if forward.length() == 0.0 {
            return Err("eye and target are the same point".into());
        }
        let f = forward.normalize();
        if self.up.length() == 0.0 || f.cross(self.up.normalize()).length() < 1e-6 {
            return Err("up is zero or parallel to the view direction".into());
        }
        let fov = self.vertical_fov_degrees;
        if !(fov > 0.0 && fov < 180.0) {
            return Err(format!("fov {fov} is not between 0 and 180 degrees"));
        }
        Ok(())
    }
}

impl std::str::FromStr for Camera {
    type Err = CameraParseError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Camera::parse(s)
    }
}

fn parse_number(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(format!("'{}' is not a finite number", text.trim())),
    }
}

fn parse_vector(text: &str) -> Result<DVec3, String> {
    let parts: Vec<&str> = text.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("'{text}' needs 3 comma-separated numbers"));
    }
    Ok(DVec3::new(
        parse_number(parts[0])?,
        parse_number(parts[1])?,
        parse_number(parts[2])?,
    ))
}

/// Linear radiosity to 8-bit sRGB.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToneMap {
    /// Multiplier applied to linear radiosity before clipping to 1.
    pub exposure: f64,
}

impl ToneMap {
    /// Exposure mapping the [`EXPOSURE_PERCENTILE`] of the positive luminances to white
    /// (exposure 1 when nothing is lit).
    pub fn from_luminances(mut lums: Vec<f64>) -> ToneMap {
        lums.retain(|l| *l > 0.0 && l.is_finite());
        if lums.is_empty() {
            return ToneMap { exposure: 1.0 };
        }
        let k = (((lums.len() - 1) as f64) * EXPOSURE_PERCENTILE).round() as usize;
        let (_, white, _) = lums.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
        ToneMap {
            exposure: 1.0 / *white,
        }
    }

    /// The tone map for a whole solution: percentile over every side that has area or light
    /// (what the PLY export shows).
    pub fn for_solution(set: &SurfelSet, solution: &Solution) -> ToneMap {
        let mut lums = Vec::new();
        for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
            for side in [FRONT, BACK] {
                if s.area > 0.0 || b[side].iter().any(|&v| v != 0.0) {
                    lums.push(luminance(b[side]));
                }
            }
        }
        ToneMap::from_luminances(lums)
    }

    /// The tone map of a results file: the same percentile as [`ToneMap::for_solution`], over
    /// the records' sides that have area or light.
    pub fn for_results(results: &super::Results) -> ToneMap {
        let mut lums = Vec::new();
        for r in &results.records {
            for side in [FRONT, BACK] {
                if r.side_is_present(side) {
                    lums.push(luminance(r.radiosity[side]));
                }
            }
        }
        ToneMap::from_luminances(lums)
    }

    /// The display value of a linear radiosity before the sRGB encoding: exposed and clipped to
    /// `[0, 1]` (0 for NaN).
    pub fn linear(&self, rgb: [f32; 3]) -> [f32; 3] {
        rgb.map(|c| {
            let v = (c as f64 * self.exposure).clamp(0.0, 1.0);
            if v.is_nan() {
                0.0
            } else {
                v as f32
            }
        })
    }

    /// 8-bit sRGB colour of a linear radiosity.
    pub fn map(&self, rgb: [f32; 3]) -> [u8; 3] {
        rgb.map(|c| {
            let v = (c as f64 * self.exposure).clamp(0.0, 1.0);
            let v = if v.is_nan() { 0.0 } else { v };
            let s = if v <= 0.0031308 {
                12.92 * v
            } else {
                1.055 * v.powf(1.0 / 2.4) - 0.055
            };
            (s * 255.0 + 0.5).clamp(0.0, 255.0) as u8
        })
    }
}

/// Camera basis and projection for one image size.
struct View {
    eye: DVec3,
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    width: usize,
    height: usize,
    /// Pixels per world unit at depth 1.
    focal_px: f64,
}

impl View {
    fn new(camera: &Camera, width: u32, height: u32) -> Result<View, String> {
        camera.validate()?;
        if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
            return Err(format!(
                "image size {width}x{height} is not between 1x1 and {MAX_SIDE}x{MAX_SIDE}"
            ));
        }
        let forward = (camera.target - camera.eye).normalize();
        let right = forward.cross(camera.up).normalize();
        let up = right.cross(forward);
        let tan_half = (camera.vertical_fov_degrees.to_radians() * 0.5).tan();
        Ok(View {
            eye: camera.eye,
            forward,
            right,
            up,
            width: width as usize,
            height: height as usize,
            focal_px: 0.5 * height as f64 / tan_half,
        })
    }
}

/// A rendered frame in linear radiosity, before tone mapping.
struct Frame {
    width: usize,
    depth: Vec<f32>,
    color: Vec<[f32; 3]>,
}

impl Frame {
    fn covered(&self) -> impl Iterator<Item = [f32; 3]> + '_ {
        self.depth
            .iter()
            .zip(&self.color)
            .filter(|(d, _)| d.is_finite())
            .map(|(_, c)| *c)
    }
}

/// Splats every surfel side facing the camera (see the module header).
fn rasterize(set: &SurfelSet, solution: &Solution, view: &View) -> Frame {
    rasterize_every(set, solution, view, 1)
}

/// Surfels a candidate view of [`auto_camera`] draws at most: a camera is chosen from about 180
/// small views, and drawing every surfel of a million-surfel building in each took seconds.
const CANDIDATE_SURFELS: usize = 100_000;

/// As [`rasterize`], drawing every `every`-th surfel only, each splat that much larger in area
/// so that the picture stays covered (for scoring candidate views).
fn rasterize_every(set: &SurfelSet, solution: &Solution, view: &View, every: usize) -> Frame {
    let (w, h) = (view.width, view.height);
    let mut frame = Frame {
        width: w,
        depth: vec![f32::INFINITY; w * h],
        color: vec![[0.0; 3]; w * h],
    };
    let voxel = set.grid.voxel_size;
    let near = 1e-3 * voxel;
    // A splat larger than this is a surfel practically at the eye; drawing it would only cover
    // the picture with one voxel and cost width x height.
    let max_half = 0.25 * w.max(h) as f64 + 1.0;
    let grow = (every as f64).sqrt();
    let every = every.max(1);
    for (s, b) in set.surfels.iter().zip(&solution.radiosity).step_by(every) {
        let p = set.grid.to_world(s.position());
        let to_eye = view.eye - p;
        let facing = s.side_normal(FRONT).dot(to_eye);
        let side = if facing > 0.0 {
            FRONT
        } else if facing < 0.0 {
            BACK
        } else {
            continue;
        };
        let d = p - view.eye;
        let z = d.dot(view.forward);
        if z <= near {
            continue;
        }
        let sx = 0.5 * w as f64 + d.dot(view.right) * view.focal_px / z;
        let sy = 0.5 * h as f64 - d.dot(view.up) * view.focal_px / z;
        let half = (0.5 * 1.2 * grow * voxel * view.focal_px / z).clamp(0.5, max_half);
        // Pixels whose centres (i + 0.5) lie within `half` of the splat centre.
        let x0 = (sx - half - 0.5).ceil().max(0.0);
        let x1 = (sx + half - 0.5).floor().min(w as f64 - 1.0);
        let y0 = (sy - half - 0.5).ceil().max(0.0);
        let y1 = (sy + half - 0.5).floor().min(h as f64 - 1.0);
        if !(x0 <= x1 && y0 <= y1) {
            continue;
        }
        let depth = z as f32;
        for y in y0 as usize..=y1 as usize {
            for x in x0 as usize..=x1 as usize {
                let i = y * w + x;
                if depth < frame.depth[i] {
                    frame.depth[i] = depth;
                    frame.color[i] = b[side];
                }
            }
        }
    }
    frame
}

/// Draws the triangles of a baked mesh that face the camera (each side of a two-sided surface
/// is a triangle of its own), interpolating the radiosity across each with perspective-correct
/// barycentric weights: a smooth picture, without the voxel squares of [`rasterize`]. A triangle
/// with a corner behind the near plane is left out (baked triangles are at most a few voxels
/// across, so only what touches the eye goes).
fn rasterize_mesh(mesh: &BakedMesh, view: &View, near: f64) -> Frame {
    let (w, h) = (view.width, view.height);
    let mut frame = Frame {
        width: w,
        depth: vec![f32::INFINITY; w * h],
        color: vec![[0.0; 3]; w * h],
    };
    for t in mesh.indices.chunks_exact(3) {
        let v = [t[0] as usize, t[1] as usize, t[2] as usize];
        let p = v.map(|k| DVec3::from(mesh.positions[k].map(f64::from)));
        let normal = DVec3::from(mesh.normals[v[0]].map(f64::from));
        if normal.dot(view.eye - p[0]) <= 0.0 {
            continue;
        }
        let d = p.map(|q| q - view.eye);
        let z = d.map(|q| q.dot(view.forward));
        if z.iter().any(|&z| z <= near) {
            continue;
        }
        let sx: [f64; 3] =
            std::array::from_fn(|k| 0.5 * w as f64 + d[k].dot(view.right) * view.focal_px / z[k]);
        let sy: [f64; 3] =
            std::array::from_fn(|k| 0.5 * h as f64 - d[k].dot(view.up) * view.focal_px / z[k]);
        let area = (sx[1] - sx[0]) * (sy[2] - sy[0]) - (sx[2] - sx[0]) * (sy[1] - sy[0]);
        if area == 0.0 || !area.is_finite() {
            continue;
        }
        let x0 = (sx.iter().copied().fold(f64::INFINITY, f64::min) - 0.5)
            .ceil()
            .max(0.0);
        let x1 = (sx.iter().copied().fold(f64::NEG_INFINITY, f64::max) - 0.5)
            .floor()
            .min(w as f64 - 1.0);
        let y0 = (sy.iter().copied().fold(f64::INFINITY, f64::min) - 0.5)
            .ceil()
            .max(0.0);
        let y1 = (sy.iter().copied().fold(f64::NEG_INFINITY, f64::max) - 0.5)
            .floor()
            .min(h as f64 - 1.0);
        if !(x0 <= x1 && y0 <= y1) {
            continue;
        }
        let inv_z = z.map(|z| 1.0 / z);
        let b = v.map(|k| mesh.radiosity[k]);
        for y in y0 as usize..=y1 as usize {
            let py = y as f64 + 0.5;
            for x in x0 as usize..=x1 as usize {
                let px = x as f64 + 0.5;
                // Screen-space barycentric weights, then perspective-correct ones.
                let l0 = ((sx[1] - px) * (sy[2] - py) - (sx[2] - px) * (sy[1] - py)) / area;
                let l1 = ((sx[2] - px) * (sy[0] - py) - (sx[0] - px) * (sy[2] - py)) / area;
                let l2 = 1.0 - l0 - l1;
                if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                    continue;
                }
                let q = [l0 * inv_z[0], l1 * inv_z[1], l2 * inv_z[2]];
                let one_over_z = q[0] + q[1] + q[2];
                let depth = (1.0 / one_over_z) as f32;
                let i = y * w + x;
                if depth < frame.depth[i] {
                    frame.depth[i] = depth;
                    frame.color[i] = std::array::from_fn(|c| {
                        ((q[0] * b[0][c] as f64 + q[1] * b[1][c] as f64 + q[2] * b[2][c] as f64)
                            / one_over_z) as f32
                    });
                }
            }
        }
    }
    frame
}

/// A tone-mapped picture.
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// Row-major RGB, 3 bytes per pixel.
    pub rgb: Vec<u8>,
    pub tone: ToneMap,
}

fn render_image(
    set: &SurfelSet,
    solution: &Solution,
    camera: &Camera,
    width: u32,
    height: u32,
) -> Result<Image, String> {
    let view = View::new(camera, width, height)?;
    Ok(tone_map_frame(
        &rasterize(set, solution, &view),
        width,
        height,
    ))
}

/// The frame tone-mapped by the percentile of what it shows, the background grey.
fn tone_map_frame(frame: &Frame, width: u32, height: u32) -> Image {
    let tone = ToneMap::from_luminances(frame.covered().map(luminance).collect());
    let mut rgb = Vec::with_capacity(frame.color.len() * 3);
    for (d, c) in frame.depth.iter().zip(&frame.color) {
        let px = if d.is_finite() {
            tone.map(*c)
        } else {
            BACKGROUND
        };
        rgb.extend_from_slice(&px);
    }
    debug_assert_eq!(frame.width, width as usize);
    Image {
        width,
        height,
        rgb,
        tone,
    }
}

/// Renders the solution seen from `camera` into a `width` x `height` PNG at `path` (atomically).
pub fn render_png(
    path: &Path,
    set: &SurfelSet,
    solution: &Solution,
    camera: &Camera,
    width: u32,
    height: u32,
) -> Result<(), OutputError> {
    check_pair(path, set, solution)?;
    let image = render_image(set, solution, camera, width, height)
        .map_err(|what| OutputError::invalid(path, what))?;
    write_png(path, &image)
}

/// What a picture is drawn from.
#[derive(Clone, Copy)]
pub enum Drawn<'a> {
    /// The surfels, as squares (a shard set's solve: no triangles).
    Surfels(&'a SurfelSet, &'a Solution),
    /// The baked mesh, smooth (see [`rasterize_mesh`]).
    Mesh(&'a BakedMesh),
}

/// Renders `drawn` seen from `camera` into a PNG at `png` and, if `exr` is given, the same
/// picture's linear radiosity into an OpenEXR file there (RGBA half floats, alpha 0 where
/// nothing is drawn); each atomically.
pub fn render_pictures(
    png: &Path,
    exr: Option<&Path>,
    drawn: Drawn,
    camera: &Camera,
    width: u32,
    height: u32,
) -> Result<(), OutputError> {
    let view = View::new(camera, width, height).map_err(|what| OutputError::invalid(png, what))?;
    let frame = match drawn {
        Drawn::Surfels(set, solution) => {
            check_pair(png, set, solution)?;
            rasterize(set, solution, &view)
        }
        Drawn::Mesh(mesh) => {
            let near = 1e-6 * camera.eye.distance(camera.target).max(f64::MIN_POSITIVE);
            rasterize_mesh(mesh, &view, near)
        }
    };
    write_png(png, &tone_map_frame(&frame, width, height))?;
    match exr {
        Some(exr) => write_exr(exr, &frame, width as usize, height as usize),
        None => Ok(()),
    }
}

/// The frame's linear radiosity as OpenEXR: RGBA, 16-bit floats (ZIP compressed), alpha 0 where
/// nothing is drawn. Encoded in memory (the encoder needs to seek), then written atomically.
fn write_exr(path: &Path, frame: &Frame, width: usize, height: usize) -> Result<(), OutputError> {
    use exr::prelude::*;
    let pixels = SpecificChannels::rgba(|Vec2(x, y): Vec2<usize>| {
        let i = y * width + x;
        if frame.depth[i].is_finite() {
            let c = frame.color[i];
            (
                f16::from_f32(c[0]),
                f16::from_f32(c[1]),
                f16::from_f32(c[2]),
                f16::ONE,
            )
        } else {
            (f16::ZERO, f16::ZERO, f16::ZERO, f16::ZERO)
        }
    });
    let mut layer = Layer::new(
        (width, height),
        LayerAttributes::named("radiosity"),
        Encoding::SMALL_LOSSLESS,
        pixels,
    );
    layer.attributes.comments = Some(Text::from("voxrad: linear radiosity B, units of Ke"));
    let image = exr::prelude::Image::from_layer(layer);
    let mut bytes = std::io::Cursor::new(Vec::new());
    image
        .write()
        .to_buffered(&mut bytes)
        .map_err(|e| OutputError::invalid(path, format!("cannot encode OpenEXR: {e}")))?;
    atomic::write_atomically(path, |w| w.write_all(bytes.get_ref()))
}

fn write_png(path: &Path, image: &Image) -> Result<(), OutputError> {
    atomic::write_atomically(path, |w| {
        let mut encoder = png::Encoder::new(w, image.width, image.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut writer = encoder.write_header().map_err(png_io)?;
        writer.write_image_data(&image.rgb).map_err(png_io)?;
        writer.finish().map_err(png_io)
    })
}

fn png_io(e: png::EncodingError) -> std::io::Error {
    match e {
        png::EncodingError::IoError(e) => e,
        other => std::io::Error::other(other),
    }
}

/// The 14 candidate view directions (from the scene towards the eye): axes first, so that on a
/// tie the plainer view wins.
fn candidate_directions() -> Vec<DVec3> {
    let mut dirs = vec![
        DVec3::Z,
        DVec3::NEG_Z,
        DVec3::X,
        DVec3::NEG_X,
        DVec3::Y,
        DVec3::NEG_Y,
    ];
    for sx in [1.0, -1.0] {
        for sy in [1.0, -1.0] {
            for sz in [1.0, -1.0] {
                dirs.push(DVec3::new(sx, sy, sz).normalize());
            }
        }
    }
    dirs
}

/// A camera looking at `center` from direction `dir`, far enough that all `corners` fit inside
/// the vertical field of view (and, for images at least as wide as tall, the horizontal one).
fn framed(center: DVec3, corners: &[DVec3], dir: DVec3, fov_degrees: f64, min_dist: f64) -> Camera {
    let up_hint = if dir.y.abs() > 0.9 {
        DVec3::Z
    } else {
        DVec3::Y
    };
    let forward = -dir;
    let right = forward.cross(up_hint).normalize();
    let up = right.cross(forward);
    let tan_half = (fov_degrees.to_radians() * 0.5).tan();
    let mut dist = min_dist;
    for &c in corners {
        let q = c - center;
        let lateral = q.dot(up).abs().max(q.dot(right).abs());
        dist = dist.max(q.dot(dir) + lateral / tan_half);
    }
    Camera {
        eye: center + dir * dist * 1.05,
        target: center,
        up: up_hint,
        vertical_fov_degrees: fov_degrees,
    }
}

/// Frames the scene automatically (see the module header).
pub fn auto_camera(set: &SurfelSet, solution: &Solution) -> Camera {
    let grid = &set.grid;
    let voxel = grid.voxel_size;
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for s in &set.surfels {
        let p = grid.to_world(s.position());
        lo = lo.min(p);
        hi = hi.max(p);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        // No surfels: frame the grid itself.
        lo = DVec3::from(grid.origin);
        hi = lo
            + DVec3::new(
                grid.dims[0] as f64,
                grid.dims[1] as f64,
                grid.dims[2] as f64,
            ) * voxel;
    }
    lo -= DVec3::splat(0.5 * voxel);
    hi += DVec3::splat(0.5 * voxel);
    let center = 0.5 * (lo + hi);
    let corners: Vec<DVec3> = (0..8)
        .map(|k| {
            DVec3::new(
                if k & 1 == 0 { lo.x } else { hi.x },
                if k & 2 == 0 { lo.y } else { hi.y },
                if k & 4 == 0 { lo.z } else { hi.z },
            )
        })
        .collect();
    let min_dist = 2.0 * voxel.max(f64::MIN_POSITIVE);
    let cameras: Vec<Camera> = candidate_directions()
        .into_iter()
        .map(|d| framed(center, &corners, d, DEFAULT_FOV, min_dist))
        .collect();
    if set.surfels.len() != solution.radiosity.len() {
        return cameras[0];
    }
    let (best, seen, covered) = best_of(set, solution, cameras, f64::INFINITY, 0.0);
    // A closed scene (a building) is dark from outside: if what the best outside view sees is
    // far dimmer than the lit surfaces of the scene, look from inside instead, from a few
    // points in the bounds and along the six axes, with a wider lens.
    let (mut lit_area, mut lit_sum) = (0.0f64, 0.0f64);
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        for side in b {
            let l = luminance(*side);
            if l > 0.0 {
                lit_area += s.area as f64;
                lit_sum += s.area as f64 * l;
            }
        }
    }
    let scene_mean = if lit_area > 0.0 {
        lit_sum / lit_area
    } else {
        0.0
    };
    let _ = (seen, covered);
    let seen_median = best_view_median(set, solution, &best);
    if scene_mean > 0.0 && seen_median < 0.05 * scene_mean {
        let mut inside = Vec::new();
        for fx in [0.25, 0.5, 0.75] {
            for fy in [0.25, 0.5, 0.75] {
                for fz in [0.25, 0.5, 0.75] {
                    let eye = lo + (hi - lo) * DVec3::new(fx, fy, fz);
                    for dir in &candidate_directions()[..6] {
                        let up = if dir.y.abs() > 0.9 {
                            DVec3::Z
                        } else {
                            DVec3::Y
                        };
                        inside.push(Camera {
                            eye,
                            target: eye + *dir,
                            up,
                            vertical_fov_degrees: 70.0,
                        });
                    }
                }
            }
        }
        // Luminance capped at the scene's mean, so that a view filled with lit walls beats a
        // close-up of a lamp.
        let (camera, inside_seen, inside_covered) =
            best_of(set, solution, inside, scene_mean, (hi - lo).length());
        if inside_covered > 0 && inside_seen > 0.0 {
            return camera;
        }
    }
    best
}

/// Median luminance of the covered pixels of `camera`'s 64 x 64 view (0 if nothing is covered):
/// from outside a closed scene most pixels are unlit walls, whatever bright seams show.
fn best_view_median(set: &SurfelSet, solution: &Solution, camera: &Camera) -> f64 {
    let Ok(view) = View::new(camera, 64, 64) else {
        return 0.0;
    };
    let mut lums: Vec<f64> = rasterize_every(set, solution, &view, candidate_stride(set))
        .covered()
        .map(luminance)
        .collect();
    if lums.is_empty() {
        return 0.0;
    }
    lums.sort_by(|a, b| a.total_cmp(b));
    lums[lums.len() / 2]
}

/// The camera whose 64 x 64 depth-buffered view sees the most light (each pixel's luminance
/// capped at `cap`); with that light and the number of covered pixels. With `room_size` > 0
/// (cameras inside the scene), a view whose median depth is under a tenth of `room_size` (a
/// camera pressed against a wall) is scored down in proportion.
fn best_of(
    set: &SurfelSet,
    solution: &Solution,
    cameras: Vec<Camera>,
    cap: f64,
    room_size: f64,
) -> (Camera, f64, usize) {
    let every = candidate_stride(set);
    // The views are scored in parallel, then compared in their order: the same choice for any
    // thread count.
    let scores: Vec<Option<(f64, usize)>> = cameras
        .par_iter()
        .map(|camera| {
            let view = View::new(camera, 64, 64).ok()?;
            Some(score_view(
                &rasterize_every(set, solution, &view, every),
                cap,
                room_size,
            ))
        })
        .collect();
    let mut best = (cameras[0], f64::NEG_INFINITY, 0);
    for (camera, score) in cameras.into_iter().zip(scores) {
        if let Some((seen, covered)) = score {
            if seen > best.1 {
                best = (camera, seen, covered);
            }
        }
    }
    best
}

/// Every how many surfels a candidate view draws one (see [`CANDIDATE_SURFELS`]).
fn candidate_stride(set: &SurfelSet) -> usize {
    set.surfels.len().div_ceil(CANDIDATE_SURFELS).max(1)
}

/// The light a candidate view sees (each pixel's luminance capped at `cap`, scored down for a
/// camera pressed against a wall, see [`best_of`]) and its covered pixels.
fn score_view(frame: &Frame, cap: f64, room_size: f64) -> (f64, usize) {
    let (mut seen, covered) = frame
        .covered()
        .fold((0.0, 0), |(s, c), rgb| (s + luminance(rgb).min(cap), c + 1));
    if room_size > 0.0 && covered > 0 {
        let mut depths: Vec<f32> = frame
            .depth
            .iter()
            .copied()
            .filter(|d| d.is_finite())
            .collect();
        depths.sort_by(|a, b| a.total_cmp(b));
        let median = depths[depths.len() / 2] as f64;
        seen *= (median / (0.1 * room_size)).min(1.0);
    }
    (seen, covered)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::testutil;

    fn decode(path: &Path) -> (u32, u32, Vec<u8>) {
        let file = std::io::BufReader::new(std::fs::File::open(path).unwrap());
        let mut reader = png::Decoder::new(file).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf)
    }

    fn lum_at(buf: &[u8], width: u32, x: u32, y: u32) -> u32 {
        let i = 3 * (y * width + x) as usize;
        buf[i] as u32 + buf[i + 1] as u32 + buf[i + 2] as u32
    }

    #[test]
    fn lit_square_renders_brighter_in_the_middle() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("render.png");
        let (set, solution) = testutil::lit_square(8);
        // The square spans 2 x 2 world units around (0, 3, 0.625); look at it from 6 units.
        let camera = Camera::parse("eye=0,3,6.625; target=0,3,0.625; fov=40").unwrap();
        render_png(&path, &set, &solution, &camera, 80, 60).unwrap();
        let (w, h, buf) = decode(&path);
        assert_eq!((w, h), (80, 60));
        assert!(lum_at(&buf, w, w / 2, h / 2) > lum_at(&buf, w, 0, 0));
        assert_eq!(&buf[0..3], &BACKGROUND);
        // The auto camera also sees the lit front.
        let auto = auto_camera(&set, &solution);
        assert!(auto.eye.z > auto.target.z + 1.0, "{auto:?}");
        render_png(&path, &set, &solution, &auto, 64, 64).unwrap();
        let (w, h, buf) = decode(&path);
        assert!(lum_at(&buf, w, w / 2, h / 2) > lum_at(&buf, w, 0, 0));
    }

    /// An 8-voxel box open towards +z: floor, ceiling with a bright lamp, left, right and back
    /// walls on the planes through the centres of the outer voxel layers, fronts facing inwards
    /// and lit, backs dark. As a voxelizer would, each surfel's point is the centroid of its
    /// wall's part inside the voxel, so the two surfels of an edge voxel do not coincide.
    fn open_box() -> (SurfelSet, Solution) {
        let mut surfels = Vec::new();
        let mut radiosity = Vec::new();
        let mut add = |voxel: [i32; 3], normal: [f32; 3], b: f32| {
            let point = [0, 1, 2].map(|k| {
                if normal[k] != 0.0 {
                    0.5
                } else {
                    let v = voxel[k] as f32;
                    0.5 * (v.max(0.5) + (v + 1.0).min(7.5)) - v
                }
            });
            surfels.push(testutil::surfel(voxel, point, normal, 1.0));
            radiosity.push([[b, b, b], [0.0; 3]]);
        };
        for a in 0..8 {
            for c in 0..8 {
                add([a, 0, c], [0.0, 1.0, 0.0], 1.0);
                let lamp = (3..5).contains(&a) && (3..5).contains(&c);
                add([a, 7, c], [0.0, -1.0, 0.0], if lamp { 30.0 } else { 0.5 });
                add([0, a, c], [1.0, 0.0, 0.0], 0.8);
                add([7, a, c], [-1.0, 0.0, 0.0], 0.8);
                add([a, c, 0], [0.0, 0.0, 1.0], 0.8);
            }
        }
        let set = testutil::set_of(surfels, 1.0);
        (
            set,
            Solution {
                radiosity,
                stats: Default::default(),
            },
        )
    }

    #[test]
    fn auto_camera_goes_inside_a_closed_lit_room() {
        use crate::scene::{Material, Scene};
        use crate::voxel::voxelize::{voxelize, GridSpec};
        let mut scene = Scene::default();
        let wall = scene.add_material(Material::new("wall", [0.5; 3], [1.0; 3]));
        scene.add_box(DVec3::ZERO, DVec3::new(2.0, 1.0, 1.5), wall, true);
        let set = voxelize(&scene, GridSpec::Resolution(24)).unwrap();
        let solution = crate::solve::solve(
            &set,
            &crate::solve::SolveOptions {
                directions: 50,
                max_iterations: 3,
                tolerance: None,
                threads: 1,
                ..Default::default()
            },
        )
        .unwrap();
        let eye = auto_camera(&set, &solution).eye;
        assert!(
            eye.cmpgt(DVec3::ZERO).all() && eye.cmplt(DVec3::new(2.0, 1.0, 1.5)).all(),
            "camera outside the closed room: {eye:?}"
        );
    }

    #[test]
    fn auto_camera_looks_into_the_open_side() {
        let (set, solution) = open_box();
        let camera = auto_camera(&set, &solution);
        let view = (camera.target - camera.eye).normalize();
        assert!(view.dot(DVec3::NEG_Z) > 0.99, "{camera:?}");
        camera.validate().unwrap();
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("box.png");
        render_png(&path, &set, &solution, &camera, 32, 32).unwrap();
        let (w, h, buf) = decode(&path);
        assert!(lum_at(&buf, w, w / 2, h / 2) > 3 * BACKGROUND[0] as u32);
    }

    #[test]
    fn camera_text_is_parsed_and_checked() {
        let c = Camera::parse(" target=0,0,0 ; eye=1, 2, 3;fov=30 ").unwrap();
        assert_eq!(c.eye, DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(c.up, DVec3::Y);
        assert_eq!(c.vertical_fov_degrees, 30.0);
        assert_eq!(
            "eye=1,2,3;target=0,0,0"
                .parse::<Camera>()
                .unwrap()
                .vertical_fov_degrees,
            40.0
        );
        for (bad, says) in [
            ("eye=1,2;target=0,0,0", "3 comma-separated"),
            ("eye=1,2,x;target=0,0,0", "'x' is not a finite number"),
            ("eye=1,2,3", "target is missing"),
            ("eye=1,2,3;target=1,2,3", "same point"),
            ("eye=1,2,3;target=0,0,0;fov=200", "between 0 and 180"),
            ("eye=0,5,0;target=0,0,0", "parallel"),
            ("eye=1,2,3;target=0,0,0;zoom=2", "unknown key 'zoom'"),
            ("eye 1,2,3", "not KEY=VALUE"),
            ("eye=1,2,3;eye=1,2,3;target=0,0,0", "twice"),
            ("eye=nan,2,3;target=0,0,0", "finite"),
        ] {
            let e = Camera::parse(bad).unwrap_err();
            assert!(e.to_string().contains(says), "{bad}: {e}");
            assert!(e.to_string().contains(bad), "{e}");
        }
    }

    #[test]
    fn bad_size_and_mismatched_solution_name_the_file() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("render.png");
        let (set, mut solution) = testutil::lit_square(2);
        let camera = auto_camera(&set, &solution);
        let e = render_png(&path, &set, &solution, &camera, 0, 10).unwrap_err();
        assert!(e.to_string().contains("render.png"), "{e}");
        solution.radiosity.pop();
        let e = render_png(&path, &set, &solution, &camera, 10, 10).unwrap_err();
        assert!(e.to_string().contains("render.png"), "{e}");
        assert!(!path.exists());
    }

    #[test]
    fn tone_map_percentile_and_srgb() {
        let mut lums: Vec<f64> = (1..=100).map(f64::from).collect();
        lums.push(0.0);
        lums.push(1e9); // one hot pixel must not set the exposure
        let t = ToneMap::from_luminances(lums);
        assert!(t.exposure > 1.0 / 200.0 && t.exposure < 1.0 / 90.0, "{t:?}");
        assert_eq!(t.map([1e6; 3]), [255; 3]);
        assert_eq!(t.map([0.0; 3]), [0; 3]);
        assert_eq!(ToneMap::from_luminances(vec![0.0]).exposure, 1.0);
        // Mid grey in linear light is brighter than half in sRGB.
        let mid = ToneMap { exposure: 1.0 }.map([0.5; 3]);
        assert!(mid[0] > 180 && mid[0] < 192, "{mid:?}");
    }
}
