//! What the data mode out of core reports: every rank's phases, disk traffic and largest share,
//! the surfels exchanged per direction and the imbalance, added over ranks.

use super::held::WIRE_LEN;
use super::Solver;
use crate::distribute::data::{DataStats, PhaseSeconds, RankOutOfCore};
use crate::outcore::files::IoCounters;

/// One rank's bookkeeping over the solve.
pub(super) struct Tally {
    /// Records this rank sent away, per direction (summed over iterations).
    pub moved: Vec<f64>,
    /// Each direction's imbalance (the same on every rank; 0 for a direction never cut).
    pub imbalance: Vec<f64>,
    pub seconds: PhaseSeconds,
    pub io: IoCounters,
    /// The most records held for one direction.
    pub largest_share: u64,
    pub bands: u64,
    /// Passes that gathered several directions, and the directions beyond one each.
    pub joint: (u64, u64),
    /// Steps skipped as quiet (the same on every rank).
    pub quiet_steps_skipped: u64,
}

/// The statistics of all ranks, and the totals over ranks.
pub(super) struct Totals {
    pub data: DataStats,
    pub bytes_read: u64,
    pub bytes_written: u64,
    pub bands: u64,
}

impl Solver<'_> {
    /// Adds every rank's tally over ranks (collective). `surfels` of the scene, `iterations` run.
    pub(super) fn summarize(&self, tally: &Tally, surfels: u64, iterations: usize) -> Totals {
        let (ranks, me) = (self.comm.size(), self.comm.rank());
        let d_count = tally.moved.len();
        // Per rank: the phases, bytes read, bytes written, largest share in bytes, joint
        // passes and directions.
        const ROW: usize = PhaseSeconds::FIELDS + 5;
        let mut table = vec![0.0f64; d_count + ROW * ranks + 1];
        table[..d_count].copy_from_slice(&tally.moved);
        let at = d_count + me * ROW;
        table[at..at + PhaseSeconds::FIELDS].copy_from_slice(&tally.seconds.to_array());
        table[at + PhaseSeconds::FIELDS] = tally.io.read as f64;
        table[at + PhaseSeconds::FIELDS + 1] = tally.io.written as f64;
        table[at + PhaseSeconds::FIELDS + 2] = (tally.largest_share * WIRE_LEN as u64) as f64;
        table[at + PhaseSeconds::FIELDS + 3] = tally.joint.0 as f64;
        table[at + PhaseSeconds::FIELDS + 4] = tally.joint.1 as f64;
        table[d_count + ROW * ranks] = tally.bands as f64;
        self.comm.sum_in_place(&mut table);
        let updates = (surfels * d_count as u64 * iterations.max(1) as u64).max(1) as f64;
        let fractions: Vec<f64> = table[..d_count]
            .iter()
            .map(|&m| m / (surfels.max(1) * iterations.max(1) as u64) as f64)
            .collect();
        let mut per_rank = Vec::with_capacity(ranks);
        let mut out_of_core = Vec::with_capacity(ranks);
        let (mut bytes_read, mut bytes_written) = (0u64, 0u64);
        for row in table[d_count..d_count + ROW * ranks].chunks_exact(ROW) {
            per_rank.push(PhaseSeconds::from_slice(row));
            let (read, written) = (row[PhaseSeconds::FIELDS], row[PhaseSeconds::FIELDS + 1]);
            bytes_read += read as u64;
            bytes_written += written as u64;
            out_of_core.push(RankOutOfCore {
                bytes_read: read as u64,
                bytes_written: written as u64,
                bytes_read_per_voxel_direction: read / updates,
                bytes_written_per_voxel_direction: written / updates,
                largest_share_bytes: row[PhaseSeconds::FIELDS + 2] as u64,
                joint_passes: row[PhaseSeconds::FIELDS + 3] as u64,
                joint_directions: row[PhaseSeconds::FIELDS + 4] as u64,
                // Measured by the caller at the very end.
                peak_rss_bytes: 0,
                start_rss_bytes: 0,
            });
        }
        let used: Vec<f64> = tally
            .imbalance
            .iter()
            .copied()
            .filter(|&x| x > 0.0)
            .collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let bytes_moved = (table[..d_count].iter().sum::<f64>() as u64) * WIRE_LEN as u64;
        Totals {
            data: DataStats {
                groups: self.groups,
                ranks_per_group: self.group.size(),
                exchanged_fraction: mean(&fractions),
                max_exchanged_fraction: max(&fractions),
                exchanged_by_direction: fractions,
                imbalance: if used.is_empty() { 1.0 } else { mean(&used) },
                max_imbalance: if used.is_empty() { 1.0 } else { max(&used) },
                bytes_packed: bytes_moved,
                bytes_sent: bytes_moved,
                per_rank,
                out_of_core,
                quiet_steps_skipped: tally.quiet_steps_skipped,
                ..Default::default()
            },
            bytes_read,
            bytes_written,
            bands: table[d_count + ROW * ranks] as u64,
        }
    }
}
