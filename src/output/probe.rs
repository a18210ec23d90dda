//! Probes: the radiosity at given surface points, on the side facing a given normal.
//!
//! Input is a CSV of rows `x,y,z,nx,ny,nz` in world units (one optional header line, recognised
//! by having no numeric field; blank lines skipped). For each row, the answer is the area-weighted
//! mean radiosity of the surfel sides within [`PROBE_RADIUS_VOXELS`] voxels of the point whose
//! side normal agrees with `n` (dot product above [`MIN_NORMAL_DOT`]): the normal test picks the
//! side of a wall the probe is on, and keeps the other wall of a corner out. Of those, only the
//! layer nearest the probe point along `n` counts (sides within [`LAYER_VOXELS`] of the height,
//! along `n`, of the side nearest the point's tangent plane): in a slab thinner than the search
//! radius the far face's inner side faces the same way as the near face's outer side but looks
//! into the slab, under a rug the floor faces up as the rug does but is covered, and a lamp hung
//! just under a ceiling faces down as the ceiling does but is another surface. If every such side
//! has zero area (voxels only touched by the surface), sides are weighted by inverse distance. If
//! there is none, the radiosity is 0 and [`ProbeRow::found`] is false.
//!
//! A hash map from columns of voxels `(x, y)` to their occupied voxels, in order of z, makes
//! each lookup touch only the 4x4x4 voxels around the point, whatever the scene size, with one
//! hash look-up a column.
//!
//! The irradiance `H` (the light arriving on that side; a side reflects `rho H`) is averaged the
//! same way from each side's `(B - E) / rho` (see [`Record::irradiance`]); it is NaN in a channel
//! where a side averaged has no reflectance there, or where the results file predates materials.
//!
//! Output is a header line [`PROBE_HEADER`], then rows `x,y,z,nx,ny,nz,B_r,B_g,B_b,H_r,H_g,H_b`,
//! the point and normal echoed as given.

use super::results::{Record, Results};
use super::{atomic, OutputError};
use crate::solve::mix_hash::MixMap;
use crate::voxel::{BACK, FRONT};
use glam::DVec3;
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};

/// The first line of the probe output.
pub const PROBE_HEADER: &str = "x,y,z,nx,ny,nz,B_r,B_g,B_b,H_r,H_g,H_b";

/// Search radius around the probe point, in voxels.
pub const PROBE_RADIUS_VOXELS: f64 = 1.5;
/// Longest line accepted in a points file (six numbers need far less).
pub const MAX_LINE_BYTES: usize = 4096;
/// Smallest cosine between a surfel side's normal and the probe normal for the side to count.
pub const MIN_NORMAL_DOT: f64 = 0.5;
/// Thickness (voxels, along the probe normal) of the layer of sides a probe averages. The surfels
/// of a plane all lie on it, so the layer only has to allow for a probe normal a little off the
/// plane's (1e-3 off moves a side 1.5 voxels away by 0.0015). Sheets of other surfaces facing the
/// same way lie outside it: a rug 1 cm thick at 16 cm voxels (0.06 voxel above the floor), and a
/// lamp hung 1 cm under a ceiling at 39 cm voxels (0.026 voxel), which a layer of 0.05 voxel
/// took in and read probes on the ceiling beside it as the lamp (44 times too bright).
pub const LAYER_VOXELS: f64 = 0.01;

/// The answer for one probe point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProbeRow {
    /// The point, as given (world units).
    pub point: DVec3,
    /// The normal, as given (not normalised).
    pub normal: DVec3,
    /// Radiosity on the side facing `normal`, RGB.
    pub radiosity: [f64; 3],
    /// Irradiance arriving on that side, RGB (NaN where unknown, see the module header).
    pub irradiance: [f64; 3],
    /// False if no surfel side near the point faces `normal` (then `radiosity` is 0).
    pub found: bool,
    /// Number of surfel sides averaged.
    pub samples: usize,
    /// The material (index into the results' table) of the side of most weight averaged.
    pub material: Option<u32>,
}

/// Why probing failed. Every case names the CSV file; row errors also the line (1-based).
#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}:{line}: {what}", path.display())]
    BadRow {
        path: PathBuf,
        line: usize,
        what: String,
    },
}

/// Surfels of a results file, indexed by voxel for fast neighbourhood lookups.
pub struct ProbeIndex<'a> {
    results: &'a Results,
    /// Record indices sorted by voxel, so each voxel's records are one contiguous run.
    order: Vec<usize>,
    /// Each voxel's run in `order` as (z, start, length), by voxel: the voxels of one column
    /// `(x, y)` are one run of this list, in order of z. Only voxels `voxel::packed_voxel`
    /// takes are listed.
    voxels: Vec<(i32, usize, usize)>,
    /// Column `(x, y)` (by `voxel::packed_voxel` of `[x, y, 0]`) -> its range in `voxels`. A
    /// look-up reads the 4 x 4 x 4 voxels around its point as 16 columns: one hash look-up
    /// each instead of one a voxel, whose cache misses in a table of every voxel of the scene
    /// were most of a bake's look-up time.
    columns: MixMap<(usize, usize)>,
}

impl<'a> ProbeIndex<'a> {
    pub fn new(results: &'a Results) -> Self {
        let records = &results.records;
        let mut order: Vec<usize> = (0..records.len()).collect();
        // Stable, so records of one voxel keep their file order (deterministic averages).
        order.sort_by_key(|&i| records[i].voxel);
        let mut voxels = Vec::new();
        let mut columns = MixMap::default();
        let mut column: Option<(u64, usize)> = None;
        let mut start = 0;
        while start < order.len() {
            let voxel = records[order[start]].voxel;
            let mut end = start + 1;
            while end < order.len() && records[order[end]].voxel == voxel {
                end += 1;
            }
            if crate::voxel::packed_voxel(voxel).is_some() {
                let key = crate::voxel::packed_voxel([voxel[0], voxel[1], 0])
                    .expect("a column of a voxel in range");
                if column.is_some_and(|(k, _)| k != key) {
                    let (k, first) = column.take().expect("a column");
                    columns.insert(k, (first, voxels.len()));
                }
                if column.is_none() {
                    column = Some((key, voxels.len()));
                }
                voxels.push((voxel[2], start, end - start));
            }
            start = end;
        }
        if let Some((k, first)) = column {
            columns.insert(k, (first, voxels.len()));
        }
        ProbeIndex {
            results,
            order,
            voxels,
            columns,
        }
    }

    /// The records of the voxels `(x, y, z)` for `z` in `z_range`, voxel by voxel in order of z.
    fn records_in_column(
        &self,
        x: i32,
        y: i32,
        z_range: std::ops::RangeInclusive<i32>,
    ) -> impl Iterator<Item = &Record> + '_ {
        let column = crate::voxel::packed_voxel([x, y, 0])
            .and_then(|key| self.columns.get(&key).copied())
            .map_or(&[][..], |(first, end)| &self.voxels[first..end]);
        let from = column.partition_point(|v| v.0 < *z_range.start());
        column[from..]
            .iter()
            .take_while(move |v| v.0 <= *z_range.end())
            .flat_map(move |&(_, start, len)| {
                self.order[start..start + len]
                    .iter()
                    .map(move |&i| &self.results.records[i])
            })
    }

    /// Radiosity at `point` (world units) on the side facing `normal` (see the module header).
    /// `normal` need not be unit length; a zero or non-finite normal finds nothing.
    pub fn lookup(&self, point: DVec3, normal: DVec3) -> ProbeRow {
        MATCHES.with_borrow_mut(|matches| self.lookup_with::<true>(point, normal, matches))
    }

    /// The radiosity of [`Self::lookup`] alone, the same bits, without the irradiance and the
    /// material: what a bake reads at every vertex of a scene (without the irradiance's
    /// divisions and a new list of matches per call, a bake of a building took about a tenth
    /// less time: docs/throughput.md).
    pub fn radiosity_at(&self, point: DVec3, normal: DVec3) -> [f64; 3] {
        MATCHES
            .with_borrow_mut(|matches| self.lookup_with::<false>(point, normal, matches).radiosity)
    }

    /// [`Self::lookup`], with the irradiance and the material where `IRRADIANCE`, listing the
    /// matching sides in `matches`.
    fn lookup_with<const IRRADIANCE: bool>(
        &self,
        point: DVec3,
        normal: DVec3,
        matches: &mut Vec<Match>,
    ) -> ProbeRow {
        let mut row = ProbeRow {
            point,
            normal,
            radiosity: [0.0; 3],
            irradiance: [0.0; 3],
            found: false,
            samples: 0,
            material: None,
        };
        let n = normal.normalize_or_zero();
        let q = self.results.grid.to_voxel_units(point);
        if n == DVec3::ZERO || !q.is_finite() {
            return row;
        }
        let r = PROBE_RADIUS_VOXELS;
        let lo = (q - DVec3::splat(r)).floor();
        let hi = (q + DVec3::splat(r)).floor();
        let in_range = |v: f64| v >= i32::MIN as f64 && v <= i32::MAX as f64;
        if ![lo.x, lo.y, lo.z, hi.x, hi.y, hi.z]
            .into_iter()
            .all(in_range)
        {
            return row;
        }
        // (area, inverse distance, radiosity, height along n above the probe point) of every
        // matching side.
        let materials = &self.results.materials;
        matches.clear();
        for x in lo.x as i32..=hi.x as i32 {
            for y in lo.y as i32..=hi.y as i32 {
                for rec in self.records_in_column(x, y, lo.z as i32..=hi.z as i32) {
                    let d = rec.position().distance(q);
                    if d > r {
                        continue;
                    }
                    let height = (rec.position() - q).dot(n);
                    for side in [FRONT, BACK] {
                        if rec.side_normal(side).dot(n) > MIN_NORMAL_DOT {
                            matches.push(Match {
                                area: rec.area as f64,
                                inverse_distance: 1.0 / d.max(1e-3),
                                radiosity: rec.radiosity[side],
                                irradiance: if IRRADIANCE {
                                    rec.irradiance(side, materials)
                                        .map(|h| h.unwrap_or(f64::NAN))
                                } else {
                                    [0.0; 3]
                                },
                                height,
                                material: rec.material[side],
                            });
                        }
                    }
                }
            }
        }
        if matches.is_empty() {
            return row;
        }
        let nearest = matches
            .iter()
            .map(|m| m.height)
            .min_by(|a, b| a.abs().total_cmp(&b.abs()))
            .unwrap_or(0.0);
        matches.retain(|m| (m.height - nearest).abs() <= LAYER_VOXELS);
        let total_area: f64 = matches.iter().map(|m| m.area).sum();
        let weight = |m: &Match| {
            if total_area > 0.0 {
                m.area
            } else {
                m.inverse_distance
            }
        };
        let total: f64 = matches.iter().map(weight).sum();
        for m in matches.iter() {
            let w = weight(m) / total;
            for c in 0..3 {
                row.radiosity[c] += w * m.radiosity[c] as f64;
                // A side of no weight (a voxel only touched) adds nothing, even an unknown.
                if IRRADIANCE && w > 0.0 {
                    row.irradiance[c] += w * m.irradiance[c];
                }
            }
        }
        row.found = true;
        row.samples = matches.len();
        if !IRRADIANCE {
            return row;
        }
        row.material = matches
            .iter()
            .max_by(|a, b| weight(a).total_cmp(&weight(b)))
            .map(|m| m.material)
            .filter(|&m| (m as usize) < materials.len());
        row
    }
}

thread_local! {
    /// The matching sides of one look-up, kept from call to call: a bake makes millions.
    static MATCHES: std::cell::RefCell<Vec<Match>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// A surfel side near a probe point that faces the probe's normal.
struct Match {
    area: f64,
    inverse_distance: f64,
    radiosity: [f32; 3],
    irradiance: [f64; 3],
    /// Height of the side's point above the probe point along the normal (voxels).
    height: f64,
    material: u32,
}

/// Reads probe points `(point, normal)` from a CSV file (see the module header).
pub fn read_points(path: &Path) -> Result<Vec<(DVec3, DVec3)>, ProbeError> {
    let file = File::open(path).map_err(|source| ProbeError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    read_points_from(path, BufReader::new(file))
}

/// Reads probe points from any reader (a file, standard input, bytes in memory); `path` names
/// the source in errors.
pub fn read_points_from(
    path: &Path,
    mut reader: impl BufRead,
) -> Result<Vec<(DVec3, DVec3)>, ProbeError> {
    let io = |source| ProbeError::Io {
        path: path.to_path_buf(),
        source,
    };
    let bad = |line: usize, what: String| ProbeError::BadRow {
        path: path.to_path_buf(),
        line,
        what,
    };
    let mut points = Vec::new();
    let mut raw = Vec::new();
    let mut line_no = 0;
    let mut seen_content = false;
    loop {
        raw.clear();
        // At most one line longer than any sensible row is held: a file without line ends (or
        // `/dev/zero`) must not be read into memory whole.
        let limit = MAX_LINE_BYTES as u64 + 1;
        if (&mut reader)
            .take(limit)
            .read_until(b'\n', &mut raw)
            .map_err(io)?
            == 0
        {
            break;
        }
        line_no += 1;
        if raw.len() > MAX_LINE_BYTES {
            return Err(bad(
                line_no,
                format!("the line is longer than {MAX_LINE_BYTES} bytes; rows are x,y,z,nx,ny,nz"),
            ));
        }
        let text = std::str::from_utf8(&raw)
            .map_err(|_| bad(line_no, "the line is not UTF-8 text".into()))?;
        let text = text.trim_start_matches('\u{feff}').trim();
        if text.is_empty() {
            continue;
        }
        let fields: Vec<&str> = text.split(',').map(str::trim).collect();
        let first = !seen_content;
        seen_content = true;
        if first && fields.iter().all(|f| f.parse::<f64>().is_err()) {
            continue; // a header line
        }
        if fields.len() != 6 {
            return Err(bad(
                line_no,
                format!(
                    "expected 6 columns x,y,z,nx,ny,nz but found {}",
                    fields.len()
                ),
            ));
        }
        let mut v = [0.0f64; 6];
        for (k, f) in fields.iter().enumerate() {
            v[k] = match f.parse::<f64>() {
                Ok(x) if x.is_finite() => x,
                _ => {
                    return Err(bad(
                        line_no,
                        format!("column {} ('{f}') is not a finite number", k + 1),
                    ))
                }
            };
        }
        let normal = DVec3::new(v[3], v[4], v[5]);
        if normal.length() == 0.0 {
            return Err(bad(line_no, "the normal is zero".into()));
        }
        points.push((DVec3::new(v[0], v[1], v[2]), normal));
    }
    Ok(points)
}

/// Probes every point of `points_csv` in `results`.
pub fn probe(results: &Results, points_csv: &Path) -> Result<Vec<ProbeRow>, ProbeError> {
    let points = read_points(points_csv)?;
    let index = ProbeIndex::new(results);
    Ok(points
        .into_iter()
        .map(|(p, n)| index.lookup(p, n))
        .collect())
}

/// Writes probe rows as CSV: the header line [`PROBE_HEADER`], then
/// `x,y,z,nx,ny,nz,B_r,B_g,B_b,H_r,H_g,H_b` rows.
pub fn write_rows(out: &mut dyn Write, rows: &[ProbeRow]) -> std::io::Result<()> {
    writeln!(out, "{PROBE_HEADER}")?;
    for r in rows {
        let (p, n, b, h) = (r.point, r.normal, r.radiosity, r.irradiance);
        writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{}",
            p.x, p.y, p.z, n.x, n.y, n.z, b[0], b[1], b[2], h[0], h[1], h[2]
        )?;
    }
    Ok(())
}

/// Writes probe rows to a CSV file, atomically.
pub fn write_probe_csv(path: &Path, rows: &[ProbeRow]) -> Result<(), OutputError> {
    atomic::write_atomically(path, |w| write_rows(w, rows))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::testutil;
    use crate::solve::Solution;
    use crate::voxel::Surfel;

    /// A wall in the plane x = 2.5 (voxel units), front facing +x with B = (1, 2, 3), back facing
    /// -x with B = (4, 5, 6); one voxel of the wall also holds a floor surfel facing +y (B = 9).
    fn wall() -> Results {
        let mut surfels = Vec::new();
        let mut radiosity = Vec::new();
        for y in 0..6 {
            for z in 0..6 {
                surfels.push(testutil::surfel([2, y, z], [0.5; 3], [1.0, 0.0, 0.0], 1.0));
                radiosity.push([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
            }
        }
        surfels.push(testutil::surfel(
            [2, 0, 3],
            [0.5, 0.0, 0.5],
            [0.0, 1.0, 0.0],
            0.5,
        ));
        radiosity.push([[9.0; 3], [0.0; 3]]);
        results_of(surfels, radiosity)
    }

    /// The results of surfels with the given radiosity, on the grid of `testutil::set_of` (voxel
    /// size 0.5).
    fn results_of(surfels: Vec<Surfel>, radiosity: Vec<[[f32; 3]; 2]>) -> Results {
        let set = testutil::set_of(surfels, 0.5);
        let solution = Solution {
            radiosity,
            stats: Default::default(),
        };
        Results::from_solution(&set, &solution).unwrap()
    }

    /// World position of a voxel-unit point of the `wall` grid (origin (-1, 2, 0.5), size 0.5).
    fn world(x: f64, y: f64, z: f64) -> String {
        format!("{},{},{}", -1.0 + 0.5 * x, 2.0 + 0.5 * y, 0.5 + 0.5 * z)
    }

    #[test]
    fn probe_picks_the_side_facing_the_normal() {
        let dir = tempfile::TempDir::new().unwrap();
        let csv = dir.path().join("points.csv");
        let text = format!(
            "x,y,z,nx,ny,nz\n\n{},1,0,0\n{},-2,0.1,0\n{},0,1,0\n{},0,0,1\n{},1,0,0\n",
            world(2.5, 3.0, 3.0),
            world(2.5, 3.0, 3.0),
            world(2.5, 0.0, 3.0),
            world(2.5, 3.0, 3.0),
            world(40.0, 3.0, 3.0),
        );
        std::fs::write(&csv, text).unwrap();
        let results = wall();
        let rows = probe(&results, &csv).unwrap();
        assert_eq!(rows.len(), 5);
        assert_eq!(rows[0].radiosity, [1.0, 2.0, 3.0]);
        assert!(rows[0].found && rows[0].samples > 1);
        assert_eq!(rows[1].radiosity, [4.0, 5.0, 6.0]);
        assert_eq!(rows[2].radiosity, [9.0; 3]);
        // Nothing faces +z, and nothing is near x = 40.
        for r in &rows[3..] {
            assert!(!r.found);
            assert_eq!(r.radiosity, [0.0; 3]);
        }
        // Irradiance: the wall's material reflects half and emits nothing, so H = 2 B.
        assert_eq!(rows[0].irradiance, [2.0, 4.0, 6.0]);
        assert_eq!(rows[1].irradiance, [8.0, 10.0, 12.0]);
        let mut out = Vec::new();
        write_rows(&mut out, &rows[..1]).unwrap();
        assert_eq!(
            String::from_utf8(out).unwrap(),
            format!(
                "{PROBE_HEADER}\n{},1,0,0,1,2,3,2,4,6\n",
                world(2.5, 3.0, 3.0)
            )
        );
        let path = dir.path().join("probes.csv");
        write_probe_csv(&path, &rows).unwrap();
        let back = std::fs::read_to_string(&path).unwrap();
        assert_eq!(back.lines().count(), 6);
    }

    #[test]
    fn a_thin_slab_is_probed_on_its_outer_side_only() {
        // A slab 0.3 voxel thick in the plane x = 2.5: its +x face (front +x, lit: B = 7) and its
        // -x face 0.3 behind (front -x, dark; its back side, facing +x, looks into the slab and
        // has B = 0). A probe on the +x face must read 7, not a mean with the inner side.
        let mut surfels = Vec::new();
        let mut radiosity = Vec::new();
        for y in 0..4 {
            for z in 0..4 {
                surfels.push(testutil::surfel(
                    [2, y, z],
                    [0.65, 0.5, 0.5],
                    [1.0, 0.0, 0.0],
                    1.0,
                ));
                radiosity.push([[7.0; 3], [0.0; 3]]);
                surfels.push(testutil::surfel(
                    [2, y, z],
                    [0.35, 0.5, 0.5],
                    [-1.0, 0.0, 0.0],
                    1.0,
                ));
                radiosity.push([[2.0; 3], [0.0; 3]]);
            }
        }
        let results = results_of(surfels, radiosity);
        let index = ProbeIndex::new(&results);
        let on_plus = DVec3::new(-1.0 + 0.5 * 2.65, 2.0 + 0.5 * 2.0, 0.5 + 0.5 * 2.0);
        let row = index.lookup(on_plus, DVec3::X);
        assert_eq!(row.radiosity, [7.0; 3]);
        let on_minus = DVec3::new(-1.0 + 0.5 * 2.35, 2.0 + 0.5 * 2.0, 0.5 + 0.5 * 2.0);
        let row = index.lookup(on_minus, -DVec3::X);
        assert_eq!(row.radiosity, [2.0; 3]);
    }

    #[test]
    fn a_lamp_hung_just_under_a_ceiling_is_not_the_ceiling() {
        // A ceiling facing -y at height 2.5 (B = 1) and, 0.026 voxel under it, a lamp facing -y
        // (B = 100): the corridor of tests/data/reference at resolution 32, where lamps 1 cm
        // under the ceiling read as the ceiling and put probes beside them 44 times too bright.
        let mut surfels = Vec::new();
        let mut radiosity = Vec::new();
        for x in 0..4 {
            for z in 0..4 {
                surfels.push(testutil::surfel(
                    [x, 2, z],
                    [0.5, 0.5, 0.5],
                    [0.0, -1.0, 0.0],
                    1.0,
                ));
                radiosity.push([[1.0; 3], [0.0; 3]]);
                if x < 2 {
                    surfels.push(testutil::surfel(
                        [x, 2, z],
                        [0.5, 0.474, 0.5],
                        [0.0, -1.0, 0.0],
                        1.0,
                    ));
                    radiosity.push([[100.0; 3], [0.0; 3]]);
                }
            }
        }
        let results = results_of(surfels, radiosity);
        let index = ProbeIndex::new(&results);
        let voxel_units = |x: f64, y: f64, z: f64| results.grid.to_world(DVec3::new(x, y, z));
        let ceiling = index.lookup(voxel_units(2.0, 2.5, 2.0), -DVec3::Y);
        assert_eq!(ceiling.radiosity, [1.0; 3]);
        let lamp = index.lookup(voxel_units(1.0, 2.474, 2.0), -DVec3::Y);
        assert_eq!(lamp.radiosity, [100.0; 3]);
    }

    #[test]
    fn zero_area_sides_fall_back_to_inverse_distance() {
        let set = testutil::set_of(
            vec![
                testutil::surfel([0, 0, 0], [0.5; 3], [0.0, 0.0, 1.0], 0.0),
                testutil::surfel([1, 0, 0], [0.5; 3], [0.0, 0.0, 1.0], 0.0),
            ],
            1.0,
        );
        let results = Results::from_solution(
            &set,
            &Solution {
                radiosity: vec![[[1.0; 3], [0.0; 3]], [[4.0; 3], [0.0; 3]]],
                stats: Default::default(),
            },
        )
        .unwrap();
        let index = ProbeIndex::new(&results);
        // Exactly between them: equal weights.
        let p = results.grid.to_world(DVec3::new(1.0, 0.5, 0.5));
        let row = index.lookup(p, DVec3::Z);
        assert!(row.found);
        assert!((row.radiosity[0] - 2.5).abs() < 1e-9, "{row:?}");
    }

    #[test]
    fn bad_rows_name_the_file_and_line() {
        let dir = tempfile::TempDir::new().unwrap();
        let csv = dir.path().join("points.csv");
        let results = wall();
        for (text, line, says) in [
            (
                "x,y,z,nx,ny,nz\n1,2,3,0,0,1\n1,2,3,0,0\n",
                3,
                "expected 6 columns",
            ),
            ("1,2,3,0,0,1\n\n1,2,abc,0,0,1\n", 3, "column 3 ('abc')"),
            ("1,2,NaN,0,0,1\n", 1, "column 3 ('NaN')"),
            ("1,2,3,0,0,1\n1,2,3,0,0,0\n", 2, "normal is zero"),
            ("x,y,z,nx,ny,nz\nx,y,z,nx,ny,nz\n", 2, "column 1"),
        ] {
            std::fs::write(&csv, text).unwrap();
            let e = probe(&results, &csv).unwrap_err();
            match &e {
                ProbeError::BadRow { line: l, .. } => assert_eq!(*l, line, "{text:?}: {e}"),
                other => panic!("{other}"),
            }
            let msg = e.to_string();
            assert!(msg.contains(&format!("points.csv:{line}:")), "{msg}");
            assert!(msg.contains(says), "{msg}");
        }
        let e = probe(&results, &dir.path().join("missing.csv")).unwrap_err();
        assert!(e.to_string().contains("missing.csv"), "{e}");
    }

    proptest::proptest! {
        /// A look-up's neighbourhood, read column by column, lists the records of every voxel
        /// of the box in the order of a plain scan (x, then y, then z, then the file's order),
        /// the voxels outside the grid's range and the empty ones giving nothing: what a
        /// look-up per voxel listed.
        #[test]
        fn columns_list_the_box_as_a_scan_of_every_record_does(
            // Several records a voxel, in any file order, many sharing a column.
            voxels in proptest::collection::vec([0..6i32, 0..6, 0..9], 1..400),
            lo in [-2..6i32, -2..6, -2..9],
        ) {
            let records = voxels
                .iter()
                .enumerate()
                .map(|(k, &voxel)| {
                    let mut surfel = testutil::surfel(voxel, [0.5; 3], [1.0, 0.0, 0.0], 1.0);
                    surfel.area = k as f32;
                    Record::from_surfel(&surfel, [[0.0; 3]; 2])
                })
                .collect();
            let results = Results {
                grid: wall().grid,
                records,
                materials: Vec::new(),
            };
            let index = ProbeIndex::new(&results);
            let hi = lo.map(|c| c + 3);
            let inside = |v: [i32; 3]| (0..3).all(|k| (lo[k]..=hi[k]).contains(&v[k]));
            let mut expected: Vec<usize> =
                (0..voxels.len()).filter(|&i| inside(voxels[i])).collect();
            expected.sort_by_key(|&i| voxels[i]);
            let mut listed = Vec::new();
            for x in lo[0]..=hi[0] {
                for y in lo[1]..=hi[1] {
                    listed.extend(
                        index
                            .records_in_column(x, y, lo[2]..=hi[2])
                            .map(|r| r.area as usize),
                    );
                }
            }
            proptest::prop_assert_eq!(listed, expected);
        }
    }
}
