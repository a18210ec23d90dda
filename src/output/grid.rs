//! A workplane grid of irradiance sensors (`voxrad grid`): the light arriving on a horizontal
//! plane, as lighting engineers compute it 0.8 m above a floor, with the figures lighting
//! standards ask for (minimum, mean, maximum and uniformity `U0 = min / mean`).
//!
//! The sensors lie at the centres of square cells of side `spacing` on the plane at `height`
//! along the up axis (`+y` by default, as OBJ scenes use), over the scene's extent in the two
//! other axes unless given, and face up; each gathers with [`SensorField::irradiance`]. Written
//! as `PREFIX.csv` (header `x,y,z,nx,ny,nz,H_r,H_g,H_b,H`, `H` the Rec. 709 luminance of the RGB
//! irradiance, in the units of `Ke`) and `PREFIX.png`: the grid in false colour (viridis) with a
//! colour bar and the figures written beside it.

use super::sensor::SensorField;
use super::{atomic, luminance, OutputError};
use font8x8::UnicodeFonts;
use glam::DVec3;
use plotters::prelude::{ColorMap, ViridisRGB};
use rayon::prelude::*;
use std::path::Path;

/// Where the sensors are.
#[derive(Clone, Debug, PartialEq)]
pub struct GridSpec {
    /// The up axis (0 x, 1 y, 2 z); the sensors face along it.
    pub up: usize,
    /// The plane's coordinate along `up` (world units).
    pub height: f64,
    /// Side of a cell (world units).
    pub spacing: f64,
    /// The extent in the two other axes, in axis order (`[low, high]` each); `None`: the
    /// scene's.
    pub extent: [Option<[f64; 2]>; 2],
}

/// The sensors' answers.
#[derive(Clone, Debug)]
pub struct GridResult {
    /// Cells along the first and the second of the other axes.
    pub counts: [usize; 2],
    /// Sensor positions, row by row (the second axis outer).
    pub points: Vec<DVec3>,
    pub normal: DVec3,
    /// RGB irradiance at each sensor.
    pub irradiance: Vec<[f64; 3]>,
    pub spec: GridSpec,
}

/// The figures of a grid (of the luminance of `H`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridFigures {
    pub min: f64,
    pub mean: f64,
    pub max: f64,
    /// `min / mean` (0 when the mean is 0).
    pub uniformity: f64,
}

/// Most sensors one grid may hold.
pub const MAX_SENSORS: usize = 4_000_000;

/// The two axes across `up`, in order.
pub fn across(up: usize) -> [usize; 2] {
    match up {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    }
}

impl GridResult {
    /// Places the sensors of `spec` (over `scene_box`, world `[low, high]` corners, where the
    /// spec gives no extent) and gathers at each. Errors say what is wrong with the spec.
    pub fn gather(
        field: &SensorField,
        spec: &GridSpec,
        scene_box: [DVec3; 2],
    ) -> Result<GridResult, String> {
        if !(spec.spacing > 0.0 && spec.spacing.is_finite()) {
            return Err(format!(
                "the spacing {} is not a positive number",
                spec.spacing
            ));
        }
        if !spec.height.is_finite() {
            return Err(format!("the height {} is not a finite number", spec.height));
        }
        let axes = across(spec.up);
        let extent: [[f64; 2]; 2] = std::array::from_fn(|k| {
            spec.extent[k].unwrap_or([scene_box[0][axes[k]], scene_box[1][axes[k]]])
        });
        let mut counts = [0usize; 2];
        for (k, [lo, hi]) in extent.iter().enumerate() {
            if !(lo.is_finite() && hi.is_finite() && hi > lo) {
                return Err(format!("the extent {lo} to {hi} is empty"));
            }
            counts[k] = ((hi - lo) / spec.spacing).round().max(1.0) as usize;
        }
        if counts[0].saturating_mul(counts[1]) > MAX_SENSORS {
            return Err(format!(
                "{} x {} sensors is more than {MAX_SENSORS}; choose a larger spacing",
                counts[0], counts[1]
            ));
        }
        let mut normal = DVec3::ZERO;
        normal[spec.up] = 1.0;
        let mut points = Vec::with_capacity(counts[0] * counts[1]);
        for j in 0..counts[1] {
            for i in 0..counts[0] {
                // Cell centres, the cells spread evenly over the extent.
                let step = |k: usize, n: usize| {
                    let [lo, hi] = extent[k];
                    lo + (hi - lo) * (n as f64 + 0.5) / counts[k] as f64
                };
                let mut p = DVec3::ZERO;
                p[spec.up] = spec.height;
                p[axes[0]] = step(0, i);
                p[axes[1]] = step(1, j);
                points.push(p);
            }
        }
        let irradiance = points
            .par_iter()
            .map(|&p| field.irradiance(p, normal))
            .collect();
        Ok(GridResult {
            counts,
            points,
            normal,
            irradiance,
            spec: GridSpec {
                extent: extent.map(Some),
                ..spec.clone()
            },
        })
    }

    /// Minimum, mean, maximum and uniformity of the luminance of `H`.
    pub fn figures(&self) -> GridFigures {
        let values: Vec<f64> = self.irradiance.iter().map(|h| luminance_f64(*h)).collect();
        let min = values.iter().copied().fold(f64::INFINITY, f64::min);
        let max = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mean = values.iter().sum::<f64>() / values.len().max(1) as f64;
        GridFigures {
            min,
            mean,
            max,
            uniformity: if mean > 0.0 { min / mean } else { 0.0 },
        }
    }

    /// Writes `PREFIX.csv` (see the module header).
    pub fn write_csv(&self, path: &Path) -> Result<(), OutputError> {
        atomic::write_atomically(path, |w| {
            writeln!(w, "x,y,z,nx,ny,nz,H_r,H_g,H_b,H")?;
            for (p, h) in self.points.iter().zip(&self.irradiance) {
                let n = self.normal;
                writeln!(
                    w,
                    "{},{},{},{},{},{},{},{},{},{}",
                    p.x,
                    p.y,
                    p.z,
                    n.x,
                    n.y,
                    n.z,
                    h[0],
                    h[1],
                    h[2],
                    luminance_f64(*h)
                )?;
            }
            Ok(())
        })
    }

    /// Writes `PREFIX.png` (see the module header).
    pub fn write_png(&self, path: &Path) -> Result<(), OutputError> {
        let figures = self.figures();
        let [na, nb] = self.counts;
        // Cells as squares of whole pixels, the map about 600 pixels across.
        let cell = (600 / na.max(nb)).clamp(1, 64);
        let (map_w, map_h) = (na * cell, nb * cell);
        let margin = 16;
        let panel = 300;
        let width = margin + map_w + margin + panel;
        let height = (margin + map_h + margin).max(margin + 15 * LINE + margin);
        let mut image = Canvas::new(width, height, [255, 255, 255]);
        let (lo, hi) = (
            figures.min,
            figures.max.max(figures.min + f64::MIN_POSITIVE),
        );
        for j in 0..nb {
            for i in 0..na {
                let v = luminance_f64(self.irradiance[j * na + i]);
                let c = colour(v, lo, hi);
                // The second axis grows downwards in the picture, as a plan seen from above
                // with +y up has +z towards the viewer.
                image.fill(margin + i * cell, margin + j * cell, cell, cell, c);
            }
        }
        // The colour bar, maximum at the top.
        let (bar_x, bar_w, bar_h) = (margin + map_w + margin, 24, map_h.max(15 * LINE));
        for y in 0..bar_h {
            let v = hi - (hi - lo) * y as f64 / (bar_h - 1).max(1) as f64;
            image.fill(bar_x, margin + y, bar_w, 1, colour(v, lo, hi));
        }
        let text_x = bar_x + bar_w + 8;
        image.text(text_x, margin, &format!("{}", Number(hi)));
        image.text(
            text_x,
            margin + bar_h - 8 * SCALE,
            &format!("{}", Number(lo)),
        );
        let axis = ["x", "y", "z"][self.spec.up];
        let lines = [
            "irradiance H".to_string(),
            "(units of Ke)".to_string(),
            format!("at {axis} = {}", Number(self.spec.height)),
            format!("spacing {}", Number(self.spec.spacing)),
            format!("{} x {} sensors", na, nb),
            String::new(),
            format!("min  {}", Number(figures.min)),
            format!("mean {}", Number(figures.mean)),
            format!("max  {}", Number(figures.max)),
            format!("U0   {:.3}", figures.uniformity),
        ];
        for (k, line) in lines.iter().enumerate() {
            image.text(text_x, margin + (3 + k) * LINE, line);
        }
        image.write_png(path)
    }
}

fn luminance_f64(h: [f64; 3]) -> f64 {
    luminance(h.map(|v| v as f32))
}

/// The viridis colour of `v` between `lo` and `hi`: the lowest where the range is empty (a grid
/// whose sensors all read alike) or `v` is not a number (plotters' colour map panics on both).
fn colour(v: f64, lo: f64, hi: f64) -> [u8; 3] {
    let t = if hi > lo { (v - lo) / (hi - lo) } else { 0.0 };
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    let c = ViridisRGB.get_color_normalized(t as f32, 0.0, 1.0);
    [c.0, c.1, c.2]
}

/// A number with four significant digits, without an exponent where it reads well.
struct Number(f64);

impl std::fmt::Display for Number {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let v = self.0;
        if v == 0.0 {
            write!(f, "0")
        } else if (1e-3..1e6).contains(&v.abs()) {
            let digits = (3 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
            write!(f, "{v:.digits$}")
        } else {
            write!(f, "{v:.3e}")
        }
    }
}

/// Text is drawn with the 8 x 8 bitmap font of `font8x8` at this scale.
const SCALE: usize = 2;
/// Height of a line of text, pixels.
const LINE: usize = 8 * SCALE + 6;

/// An RGB picture being drawn.
struct Canvas {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
}

impl Canvas {
    fn new(width: usize, height: usize, background: [u8; 3]) -> Canvas {
        Canvas {
            width,
            height,
            rgb: background.repeat(width * height),
        }
    }

    fn fill(&mut self, x: usize, y: usize, w: usize, h: usize, c: [u8; 3]) {
        for yy in y..(y + h).min(self.height) {
            for xx in x..(x + w).min(self.width) {
                let i = 3 * (yy * self.width + xx);
                self.rgb[i..i + 3].copy_from_slice(&c);
            }
        }
    }

    fn text(&mut self, x: usize, y: usize, text: &str) {
        for (k, ch) in text.chars().enumerate() {
            let glyph = font8x8::BASIC_FONTS.get(ch).unwrap_or([0; 8]);
            for (row, bits) in glyph.iter().enumerate() {
                for col in 0..8 {
                    if bits & (1 << col) != 0 {
                        self.fill(
                            x + (8 * k + col) * SCALE,
                            y + row * SCALE,
                            SCALE,
                            SCALE,
                            [0, 0, 0],
                        );
                    }
                }
            }
        }
    }

    fn write_png(&self, path: &Path) -> Result<(), OutputError> {
        atomic::write_atomically(path, |w| {
            let mut encoder = png::Encoder::new(w, self.width as u32, self.height as u32);
            encoder.set_color(png::ColorType::Rgb);
            encoder.set_depth(png::BitDepth::Eight);
            let mut writer = encoder.write_header().map_err(std::io::Error::other)?;
            writer
                .write_image_data(&self.rgb)
                .map_err(std::io::Error::other)?;
            writer.finish().map_err(std::io::Error::other)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_read_well() {
        assert_eq!(Number(0.0).to_string(), "0");
        assert_eq!(Number(123.456).to_string(), "123.5");
        assert_eq!(Number(0.5).to_string(), "0.5000");
        assert_eq!(Number(2.5e7).to_string(), "2.500e7");
    }

    /// A grid whose sensors all read alike, or read NaN, still draws (the colour map of
    /// plotters panics on an empty range).
    #[test]
    fn colours_of_an_empty_range_and_of_nan() {
        assert_eq!(colour(2.0, 2.0, 2.0), colour(0.0, 0.0, 1.0));
        assert_eq!(colour(f64::NAN, 0.0, 1.0), colour(0.0, 0.0, 1.0));
        assert_eq!(colour(5.0, 0.0, 1.0), colour(1.0, 0.0, 1.0));
        let grid = GridResult {
            counts: [1, 1],
            points: vec![DVec3::ZERO],
            normal: DVec3::Y,
            irradiance: vec![[1.0; 3]],
            spec: GridSpec {
                up: 1,
                height: 0.0,
                spacing: 1.0,
                extent: [None, None],
            },
        };
        let dir = tempfile::TempDir::new().unwrap();
        grid.write_png(&dir.path().join("one.png")).unwrap();
    }

    #[test]
    fn the_other_axes_keep_their_order() {
        assert_eq!(across(1), [0, 2]);
        assert_eq!(across(0), [1, 2]);
        assert_eq!(across(2), [0, 1]);
    }
}
