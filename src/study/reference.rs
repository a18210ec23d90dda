//! Path-traced reference data: radiosity at fixed probe points, computed outside voxrad.
//!
//! The files live in one directory per scene (`tests/data/reference/<scene>/`, made by
//! `tools/reference/mitsuba_reference.py` with Mitsuba 3, see that directory's README):
//! `reference.csv` (header, then `x,y,z,nx,ny,nz,B_r,B_g,B_b,se_B_r,se_B_g,se_B_b,...` per probe),
//! optionally `surfaces.csv` (`probe,surface`: a label per probe, for means over one face) and
//! the scene itself (`scene.obj`, or the Cornell box of `examples/`).
//!
//! This module only reads them: the accuracy tests and `voxrad study` compare voxrad's answer at
//! the probes with these values, so that an error voxrad makes at every setting still shows.

use glam::DVec3;
use std::path::{Path, PathBuf};

/// One probe's reference answer.
#[derive(Clone, Debug, PartialEq)]
pub struct ReferenceProbe {
    pub point: DVec3,
    pub normal: DVec3,
    /// `B_r + B_g + B_b` on the side `normal` faces.
    pub radiosity: f64,
    /// Monte Carlo standard error of `radiosity` (channels added as independent).
    pub standard_error: f64,
    /// The kind of surface the probe is on (`floor`, `slab -x`, ...); `"all"` without labels.
    pub surface: String,
    /// `H_r + H_g + H_b`, the irradiance arriving on that side, and its standard error, where the
    /// file has the columns `H_r,H_g,H_b,se_H_r,se_H_g,se_H_b`.
    pub irradiance: Option<(f64, f64)>,
}

/// A scene's reference data.
#[derive(Clone, Debug)]
pub struct Reference {
    pub dir: PathBuf,
    pub probes: Vec<ReferenceProbe>,
}

/// Why reference data could not be read; names the file and, for a bad row, its line.
#[derive(Debug, thiserror::Error)]
pub enum ReferenceError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}:{line}: {what}", path.display())]
    Bad {
        path: PathBuf,
        line: usize,
        what: String,
    },
}

/// Columns of `reference.csv` that are read, by name.
const COLUMNS: [&str; 12] = [
    "x", "y", "z", "nx", "ny", "nz", "B_r", "B_g", "B_b", "se_B_r", "se_B_g", "se_B_b",
];
/// Columns of the irradiance, read where the header has them all.
const IRRADIANCE_COLUMNS: [&str; 6] = ["H_r", "H_g", "H_b", "se_H_r", "se_H_g", "se_H_b"];

impl Reference {
    /// Reads `dir/reference.csv` and, where it exists, `dir/surfaces.csv`.
    pub fn load(dir: &Path) -> Result<Reference, ReferenceError> {
        let path = dir.join("reference.csv");
        let text = read(&path)?;
        let labels = dir.join("surfaces.csv");
        let labels = if labels.exists() {
            Some((read(&labels)?, labels))
        } else {
            None
        };
        Self::parse(
            dir,
            &path,
            &text,
            labels.as_ref().map(|(t, p)| (t.as_str(), p.as_path())),
        )
    }

    /// The Cornell box's reference, built into the program (the study's 300 probe points).
    pub fn cornell() -> Reference {
        let dir = Path::new("tests/data/reference/cornell");
        Self::parse(
            dir,
            &dir.join("reference.csv"),
            include_str!("../../tests/data/reference/cornell/reference.csv"),
            Some((
                include_str!("../../tests/data/reference/cornell/surfaces.csv"),
                &dir.join("surfaces.csv"),
            )),
        )
        .expect("the built-in Cornell reference parses (a unit test reads it)")
    }

    /// Parses the text of `reference.csv` (read from `path`, named in errors) and optionally of
    /// `surfaces.csv`.
    pub fn parse(
        dir: &Path,
        path: &Path,
        text: &str,
        labels: Option<(&str, &Path)>,
    ) -> Result<Reference, ReferenceError> {
        let path = path.to_path_buf();
        let bad = |line: usize, what: String| ReferenceError::Bad {
            path: path.clone(),
            line,
            what,
        };
        let mut lines = text.lines().enumerate();
        let header: Vec<&str> = match lines.next() {
            Some((_, h)) => h.split(',').map(str::trim).collect(),
            None => return Err(bad(1, "the file is empty; expected a header line".into())),
        };
        let at: Vec<usize> = COLUMNS
            .iter()
            .map(|name| {
                header
                    .iter()
                    .position(|h| h == name)
                    .ok_or_else(|| bad(1, format!("the header has no column '{name}'")))
            })
            .collect::<Result<_, _>>()?;
        let irradiance_at: Option<Vec<usize>> = IRRADIANCE_COLUMNS
            .iter()
            .map(|name| header.iter().position(|h| h == name))
            .collect();
        let mut probes = Vec::new();
        for (k, line) in lines {
            if line.trim().is_empty() {
                continue;
            }
            let fields: Vec<&str> = line.split(',').map(str::trim).collect();
            let mut v = [0.0f64; 18];
            let columns = at.iter().chain(irradiance_at.iter().flatten());
            for (slot, &column) in v.iter_mut().zip(columns) {
                let field = fields
                    .get(column)
                    .ok_or_else(|| bad(k + 1, format!("expected {} columns", header.len())))?;
                *slot = field
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| bad(k + 1, format!("'{field}' is not a finite number")))?;
            }
            probes.push(ReferenceProbe {
                point: DVec3::new(v[0], v[1], v[2]),
                normal: DVec3::new(v[3], v[4], v[5]),
                radiosity: v[6] + v[7] + v[8],
                standard_error: (v[9] * v[9] + v[10] * v[10] + v[11] * v[11]).sqrt(),
                surface: "all".to_string(),
                irradiance: irradiance_at.is_some().then(|| {
                    (
                        v[12] + v[13] + v[14],
                        (v[15] * v[15] + v[16] * v[16] + v[17] * v[17]).sqrt(),
                    )
                }),
            });
        }
        if probes.is_empty() {
            return Err(bad(2, "the file holds no probe".into()));
        }
        if let Some((text, labels)) = labels {
            let labels = labels.to_path_buf();
            let mut count = 0;
            for (k, line) in text.lines().enumerate().skip(1) {
                if line.trim().is_empty() {
                    continue;
                }
                let bad = |what: String| ReferenceError::Bad {
                    path: labels.clone(),
                    line: k + 1,
                    what,
                };
                let (index, surface) = line
                    .split_once(',')
                    .ok_or_else(|| bad("expected 'probe,surface'".into()))?;
                let index: usize = index
                    .trim()
                    .parse()
                    .map_err(|_| bad(format!("'{index}' is not a probe number")))?;
                let probe = probes
                    .get_mut(index)
                    .ok_or_else(|| bad(format!("probe {index} is not in reference.csv")))?;
                probe.surface = surface.trim().to_string();
                count += 1;
            }
            if count != probes.len() {
                return Err(ReferenceError::Bad {
                    path: labels,
                    line: 1,
                    what: format!(
                        "{count} labels for {} probes in reference.csv",
                        probes.len()
                    ),
                });
            }
        }
        Ok(Reference {
            dir: dir.to_path_buf(),
            probes,
        })
    }

    /// The reference for the irradiance `H` in place of the radiosity (so that
    /// [`Reference::compare`] compares irradiance), where the file has it for every probe.
    pub fn irradiance(&self) -> Option<Reference> {
        let probes = self
            .probes
            .iter()
            .map(|p| {
                p.irradiance.map(|(h, se)| ReferenceProbe {
                    radiosity: h,
                    standard_error: se,
                    irradiance: None,
                    ..p.clone()
                })
            })
            .collect::<Option<Vec<_>>>()?;
        Some(Reference {
            dir: self.dir.clone(),
            probes,
        })
    }

    /// The probe points and normals, in file order.
    pub fn points(&self) -> Vec<(DVec3, DVec3)> {
        self.probes.iter().map(|p| (p.point, p.normal)).collect()
    }

    /// The distinct surface labels, in order of first appearance.
    pub fn surfaces(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for p in &self.probes {
            if !out.contains(&p.surface) {
                out.push(p.surface.clone());
            }
        }
        out
    }
}

fn read(path: &Path) -> Result<String, ReferenceError> {
    std::fs::read_to_string(path).map_err(|source| ReferenceError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Compares probe values (sum of channels; `None` where voxrad found no surface) with the
/// reference.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    /// Probes compared (the reference sees at least [`MIN_FRACTION_OF_MEDIAN`] of its median and
    /// voxrad found the surface).
    pub compared: usize,
    /// Mean and largest relative error `|v - r| / r` over the compared probes.
    pub mean: f64,
    pub max: f64,
    /// Mean relative standard error of the reference over the compared probes: errors below it
    /// cannot be told from the reference's own noise.
    pub reference_noise: f64,
    /// Per surface label: the relative error of the mean over its probes,
    /// `(mean v - mean r) / mean r`, with the probes compared.
    pub surfaces: Vec<(String, f64, usize)>,
}

/// Fraction of the median reference value below which a probe is not compared (probes in deep
/// shadow, where a relative error says nothing).
pub const MIN_FRACTION_OF_MEDIAN: f64 = 0.05;

impl Reference {
    /// Compares `values` (one per probe, in file order) with the reference.
    pub fn compare(&self, values: &[Option<f64>]) -> Comparison {
        let mut sorted: Vec<f64> = self.probes.iter().map(|p| p.radiosity).collect();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        let (mut sum, mut max, mut noise, mut compared) = (0.0, 0.0f64, 0.0, 0usize);
        let mut per_surface: Vec<(String, f64, f64, usize)> = Vec::new();
        for (p, v) in self.probes.iter().zip(values) {
            let Some(v) = *v else { continue };
            if p.radiosity < MIN_FRACTION_OF_MEDIAN * median || p.radiosity <= 0.0 {
                continue;
            }
            let e = (v - p.radiosity).abs() / p.radiosity;
            sum += e;
            max = max.max(e);
            noise += p.standard_error / p.radiosity;
            compared += 1;
            match per_surface.iter_mut().find(|s| s.0 == p.surface) {
                Some(s) => {
                    s.1 += v;
                    s.2 += p.radiosity;
                    s.3 += 1;
                }
                None => per_surface.push((p.surface.clone(), v, p.radiosity, 1)),
            }
        }
        let n = compared.max(1) as f64;
        Comparison {
            compared,
            mean: sum / n,
            max,
            reference_noise: noise / n,
            surfaces: per_surface
                .into_iter()
                .map(|(name, v, r, k)| (name, (v - r) / r, k))
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir_with(files: &[(&str, &str)]) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        for (name, text) in files {
            std::fs::write(dir.path().join(name), text).unwrap();
        }
        dir
    }

    const HEADER: &str = "x,y,z,nx,ny,nz,B_r,B_g,B_b,se_B_r,se_B_g,se_B_b,paths\n";

    #[test]
    fn reads_values_labels_and_compares() {
        let dir = dir_with(&[
            (
                "reference.csv",
                &format!("{HEADER}0,0,0,0,1,0,1,1,1,0.03,0.04,0\n1,0,0,0,1,0,2,2,2,0,0,0\n"),
            ),
            ("surfaces.csv", "probe,surface\n0,floor\n1,wall\n"),
        ]);
        let r = Reference::load(dir.path()).unwrap();
        assert_eq!(r.probes.len(), 2);
        assert_eq!(r.probes[0].radiosity, 3.0);
        assert!((r.probes[0].standard_error - 0.05).abs() < 1e-12);
        assert_eq!(r.surfaces(), vec!["floor".to_string(), "wall".to_string()]);
        let c = r.compare(&[Some(3.3), Some(6.0)]);
        assert_eq!(c.compared, 2);
        assert!((c.mean - 0.05).abs() < 1e-12 && (c.max - 0.1).abs() < 1e-12);
        assert!((c.surfaces[0].1 - 0.1).abs() < 1e-12);
        // No H columns: no irradiance reference.
        assert!(r.irradiance().is_none());
    }

    #[test]
    fn reads_the_irradiance_where_the_header_has_it() {
        let header = "x,y,z,nx,ny,nz,B_r,B_g,B_b,se_B_r,se_B_g,se_B_b,H_r,H_g,H_b,se_H_r,\
                      se_H_g,se_H_b,paths\n";
        let dir = dir_with(&[(
            "reference.csv",
            &format!("{header}0,0,0,0,1,0,1,1,1,0,0,0,2,2,4,0.03,0.04,0,100\n"),
        )]);
        let r = Reference::load(dir.path()).unwrap();
        assert_eq!(r.probes[0].irradiance, Some((8.0, 0.05)));
        let h = r.irradiance().unwrap();
        assert_eq!(h.probes[0].radiosity, 8.0);
        assert!((h.compare(&[Some(8.8)]).max - 0.1).abs() < 1e-12);
    }

    #[test]
    fn the_built_in_cornell_reference_is_the_studys_probes() {
        let r = Reference::cornell();
        assert_eq!(r.probes.len(), 300);
        let points = crate::study::probe_points(&crate::gen::cornell_box(), 300, 0x5eed);
        for (p, (q, n)) in r.probes.iter().zip(&points) {
            assert!(p.point.distance(*q) < 1e-9 && p.normal.distance(n.normalize()) < 1e-9);
        }
    }

    #[test]
    fn bad_files_name_the_file_and_line() {
        let dir = dir_with(&[(
            "reference.csv",
            &format!("{HEADER}0,0,0,0,1,0,1,x,1,0,0,0\n"),
        )]);
        let e = Reference::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains("reference.csv:2") && e.contains("'x'"), "{e}");
        let dir = dir_with(&[("reference.csv", "x,y,z\n0,0,0\n")]);
        let e = Reference::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains("reference.csv:1") && e.contains("nx"), "{e}");
        let dir = dir_with(&[
            (
                "reference.csv",
                &format!("{HEADER}0,0,0,0,1,0,1,1,1,0,0,0\n"),
            ),
            ("surfaces.csv", "probe,surface\n3,floor\n"),
        ]);
        let e = Reference::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains("surfaces.csv:2"), "{e}");
        let e = Reference::load(Path::new("no/such/dir"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("reference.csv"), "{e}");
    }
}
