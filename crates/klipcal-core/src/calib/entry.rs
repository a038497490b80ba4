//! PURE: one entry of caliper readings as a person types it, taken whole or refused whole.
//!
//! The grammar, decided so that no national habit can turn into a different number or a
//! different count of readings:
//! - **a field holds one reading** (the page's fields, the console's `VALUE=`): its comma can
//!   only be a decimal mark, so `10,10` is 10.10;
//! - **a list** (the console's `VALUES=`) separates readings with commas (white space too,
//!   which only reaches klipcal through the API or quoted; Klipper splits a console line at
//!   spaces), so its decimal mark is the dot;
//! - **every reading is written as the caliper shows it, with its decimals** (`10.10`, not
//!   `10`), and with no more decimals than the caliper has (`ab.caliper_resolution_mm`: 0.01 mm
//!   shows 2). A comma used as a decimal mark in a list therefore always leaves an item without
//!   decimals (`10,10` → `10` and `10`), and the entry is refused with "use a dot: 10.10";
//!   thousands separators (`1,234.56`, `1.234,56`, `1 234,56`, `1'234.56`) are refused the
//!   same way or as not a number;
//! - a unit `mm` may follow a reading (`10.10mm`, `10.10 mm`); any other unit, an exponent,
//!   a sign (`-10.05`: a reading can't be negative), two decimal marks or a `;` (Klipper's
//!   comment) is refused;
//! - at most [`MAX_ITEMS`] readings in one entry;
//! - every reading must lie in the pair's plausibility window: nominal ± (the absolute
//!   tolerance + nominal × the largest change the calibration allows), so a real change up to
//!   the change limit can always be entered;
//! - when any item is refused, nothing of the entry is kept, and the answer names the item
//!   where the user typed it (`field 2` on the page, `item 3` of a list) and why.
//!
//! `tests::no_national_style_reads_as_another_number` checks these rules on numbers written in
//! many national styles: each is read as exactly the intended values or refused whole.

/// Most readings one entry may carry.
pub const MAX_ITEMS: usize = 50;

/// A pair's plausibility window and the caliper's resolution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    /// Nominal distance, mm.
    pub nominal_mm: f64,
    /// Absolute tolerance, mm (the floor of the window).
    pub tolerance_mm: f64,
    /// Largest change of scale the calibration allows, percent.
    pub max_change_pct: f64,
    /// The caliper's last digit, mm (`ab.caliper_resolution_mm`): a reading has at most as
    /// many decimals as it.
    pub resolution_mm: f64,
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

    /// Decimals the caliper shows (0.01 mm → 2, 0.005 mm → 3).
    #[must_use]
    pub fn decimals(&self) -> usize {
        decimals_of(self.resolution_mm)
    }
}

/// Decimals of a resolution (0.01 → 2, 0.02 → 2, 0.005 → 3, 0.1 → 1), at most 6.
#[must_use]
pub fn decimals_of(resolution_mm: f64) -> usize {
    (0..=6)
        .find(|d| {
            let x = resolution_mm * 10f64.powi(*d as i32);
            (x - x.round()).abs() < 1e-6
        })
        .unwrap_or(6)
}

/// Why an entry was refused: the item, where it was typed, and what is expected (without
/// the pair or "nothing saved", which the caller adds).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Refused(pub String);

/// One reading as typed, and where.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Item {
    /// The text as typed.
    pub text: String,
    /// Where it was typed, as the answer names it (`field 2`, `item 3`, `VALUE`).
    pub label: String,
    /// A field (one reading): its comma is a decimal mark. A list's item: never.
    pub comma_is_decimal: bool,
    /// A list's item: its neighbours (for the "use a dot" hint).
    pub in_list: bool,
    /// Typed by a person (the grammar applies); false for a number a program sent (a JSON
    /// number through the API), read as it is.
    pub typed: bool,
}

/// The page's fields, one reading each: blank fields are skipped, the others keep their
/// place (`field 2` is the second field however many before it are blank).
#[cfg(test)]
#[must_use]
pub fn fields(texts: &[String]) -> Vec<Item> {
    texts
        .iter()
        .enumerate()
        .filter_map(|(i, t)| field(t, i + 1))
        .collect()
}

/// The page's field number `n` (from 1), or `None` when blank.
#[must_use]
pub fn field(text: &str, n: usize) -> Option<Item> {
    (!text.trim().is_empty()).then(|| Item {
        text: text.trim().to_string(),
        label: format!("field {n}"),
        comma_is_decimal: true,
        in_list: false,
        typed: true,
    })
}

/// A number a program sent as a number (a JSON number): no text to misread.
#[must_use]
pub fn sent_number(v: f64, label: &str) -> Item {
    Item {
        text: v.to_string(),
        label: label.to_string(),
        comma_is_decimal: false,
        in_list: false,
        typed: false,
    }
}

/// One reading typed on its own (the console's `VALUE=`): a comma is its decimal mark.
#[must_use]
pub fn single(text: &str, label: &str) -> Vec<Item> {
    if text.trim().is_empty() {
        return Vec::new();
    }
    vec![Item {
        text: text.trim().to_string(),
        label: label.to_string(),
        comma_is_decimal: true,
        in_list: false,
        typed: true,
    }]
}

/// A list of readings (the console's `VALUES=`): commas (or white space) separate them; a
/// trailing or doubled comma is tolerated; a lone `mm` belongs to the number before it.
#[must_use]
pub fn list(text: &str) -> Vec<Item> {
    let mut out: Vec<String> = Vec::new();
    for raw in text.split([',', ' ', '\t', '\n', '\r']) {
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
    out.into_iter()
        .enumerate()
        .map(|(i, text)| Item {
            text,
            label: format!("item {}", i + 1),
            comma_is_decimal: false,
            in_list: true,
            typed: true,
        })
        .collect()
}

/// A reading of about `nominal` as a caliper shows it (`10.10`, `150.10`).
fn shown(nominal_mm: f64) -> String {
    format!("{:.2}", nominal_mm + 0.1)
}

/// One item as a number of mm, or why not.
fn number(item: &Item, window: &Window) -> Result<f64, String> {
    if !item.typed {
        return match item.text.parse::<f64>() {
            Ok(v) if v.is_finite() && v < 0.0 => Err("a reading can't be negative".into()),
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err("not a number".into()),
        };
    }
    let eg = shown(window.nominal_mm);
    let t = item.text.trim();
    let t = if t.len() >= 2
        && t.is_char_boundary(t.len() - 2)
        && t[t.len() - 2..].eq_ignore_ascii_case("mm")
    {
        t[..t.len() - 2].trim_end()
    } else {
        t
    };
    if t.is_empty() {
        return Err("a unit without a number".into());
    }
    if t.contains(';') {
        return Err(
            "a semicolon does not separate readings: Klipper reads it as the start of a \
                    comment and drops the rest of the line; separate readings with commas"
                .into(),
        );
    }
    if t.starts_with('-') || t.starts_with('\u{2212}') {
        return Err(format!(
            "a reading can't be negative: write the distance as shown on the caliper, e.g. {eg}"
        ));
    }
    if t.starts_with('+') {
        return Err(format!(
            "a sign: write the reading as shown on the caliper, e.g. {eg}"
        ));
    }
    let has_comma = t.contains(',');
    if has_comma && t.contains('.') {
        return Err(format!(
            "a comma and a dot: a thousands separator? write the reading as shown on the \
             caliper, e.g. {eg}"
        ));
    }
    let digits = if item.comma_is_decimal {
        t.replace(',', ".")
    } else {
        t.to_string()
    };
    let mark = if item.comma_is_decimal {
        "a dot or a comma as the decimal mark"
    } else {
        "a dot as the decimal mark"
    };
    if !digits.chars().all(|c| c.is_ascii_digit() || c == '.') {
        return Err(format!(
            "not a number; write millimetres as shown on the caliper, with {mark}, e.g. {eg}"
        ));
    }
    if digits.matches('.').count() > 1 {
        return Err("two decimal marks".into());
    }
    let Some((whole, frac)) = digits.split_once('.') else {
        return Err(format!(
            "write the reading as shown on the caliper, with its decimals, e.g. {eg}"
        ));
    };
    if whole.is_empty() || frac.is_empty() {
        return Err(format!(
            "write the reading as shown on the caliper, e.g. {eg}"
        ));
    }
    let most = window.decimals();
    if frac.len() > most {
        return Err(format!(
            "{} decimals; a caliper reading to {} mm has at most {most} \
             (ab.caliper_resolution_mm)",
            frac.len(),
            fmt_mm(window.resolution_mm)
        ));
    }
    digits
        .parse::<f64>()
        .map_err(|_| "not a number".to_string())
}

/// Parses a whole entry for one pair: every reading, or a refusal naming the first bad item.
///
/// # Errors
/// [`Refused`] when the entry is empty, too long, or any item is not a plausible reading.
pub fn parse(items: &[Item], pair: &str, window: &Window) -> Result<Vec<f64>, Refused> {
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
    for item in items {
        let problem = match one(item, pair, window) {
            Ok(v) => {
                values.push(v);
                continue;
            }
            Err(why) => why,
        };
        let mut msg = format!("{} \"{}\": {problem}", item.label, item.text);
        if let Some(joined) = comma_decimal(items, window) {
            msg.push_str(&format!(
                ". It looks like a comma was used as the decimal mark: use a dot: {joined}"
            ));
        }
        return Err(Refused(msg));
    }
    Ok(values)
}

/// One item as a plausible reading of the pair, or why not (the problem alone).
///
/// # Errors
/// The item is not a reading as a caliper shows it, or not in the pair's window.
pub fn one(item: &Item, pair: &str, window: &Window) -> Result<f64, String> {
    match number(item, window) {
        Ok(v) if v <= 0.0 => Err("a reading must be a distance above 0 mm".to_string()),
        Ok(v) if !window.contains(v) => Err(format!(
            "outside the plausible {:.2}–{:.2} mm for {pair} (nominal {} mm); measure outer \
             face to outer face",
            window.nominal_mm - window.half_width_mm(),
            window.nominal_mm + window.half_width_mm(),
            fmt_mm(window.nominal_mm)
        )),
        other => other,
    }
}

/// Two neighbouring list items that, joined with a dot, make a plausible reading (`150`, `69`).
fn comma_decimal(items: &[Item], window: &Window) -> Option<String> {
    items.windows(2).find_map(|w| {
        let (a, b) = (&w[0], &w[1]);
        if !(a.in_list && b.in_list) {
            return None;
        }
        let ok = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_digit());
        let b_digits = b.text.strip_suffix("mm").unwrap_or(&b.text);
        if !(ok(&a.text) && ok(b_digits)) {
            return None;
        }
        let joined = format!("{}.{b_digits}", a.text);
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
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    fn w(nominal_mm: f64) -> Window {
        Window {
            nominal_mm,
            tolerance_mm: 2.0,
            max_change_pct: 3.0,
            resolution_mm: 0.01,
        }
    }

    fn entry(text: &str, nominal: f64) -> Result<Vec<f64>, Refused> {
        parse(&list(text), "A-D2", &w(nominal))
    }

    fn page(texts: &[&str], nominal: f64) -> Result<Vec<f64>, Refused> {
        let texts: Vec<String> = texts.iter().map(|s| (*s).to_string()).collect();
        parse(&fields(&texts), "A-D2", &w(nominal))
    }

    #[test]
    fn a_comma_in_a_list_is_refused_whole_and_named() {
        let e = entry("150,69", 150.0).unwrap_err().0;
        assert!(e.contains("use a dot: 150.69"), "{e}");
        assert!(e.contains("item 1 \"150\""), "{e}");
        assert!(e.contains("with its decimals, e.g. 150.10"), "{e}");
        // 150.02 alone would be plausible: the entry is refused whole.
        let e = entry("150.02, 150,69", 150.0).unwrap_err().0;
        assert!(e.contains("item 2 \"150\""), "{e}");
        assert!(e.contains("use a dot: 150.69"), "{e}");
        // The console line: four numbers that would have been read as 10 and 10 and…
        let e = entry("10,10,10,09", 10.0).unwrap_err().0;
        assert!(e.contains("use a dot: 10.10"), "{e}");
    }

    #[test]
    fn a_field_holds_one_reading_and_its_comma_is_the_decimal_mark() {
        assert_eq!(page(&["10,10"], 10.0).unwrap(), vec![10.10]);
        assert_eq!(
            page(&["10.02", "", "10,03 mm", "10.01mm"], 10.0).unwrap(),
            vec![10.02, 10.03, 10.01]
        );
        // Named by the field the user typed in (the second), not by a count of items.
        let e = page(&["150.02", "149,83", "1"], 150.0).unwrap_err().0;
        assert!(e.starts_with("field 3 \"1\""), "{e}");
        let e = page(&["150.02", "14,83"], 150.0).unwrap_err().0;
        assert!(e.starts_with("field 2 \"14,83\": outside"), "{e}");
        let e = page(&["", "10"], 10.0).unwrap_err().0;
        assert!(
            e.contains(
                "field 2 \"10\": write the reading as shown on the caliper, with its \
                        decimals, e.g. 10.10"
            ),
            "{e}"
        );
        assert!(single("10,09", "VALUE").len() == 1);
        assert_eq!(
            parse(&single("10,09", "VALUE"), "A-D1", &w(10.0)).unwrap(),
            vec![10.09]
        );
    }

    #[test]
    fn signs_units_and_decimals_are_refused_by_name() {
        let e = entry("-10.05", 10.0).unwrap_err().0;
        assert!(e.contains("a reading can't be negative"), "{e}");
        assert!(!e.contains("not a number"), "{e}");
        let e = entry("10.123", 10.0).unwrap_err().0;
        assert!(
            e.contains("3 decimals; a caliper reading to 0.01 mm has at most 2"),
            "{e}"
        );
        let fine = Window {
            resolution_mm: 0.005,
            ..w(10.0)
        };
        assert_eq!(parse(&list("10.125"), "A-D1", &fine).unwrap(), vec![10.125]);
        let e = entry("10.10;10.09", 10.0).unwrap_err().0;
        assert!(
            e.contains("Klipper reads it as the start of a comment"),
            "{e}"
        );
        for bad in [
            "1e1", "10.0.2", "+10.02", "10.02cm", "ten", "mm", "10.", ".5", "1,234.56",
        ] {
            assert!(entry(bad, 10.0).is_err(), "{bad}");
        }
        let e = page(&["1.234,56"], 10.0).unwrap_err().0;
        assert!(e.contains("a comma and a dot"), "{e}");
    }

    #[test]
    fn separators_units_and_trailing_commas_are_read_as_decided() {
        assert_eq!(entry("10.02,10.03,10.01 10.04", 10.0).unwrap().len(), 4);
        assert_eq!(entry("10.02,,10.03,", 10.0).unwrap(), vec![10.02, 10.03]);
        assert_eq!(
            entry("10.02mm, 10.03 mm", 10.0).unwrap(),
            vec![10.02, 10.03]
        );
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
        assert!(entry("11.90", 10.0).is_ok());
        assert!(entry("12.50", 10.0).is_err());
        assert!(entry("0.00", 10.0).unwrap_err().0.contains("above 0 mm"));
    }

    #[test]
    fn resolutions_have_their_decimals() {
        assert_eq!(decimals_of(0.01), 2);
        assert_eq!(decimals_of(0.02), 2);
        assert_eq!(decimals_of(0.005), 3);
        assert_eq!(decimals_of(0.1), 1);
        assert_eq!(decimals_of(0.001), 3);
    }

    /// A number with `d` decimals in a national style: the decimal mark, the thousands
    /// separator (none, `,`, `.`, space, no-break space, narrow no-break space, `'`), and
    /// whether trailing zeros are dropped.
    fn styled(v: f64, d: usize, dec: char, thou: Option<&str>, trim: bool) -> String {
        let s = format!("{:.*}", d, v.abs());
        let (whole, frac) = s.split_once('.').map_or((s.as_str(), ""), |(a, b)| (a, b));
        let mut w = String::new();
        for (i, c) in whole.chars().enumerate() {
            if i > 0 && (whole.len() - i) % 3 == 0 {
                if let Some(t) = thou {
                    w.push_str(t);
                }
            }
            w.push(c);
        }
        let frac = if trim {
            frac.trim_end_matches('0')
        } else {
            frac
        };
        let mut out = if frac.is_empty() {
            w
        } else {
            format!("{w}{dec}{frac}")
        };
        if v < 0.0 {
            out.insert(0, '-');
        }
        out
    }

    /// One value as a person might type it; whether the grammar promises to read it (in a
    /// field, `comma_ok`; in a list, only with a dot).
    fn person(rng: &mut StdRng, v: f64, d: usize) -> (String, bool, bool) {
        let thou = [
            None,
            Some(","),
            Some("."),
            Some(" "),
            Some("\u{a0}"),
            Some("\u{202f}"),
            Some("'"),
        ][rng.random_range(0..7)];
        let dec = if rng.random_bool(0.5) { '.' } else { ',' };
        let trim = rng.random_bool(0.2);
        let mut s = styled(v, d, dec, thou, trim);
        let grouped = v.abs() >= 1000.0 && thou.is_some();
        let has_decimals = s.contains(dec);
        let mut plain = !grouped && has_decimals && v > 0.0;
        match rng.random_range(0..12) {
            0 => s.push_str("mm"),
            1 => s.push_str(" mm"),
            2 => s.push_str("MM"),
            3 => {
                s = styled(v / 10.0, d + 1, dec, thou, trim) + "cm";
                plain = false;
            }
            4 => {
                s.insert(0, '+');
                plain = false;
            }
            5 => {
                s = format!("{v:e}");
                plain = false;
            }
            6 => s.insert(0, '0'),
            _ => {}
        }
        let field_ok = plain && !s.contains(' ') || (plain && s.ends_with(" mm") && !grouped);
        let list_ok = field_ok && dec == '.';
        (s, field_ok, list_ok)
    }

    #[test]
    fn no_national_style_reads_as_another_number() {
        let mut rng = StdRng::seed_from_u64(25);
        let (mut cases, mut read, mut promised) = (0, 0, 0);
        for _ in 0..40_000 {
            let resolution_mm = [0.01, 0.02, 0.1, 0.005][rng.random_range(0..4)];
            let d = decimals_of(resolution_mm);
            // Thousands groups of 3 digits look like 3 decimals: a 3-decimal caliper reads
            // only caliper-sized numbers (≤ 300 mm) in this test; see the module's rules.
            let nominal_mm: f64 = if d >= 3 || rng.random_bool(0.6) {
                [10.0, 150.0, rng.random_range(1.0..300.0)][rng.random_range(0..3)]
            } else {
                rng.random_range(1.0..20_000.0)
            };
            let window = Window {
                nominal_mm,
                tolerance_mm: 2.0,
                max_change_pct: 3.0,
                resolution_mm,
            };
            let n = rng.random_range(1..=6);
            let intended: Vec<f64> = (0..n)
                .map(|_| {
                    let v = if rng.random_bool(0.85) {
                        nominal_mm + rng.random_range(-1.0..1.0) * window.half_width_mm()
                    } else if d >= 3 {
                        rng.random_range(-300.0..300.0)
                    } else {
                        rng.random_range(-20_000.0..20_000.0)
                    };
                    let step = 10f64.powi(d as i32);
                    (v * step).round() / step
                })
                .collect();
            let typed: Vec<(String, bool, bool)> =
                intended.iter().map(|&v| person(&mut rng, v, d)).collect();
            let in_window = intended.iter().all(|&v| v > 0.0 && window.contains(v));
            let (items, promise) = match rng.random_range(0..3) {
                0 => {
                    // The page: one field each, some left blank.
                    let mut texts = Vec::new();
                    for t in &typed {
                        if rng.random_bool(0.2) {
                            texts.push(String::new());
                        }
                        texts.push(t.0.clone());
                    }
                    (fields(&texts), typed.iter().all(|t| t.1))
                }
                1 => {
                    let sep = [",", ", ", " ,", ",,", " ", ";", "/", "|", "\t", ", "]
                        [rng.random_range(0..10)];
                    let text = typed.iter().map(|t| t.0.as_str()).collect::<Vec<_>>();
                    let ok = typed.iter().all(|t| t.2 && !t.0.contains(' '))
                        && [",", ", ", " ,", ",,", " ", "\t"].contains(&sep);
                    (list(&text.join(sep)), ok)
                }
                _ => {
                    let one = &typed[0];
                    (single(&one.0, "VALUE"), one.1 && n == 1)
                }
            };
            let promise = promise && in_window;
            cases += 1;
            match parse(&items, "P", &window) {
                Ok(got) => {
                    read += 1;
                    let want = if matches!(items.first(), Some(i) if i.label == "VALUE") {
                        vec![intended[0]]
                    } else {
                        intended.clone()
                    };
                    assert_eq!(got.len(), want.len(), "{typed:?} → {got:?}");
                    for (g, v) in got.iter().zip(&want) {
                        assert!(
                            (g - v).abs() < 1e-9,
                            "{typed:?} read as {got:?}, meant {want:?}"
                        );
                    }
                }
                Err(e) => assert!(!promise, "{typed:?} refused: {}", e.0),
            }
            promised += usize::from(promise);
        }
        // Not vacuous: a good share of entries are read, every one the grammar promises.
        eprintln!("{cases} entries, {read} read, {promised} promised");
        assert!(
            read >= promised && promised > cases / 20,
            "{read} {promised} {cases}"
        );
    }
}
