//! The study's picture: mean error against time on log-log axes, one polyline per knob, the
//! Pareto front as a black staircase with its runs ringed.
//!
//! Drawn with plotters' bitmap backend into a buffer and encoded with the `png` crate, with no
//! text at all: plotters' text needs a font feature that pulls in system font libraries
//! (fontconfig/freetype) or a bundled font file. The axes' ranges and the colours are stated in
//! `study.md` instead ([`LEGEND`], [`error_range`], [`time_range`]).

use super::Run;
use plotters::prelude::*;

/// The knobs in drawing order and their colours.
const KNOBS: [(&str, RGBColor); 5] = [
    ("directions", RGBColor(31, 119, 180)),
    ("tolerance", RGBColor(44, 160, 44)),
    ("tolerance+extrapolation", RGBColor(255, 127, 14)),
    ("resolution", RGBColor(214, 39, 40)),
    ("direct", RGBColor(148, 103, 189)),
];

/// The colours in words, for the Markdown.
pub const LEGEND: &str = "directions blue, tolerance green, tolerance with tail extrapolation \
                          orange, resolution red, direct-light pass purple (in the order of \
                          the table); the quality presets are grey squares";

/// Errors below this are drawn at it (an exact extrapolation can reach 1e-16).
const ERROR_FLOOR: f64 = 1e-7;

fn shown_error(r: &Run) -> f64 {
    if r.mean_error.is_finite() {
        r.mean_error.max(ERROR_FLOOR)
    } else {
        ERROR_FLOOR
    }
}

/// Decade-rounded range (low, high) of the plotted errors.
pub fn error_range(runs: &[Run]) -> (f64, f64) {
    decades(runs.iter().map(shown_error))
}

/// Decade-rounded range (low, high) of the run times.
pub fn time_range(runs: &[Run]) -> (f64, f64) {
    decades(runs.iter().map(|r| r.seconds.max(1e-4)))
}

fn decades(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    if lo > hi {
        return (1e-3, 1.0);
    }
    let lo = 10f64.powf(lo.log10().floor());
    let mut hi = 10f64.powf(hi.log10().ceil());
    if hi <= lo {
        hi = lo * 10.0;
    }
    (lo, hi)
}

/// The PNG bytes of the picture, `width` x `height` pixels.
pub fn render(runs: &[Run], width: u32, height: u32) -> Result<Vec<u8>, String> {
    let mut rgb = vec![255u8; (width * height * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
        draw(&root, runs).map_err(|e| format!("cannot draw the study plot: {e}"))?;
        root.present()
            .map_err(|e| format!("cannot draw the study plot: {e}"))?;
    }
    let mut png_bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut png_bytes, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
        writer.write_image_data(&rgb).map_err(|e| e.to_string())?;
    }
    Ok(png_bytes)
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

fn draw(root: &Area, runs: &[Run]) -> Result<(), Box<dyn std::error::Error>> {
    let (t0, t1) = time_range(runs);
    let (e0, e1) = error_range(runs);
    let (w, h) = root.dim_in_pixel();
    let (left, top, right, bottom) = (30i32, 20i32, w as i32 - 20, h as i32 - 30);
    // Log coordinates mapped by hand: no text, so no chart builder (its mesh wants a font).
    let x = |t: f64| {
        let f = (t.max(t0).log10() - t0.log10()) / (t1.log10() - t0.log10());
        left + (f * (right - left) as f64).round() as i32
    };
    let y = |e: f64| {
        let f = (e.max(e0).log10() - e0.log10()) / (e1.log10() - e0.log10());
        bottom - (f * (bottom - top) as f64).round() as i32
    };
    let grid = RGBColor(225, 225, 225);
    // Decade grid lines, then the axes.
    let mut t = t0;
    while t <= t1 * 1.0001 {
        root.draw(&PathElement::new([(x(t), top), (x(t), bottom)], grid))?;
        t *= 10.0;
    }
    let mut e = e0;
    while e <= e1 * 1.0001 {
        root.draw(&PathElement::new([(left, y(e)), (right, y(e))], grid))?;
        e *= 10.0;
    }
    root.draw(&PathElement::new(
        [(left, top), (left, bottom), (right, bottom)],
        BLACK.stroke_width(2),
    ))?;
    for (knob, colour) in KNOBS {
        let points: Vec<(i32, i32)> = runs
            .iter()
            .filter(|r| r.knob == knob)
            .map(|r| (x(r.seconds), y(shown_error(r))))
            .collect();
        root.draw(&PathElement::new(points.clone(), colour.stroke_width(2)))?;
        for p in points {
            root.draw(&Circle::new(p, 4, colour.filled()))?;
        }
    }
    // Quality presets: grey squares.
    for r in runs.iter().filter(|r| !KNOBS.iter().any(|k| k.0 == r.knob)) {
        let (px, py) = (x(r.seconds), y(shown_error(r)));
        root.draw(&Rectangle::new(
            [(px - 5, py - 5), (px + 5, py + 5)],
            RGBColor(110, 110, 110).filled(),
        ))?;
    }
    // The Pareto front: a staircase through its runs in time order.
    let mut front: Vec<&Run> = runs.iter().filter(|r| r.pareto).collect();
    front.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
    let mut stairs = Vec::new();
    for (k, r) in front.iter().enumerate() {
        let p = (x(r.seconds), y(shown_error(r)));
        if k > 0 {
            stairs.push((p.0, stairs.last().map_or(p.1, |q: &(i32, i32)| q.1)));
        }
        stairs.push(p);
    }
    root.draw(&PathElement::new(stairs, BLACK.stroke_width(1)))?;
    for r in front {
        root.draw(&Circle::new(
            (x(r.seconds), y(shown_error(r))),
            8,
            BLACK.stroke_width(2),
        ))?;
    }
    Ok(())
}
