//! Numbers a user types on the command line, checked before they are used: finite, within
//! the range that means something, and `inf` only where it has a meaning ("for ever").
//! Each returns the message a flag parser shows next to the flag's name.

use std::ops::RangeInclusive;
use std::time::Duration;

/// A finite number within `range`; `inf`, `nan` and text that is not a number are refused.
pub fn number_in(text: &str, range: RangeInclusive<f64>) -> Result<f64, String> {
    let value: f64 = text
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a number"))?;
    if value.is_finite() && range.contains(&value) {
        Ok(value)
    } else {
        Err(format!(
            "must be a finite number from {} to {}",
            range.start(),
            range.end()
        ))
    }
}

/// Longest finite timeout accepted (seconds): about 31 years; longer is `inf`.
pub const MAX_TIMEOUT_SECONDS: f64 = 1e9;

/// A timeout: `Timeout(None)` waits for ever.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Timeout(pub Option<Duration>);

/// A timeout in seconds, greater than 0 and at most [`MAX_TIMEOUT_SECONDS`]: `inf` means
/// wait for ever.
///
/// ```
/// use orbit_nerf_host::values::{Timeout, timeout_seconds};
/// use std::time::Duration;
///
/// assert_eq!(timeout_seconds("inf"), Ok(Timeout(None)));
/// assert_eq!(timeout_seconds("2.5"), Ok(Timeout(Some(Duration::from_millis(2500)))));
/// assert!(timeout_seconds("0").is_err());
/// ```
pub fn timeout_seconds(text: &str) -> Result<Timeout, String> {
    if matches!(
        text.trim().to_ascii_lowercase().as_str(),
        "inf" | "+inf" | "infinity"
    ) {
        return Ok(Timeout(None));
    }
    let seconds = number_in(text, 0.0..=MAX_TIMEOUT_SECONDS)
        .map_err(|e| format!("{e} seconds, or inf to wait for ever"))?;
    if seconds == 0.0 {
        return Err("must be greater than 0 seconds (or inf to wait for ever)".into());
    }
    Ok(Timeout(Some(Duration::from_secs_f64(seconds))))
}

/// A size in bytes: a whole number with an optional unit `K`, `M`, `G`, `T` (powers of 1024,
/// `KiB`/`KB` spellings too), greater than 0. Fractions (`1.5G`) are refused.
///
/// ```
/// use orbit_nerf_host::values::byte_size;
///
/// assert_eq!(byte_size("512M"), Ok(512 * 1024 * 1024));
/// assert_eq!(byte_size("8 GiB"), Ok(8 << 30));
/// assert_eq!(byte_size("4096"), Ok(4096));
/// assert!(byte_size("0G").is_err());
/// assert!(byte_size("1.5G").is_err());
/// ```
pub fn byte_size(text: &str) -> Result<u64, String> {
    let text = text.trim();
    let split = text
        .find(|c: char| !c.is_ascii_digit())
        .unwrap_or(text.len());
    let (digits, unit) = text.split_at(split);
    let value: u64 = digits
        .parse()
        .map_err(|_| format!("`{text}` is not a size such as 8G, 512M or 1048576"))?;
    let shift = match unit.trim().to_ascii_uppercase().as_str() {
        "" | "B" => 0,
        "K" | "KB" | "KIB" => 10,
        "M" | "MB" | "MIB" => 20,
        "G" | "GB" | "GIB" => 30,
        "T" | "TB" | "TIB" => 40,
        other => return Err(format!("unknown unit `{other}` (use K, M, G or T)")),
    };
    match value.checked_mul(1 << shift) {
        Some(0) => Err("must be greater than 0".into()),
        Some(bytes) => Ok(bytes),
        None => Err(format!("`{text}` is more than 2^64 bytes")),
    }
}

/// A whole number within `range` (counts such as threads).
pub fn count_in(text: &str, range: RangeInclusive<usize>) -> Result<usize, String> {
    let value: usize = text
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a whole number"))?;
    if range.contains(&value) {
        Ok(value)
    } else {
        Err(format!("must be from {} to {}", range.start(), range.end()))
    }
}

/// A direction `x,y,z`: three finite numbers within +-1e6, not all zero.
pub fn direction(text: &str) -> Result<[f32; 3], String> {
    let values: Vec<f32> = text
        .split(',')
        .map(|v| number_in(v, -1e6..=1e6).map(|v| v as f32))
        .collect::<Result<_, _>>()?;
    match values[..] {
        [x, y, z] if x != 0.0 || y != 0.0 || z != 0.0 => Ok([x, y, z]),
        [_, _, _] => Err("the zero vector has no direction".into()),
        _ => Err(format!("`{text}`: expected x,y,z")),
    }
}

/// A number above 0 and within `1e-9..=1e9` (a density threshold, a scale).
pub fn positive(text: &str) -> Result<f32, String> {
    number_in(text, 1e-9..=1e9).and_then(|v| {
        (v > 0.0)
            .then_some(v as f32)
            .ok_or_else(|| "must be greater than 0".into())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_outside_their_range_or_not_finite_are_refused() {
        for bad in ["nan", "inf", "-inf", "-1", "1e400", "x", ""] {
            assert!(number_in(bad, 0.0..=10.0).is_err(), "{bad}");
        }
        assert_eq!(number_in(" 2.5 ", 0.0..=10.0), Ok(2.5));
    }

    #[test]
    fn a_timeout_of_inf_waits_for_ever_and_zero_or_nan_is_refused() {
        assert_eq!(timeout_seconds("inf"), Ok(Timeout(None)));
        assert_eq!(timeout_seconds("Infinity"), Ok(Timeout(None)));
        assert_eq!(
            timeout_seconds("1.5"),
            Ok(Timeout(Some(Duration::from_millis(1500))))
        );
        for bad in ["0", "-3", "nan", "-inf", "1e300"] {
            assert!(timeout_seconds(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn byte_sizes_take_units_and_refuse_zero_overflow_and_junk() {
        assert_eq!(byte_size("1048576"), Ok(1 << 20));
        assert_eq!(byte_size("8G"), Ok(8 << 30));
        assert_eq!(byte_size("512 MiB"), Ok(512 << 20));
        for bad in ["0", "0G", "-1G", "1.5G", "8X", "", "99999999999T", "inf"] {
            assert!(byte_size(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn counts_are_checked_against_their_range() {
        assert_eq!(count_in("4", 1..=8), Ok(4));
        for bad in ["0", "9", "-1", "1.5", "18446744073709551616"] {
            assert!(count_in(bad, 1..=8).is_err(), "{bad}");
        }
    }
}
