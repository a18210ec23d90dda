//! The elastic line distribution of the data mode (paper, section 4): which rank owns which
//! whole lines of one direction, so that every rank holds about the same number of surfels.
//!
//! **Where a line sits.** The paper cuts the `(i, j)` plane of each direction. Those indices
//! start again from a new origin, along new axes, whenever the main axis of the direction
//! changes, so two close directions on either side of such a change would share almost no
//! owners, and every surfel would move. Here a line is placed by where it crosses one fixed plane
//! per octant order: the plane through the grid's centre whose normal is `(sx, sy, 1)`, with the
//! signs of the order (`geometry::order`). Every direction of that order crosses the plane at an
//! angle of at most about 55 degrees from its normal, and the crossing point of the line through
//! a voxel moves smoothly as the direction turns. The point is taken from the line's exact
//! integer description (its `(i, j)` and the frame's layer shifts), so all voxels of one discrete
//! line land in the same bin: lines stay whole. Bins are a quarter of a voxel wide.
//!
//! **Which way the cuts run.** As the direction turns by `ds`, the crossing point of a voxel at
//! distance `t` from the plane (along the direction) moves by `t` times `ds` projected along the
//! direction onto the plane. The walk over a cube face (`geometry::directions`) steps along one
//! axis of the face for many directions in a row, so on each face the points drift mostly along
//! one line of the plane. The plane's axes are chosen per face: `columns` along that drift,
//! `rows` across it. Cuts between rows then run parallel to the drift, and points slide along
//! them instead of across: few surfels change owner from one direction to the next.
//!
//! **Balancing.** The row sums of the bin histogram (added over ranks) are cut into `R` bands of
//! equal load, then each band's column histogram into `C` pieces, `R * C` ranks in all. `C` is
//! the largest divisor of the rank count not above half its square root: mostly bands, whose
//! boundaries follow the drift, with a few column cuts once the bands would get thin. Where
//! `C` is 1 (two and three ranks) no column histogram is made: a band's load is its rows'.

use crate::geometry::lines::LineFrame;
use crate::geometry::order;
use glam::DVec3;

/// Bins of the crossing plane of one octant order over a grid.
#[derive(Clone, Debug)]
pub struct Projection {
    centre: DVec3,
    normal: DVec3,
    e1: DVec3,
    e2: DVec3,
    /// Bins on each side of the centre along each plane axis.
    half: i64,
}

/// Bins per voxel along each plane axis.
const BINS_PER_VOXEL: f64 = 4.0;

impl Projection {
    /// The crossing plane of order `order` over a grid of `dims` voxels, with axes for the
    /// directions of the cube face whose main axis is `face` (see [`walk_face`]).
    pub fn new(order: usize, face: usize, dims: [u32; 3]) -> Self {
        let s = order::signs(order);
        let normal = DVec3::new(s[0] as f64, s[1] as f64, s[2] as f64).normalize();
        // The face's central direction, and the axis the walk steps along on that face.
        let mut centre_dir = DVec3::ZERO;
        centre_dir[face] = s[face] as f64;
        let mut step = DVec3::ZERO;
        step[(face + 2) % 3] = 1.0;
        // The drift: the step projected along the direction onto the plane.
        let drift = step - centre_dir * (normal.dot(step) / normal.dot(centre_dir));
        let e2 = drift.normalize();
        let e1 = normal.cross(e2).normalize();
        let centre = DVec3::new(dims[0] as f64, dims[1] as f64, dims[2] as f64) * 0.5;
        // A line through the grid crosses the plane within (1 + sqrt 3) half-diagonals of the
        // centre (the direction's cosine to the normal is at least 1 / sqrt 3).
        let extent = dims.iter().map(|&d| d as f64).sum::<f64>();
        let half = (1.4 * extent * BINS_PER_VOXEL).ceil() as i64 + 2;
        Projection {
            centre,
            normal,
            e1,
            e2,
            half,
        }
    }

    /// Number of bins along each plane axis.
    pub fn bins(&self) -> usize {
        (2 * self.half + 1) as usize
    }

    /// The crossing point of the line `(i, j)` of `frame` (direction `vector`), in the
    /// plane's coordinates (bins from the centre, unrounded).
    fn crossing(&self, frame: &LineFrame, vector: [i64; 3], i: f64, j: f64) -> [f64; 2] {
        // The line's point on layer 0 of the main axis.
        let (su0, sv0) = frame.layer_shift(0);
        let mut p = [0.0f64; 3];
        p[frame.u] = i - su0 as f64;
        p[frame.v] = j - sv0 as f64;
        let p = DVec3::from_array(p);
        let s = DVec3::new(vector[0] as f64, vector[1] as f64, vector[2] as f64);
        let t = self.normal.dot(self.centre - p) / self.normal.dot(s);
        let d = p + s * t - self.centre;
        [
            self.e1.dot(d) * BINS_PER_VOXEL,
            self.e2.dot(d) * BINS_PER_VOXEL,
        ]
    }

    /// The bins of the lines of one direction: the crossing point is an affine function of a
    /// line's `(i, j)`, evaluated from its coefficients (the same arithmetic on every rank, and
    /// for every voxel of a line, since it reads only `(i, j)`).
    pub fn lines<'a>(&self, frame: &'a LineFrame, vector: [i64; 3]) -> LineBins<'a> {
        let origin = self.crossing(frame, vector, 0.0, 0.0);
        let di = self.crossing(frame, vector, 1.0, 0.0);
        let dj = self.crossing(frame, vector, 0.0, 1.0);
        LineBins {
            frame,
            origin,
            along_i: [di[0] - origin[0], di[1] - origin[1]],
            along_j: [dj[0] - origin[0], dj[1] - origin[1]],
            half: self.half,
        }
    }
}

/// The bins of the lines of one direction (see [`Projection::lines`]).
pub struct LineBins<'a> {
    frame: &'a LineFrame,
    origin: [f64; 2],
    along_i: [f64; 2],
    along_j: [f64; 2],
    half: i64,
}

impl LineBins<'_> {
    /// The bin `(row, column)` of the line through `voxel`.
    #[inline(always)]
    pub fn bin(&self, voxel: [i32; 3]) -> (usize, usize) {
        let f = self.frame;
        let (su, sv) = f.layer_shift(voxel[f.main] as usize);
        let i = (voxel[f.u] as i64 + su as i64) as f64;
        let j = (voxel[f.v] as i64 + sv as i64) as f64;
        let to_bin = |k: usize| {
            let x = self.origin[k] + self.along_i[k] * i + self.along_j[k] * j;
            (floor(x) + self.half).clamp(0, 2 * self.half) as usize
        };
        (to_bin(0), to_bin(1))
    }
}

/// `x` rounded down, without a call into the maths library (`f64::floor` is one on CPUs
/// without SSE 4.1, and this runs for every surfel and direction).
#[inline(always)]
fn floor(x: f64) -> i64 {
    let t = x as i64;
    t - ((t as f64) > x) as i64
}

/// Which rank owns each bin of one direction: bands of rows, then pieces of each band's columns.
#[derive(Clone, Debug, PartialEq)]
pub struct Distribution {
    /// `bands + 1` row boundaries: band `b` holds rows `row_cuts[b]..row_cuts[b + 1]`.
    row_cuts: Vec<usize>,
    /// Per band, `pieces + 1` column boundaries.
    column_cuts: Vec<Vec<usize>>,
    /// Surfels each rank owns (from the global histogram).
    pub loads: Vec<f64>,
}

impl Distribution {
    /// Number of row bands.
    pub fn bands(&self) -> usize {
        self.row_cuts.len() - 1
    }

    /// The owner of bin `(row, column)`.
    #[inline]
    pub fn owner(&self, row: usize, column: usize) -> usize {
        let band = interval_of(&self.row_cuts, row);
        let cuts = &self.column_cuts[band];
        band * (cuts.len() - 1) + interval_of(cuts, column)
    }

    /// A faster [`Distribution::owner`] for one pass over the surfels: the band of every row
    /// tabulated (the remembered distributions keep only their cuts).
    pub fn table(&self) -> OwnerTable<'_> {
        let rows = self.row_cuts.last().copied().unwrap_or(0);
        let mut band_of_row = Vec::with_capacity(rows);
        for (band, w) in self.row_cuts.windows(2).enumerate() {
            band_of_row.extend(std::iter::repeat_n(band as u32, w[1] - w[0]));
        }
        OwnerTable {
            distribution: self,
            band_of_row,
        }
    }

    /// Largest over mean load: 1 is perfect balance.
    pub fn imbalance(&self) -> f64 {
        let total: f64 = self.loads.iter().sum();
        if total == 0.0 {
            return 1.0;
        }
        let max = self.loads.iter().copied().fold(0.0, f64::max);
        max * self.loads.len() as f64 / total
    }
}

/// [`Distribution::owner`] with the bands of rows tabulated.
pub struct OwnerTable<'a> {
    distribution: &'a Distribution,
    band_of_row: Vec<u32>,
}

impl OwnerTable<'_> {
    #[inline]
    pub fn owner(&self, row: usize, column: usize) -> usize {
        let band = self.band_of_row[row] as usize;
        let cuts = &self.distribution.column_cuts[band];
        let pieces = cuts.len() - 1;
        if pieces == 1 {
            band
        } else {
            band * pieces + interval_of(cuts, column)
        }
    }
}

/// Row bands for `ranks` ranks: the rank count over the column pieces, the largest divisor not
/// above half the square root.
pub fn row_bands(ranks: usize) -> usize {
    let pieces = (1..=ranks.max(1))
        .filter(|c| ranks % c == 0 && 4 * c * c <= ranks)
        .max()
        .unwrap_or(1);
    ranks.max(1) / pieces
}

/// The cube face (main axis) a direction belongs to in the walk of `geometry::directions`: the
/// largest component, ties to the later axis.
pub fn walk_face(vector: [i64; 3]) -> usize {
    (0..3).max_by_key(|&k| (vector[k].abs(), k)).unwrap_or(2)
}

/// Imbalance (largest over mean load) a distribution may have before more column cuts are tried.
pub const IMBALANCE_GOAL: f64 = 1.05;

/// The elastic distribution over `ranks` ranks. `rows` is the global row histogram; `columns`
/// gives, for bands of rows, their global column histograms (the caller adds them over ranks),
/// as many bins as `rows`; it is asked only where a band is cut into several pieces.
///
/// It starts with `preferred` bands (the previous direction's count, so that consecutive
/// directions keep the same shape of pieces), or else the count of [`row_bands`]. A wall seen
/// edge-on along the drift puts a whole plane of lines into one row, which no band cut can split:
/// while the imbalance is above [`IMBALANCE_GOAL`], other band counts with more or fewer column
/// pieces are tried, and the best is kept.
pub fn distribute(
    ranks: usize,
    rows: &[f64],
    preferred: Option<usize>,
    mut columns: impl FnMut(&[usize]) -> Vec<Vec<f64>>,
) -> Distribution {
    let ranks = ranks.max(1);
    let first = preferred
        .filter(|&b| b >= 1 && ranks % b == 0)
        .unwrap_or_else(|| row_bands(ranks));
    let others = (1..=row_bands(ranks))
        .rev()
        .filter(|&b| ranks % b == 0 && b != first);
    let mut best: Option<Distribution> = None;
    for bands in std::iter::once(first).chain(others) {
        let candidate = cut(ranks, bands, rows, &mut columns);
        let better = best
            .as_ref()
            .is_none_or(|b| candidate.imbalance() < b.imbalance());
        if better {
            best = Some(candidate);
        }
        if best
            .as_ref()
            .is_some_and(|b| b.imbalance() <= IMBALANCE_GOAL)
        {
            break;
        }
    }
    best.expect("one band count at least")
}

/// Rows into `bands` bands, each band's columns into `ranks / bands` pieces.
fn cut(
    ranks: usize,
    bands: usize,
    rows: &[f64],
    columns: &mut impl FnMut(&[usize]) -> Vec<Vec<f64>>,
) -> Distribution {
    let pieces = ranks / bands;
    let row_cuts = equal_cuts(rows, bands);
    if pieces == 1 {
        return whole_bands(row_cuts, rows);
    }
    let histograms = columns(&row_cuts);
    let mut column_cuts = Vec::with_capacity(bands);
    let mut loads = Vec::with_capacity(ranks);
    for hist in &histograms {
        let cuts = equal_cuts(hist, pieces);
        for w in cuts.windows(2) {
            loads.push(hist[w[0]..w[1]].iter().sum());
        }
        column_cuts.push(cuts);
    }
    Distribution {
        row_cuts,
        column_cuts,
        loads,
    }
}

/// The bands of `row_cuts`, one rank each: a band's load is its rows' (counts, exact in `f64`
/// in any order, so the same as its column histogram's), and the column histograms, a pass over
/// the held surfels and a sum over the ranks for every direction, are not needed. Two and three
/// ranks cut so.
fn whole_bands(row_cuts: Vec<usize>, rows: &[f64]) -> Distribution {
    let loads = row_cuts
        .windows(2)
        .map(|w| rows[w[0]..w[1]].iter().sum())
        .collect();
    Distribution {
        column_cuts: vec![vec![0, rows.len()]; row_cuts.len() - 1],
        row_cuts,
        loads,
    }
}

/// `parts + 1` boundaries cutting `hist` into `parts` runs of about equal sums: each inner
/// boundary is the one whose prefix sum is nearest to its share.
pub fn equal_cuts(hist: &[f64], parts: usize) -> Vec<usize> {
    let mut prefix = Vec::with_capacity(hist.len() + 1);
    prefix.push(0.0);
    for &h in hist {
        prefix.push(prefix.last().copied().unwrap_or(0.0) + h);
    }
    let total = prefix.last().copied().unwrap_or(0.0);
    let mut cuts = vec![0];
    for m in 1..parts {
        let target = total * m as f64 / parts as f64;
        // First boundary whose prefix reaches the target, or the one before if nearer.
        let mut at = prefix.partition_point(|&p| p < target).min(hist.len());
        if at > 0 && target - prefix[at - 1] < prefix[at] - target {
            at -= 1;
        }
        let previous = cuts.last().copied().unwrap_or(0);
        cuts.push(at.max(previous));
    }
    cuts.push(hist.len());
    cuts
}

/// The interval `k` with `cuts[k] <= x < cuts[k + 1]` (the last one for `x` past the end).
#[inline]
fn interval_of(cuts: &[usize], x: usize) -> usize {
    (cuts.partition_point(|&c| c <= x).max(1) - 1).min(cuts.len() - 2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::directions::DirectionSet;

    #[test]
    fn cuts_are_balanced_and_cover_everything() {
        let hist: Vec<f64> = (0..100).map(|k| ((k * 37) % 11) as f64).collect();
        for parts in 1..8 {
            let cuts = equal_cuts(&hist, parts);
            assert_eq!(cuts.len(), parts + 1);
            assert_eq!((cuts[0], cuts[parts]), (0, 100));
            assert!(cuts.windows(2).all(|w| w[0] <= w[1]));
            let total: f64 = hist.iter().sum();
            for w in cuts.windows(2) {
                let load: f64 = hist[w[0]..w[1]].iter().sum();
                // Within one bin (at most 10) of the share.
                assert!(
                    (load - total / parts as f64).abs() <= 10.0 * 2.0,
                    "{parts}: {load}"
                );
            }
        }
    }

    #[test]
    fn every_voxel_of_a_line_lands_in_one_bin() {
        let dims = [13, 9, 11];
        for d in &DirectionSet::cube(3).directions {
            let frame = LineFrame::new(d.vector, dims);
            let projection = Projection::new(order::order_of(d.vector), walk_face(d.vector), dims);
            let mut bin_of_line = std::collections::HashMap::new();
            for x in 0..13 {
                for y in 0..9 {
                    for z in 0..11 {
                        let v = [x, y, z];
                        let bin = projection.lines(&frame, d.vector).bin(v);
                        assert!(bin.0 < projection.bins() && bin.1 < projection.bins());
                        let line = frame.line_index(v);
                        assert_eq!(*bin_of_line.entry(line).or_insert(bin), bin, "{d:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn whole_bands_need_no_columns_and_cut_as_columns_would() {
        let rows: Vec<f64> = (0..60).map(|k| ((k * 29) % 13) as f64).collect();
        // The column histogram of a band: its rows' counts spread over the columns.
        let columns = |cuts: &[usize]| -> Vec<Vec<f64>> {
            cuts.windows(2)
                .map(|w| {
                    let mut hist = vec![0.0; rows.len()];
                    for (r, &count) in rows.iter().enumerate().take(w[1]).skip(w[0]) {
                        hist[(r * 7) % rows.len()] += count;
                    }
                    hist
                })
                .collect()
        };
        for bands in 1..6 {
            let row_cuts = equal_cuts(&rows, bands);
            let whole = whole_bands(row_cuts.clone(), &rows);
            // What cutting each band's column histogram into one piece gives.
            let histograms = columns(&row_cuts);
            let by_columns = Distribution {
                row_cuts,
                column_cuts: histograms.iter().map(|h| equal_cuts(h, 1)).collect(),
                loads: histograms.iter().map(|h| h.iter().sum()).collect(),
            };
            assert_eq!(whole, by_columns, "{bands} bands");
        }
        for ranks in [2, 3] {
            let dist = distribute(ranks, &rows, None, |_| panic!("no column histogram"));
            assert_eq!(dist.bands(), ranks);
        }
    }

    #[test]
    fn owners_cover_all_ranks_with_equal_loads() {
        let rows: Vec<f64> = vec![10.0; 40];
        for ranks in 1..9 {
            let dist = distribute(ranks, &rows, None, |cuts| {
                cuts.windows(2)
                    .map(|w| vec![(w[1] - w[0]) as f64 * 10.0 / 40.0; 40])
                    .collect()
            });
            assert_eq!(dist.loads.len(), ranks);
            assert!(dist.imbalance() < 1.3, "{ranks}: {:?}", dist.loads);
            let mut seen = vec![false; ranks];
            let table = dist.table();
            for r in 0..40 {
                for c in 0..40 {
                    assert_eq!(table.owner(r, c), dist.owner(r, c));
                    seen[dist.owner(r, c)] = true;
                }
            }
            assert!(seen.iter().all(|&s| s), "{ranks}");
        }
    }
}
