//! The run report, `report.json`: what was solved, how well, how fast, and with what memory.
//!
//! Other programs read this file (see the brief, "Interfaces other programs rely on"), so keys are
//! only ever added, never renamed. Keys: `version` (crate version), `scene`, `mode`, `ranks`,
//! `threads`, `resolution`, `voxel_size`, `voxels`, `surfels`, `directions`, `iterations`,
//! `converged`, `residual`, `tolerance`, `seconds` (`total` plus one entry per phase),
//! `peak_rss_bytes`, `voxel_direction_updates_per_second`, `effects` (`[{name, simulated, why}]`),
//! `energy` (`emitted_power`, `absorbed_power`, `escaped_power` as RGB, and `balance`), and in
//! data mode `exchanged_fraction` and `imbalance` (absent otherwise), and after `--resume`
//! `resumed_from_iteration`.
//!
//! The file is written atomically (see [`super::atomic`]) as pretty-printed JSON.

use super::{atomic, OutputError, REPORT_FILE};
use crate::solve::SolveStats;
use crate::voxel::SurfelSet;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub use crate::solve::effects::Effect;

/// Power balance of the solution, per RGB channel, in world units (radiosity times area).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Energy {
    pub emitted_power: [f64; 3],
    pub absorbed_power: [f64; 3],
    /// `emitted - absorbed`: power that left the scene (through openings) rather than being
    /// absorbed. Near 0 for a closed scene.
    pub escaped_power: [f64; 3],
    /// `(sum emitted - sum absorbed) / sum emitted`, the escaped fraction of the emitted power:
    /// 0 for a closed scene at convergence, positive for an open one, negative if the solve
    /// created energy (a bug). 0 when nothing is emitted.
    pub balance: f64,
}

impl Energy {
    pub fn new(emitted_power: [f64; 3], absorbed_power: [f64; 3]) -> Self {
        let escaped_power = [0, 1, 2].map(|c| emitted_power[c] - absorbed_power[c]);
        let emitted: f64 = emitted_power.iter().sum();
        let absorbed: f64 = absorbed_power.iter().sum();
        let balance = if emitted > 0.0 {
            (emitted - absorbed) / emitted
        } else {
            0.0
        };
        Energy {
            emitted_power,
            absorbed_power,
            escaped_power,
            balance,
        }
    }
}

/// What the caller knows about the run that the solver's statistics do not.
#[derive(Clone, Debug, PartialEq)]
pub struct RunInfo {
    /// The scene file or shard set, as given on the command line.
    pub scene: String,
    /// `single`, or under MPI `directions`, `data` or `hybrid`.
    pub mode: String,
    pub ranks: usize,
    /// Voxels along the scene's longest side.
    pub resolution: u32,
    pub tolerance: f64,
}

/// The contents of `report.json` (see the module header for the keys).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub version: String,
    pub scene: String,
    pub mode: String,
    pub ranks: usize,
    pub threads: usize,
    pub resolution: u32,
    pub voxel_size: f64,
    pub voxels: u64,
    pub surfels: u64,
    pub directions: usize,
    pub iterations: usize,
    pub converged: bool,
    /// The changes stopped shrinking at the rounding of f32 storage before the tolerance was
    /// reached: the result is as close as it gets (absent when false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stalled: bool,
    pub residual: f64,
    pub tolerance: f64,
    /// Wall-clock seconds: `total` and one entry per phase.
    pub seconds: BTreeMap<String, f64>,
    pub peak_rss_bytes: u64,
    /// voxels x directions x iterations / seconds spent iterating (dispatch + propagate).
    pub voxel_direction_updates_per_second: f64,
    pub effects: Vec<Effect>,
    pub energy: Energy,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exchanged_fraction: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imbalance: Option<f64>,
    /// Distributed solves: seconds of each rank (index = rank) in dispatch, propagate and the
    /// reduction across ranks.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub per_rank: Vec<RankSeconds>,
    /// The partner links kept between iterations (see `solve::links`; out of core none are kept:
    /// `kept_directions` 0, every iteration searches again).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub links: Option<crate::solve::stats::LinkStats>,
    /// Present when the solve ran out of core (a shard set, or `--memory`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub out_of_core: Option<OutOfCoreReport>,
    /// Data and hybrid modes: groups, what moved between ranks, balance, and every rank's
    /// seconds per phase (balance, fill, exchange, merge, dispatch, propagate, reduce).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data_distribution: Option<crate::solve::stats::DataStats>,
    /// Present when the solve continued from a checkpoint (`--resume`): the iteration it held.
    /// `iterations` counts from the start; the times and rates are this run's alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resumed_from_iteration: Option<usize>,
}

/// One rank's time in a distributed solve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RankSeconds {
    pub dispatch: f64,
    pub propagate: f64,
    pub reduce: f64,
}

/// What an out-of-core solve held and moved.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OutOfCoreReport {
    pub memory_budget_bytes: u64,
    /// Bytes read from and written to the shard set and the work files, over the whole solve.
    pub bytes_read: u64,
    pub bytes_written: u64,
    /// The same per surfel and direction of every iteration.
    pub bytes_read_per_voxel_direction: f64,
    pub bytes_written_per_voxel_direction: f64,
    /// Bands the directions were cut into, over all iterations.
    pub bands: u64,
    /// The direct-light pass's parts: groups of dense directions whose lines' surfels were held
    /// at once, or pieces of a group's lines (one pass over the scene each; 0 without the pass).
    #[serde(default)]
    pub direct_light_parts: u64,
    /// Groups of dense directions whose lines' surfels did not fit the budget at once, taken in
    /// parts of their lines (`outcore::direct`).
    #[serde(default)]
    pub direct_light_split_groups: u64,
}

impl OutOfCoreReport {
    /// The figures of a solve that read `bytes_read` and wrote `bytes_written` for `updates`
    /// surfel-direction updates (surfels x directions x iterations) under `budget` bytes.
    pub fn new(budget: u64, bytes_read: u64, bytes_written: u64, bands: u64, updates: u64) -> Self {
        let updates = updates.max(1) as f64;
        OutOfCoreReport {
            memory_budget_bytes: budget,
            bytes_read,
            bytes_written,
            bytes_read_per_voxel_direction: bytes_read as f64 / updates,
            bytes_written_per_voxel_direction: bytes_written as f64 / updates,
            bands,
            direct_light_parts: 0,
            direct_light_split_groups: 0,
        }
    }
}

impl Report {
    /// Records what an out-of-core solve of `surfels` surfels under `budget` read, wrote and
    /// cut into bands, the direct-light pass's parts, and the effect "out of core" (`held`
    /// says where the surfels were held, and within what). Both out-of-core paths report
    /// through this.
    #[allow(clippy::too_many_arguments)]
    pub fn add_out_of_core(
        &mut self,
        budget: u64,
        bytes_read: u64,
        bytes_written: u64,
        bands: u64,
        surfels: u64,
        stats: &SolveStats,
        held: &str,
    ) {
        let updates = surfels * stats.directions as u64 * stats.iterations as u64;
        let mut ooc = OutOfCoreReport::new(budget, bytes_read, bytes_written, bands, updates);
        ooc.direct_light_parts = stats.direct.as_ref().map_or(0, |d| d.parts);
        ooc.direct_light_split_groups = stats.direct.as_ref().map_or(0, |d| d.split_groups);
        self.out_of_core = Some(ooc);
        self.effects.push(Effect::new("out of core", true, held));
    }

    /// A report from the solver's statistics. `seconds` starts with the solver's phases and a
    /// `total` equal to their sum; callers add their own phases (reading, voxelizing, writing)
    /// with [`Report::set_phase`] and the true wall-clock total with [`Report::set_total`].
    /// `peak_rss_bytes` is measured now; call [`Report::refresh_peak_rss`] again just before
    /// writing to include later phases.
    pub fn new(run: RunInfo, set: &SurfelSet, stats: &SolveStats) -> Self {
        Self::from_counts(
            run,
            set.voxel_count() as u64,
            set.surfels.len() as u64,
            set.grid.voxel_size,
            stats,
        )
    }

    /// As [`Report::new`], from the counts of a scene not held in memory.
    pub fn from_counts(
        run: RunInfo,
        voxels: u64,
        surfels: u64,
        voxel_size: f64,
        stats: &SolveStats,
    ) -> Self {
        let mut seconds = BTreeMap::new();
        seconds.insert("normalize".to_string(), stats.normalize_seconds);
        seconds.insert("dispatch".to_string(), stats.dispatch_seconds);
        seconds.insert("propagate".to_string(), stats.propagate_seconds);
        if let Some(direct) = &stats.direct {
            // Before the iterations, inside the solve: the direct-light pass (every path).
            seconds.insert("direct".to_string(), direct.seconds);
        }
        let total = stats.normalize_seconds + stats.dispatch_seconds + stats.propagate_seconds;
        seconds.insert("total".to_string(), total);
        let iterating = stats.dispatch_seconds + stats.propagate_seconds;
        // A resumed solve iterated only since its checkpoint.
        let iterated = stats.iterations - stats.resumed_from_iteration.unwrap_or(0);
        let updates = voxels as f64 * stats.directions as f64 * iterated as f64;
        let rate = if iterating > 0.0 {
            updates / iterating
        } else {
            0.0
        };
        Report {
            version: env!("CARGO_PKG_VERSION").to_string(),
            scene: run.scene,
            mode: run.mode,
            ranks: run.ranks,
            threads: stats.threads,
            resolution: run.resolution,
            voxel_size,
            voxels,
            surfels,
            directions: stats.directions,
            iterations: stats.iterations,
            converged: stats.converged,
            stalled: stats.stalled,
            residual: stats.residual,
            tolerance: run.tolerance,
            seconds,
            peak_rss_bytes: peak_rss_bytes(),
            voxel_direction_updates_per_second: rate,
            effects: Vec::new(),
            energy: Energy::new(stats.emitted_power, stats.absorbed_power),
            exchanged_fraction: stats.data.as_ref().map(|d| d.exchanged_fraction),
            imbalance: stats.data.as_ref().map(|d| d.imbalance),
            per_rank: stats
                .per_rank_seconds
                .iter()
                .map(|&[dispatch, propagate, reduce]| RankSeconds {
                    dispatch,
                    propagate,
                    reduce,
                })
                .collect(),
            links: stats.links.clone(),
            out_of_core: None,
            data_distribution: stats.data.clone(),
            resumed_from_iteration: stats.resumed_from_iteration,
        }
    }

    /// Records the seconds one phase took (replacing an earlier value of the same phase).
    pub fn set_phase(&mut self, phase: &str, seconds: f64) {
        self.seconds.insert(phase.to_string(), seconds);
    }

    /// Records the wall-clock total.
    pub fn set_total(&mut self, seconds: f64) {
        self.set_phase("total", seconds);
    }

    /// Re-reads the process's peak RSS.
    pub fn refresh_peak_rss(&mut self) {
        self.peak_rss_bytes = peak_rss_bytes();
    }

    /// Writes `report.json` into `dir` atomically and returns its path.
    pub fn write(&self, dir: &Path) -> Result<PathBuf, OutputError> {
        let path = dir.join(REPORT_FILE);
        let json = serde_json::to_vec_pretty(self).map_err(|source| OutputError::Json {
            path: path.clone(),
            source,
        })?;
        atomic::write_atomically(&path, |w| {
            w.write_all(&json)?;
            w.write_all(b"\n")
        })?;
        Ok(path)
    }

    /// Reads a `report.json` back (for tools and tests).
    pub fn read(path: &Path) -> Result<Report, ReportReadError> {
        let text = std::fs::read(path).map_err(|source| ReportReadError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        serde_json::from_slice(&text).map_err(|source| ReportReadError::Json {
            path: path.to_path_buf(),
            source,
        })
    }
}

/// Why a report could not be read back.
#[derive(Debug, thiserror::Error)]
pub enum ReportReadError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} is not a valid report: {source}", path.display())]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
}

/// Peak resident set size of this process so far, in bytes (0 if the system will not say).
///
/// On Linux this is `VmHWM` of `/proc/self/status`: the high-water mark of this program's own
/// memory. `getrusage` is the fallback; on Linux its figure also counts what the parent had
/// resident when it forked this process (the kernel carries the high-water mark across `exec`),
/// so a small program started by a big one would report the big one's size.
pub fn peak_rss_bytes() -> u64 {
    if let Some(bytes) = status_high_water_mark() {
        return bytes;
    }
    // SAFETY: `getrusage` only writes into the zero-initialised struct we pass it.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let rc = unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) };
    if rc != 0 {
        return 0;
    }
    let maxrss = usage.ru_maxrss.max(0) as u64;
    // Linux reports KiB; macOS reports bytes.
    if cfg!(target_os = "macos") {
        maxrss
    } else {
        maxrss * 1024
    }
}

/// `VmHWM` from `/proc/self/status`, in bytes.
fn status_high_water_mark() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::testutil;

    fn sample() -> Report {
        let (set, _) = testutil::lit_square(4);
        let stats = SolveStats {
            directions: 100,
            iterations: 10,
            converged: true,
            residual: 1e-4,
            threads: 2,
            dispatch_seconds: 1.0,
            propagate_seconds: 3.0,
            normalize_seconds: 0.5,
            emitted_power: [4.0, 4.0, 2.0],
            absorbed_power: [3.0, 3.0, 2.0],
            ..Default::default()
        };
        let run = RunInfo {
            scene: "cornell.obj".into(),
            mode: "single".into(),
            ranks: 1,
            resolution: 64,
            tolerance: 1e-5,
        };
        let mut r = Report::new(run, &set, &stats);
        r.effects
            .push(Effect::new("interreflection", true, "reflectance > 0"));
        r.set_total(5.0);
        r
    }

    #[test]
    fn report_has_the_documented_keys_and_round_trips() {
        let dir = tempfile::TempDir::new().unwrap();
        let r = sample();
        assert_eq!(r.voxels, 16);
        // 16 voxels x 100 directions x 10 iterations over 4 seconds of iterating.
        assert!((r.voxel_direction_updates_per_second - 4000.0).abs() < 1e-9);
        assert_eq!(r.energy.escaped_power, [1.0, 1.0, 0.0]);
        assert!((r.energy.balance - 0.2).abs() < 1e-12);
        let path = r.write(dir.path()).unwrap();
        assert_eq!(path, dir.path().join("report.json"));
        let value: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        for key in [
            "voxels",
            "directions",
            "iterations",
            "converged",
            "residual",
            "seconds",
            "peak_rss_bytes",
            "voxel_direction_updates_per_second",
            "effects",
            "energy",
            "ranks",
            "threads",
            "mode",
            "surfels",
            "scene",
            "resolution",
            "voxel_size",
            "tolerance",
            "version",
        ] {
            assert!(value.get(key).is_some(), "missing key {key}");
        }
        assert_eq!(value["seconds"]["total"], 5.0);
        assert_eq!(value["seconds"]["propagate"], 3.0);
        assert_eq!(value["effects"][0]["simulated"], true);
        assert!(value["energy"]["emitted_power"].is_array());
        assert!(value.get("imbalance").is_none());
        assert_eq!(Report::read(&path).unwrap(), r);
    }

    #[test]
    fn peak_rss_is_plausible() {
        let rss = peak_rss_bytes();
        assert!(rss > 1 << 20 && rss < 1 << 40, "{rss}");
    }

    #[test]
    fn write_into_missing_directory_names_the_file() {
        let dir = tempfile::TempDir::new().unwrap();
        let err = sample().write(&dir.path().join("nope")).unwrap_err();
        assert!(err.to_string().contains("report.json"), "{err}");
    }
}
