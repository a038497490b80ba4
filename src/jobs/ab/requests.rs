//! The A/B operations' requests, typed at the boundary from the command table's arguments.

use super::*;

/// `klipcal_ab_start` / `KLIPCAL_AB_START`.
#[derive(Debug, Clone, PartialEq)]
pub struct StartRequest {
    /// Bed temperature, °C (0: unheated).
    pub bed_temp_c: Option<f64>,
    /// Nozzle temperature, °C.
    pub nozzle_temp_c: Option<f64>,
    /// `paper` or `full`.
    pub layout: Option<String>,
}

impl StartRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// A bad or unknown argument, named.
    pub(crate) fn from_args(a: &Args) -> anyhow::Result<Self> {
        Ok(Self {
            bed_temp_c: a.num("bed")?,
            nozzle_temp_c: a.num("extruder")?,
            layout: a.choice("layout")?.map(str::to_string),
        })
    }
}

/// `klipcal_measure` / `KLIPCAL_MEASURE`.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasureRequest {
    /// The pair id as typed.
    pub pair: String,
    /// The readings as typed, each with where it was typed ([`readings_typed`]).
    pub values: Vec<entry::Item>,
    /// Remove the pair's readings first (to enter them again, or to drop a wrong one).
    pub clear: bool,
    /// Typed on a line (`VALUES=` or `VALUE=` text: a macro, the console), not as fields.
    pub typed_line: bool,
}

impl MeasureRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// No pair, a bad CLEAR, or an unknown argument.
    pub(crate) fn from_args(a: &Args) -> anyhow::Result<Self> {
        let pair = a.text("pair").ok_or_else(|| {
            user("no PAIR given; expected e.g. KLIPCAL_MEASURE PAIR=A-D1 VALUES=10.02,10.03,10.01")
        })?;
        let mut values = readings_typed(a.raw("values"), "VALUES");
        values.extend(readings_typed(a.raw("value"), "VALUE"));
        let line = |k: &str| matches!(a.raw(k), Some(Value::String(_)));
        Ok(Self {
            pair,
            values,
            clear: a.flag("clear")?,
            typed_line: line("values") || line("value"),
        })
    }
}

/// Readings as an argument carries them: a list of fields (the page, the API: one reading
/// each, a comma is its decimal mark), the console's `VALUES=` text (a list: commas separate,
/// a dot is the decimal mark) or `VALUE=` text (one reading).
pub(super) fn readings_typed(v: Option<&Value>, key: &str) -> Vec<entry::Item> {
    match v {
        Some(Value::Array(list)) => list
            .iter()
            .enumerate()
            .filter_map(|(i, v)| match v {
                Value::String(s) => entry::field(s, i + 1),
                Value::Number(n) => n
                    .as_f64()
                    .map(|x| entry::sent_number(x, &format!("field {}", i + 1))),
                other => entry::field(&other.to_string(), i + 1),
            })
            .collect(),
        Some(Value::String(t)) if key == "VALUES" => entry::list(t),
        Some(Value::String(t)) => entry::single(t, key),
        Some(Value::Null) | None => Vec::new(),
        Some(Value::Number(n)) => n
            .as_f64()
            .map(|x| entry::sent_number(x, key))
            .into_iter()
            .collect(),
        Some(other) => entry::single(&other.to_string(), key),
    }
}

/// `klipcal_apply` / `KLIPCAL_AB_APPLY`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ApplyRequest {
    /// Apply a change beyond `ab.max_change_pct`.
    pub force: bool,
}

impl ApplyRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// A bad FORCE, or an unknown argument.
    pub(crate) fn from_args(a: &Args) -> anyhow::Result<Self> {
        Ok(Self {
            force: a.flag("force")?,
        })
    }
}

/// `klipcal_ab_check` / `KLIPCAL_AB_CHECK`.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckRequest {
    /// The pair id as typed.
    pub pair: String,
    /// The readings as typed, each with where it was typed.
    pub items: Vec<entry::Item>,
    /// The page's fields as sent (blank ones too), when the readings came as a list.
    pub fields: Option<Vec<String>>,
}

impl CheckRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// No pair.
    pub(crate) fn from_args(a: &Args) -> anyhow::Result<Self> {
        let pair = a.text("pair").ok_or_else(|| {
            user("no PAIR given; expected e.g. KLIPCAL_AB_CHECK PAIR=A-D1 VALUES=10.02,10.03")
        })?;
        let fields = match a.fields("values") {
            Some(Fields::List(list)) => Some(list),
            _ => None,
        };
        Ok(Self {
            pair,
            items: readings_typed(a.raw("values"), "VALUES"),
            fields,
        })
    }
}
