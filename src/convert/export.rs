//! A solve's `surfels.bin` streamed into PLY or CSV, whatever its size.
//!
//! The output is byte for byte what the in-memory writers (`output::ply::write_ply`,
//! `output::results::write_csv`) make from the same records, because both use the same
//! per-record writers; only the passes differ. Nothing is written before a full pass over the
//! input has checked its checksum, and every later pass checks it again at its end (the file is
//! read several times, and the output is written atomically, so a file changing in between
//! aborts the export instead of producing a mix).
//!
//! The PLY's colours need the tone map of the whole solution, the 99th percentile of the
//! luminances (`ToneMap::for_solution`), which the in-memory path finds by sorting them all.
//! Here it is found exactly in bounded memory by a radix selection over the bits of the
//! luminances (positive floats order like their bit patterns): each pass counts the values in
//! 65,536 buckets of the next 16 bits among those that share the prefix found so far, until the
//! bucket holding the percentile has few enough values to collect and select directly. Usually
//! two passes; at most five.

use super::ConvertError;
use crate::output::render::{ToneMap, EXPOSURE_PERCENTILE};
use crate::output::results::{write_csv_record, Record, ResultsReader, CSV_HEADER};
use crate::output::{atomic, luminance, ply, ResultsError};
use crate::voxel::{BACK, FRONT};
use std::path::Path;

/// The export formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Ply,
    Csv,
}

const BUFFER: usize = 1 << 20;
/// Values of one bucket collected at most, for the final selection.
const COLLECT: u64 = 1 << 16;

fn results_err(e: ResultsError) -> ConvertError {
    match &e {
        ResultsError::Io { source, .. }
            if !matches!(
                source.kind(),
                std::io::ErrorKind::NotFound | std::io::ErrorKind::PermissionDenied
            ) =>
        {
            ConvertError::Failure(e.to_string())
        }
        _ => ConvertError::BadInput(e.to_string()),
    }
}

/// What an export wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Exported {
    /// PLY vertices or CSV rows.
    pub items: u64,
    /// Passes over the input.
    pub passes: u64,
}

/// Exports the results file of the solve directory (or results file) `input` to `out`.
pub fn export(input: &Path, format: Format, out: &Path) -> Result<Exported, ConvertError> {
    let path = if input.is_dir() {
        input.join(crate::output::RESULTS_FILE)
    } else {
        input.to_path_buf()
    };
    let reader = ResultsReader::open(&path).map_err(results_err)?;
    if let (Ok(a), Ok(b)) = (std::fs::canonicalize(&path), std::fs::canonicalize(out)) {
        if a == b {
            return Err(ConvertError::BadInput(format!(
                "{}: --out is the results file itself; give another file",
                out.display()
            )));
        }
    }
    let mut passes = 0;
    let mut pass = |f: &mut dyn FnMut(&Record)| -> Result<(), ConvertError> {
        passes += 1;
        for r in reader.records(BUFFER).map_err(results_err)? {
            f(&r.map_err(results_err)?);
        }
        Ok(())
    };
    let items = match format {
        Format::Csv => {
            pass(&mut |_| {})?;
            write_streamed(
                &reader,
                out,
                |w, grid, r| write_csv_record(w, grid, r),
                |w| writeln!(w, "{CSV_HEADER}"),
            )?
        }
        Format::Ply => {
            let (tone, count) = tone_map(&mut pass)?;
            let written = write_streamed(
                &reader,
                out,
                |w, grid, r| {
                    ply::write_vertices(w, grid, r, &tone)?;
                    Ok(ply::vertices_of(r))
                },
                |w| ply::write_header(w, count),
            )?;
            if written != count {
                return Err(ConvertError::Failure(format!(
                    "{} changed while it was exported; nothing was written",
                    path.display()
                )));
            }
            written
        }
    };
    passes += 1;
    Ok(Exported { items, passes })
}

/// One pass writing `out` atomically: the header, then each record.
fn write_streamed(
    reader: &ResultsReader,
    out: &Path,
    mut record: impl FnMut(
        &mut dyn std::io::Write,
        &crate::voxel::Grid,
        &Record,
    ) -> std::io::Result<u64>,
    header: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>,
) -> Result<u64, ConvertError> {
    let mut failure: Option<ResultsError> = None;
    let mut items = 0;
    let written = atomic::write_atomically(out, |w| {
        header(w)?;
        let records = match reader.records(BUFFER) {
            Ok(r) => r,
            Err(e) => {
                failure = Some(e);
                return Err(std::io::Error::other("input failed"));
            }
        };
        for r in records {
            match r {
                Ok(r) => items += record(w, reader.grid(), &r)?,
                Err(e) => {
                    // Abort the write: the temporary file is deleted, nothing is renamed.
                    failure = Some(e);
                    return Err(std::io::Error::other("input failed"));
                }
            }
        }
        Ok(())
    });
    if let Some(e) = failure {
        return Err(results_err(e));
    }
    written?;
    Ok(items)
}

/// One pass over the records, calling the given function on each.
type Pass<'a> = dyn FnMut(&mut dyn FnMut(&Record)) -> Result<(), ConvertError> + 'a;

/// The solution's tone map (see the module header) and the PLY's vertex count, by passes over
/// the records.
fn tone_map(pass: &mut Pass<'_>) -> Result<(ToneMap, u64), ConvertError> {
    // The luminances `ToneMap::for_solution` considers, as ordered bit patterns.
    fn each_key(r: &Record, f: &mut dyn FnMut(u64)) {
        for side in [FRONT, BACK] {
            if r.side_is_present(side) {
                let l = luminance(r.radiosity[side]);
                if l > 0.0 && l.is_finite() {
                    f(l.to_bits());
                }
            }
        }
    }
    let mut vertices = 0u64;
    let mut histogram = vec![0u64; 1 << 16];
    pass(&mut |r| {
        vertices += ply::vertices_of(r);
        each_key(r, &mut |k| histogram[(k >> 48) as usize] += 1);
    })?;
    let n: u64 = histogram.iter().sum();
    if n == 0 {
        return Ok((ToneMap { exposure: 1.0 }, vertices));
    }
    // The rank `ToneMap::from_luminances` selects.
    let mut k = (((n - 1) as f64) * EXPOSURE_PERCENTILE).round() as u64;
    let mut prefix = 0u64;
    let mut shift = 48u32;
    loop {
        // The bucket of the histogram holding rank k.
        let mut below = 0;
        let mut found = None;
        for (b, &c) in histogram.iter().enumerate() {
            if below + c > k {
                found = Some(b as u64);
                break;
            }
            below += c;
        }
        // Only a file rewritten (with a valid checksum) between two passes can lose the rank.
        let bucket = found.ok_or_else(|| {
            ConvertError::Failure("the results file changed while it was exported".into())
        })?;
        let in_bucket = histogram[bucket as usize];
        k -= below;
        prefix = (prefix << 16) | bucket;
        let matches = |key: u64| key >> shift == prefix;
        if shift == 0 {
            return Ok((tone_of(f64::from_bits(prefix)), vertices));
        }
        if in_bucket <= COLLECT {
            let mut values = Vec::with_capacity(in_bucket as usize);
            pass(&mut |r| {
                each_key(r, &mut |key| {
                    if matches(key) {
                        values.push(key)
                    }
                })
            })?;
            if values.len() as u64 != in_bucket {
                return Err(ConvertError::Failure(
                    "the results file changed while it was exported".into(),
                ));
            }
            let (_, white, _) = values.select_nth_unstable(k as usize);
            return Ok((tone_of(f64::from_bits(*white)), vertices));
        }
        shift -= 16;
        histogram.iter_mut().for_each(|c| *c = 0);
        pass(&mut |r| {
            each_key(r, &mut |key| {
                if key >> (shift + 16) == prefix {
                    histogram[((key >> shift) & 0xffff) as usize] += 1;
                }
            })
        })?;
    }
}

fn tone_of(white: f64) -> ToneMap {
    ToneMap {
        exposure: 1.0 / white,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The exact percentile by radix selection equals the in-memory selection, also when one
    /// bucket holds more values than are collected.
    #[test]
    fn radix_selection_matches_the_sort() {
        for (n, spread) in [(10usize, 1.0), (300_000, 1e-9), (200_000, 1e6)] {
            let records: Vec<Record> = (0..n)
                .map(|i| {
                    let x = 1.0 + spread * ((i * 7919) % n) as f64 / n as f64;
                    Record {
                        voxel: [0; 3],
                        point: [0.0; 3],
                        normal: [0.0, 0.0, 1.0],
                        area: if i % 3 == 0 { 0.0 } else { 1.0 },
                        radiosity: [[x as f32; 3], [0.0; 3]],
                        material: [0; 2],
                        extent: [[0.0; 3], [1.0; 3]],
                    }
                })
                .collect();
            let mut lums = Vec::new();
            for r in &records {
                for side in [FRONT, BACK] {
                    if r.side_is_present(side) {
                        lums.push(luminance(r.radiosity[side]));
                    }
                }
            }
            let expected = ToneMap::from_luminances(lums.clone());
            let mut passes = 0;
            let mut pass = |f: &mut dyn FnMut(&Record)| {
                passes += 1;
                records.iter().for_each(&mut *f);
                Ok(())
            };
            let (tone, vertices) = tone_map(&mut pass).unwrap();
            assert_eq!(tone.exposure, expected.exposure, "n {n}");
            assert_eq!(vertices, lums.len() as u64);
            assert!(passes <= 5);
        }
    }
}
