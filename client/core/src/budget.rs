//! The GPU budget a client gives a scene (`--gpu-budget`, the page's `?budget=`): how many
//! bytes of GPU memory its copy of the scene may take. Within a budget the server streams a
//! working set (level 0 near the eye, coarser further away) and follows the camera; unlimited,
//! the client holds every brick. A scene that fits half the budget is served whole.

/// The native viewer's and `render`'s budget when none is given: 1 GiB. wgpu does not say how
/// much memory an adapter has; a quarter of a 4 GiB card (the smallest common discrete GPU)
/// leaves the rest to the frame and other programs. A scene that fits half of it is served
/// whole, as without a budget; a larger world streams a working set instead of failing.
pub const NATIVE_DEFAULT: u64 = 1 << 30;
/// The browser viewer's budget when the page gives none: 256 MiB, safe on phone-class GPUs.
pub const BROWSER_DEFAULT: u64 = 256 << 20;

/// Parses a budget: `unlimited`, a byte count, or a number with a unit (`K`, `M`, `G`, with or
/// without `iB`/`B`, powers of 1024): `256MiB`, `1G`, `300000000`. `None` is unlimited.
pub fn parse_budget(text: &str) -> Result<Option<u64>, String> {
    let t = text.trim();
    if t.eq_ignore_ascii_case("unlimited") || t.eq_ignore_ascii_case("none") {
        return Ok(None);
    }
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let unit = unit.trim().to_ascii_lowercase();
    let scale: u64 = match unit.trim_end_matches("ib").trim_end_matches('b') {
        "" => 1,
        "k" => 1 << 10,
        "m" => 1 << 20,
        "g" => 1 << 30,
        _ => {
            return Err(format!(
                "{text:?}: a GPU budget is `unlimited` or a size such as 256MiB, 1G or 300000000 (bytes)"
            ));
        }
    };
    let value: f64 = number
        .parse()
        .map_err(|_| format!("{text:?}: a GPU budget is `unlimited` or a size such as 256MiB"))?;
    let bytes = value * scale as f64;
    if !bytes.is_finite() || bytes < 1.0 || bytes > u64::MAX as f64 {
        return Err(format!("{text:?}: a GPU budget must be at least one byte"));
    }
    Ok(Some(bytes as u64))
}

#[cfg(test)]
mod tests {
    use super::parse_budget;

    #[test]
    fn budgets_parse_with_units_and_refuse_nonsense() {
        assert_eq!(parse_budget("unlimited"), Ok(None));
        assert_eq!(parse_budget("256MiB"), Ok(Some(256 << 20)));
        assert_eq!(parse_budget("256M"), Ok(Some(256 << 20)));
        assert_eq!(parse_budget("1.5 GiB"), Ok(Some(3 << 29)));
        assert_eq!(parse_budget("4096"), Ok(Some(4096)));
        assert_eq!(parse_budget("64kb"), Ok(Some(64 << 10)));
        for bad in ["", "lots", "12 parsecs", "0", "-5M", "MiB"] {
            assert!(parse_budget(bad).is_err(), "{bad:?}");
        }
    }
}

/// A parsed `--gpu-budget` (`None`: unlimited), for command lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct GpuBudget(pub Option<u64>);

impl std::str::FromStr for GpuBudget {
    type Err = String;
    fn from_str(s: &str) -> Result<GpuBudget, String> {
        parse_budget(s).map(GpuBudget)
    }
}

impl std::fmt::Display for GpuBudget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            None => f.write_str("unlimited"),
            Some(b) if b % (1 << 20) == 0 => write!(f, "{}MiB", b >> 20),
            Some(b) => write!(f, "{b}"),
        }
    }
}
