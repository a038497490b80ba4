//! PURE: one entry of caliper readings as a person types it, taken whole or refused whole.
//!
//! The rules, decided one by one:
//! - items are separated by `,`, `;` or white space; a trailing or doubled separator is
//!   tolerated (`10.02,,10.03,` is two readings);
//! - a dot is the decimal mark; a unit `mm` may follow a number, with or without a space
//!   (`10.02mm`, `10.02 mm`); any other letters, an exponent (`1e1`), a sign, or two dots are
//!   refused;
//! - at most [`MAX_ITEMS`] readings in one entry;
//! - every reading must lie in the pair's plausibility window: nominal ± (the absolute
//!   tolerance + nominal × the largest change the calibration allows), so a real change up to
//!   the change limit can always be entered;
//! - when any item is refused, nothing of the entry is kept, and the answer names the item
//!   and why; when two neighbouring items joined with a dot would be a plausible reading
//!   (`150,69`), the answer says "use a dot: 150.69".

/// Most readings one entry may carry.
pub const MAX_ITEMS: usize = 50;

/// A pair's plausibility window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    /// Nominal distance, mm.
    pub nominal_mm: f64,
    /// Absolute tolerance, mm (the floor of the window).
    pub tolerance_mm: f64,
    /// Largest change of scale the calibration allows, percent.
    pub max_change_pct: f64,
}

impl Window {
    /// Half-width of the window, mm.
    #[must_use]
    pub fn half_width_mm(&self) -> f64 {
        self.tolerance_mm + self.nominal_mm * self.max_change_pct / 100.0
    }

    /// Whether `v` lies in the window.
    #[must_use]
    pub fn contains(&self, v: f64) -> bool {
        (v - self.nominal_mm).abs() <= self.half_width_mm()
    }
}

/// Why an entry was refused; the text says what was wrong and what is expected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Refused(pub String);

/// Splits an entry into its items.
#[must_use]
pub fn items(text: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for raw in text.split([',', ';', ' ', '\t', '\n', '\r']) {
        let item = raw.trim();
        if item.is_empty() {
            continue;
        }
        // `10.02 mm`: a lone unit belongs to the number before it.
        if item.eq_ignore_ascii_case("mm") {
            if let Some(last) = out.last_mut() {
                if !last.to_ascii_lowercase().ends_with("mm") {
                    last.push_str("mm");
                    continue;
                }
            }
        }
        out.push(item.to_string());
    }
    out
}

/// One item as a number of mm, or why not.
fn number(item: &str) -> Result<f64, String> {
    let digits = item
        .strip_suffix("mm")
        .or_else(|| item.strip_suffix("MM"))
        .or_else(|| item.strip_suffix("Mm"))
        .unwrap_or(item);
    if digits.is_empty() {
        return Err("a unit without a number".into());
    }
    if !digits.chars().all(|c| c.is_ascii_digit() || c == '.') {
        return Err(
            "not a number; write millimetres with a dot as the decimal mark, e.g. 10.02".into(),
        );
    }
    if digits.matches('.').count() > 1 {
        return Err("two decimal marks".into());
    }
    if !digits.chars().any(|c| c.is_ascii_digit()) {
        return Err("not a number".into());
    }
    digits
        .parse::<f64>()
        .map_err(|_| "not a number".to_string())
}

/// Parses a whole entry for one pair: every reading, or a refusal naming the first bad item.
///
/// # Errors
/// [`Refused`] when the entry is empty, too long, or any item is not a plausible reading.
pub fn parse(items: &[String], pair: &str, window: &Window) -> Result<Vec<f64>, Refused> {
    if items.is_empty() {
        return Err(Refused(format!(
            "no reading for {pair}; expected VALUES={} (mm, a dot as decimal mark)",
            example(window.nominal_mm)
        )));
    }
    if items.len() > MAX_ITEMS {
        return Err(Refused(format!(
            "{} readings in one entry for {pair}; at most {MAX_ITEMS}",
            items.len()
        )));
    }
    let mut values = Vec::with_capacity(items.len());
    for (i, item) in items.iter().enumerate() {
        let problem = match number(item) {
            Ok(v) if v <= 0.0 => "a reading must be a distance above 0 mm".to_string(),
            Ok(v) if !window.contains(v) => format!(
                "outside the plausible {:.2}–{:.2} mm for {pair} (nominal {} mm); measure outer \
                 face to outer face",
                window.nominal_mm - window.half_width_mm(),
                window.nominal_mm + window.half_width_mm(),
                fmt_mm(window.nominal_mm)
            ),
            Ok(v) => {
                values.push(v);
                continue;
            }
            Err(why) => why,
        };
        let mut msg = format!(
            "{pair}: nothing saved; item {} \"{item}\": {problem}",
            i + 1
        );
        if let Some(joined) = comma_decimal(items, window) {
            msg.push_str(&format!(
                ". It looks like a comma was used as the decimal mark: use a dot: {joined}"
            ));
        }
        return Err(Refused(msg));
    }
    Ok(values)
}

/// Two neighbouring items that, joined with a dot, make a plausible reading (`150`, `69`).
fn comma_decimal(items: &[String], window: &Window) -> Option<String> {
    items.windows(2).find_map(|w| {
        let (a, b) = (&w[0], &w[1]);
        let ok = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_digit());
        let b_digits = b.strip_suffix("mm").unwrap_or(b);
        if !(ok(a) && ok(b_digits)) {
            return None;
        }
        let joined = format!("{a}.{b_digits}");
        let v: f64 = joined.parse().ok()?;
        window.contains(v).then_some(joined)
    })
}

/// A distance in mm with at most 3 decimals and no trailing zeros (`150`, `10.02`).
#[must_use]
pub fn fmt_mm(v: f64) -> String {
    let s = format!("{v:.3}");
    let s = s.trim_end_matches('0');
    s.trim_end_matches('.').to_string()
}

/// A rotation distance as klipcal shows and writes it everywhere (console, page, config):
/// to the micron of a 40 mm pulley's travel and more (6 decimals), trailing zeros dropped
/// (`40`, `40.102895`).
#[must_use]
pub fn fmt_rd(v: f64) -> String {
    let s = format!("{v:.6}");
    let s = s.trim_end_matches('0');
    s.trim_end_matches('.').to_string()
}

/// An example entry that fits a pair (`10.02,10.03,10.01`).
#[must_use]
pub fn example(nominal_mm: f64) -> String {
    [0.02, 0.03, 0.01]
        .iter()
        .map(|d| format!("{:.2}", nominal_mm + d))
        .collect::<Vec<_>>()
        .join(",")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn w(nominal_mm: f64) -> Window {
        Window {
            nominal_mm,
            tolerance_mm: 2.0,
            max_change_pct: 3.0,
        }
    }

    fn entry(text: &str, nominal: f64) -> Result<Vec<f64>, Refused> {
        parse(&items(text), "A-D2", &w(nominal))
    }

    #[test]
    fn a_comma_decimal_is_refused_whole_and_named() {
        let e = entry("150,69", 150.0).unwrap_err().0;
        assert!(e.contains("nothing saved"), "{e}");
        assert!(e.contains("use a dot: 150.69"), "{e}");
        // 150 alone would be plausible and 69 not: the entry is refused whole.
        let e = entry("150.02, 150,69", 150.0).unwrap_err().0;
        assert!(e.contains("item 3 \"69\""), "{e}");
        assert!(e.contains("use a dot: 150.69"), "{e}");
    }

    #[test]
    fn separators_units_and_trailing_commas_are_read_as_decided() {
        assert_eq!(entry("10.02,10.03;10.01 10.04", 10.0).unwrap().len(), 4);
        assert_eq!(entry("10.02,,10.03,", 10.0).unwrap(), vec![10.02, 10.03]);
        assert_eq!(
            entry("10.02mm, 10.03 mm", 10.0).unwrap(),
            vec![10.02, 10.03]
        );
        for bad in ["1e1", "10.0.2", "+10.02", "10.02cm", "ten", "mm"] {
            assert!(entry(bad, 10.0).is_err(), "{bad}");
        }
        let many = vec!["10.01"; MAX_ITEMS + 1].join(",");
        assert!(entry(&many, 10.0).unwrap_err().0.contains("at most 50"));
        assert!(entry("", 10.0)
            .unwrap_err()
            .0
            .contains("VALUES=10.02,10.03,10.01"));
        assert!(entry("", 150.0).unwrap_err().0.contains("VALUES=150.02"));
    }

    #[test]
    fn the_window_follows_the_nominal_and_the_change_limit() {
        // 150 mm, 2 mm floor + 3 % of 150 = 6.5 mm: a 2.5 % change can be entered, 4.7 % not.
        assert!(entry("153.75", 150.0).is_ok());
        assert!(entry("157.05", 150.0).is_err());
        // 10 mm: the floor dominates.
        assert!(entry("11.9", 10.0).is_ok());
        assert!(entry("12.5", 10.0).is_err());
        assert!(entry("0", 10.0).unwrap_err().0.contains("above 0 mm"));
    }

    #[test]
    fn distances_print_without_trailing_zeros() {
        assert_eq!(fmt_mm(150.0), "150");
        assert_eq!(fmt_mm(10.02), "10.02");
        assert_eq!(fmt_mm(146.4), "146.4");
    }
}
