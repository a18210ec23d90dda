//! The memory budget: parsing `--memory`, and how the solver splits it (see the `outcore`
//! module header for what is counted).

use super::files::{AxisLight, Gathered, Radiosity};
use super::OocError;
use crate::solve::dispatch::OrderedEntry;
use crate::solve::propagate::PropSurfel;

/// Parses a byte size: a number with an optional binary unit (`K`, `M`, `G`, `T`, with or
/// without `iB`/`B`; all powers of 1024), e.g. `64MiB`, `1G`, `4096`.
pub fn parse_bytes(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let value: f64 = number
        .parse()
        .map_err(|_| format!("'{text}' is not a size: expected a number and a unit like 64MiB"))?;
    let scale: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kb" | "kib" => 1 << 10,
        "m" | "mb" | "mib" => 1 << 20,
        "g" | "gb" | "gib" => 1 << 30,
        "t" | "tb" | "tib" => 1 << 40,
        other => {
            return Err(format!(
                "'{text}': unknown unit '{other}'; use K, M, G or T (powers of 1024)"
            ))
        }
    };
    let bytes = value * scale as f64;
    if !bytes.is_finite() || bytes < 1.0 || bytes > u64::MAX as f64 {
        return Err(format!("'{text}' is not a usable size"));
    }
    Ok(bytes as u64)
}

/// As [`parse_bytes`], also taking a zero size (`--links-memory 0`: keep nothing).
pub fn parse_bytes_or_zero(text: &str) -> Result<u64, String> {
    match text
        .trim()
        .trim_end_matches(|c: char| c.is_ascii_alphabetic())
    {
        number if !number.is_empty() && number.parse::<f64>() == Ok(0.0) => Ok(0),
        _ => parse_bytes(text),
    }
}

/// A byte count for messages (`64.0 MiB`).
pub fn format_bytes(bytes: u64) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < units.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", units[unit])
    }
}

/// Bytes a band holds per surfel: its propagation record, radiosity, gathered light, ordered
/// entry, list slot, line (`dispatch` finds it once) and canonical index, plus the per-line
/// scratch of propagation (about one more record per surfel of the longest line being
/// processed, bounded by this margin), plus its partner links while they are recorded (the
/// threads' pieces, the direction's copy and their compressed bytes for the file: about 13.5
/// bytes each; the compressed bytes are about a third of that, at worst 9/8 of it,
/// `super::links`).
pub const BAND_BYTES_PER_SURFEL: u64 = (std::mem::size_of::<PropSurfel>()
    + std::mem::size_of::<Radiosity>()
    + std::mem::size_of::<AxisLight>()
    + std::mem::size_of::<OrderedEntry>()
    + 4
    + 4
    + 4
    + 48
    + 3 * 27 / 2) as u64;

/// Bytes a replay holds per surfel of the bands whose light it has read together (see
/// `super::band`): their radiosity and gathered light.
pub const REPLAY_BYTES_PER_SURFEL: u64 =
    (std::mem::size_of::<Radiosity>() + std::mem::size_of::<AxisLight>()) as u64;

/// Bytes a replay holds per surfel of the one band whose links it replays: its links read
/// (compressed: about a third of the 20 bytes of the decoded links in a building, whose
/// surfels have more links than those of a plain room, at worst 9/8 of them) and decoded, and
/// a margin.
pub const REPLAY_BAND_BYTES_PER_SURFEL: u64 = 40 + 4;

/// Bytes a sort bucket holds per record: key, canonical index and the encoded record.
pub const SORT_BYTES_PER_RECORD: u64 = 88;

/// Bytes a permutation chunk holds per surfel: gathered light, previous and new radiosity.
pub const CHUNK_BYTES_PER_SURFEL: u64 =
    (std::mem::size_of::<Gathered>() + 2 * std::mem::size_of::<Radiosity>()) as u64;

/// How a budget is split.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryPlan {
    pub budget: u64,
    /// Each sequential stream's buffer (and the shard-set window).
    pub io_bytes: usize,
    /// What is left once the fixed parts (histogram, per-layer arrays, I/O buffers) are taken.
    pub working: u64,
    /// Largest band, in surfels.
    pub band_surfels: u64,
    /// Largest band, in lines (its line counters).
    pub band_lines: u64,
    /// Most surfels of the bands whose light a replay reads together (at least a band's).
    pub replay_surfels: u64,
    /// Largest sort bucket, in records.
    pub sort_records: u64,
    /// Permutation chunk, in surfels.
    pub chunk_surfels: u64,
}

impl MemoryPlan {
    /// Splits `budget` for a grid of `dims` solved with `threads` threads, holding the readers
    /// of three axis copies of `framed` surfels in compressed frames (the data mode counts a
    /// rank's held files so, with its share).
    pub fn new(budget: u64, dims: [u32; 3], threads: usize, framed: u64) -> Result<Self, OocError> {
        let io_bytes = (budget / 64).clamp(4 << 10, 1 << 20) as usize;
        let d = dims.map(u64::from);
        // The row histogram of one copy (layers x rows), per-layer cursors and the per-column
        // histogram of a direction.
        let histogram = (0..3).map(|m| d[m] * d[(m + 2) % 3] * 4).max().unwrap_or(0);
        let per_layer = 48 * (d[0] + d[1] + d[2]);
        let fixed = histogram + per_layer + 8 * io_bytes as u64;
        let minimum_working = 64 << 10;
        if budget < fixed + minimum_working {
            return Err(OocError::BudgetTooSmall {
                budget,
                needed: fixed + minimum_working,
                what: format!(
                    "the grid of {}x{}x{} voxels (its row histogram and buffers)",
                    d[0], d[1], d[2]
                ),
            });
        }
        let working = budget - fixed;
        // The iterations hold the readers of the copies' static records beside a band, a
        // replay or a permutation chunk; the set-up, the closure check and the direct-light pass
        // come before them, with the whole working memory.
        let readers = if framed > 0 {
            super::framed::readers_bytes(3, framed, io_bytes)
        } else {
            0
        };
        if working < readers + minimum_working {
            return Err(OocError::BudgetTooSmall {
                budget,
                needed: fixed + readers + minimum_working,
                what: format!(
                    "the index of the static records of {framed} surfels and the grid of \
                     {}x{}x{} voxels",
                    d[0], d[1], d[2]
                ),
            });
        }
        let iterating = working - readers;
        let counters = 4 * (threads as u64 + 2);
        let band_surfels = iterating * 3 / 4 / BAND_BYTES_PER_SURFEL;
        let replay_surfels = ((iterating * 3 / 4)
            .saturating_sub(band_surfels * REPLAY_BAND_BYTES_PER_SURFEL)
            .saturating_sub(Self::replay_chunk_of(io_bytes) * REPLAY_BYTES_PER_SURFEL)
            / REPLAY_BYTES_PER_SURFEL)
            .max(band_surfels);
        Ok(MemoryPlan {
            budget,
            io_bytes,
            working,
            band_surfels,
            band_lines: iterating / 4 / counters,
            replay_surfels,
            sort_records: working / 2 / SORT_BYTES_PER_RECORD,
            chunk_surfels: iterating / 2 / CHUNK_BYTES_PER_SURFEL,
        })
    }

    /// Records of the copy a replay reads or writes at once (see `super::band`): the light of
    /// about four I/O buffers.
    pub fn replay_chunk(&self) -> u64 {
        Self::replay_chunk_of(self.io_bytes)
    }

    fn replay_chunk_of(io_bytes: usize) -> u64 {
        (4 * io_bytes as u64 / REPLAY_BYTES_PER_SURFEL).max(1)
    }

    /// Write buffer of each of `count` bucket files sharing half the working memory.
    pub fn bucket_buffer(&self, count: u64) -> usize {
        ((self.working / 2 / count.max(1)) as usize).clamp(256, self.io_bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_in_binary_units() {
        assert_eq!(parse_bytes("4096"), Ok(4096));
        assert_eq!(parse_bytes("64MiB"), Ok(64 << 20));
        assert_eq!(parse_bytes("1G"), Ok(1 << 30));
        assert_eq!(parse_bytes("1.5 KiB"), Ok(1536));
        assert!(parse_bytes("lots").is_err());
        assert!(parse_bytes("12 parsecs").is_err());
        assert!(parse_bytes("0").is_err());
        assert_eq!(format_bytes(64 << 20), "64.0 MiB");
    }

    #[test]
    fn a_zero_size_parses_where_it_is_allowed() {
        assert_eq!(parse_bytes_or_zero("0"), Ok(0));
        assert_eq!(parse_bytes_or_zero("0MiB"), Ok(0));
        assert_eq!(parse_bytes_or_zero("2G"), Ok(2 << 30));
        assert!(parse_bytes_or_zero("0 parsecs").is_err());
        assert!(parse_bytes_or_zero("-1").is_err());
        assert!(parse_bytes_or_zero("").is_err());
    }

    #[test]
    fn a_tiny_budget_is_refused_with_what_it_needs() {
        let e = MemoryPlan::new(1 << 10, [100, 100, 100], 2, 0).unwrap_err();
        assert!(e.to_string().contains("too small"), "{e}");
        let plan = MemoryPlan::new(64 << 20, [100, 100, 100], 2, 1_000_000).unwrap();
        assert!(plan.band_surfels > 100_000);
    }
}
