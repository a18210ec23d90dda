//! Byte sizes as people write them on a command line: `64MiB`, `1.5 GiB`, `512k`, `4096`.
//!
//! Binary units (`KiB`, `MiB`, `GiB`, `TiB`, and the short `K`, `M`, `G`, `T`, `k`) are powers
//! of 1024; decimal units (`kB`, `MB`, `GB`, `TB`) powers of 1000; a bare number or `B` is bytes.
//! Memory budgets are the use, and memory is counted in binary units, hence the short forms.

/// Parses a size; the error says what is accepted.
pub fn parse_bytes(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let unit = unit.trim();
    let multiplier: u64 = match unit {
        "" | "B" | "b" => 1,
        "K" | "k" | "KiB" | "kiB" => 1 << 10,
        "M" | "MiB" => 1 << 20,
        "G" | "GiB" => 1 << 30,
        "T" | "TiB" => 1 << 40,
        "kB" | "KB" => 1_000,
        "MB" => 1_000_000,
        "GB" => 1_000_000_000,
        "TB" => 1_000_000_000_000,
        _ => return Err(bad(text)),
    };
    let value: f64 = number.parse().map_err(|_| bad(text))?;
    let bytes = value * multiplier as f64;
    if !bytes.is_finite() || bytes >= u64::MAX as f64 {
        return Err(bad(text));
    }
    Ok(bytes.round() as u64)
}

fn bad(text: &str) -> String {
    format!(
        "'{text}' is not a size: write a number with an optional unit, such as 4096, 512KiB, \
         64MiB, 1.5GiB or 2GB"
    )
}

/// A size for people: `64.0 MiB`.
pub fn human(bytes: u64) -> String {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn units() {
        assert_eq!(parse_bytes("4096"), Ok(4096));
        assert_eq!(parse_bytes("64MiB"), Ok(64 << 20));
        assert_eq!(parse_bytes("64M"), Ok(64 << 20));
        assert_eq!(parse_bytes(" 1.5 GiB "), Ok(3 << 29));
        assert_eq!(parse_bytes("1KiB"), Ok(1024));
        assert_eq!(parse_bytes("2GB"), Ok(2_000_000_000));
        assert_eq!(parse_bytes("512k"), Ok(512 << 10));
        for bad in ["", "MiB", "12 parsecs", "-5M", "1e999"] {
            let e = parse_bytes(bad).unwrap_err();
            assert!(e.contains("not a size"), "{bad}: {e}");
        }
        assert_eq!(human(64 << 20), "64.0 MiB");
        assert_eq!(human(100), "100 B");
    }
}
