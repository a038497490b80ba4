//! The A/B operations' requests, typed at the boundary from the command table's arguments.

use super::*;
use crate::jobs::core::table::ArgSpec;

/// `EXTRUDER=` of KLIPCAL_AB_START.
pub(super) const EXTRUDER: ArgSpec = arg(
    "extruder",
    ArgKind::Number {
        min: 150.0,
        max: 320.0,
    },
    "215",
    "a nozzle temperature from 150 to 320 °C",
    "",
    "nozzle temperature, °C (default ab.nozzle_temp_c)",
);
/// `LAYOUT=` of KLIPCAL_AB_START.
pub(super) const LAYOUT: ArgSpec = arg(
    "layout",
    ArgKind::Choice(&["paper", "full"]),
    "paper",
    "paper or full",
    "",
    "paper: the paper's pylons; full: also observes shear",
);
/// `VALUES=` of KLIPCAL_MEASURE.
pub(super) const VALUES: ArgSpec = arg(
    "values",
    ArgKind::Readings,
    "10.02,10.03,10.01",
    "readings separated by commas, e.g. 10.02,10.03",
    "",
    "the readings as the caliper shows them: commas between, a dot as the decimal mark",
);
/// `VALUE=` of KLIPCAL_MEASURE.
pub(super) const VALUE: ArgSpec = arg(
    "value",
    ArgKind::Readings,
    "10.02",
    "one reading, e.g. 10.02",
    "",
    "one reading (its comma is the decimal mark: 10,02 is 10.02)",
);
/// `CLEAR=` of KLIPCAL_MEASURE.
pub(super) const CLEAR: ArgSpec = arg(
    "clear",
    ArgKind::Flag,
    "1",
    "1 or 0",
    "0",
    "1: remove the pair's readings first",
);
/// `VALUES=` of KLIPCAL_AB_CHECK.
pub(super) const CHECK_VALUES: ArgSpec = arg(
    "values",
    ArgKind::Readings,
    "10.02,10.03",
    "readings separated by commas, e.g. 10.02,10.03",
    "",
    "the readings, separated by commas",
);
/// `CHOICE=` of KLIPCAL_SOAK_CHOICE.
pub(super) const CHOICE: ArgSpec = arg(
    "choice",
    ArgKind::Choice(&["print", "wait"]),
    "wait",
    "print or wait",
    "wait",
    "print: print now; wait: go on waiting (10 min more at the soak limit)",
);
/// `FORCE=` of KLIPCAL_AB_APPLY.
pub(super) const FORCE: ArgSpec = arg(
    "force",
    ArgKind::Flag,
    "1",
    "1 or 0",
    "0",
    "1: apply a change beyond ab.max_change_pct",
);

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
            bed_temp_c: a.num(&BED)?,
            nozzle_temp_c: a.num(&EXTRUDER)?,
            layout: a.choice(&LAYOUT)?.map(str::to_string),
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
        let pair = a.text(&PAIR).ok_or_else(|| {
            user("no PAIR given; expected e.g. KLIPCAL_MEASURE PAIR=A-D1 VALUES=10.02,10.03,10.01")
        })?;
        let mut values = readings_typed(a.raw(&VALUES), "VALUES");
        values.extend(readings_typed(a.raw(&VALUE), "VALUE"));
        let line = |k: &'static ArgSpec| matches!(a.raw(k), Some(Value::String(_)));
        Ok(Self {
            pair,
            values,
            clear: a.flag(&CLEAR)?,
            typed_line: line(&VALUES) || line(&VALUE),
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
            force: a.flag(&FORCE)?,
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
        let pair = a.text(&PAIR).ok_or_else(|| {
            user("no PAIR given; expected e.g. KLIPCAL_AB_CHECK PAIR=A-D1 VALUES=10.02,10.03")
        })?;
        let fields = match a.fields(&CHECK_VALUES) {
            Some(Fields::List(list)) => Some(list),
            _ => None,
        };
        Ok(Self {
            pair,
            items: readings_typed(a.raw(&CHECK_VALUES), "VALUES"),
            fields,
        })
    }
}
