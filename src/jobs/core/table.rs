//! The command table: every operation declared once — its remote method, its macro, its HTTP
//! path, and its arguments (type, range or choices, the sentence of help a macro field shows).
//! The agent's routing and the methods registered with Moonraker, the HTTP API, the page's
//! operation forms, `config/klipcal.cfg` (`klipcal macros`) and docs/operations.md's table (checked by
//! a test) all come from it. A call is read at the boundary by [`Args::parse`] against its
//! [`OpSpec`], which refuses unknown arguments by name, and each getter checks its argument's
//! range as it reads it (as Klipper's `gcmd.get_float('X', above=0.)` does); each calibration
//! then builds its typed call (`AbCall`, `MeshCall`, …) from the checked arguments, so no
//! handler reads raw JSON.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use serde_json::Value;

use super::user;

/// What an argument holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ArgKind {
    /// A number within `min..=max`.
    Number { min: f64, max: f64 },
    /// A whole number within `min..=max`.
    Whole { min: i64, max: i64 },
    /// `1` or `0` (also `true`/`false`, `yes`/`no`, `on`/`off`); absent is no.
    Flag,
    /// One of these words, case-insensitive.
    Choice(&'static [&'static str]),
    /// A word or text the calibration reads itself (a pair name, an axis).
    Text,
    /// Caliper readings: one text of items, or a JSON list of fields.
    Readings,
}

/// One argument of an operation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArgSpec {
    /// Its name, lower case (macros send it upper case).
    pub name: &'static str,
    /// What it holds.
    pub kind: ArgKind,
    /// A typical value, as a user types it (`60`, `A-D1`).
    pub example: &'static str,
    /// What is expected, as an error says it after "expected" (`a bed temperature from 0
    /// (unheated) to 130 °C`).
    pub expect: &'static str,
    /// The value the macro field shows when none is typed (`""`: klipcal's own default,
    /// from klipcal.toml).
    pub default: &'static str,
    /// The sentence of help a macro field and the page's form show.
    pub help: &'static str,
}

/// How the macro's G-code reaches klipcal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MacroBody {
    /// Says it asked the service, then calls the remote method with every parameter; `before`
    /// and `after` are G-code lines around the call (`after` runs while klipcal works: a remote
    /// call does not wait).
    Remote {
        before: &'static [&'static str],
        after: &'static [&'static str],
    },
    /// G-code only, without klipcal (a dialog's own buttons, a value kept in Klipper).
    Local(&'static [&'static str]),
}

/// The plain remote call.
pub(crate) const REMOTE: MacroBody = MacroBody::Remote {
    before: &[],
    after: &[],
};

/// One operation, declared once.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpSpec {
    /// The remote method (`klipcal_ab_start`); `None` for a macro that runs in Klipper alone.
    pub method: Option<&'static str>,
    /// The macro (`KLIPCAL_AB_START`); a leading `_` hides it from the front ends' macro panels.
    pub macro_name: &'static str,
    /// The daemon's HTTP path under `/api/` (`ab/start`), when it has one.
    pub http: Option<&'static str>,
    /// What it does: the macro's description and the page form's title.
    pub summary: &'static str,
    /// Its arguments.
    pub args: &'static [ArgSpec],
    /// The macro's G-code.
    pub body: MacroBody,
    /// `variable_*` lines of the macro (`("x", "0.0")`).
    pub variables: &'static [(&'static str, &'static str)],
    /// Comment lines written above the macro's G-code.
    pub comment: &'static [&'static str],
    /// Answered by the agent itself, before any session is looked at (`klipcal_status`: the
    /// printer's summary around the sessions; it answers without a session database, and a
    /// dialog's `ASK=` is not one of its arguments).
    pub by_agent: bool,
    /// A second HTTP path that is this operation with one flag set (`ab/clear` is
    /// `ab/measure` with `clear`).
    pub alias: Option<Alias>,
    /// Called from klipcal's page, its answer is said on the console too (a user at the
    /// printer's front end sees why a session stopped).
    pub echo: Option<Echo>,
}

/// A second HTTP path of an operation, with one of its flags set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Alias {
    /// The path under `/api/` (`ab/clear`).
    pub http: &'static str,
    /// The flag it sets to 1 (`clear`).
    pub sets: &'static str,
}

/// What the console says when an operation is called from klipcal's page.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Echo {
    /// Said when the answer has no message.
    pub fallback: &'static str,
    /// Put after the message, in brackets.
    pub note: &'static str,
}

impl OpSpec {
    /// An operation with a remote method, a macro and an HTTP path, every argument passed on.
    #[must_use]
    pub(crate) const fn remote(
        method: &'static str,
        macro_name: &'static str,
        http: &'static str,
        summary: &'static str,
        args: &'static [ArgSpec],
    ) -> Self {
        Self {
            method: Some(method),
            macro_name,
            http: Some(http),
            summary,
            args,
            body: REMOTE,
            variables: &[],
            comment: &[],
            by_agent: false,
            alias: None,
            echo: None,
        }
    }

    /// A macro that runs in Klipper alone: no remote method, no HTTP path.
    #[must_use]
    pub(crate) const fn local(
        macro_name: &'static str,
        summary: &'static str,
        args: &'static [ArgSpec],
        gcode: &'static [&'static str],
    ) -> Self {
        Self {
            method: None,
            macro_name,
            http: None,
            summary,
            args,
            body: MacroBody::Local(gcode),
            variables: &[],
            comment: &[],
            by_agent: false,
            alias: None,
            echo: None,
        }
    }

    /// The argument named `name`.
    #[must_use]
    pub(crate) fn arg(&self, name: &str) -> Option<&'static ArgSpec> {
        self.args.iter().find(|a| a.name == name)
    }
}

/// An operation and how its checked arguments become the calibration's typed call.
pub struct Op<C: 'static> {
    /// The declaration.
    pub spec: OpSpec,
    /// Builds the typed call from the checked arguments.
    pub parse: fn(&Args) -> anyhow::Result<C>,
}

/// The declarations of `ops`.
pub(crate) fn specs<C>(ops: &'static [Op<C>]) -> impl Iterator<Item = &'static OpSpec> {
    ops.iter().map(|o| &o.spec)
}

/// One call's arguments, names lower-cased, checked against their [`OpSpec`]: macros send
/// every parameter as a string (`BED="60"`), HTTP callers send JSON numbers; names arrive in
/// any case.
#[derive(Debug, Clone)]
pub struct Args {
    spec: &'static OpSpec,
    map: BTreeMap<String, Value>,
}

impl Args {
    /// Reads `args` (an object, or null for none), refusing names `spec` does not take with the
    /// list of what it takes.
    ///
    /// # Errors
    /// Not an object, an unknown argument, or one given twice.
    pub(crate) fn parse(args: &Value, spec: &'static OpSpec) -> anyhow::Result<Self> {
        let command = spec.macro_name;
        let obj = match args {
            Value::Null => &serde_json::Map::new(),
            Value::Object(o) => o,
            other => {
                return Err(user(format!(
                    "{command}: arguments must be named (an object), got {other}"
                )))
            }
        };
        let mut map = BTreeMap::new();
        for (k, v) in obj {
            let key = k.to_lowercase();
            if spec.arg(&key).is_none() {
                let names: Vec<String> = spec.args.iter().map(|a| a.name.to_uppercase()).collect();
                return Err(user(format!(
                    "{command}: unknown argument {}; it takes {}",
                    k.to_uppercase(),
                    if names.is_empty() {
                        "no arguments".to_string()
                    } else {
                        names.join(", ")
                    }
                )));
            }
            if map.insert(key, v.clone()).is_some() {
                return Err(user(format!(
                    "{command}: argument {} given twice; give it once",
                    k.to_uppercase()
                )));
            }
        }
        for a in spec.args {
            let given = match map.get(a.name) {
                None | Some(Value::Null) => false,
                Some(Value::String(s)) => !s.trim().is_empty(),
                Some(_) => true,
            };
            if !given && !a.default.is_empty() {
                map.insert(a.name.to_string(), Value::String(a.default.to_string()));
            }
        }
        Ok(Self { spec, map })
    }

    /// The value of `a`, when given and not empty; `a` must be one of the operation's own
    /// declared arguments (each getter takes the declaration, never a name, so a key that is
    /// not declared does not compile).
    fn given(&self, a: &'static ArgSpec) -> Option<&Value> {
        debug_assert!(
            self.spec.args.iter().any(|d| std::ptr::eq(d, a) || d == a),
            "{} is not an argument of {}",
            a.name,
            self.spec.macro_name
        );
        match self.map.get(a.name) {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) if s.trim().is_empty() => None,
            Some(v) => Some(v),
        }
    }

    /// The raw value, when given and not empty.
    #[must_use]
    pub(crate) fn raw(&self, a: &'static ArgSpec) -> Option<&Value> {
        self.given(a)
    }

    /// A number (`60`, `"60"`) within its declared range, when given.
    ///
    /// # Errors
    /// Not a finite number (named with an example), or out of range (with what is expected).
    pub(crate) fn num(&self, a: &'static ArgSpec) -> anyhow::Result<Option<f64>> {
        let name = a.name.to_uppercase();
        let bad = |shown: &str| {
            user(format!(
                "{name}={shown} is not a number; expected e.g. {name}={}",
                a.example
            ))
        };
        let v = match self.given(a) {
            None => return Ok(None),
            Some(Value::Number(n)) => n.as_f64().ok_or_else(|| bad(&n.to_string()))?,
            Some(Value::String(s)) => s
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| bad(s))?,
            Some(other) => return Err(bad(&other.to_string())),
        };
        match a.kind {
            ArgKind::Number { min, max } if !(min..=max).contains(&v) => {
                Err(user(format!("{name}={v}: expected {}", a.expect)))
            }
            _ => Ok(Some(v)),
        }
    }

    /// A whole number within its declared range, when given.
    ///
    /// # Errors
    /// Not a whole number, or out of range.
    pub(crate) fn int(&self, a: &'static ArgSpec) -> anyhow::Result<Option<i64>> {
        let name = a.name.to_uppercase();
        let v = match self.num(a)? {
            None => return Ok(None),
            Some(v) if v.fract() == 0.0 && v.abs() < 1e15 => v as i64,
            Some(v) => {
                return Err(user(format!(
                    "{name}={v} is not a whole number; expected e.g. {name}={}",
                    a.example
                )))
            }
        };
        match a.kind {
            ArgKind::Whole { min, max } if !(min..=max).contains(&v) => {
                Err(user(format!("{name}={v}: expected {}", a.expect)))
            }
            _ => Ok(Some(v)),
        }
    }

    /// A count (a whole number of at least 0 in its declared range), when given.
    ///
    /// # Errors
    /// Not a whole number, or out of range (the declaration's words).
    pub(crate) fn count(&self, a: &'static ArgSpec) -> anyhow::Result<Option<usize>> {
        self.int(a)?
            .map(|c| {
                usize::try_from(c).map_err(|_| {
                    user(format!(
                        "{}={c}: expected {}",
                        a.name.to_uppercase(),
                        a.expect
                    ))
                })
            })
            .transpose()
    }

    /// A word or text, trimmed, when given.
    #[must_use]
    pub(crate) fn text(&self, a: &'static ArgSpec) -> Option<String> {
        match self.given(a)? {
            Value::String(s) => Some(s.trim().to_string()),
            Value::Number(n) => Some(n.to_string()),
            Value::Bool(b) => Some(b.to_string()),
            other => Some(other.to_string()),
        }
    }

    /// A word or text that must be given: `{MACRO}: {NAME} is required; expected …` (the
    /// declaration's words) when it is not.
    ///
    /// # Errors
    /// Not given.
    pub(crate) fn required_text(&self, a: &'static ArgSpec) -> anyhow::Result<String> {
        self.text(a).ok_or_else(|| {
            user(format!(
                "{}: {} is required; expected {}",
                self.spec.macro_name,
                a.name.to_uppercase(),
                a.expect
            ))
        })
    }

    /// A yes/no flag: `1`/`0`, `true`/`false`, `yes`/`no`; absent is no.
    ///
    /// # Errors
    /// Any other value.
    pub(crate) fn flag(&self, a: &'static ArgSpec) -> anyhow::Result<bool> {
        match self.given(a) {
            None => Ok(false),
            Some(Value::Bool(b)) => Ok(*b),
            Some(v) => {
                let t = match v {
                    Value::String(s) => s.trim().to_lowercase(),
                    other => other.to_string(),
                };
                match t.as_str() {
                    "1" | "true" | "yes" | "on" => Ok(true),
                    "0" | "false" | "no" | "off" => Ok(false),
                    _ => Err(user(format!(
                        "{}={t}: expected 1 or 0",
                        a.name.to_uppercase()
                    ))),
                }
            }
        }
    }

    /// One of the argument's choices (case-insensitive), when given.
    ///
    /// # Errors
    /// Anything else, with what is expected.
    pub(crate) fn choice(&self, a: &'static ArgSpec) -> anyhow::Result<Option<&'static str>> {
        let ArgKind::Choice(choices) = a.kind else {
            return Ok(None);
        };
        match self.text(a) {
            None => Ok(None),
            Some(t) => choices
                .iter()
                .find(|c| c.eq_ignore_ascii_case(&t))
                .map(|c| Some(*c))
                .ok_or_else(|| {
                    user(format!(
                        "{}={t}: expected {}",
                        a.name.to_uppercase(),
                        a.expect
                    ))
                }),
        }
    }

    /// Readings as typed: a JSON list gives one field each, a text its items
    /// ([`crate::calib::entry::items`]).
    #[must_use]
    pub(crate) fn fields(&self, a: &'static ArgSpec) -> Option<Fields> {
        match self.given(a)? {
            Value::Array(list) => Some(Fields::List(
                list.iter()
                    .map(|v| match v {
                        Value::String(s) => s.clone(),
                        other => other.to_string(),
                    })
                    .collect(),
            )),
            Value::String(t) => Some(Fields::Text(t.clone())),
            other => Some(Fields::Text(other.to_string())),
        }
    }
}

/// Readings as they arrived.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Fields {
    /// One reading per field (the page's form, a JSON list).
    List(Vec<String>),
    /// One text of items (the console's `VALUES=`).
    Text(String),
}

/// An argument declaration, for the tables' brevity.
#[must_use]
pub(crate) const fn arg(
    name: &'static str,
    kind: ArgKind,
    example: &'static str,
    expect: &'static str,
    default: &'static str,
    help: &'static str,
) -> ArgSpec {
    ArgSpec {
        name,
        kind,
        example,
        expect,
        default,
        help,
    }
}

/// `BED=`: a bed temperature from 0 (unheated) to 130 °C; `help` names the calibration's
/// own default.
#[must_use]
pub(crate) const fn bed_arg(help: &'static str) -> ArgSpec {
    arg(
        "bed",
        ArgKind::Number {
            min: 0.0,
            max: 130.0,
        },
        "60",
        "a bed temperature from 0 (unheated) to 130 °C",
        "",
        help,
    )
}

/// The line every remote macro a user calls says first when the service has not said for a
/// while that it answers (`_KLIPCAL_ONLINE`): if nothing follows, the service is not
/// running. Helpers (`_KLIPCAL_…`, pressed in klipcal's dialogs) and a press of a dialog's
/// button (`ASK=n`) do not say it.
pub(crate) const ASKING: &str = "RESPOND PREFIX=klipcal MSG=\"asking the klipcal service...\"";

/// The condition a macro adds to say [`ASKING`] only once the service's word in
/// `_KLIPCAL_ONLINE` has run out (it renews it every few seconds while it answers).
const ONLINE_UNTIL: &str = " and not printer[\"gcode_macro _KLIPCAL_ONLINE\"].on";

/// The timer that ends the service's word: Klipper's own clock, pushed back by each
/// `_KLIPCAL_ONLINE` (a macro has no clock to read; the toolhead's estimated print time stands
/// still on a Klipper without a real MCU).
const OFFLINE_TIMER: &str = "
[delayed_gcode _KLIPCAL_OFFLINE]
# Runs once klipcal has not said for SECONDS (30) that it answers: its macros say
# \"asking the klipcal service...\" again from then.
gcode:
  SET_GCODE_VARIABLE MACRO=_KLIPCAL_ONLINE VARIABLE=on VALUE=0
";

/// `config/klipcal.cfg` for `ops`: one `[gcode_macro]` per operation, one
/// `{% set … = params.X|default(…) %}` statement per argument (how Mainsail and Fluidd find a
/// macro's fields), then the remote call with every parameter (klipcal refuses unknown ones
/// by name) or the macro's own G-code (which refuses unknown parameters itself).
#[must_use]
pub(crate) fn macros_cfg(ops: &[&OpSpec]) -> String {
    let mut out = String::from(HEADER);
    let online = ops
        .iter()
        .any(|o| o.macro_name == crate::moonraker::ONLINE_MACRO);
    for op in ops {
        out.push('\n');
        let _ = writeln!(out, "[gcode_macro {}]", op.macro_name);
        let _ = writeln!(out, "description: klipcal: {}", op.summary);
        for line in op.comment {
            let _ = writeln!(out, "# {line}");
        }
        for (k, v) in op.variables {
            let _ = writeln!(out, "variable_{k}: {v}");
        }
        out.push_str("gcode:\n");
        // A local macro's own G-code reads its parameters (with its own defaults).
        let remote = matches!(op.body, MacroBody::Remote { .. });
        for a in op.args.iter().filter(|_| remote) {
            let _ = writeln!(
                out,
                "  {{% set {} = params.{}|default({:?}) %}}",
                a.name,
                a.name.to_uppercase(),
                a.default
            );
        }
        match op.body {
            MacroBody::Remote { before, after } => {
                for l in before {
                    let _ = writeln!(out, "  {l}");
                }
                // A helper (leading `_`) is pressed in one of klipcal's dialogs, which the
                // service just sent: it says nothing first (issue 26 A.4: a backlash axis's
                // ~130 jog presses added an "asking" row each).
                // Nor does a macro pressed in a dialog (its button carries `ASK=n`, the number
                // of the question klipcal just asked; issue 40 item 6: four "asking" rows a
                // round); typed or from the macro panel it does.
                // Nor while the service says it is there (`_KLIPCAL_ONLINE`, renewed every few
                // seconds on Klipper's API socket): issue 40 item 6, six rows of a round.
                if !op.macro_name.starts_with('_') {
                    let _ = writeln!(
                        out,
                        "  {{% if '{ASK}' not in params{online} %}}\n  {ASKING}\n  {{% endif %}}",
                        ASK = crate::jobs::core::console::ASK_ARG,
                        online = if online { ONLINE_UNTIL } else { "" }
                    );
                }
                let _ = writeln!(
                    out,
                    "  {{action_call_remote_method({:?}, **params)}}",
                    op.method.unwrap_or_default()
                );
                for l in after {
                    let _ = writeln!(out, "  {l}");
                }
            }
            MacroBody::Local(lines) => {
                local_body(&mut out, op, lines);
                if op.macro_name == crate::moonraker::ONLINE_MACRO {
                    out.push_str(OFFLINE_TIMER);
                }
            }
        }
    }
    out
}

/// A local macro's G-code: unknown parameters refused by name, then its lines.
fn local_body(out: &mut String, op: &OpSpec, lines: &[&str]) {
    // ASK: the question number a dialog's button adds (any macro takes it).
    let names: Vec<String> = op
        .args
        .iter()
        .map(|a| format!("{:?}", a.name.to_uppercase()))
        .chain([format!("{:?}", super::console::ASK_ARG)])
        .collect();
    let takes = if op.args.is_empty() {
        "no arguments".to_string()
    } else {
        op.args
            .iter()
            .map(|a| a.name.to_uppercase())
            .collect::<Vec<_>>()
            .join(", ")
    };
    let _ = writeln!(
        out,
        "  {{% for name in params if name not in [{}] %}}",
        names.join(", ")
    );
    let _ = writeln!(
        out,
        "  {{action_raise_error(\"{}: unknown argument \" ~ name ~ \"; it takes {takes}\")}}",
        op.macro_name
    );
    out.push_str("  {% endfor %}\n");
    for l in lines {
        let _ = writeln!(out, "  {l}");
    }
}

/// How an argument is described in the docs and the page: `60 (0–130)`, `paper\|full`.
#[must_use]
pub(crate) fn arg_form(a: &ArgSpec) -> String {
    let what = match a.kind {
        ArgKind::Number { min, max } => format!("number {min}..{max}"),
        ArgKind::Whole { min, max } => format!("whole number {min}..{max}"),
        ArgKind::Flag => "1 or 0".to_string(),
        ArgKind::Choice(c) => c.join(" or "),
        ArgKind::Text => format!("text, e.g. {}", a.example),
        ArgKind::Readings => format!("readings, e.g. {}", a.example),
    };
    if a.default.is_empty() {
        what
    } else {
        format!("{what}, default {}", a.default)
    }
}

/// The table of every operation in docs/operations.md (between the markers
/// `<!-- operations -->` and `<!-- /operations -->`; a test keeps the two the same): macro,
/// remote method, HTTP path, arguments, what it does.
#[must_use]
pub(crate) fn markdown(ops: &[&OpSpec]) -> String {
    let cell = |t: &str| t.replace('|', "\\|");
    let mut out = String::from(
        "| macro | remote method | HTTP (`POST /api/…`) | arguments | what it does |\n|---|---|---|---|---|\n",
    );
    for op in ops {
        let args: Vec<String> = op
            .args
            .iter()
            .map(|a| {
                format!(
                    "`{}` ({}): {}",
                    a.name.to_uppercase(),
                    cell(&arg_form(a)),
                    cell(a.help)
                )
            })
            .collect();
        let _ = writeln!(
            out,
            "| `{}` | {} | {} | {} | {} |",
            op.macro_name,
            op.method.map_or("—".to_string(), |m| format!("`{m}`")),
            op.http.map_or("—".to_string(), |h| format!("`{h}`")),
            if args.is_empty() {
                "—".to_string()
            } else {
                args.join("<br>")
            },
            cell(op.summary)
        );
    }
    out
}

const START: &str = "<!-- operations -->\n";
const END: &str = "<!-- /operations -->";

/// Where the operations table of a page stands: the byte range between its markers.
fn table_span(page: &str) -> Option<std::ops::Range<usize>> {
    let from = page.find(START)? + START.len();
    let len = page[from..].find(END)?;
    Some(from..from + len)
}

/// The operations table of a page: the text between its markers.
#[must_use]
#[cfg(test)]
pub(crate) fn between_markers(page: &str) -> Option<&str> {
    table_span(page).map(|r| &page[r])
}

/// The page with `table` between its markers in place of what stood there.
///
/// # Errors
/// A page without both markers, in that order (the message names them).
pub(crate) fn with_table(page: &str, table: &str) -> Result<String, String> {
    let r = table_span(page).ok_or_else(|| {
        format!(
            "no `{}` … `{END}` markers to put the table between",
            START.trim()
        )
    })?;
    Ok(format!("{}{table}{}", &page[..r.start], &page[r.end..]))
}

const HEADER: &str = "\
# klipcal macros for Klipper. Add to printer.cfg:
#   [include klipcal.cfg]
# They become buttons in Mainsail and Fluidd. Each calls the klipcal daemon through
# Moonraker (action_call_remote_method); klipcal answers on the console with RESPOND,
# so [respond] must be enabled in printer.cfg. While the klipcal service answers it says so
# every few seconds (_KLIPCAL_ONLINE); once it has not for 30 s, each macro first says it
# asked the service: if nothing follows, the service is not running (see
# docs/troubleshooting.md). A button of klipcal's dialogs (ASK=n) never does.
# Every parameter sits on its own `{% set … = params.X|default(…) %}` line, so Mainsail
# and Fluidd show a field for it; every parameter goes to klipcal, which refuses unknown
# ones and bad values by name (a typo never falls back to a default).
#
# Generated from klipcal's command table: `klipcal macros > klipcal.cfg` writes it again.
";

/// Why a G-code line of a macro would not reach Klipper as written: Klipper's G-code parser
/// (klippy/gcode.py) ends a command at `;` anywhere on the line (also inside a RESPOND
/// message), and `#`/`*` likewise outside of a Jinja expression. `None` when the line is safe.
#[must_use]
#[cfg(test)]
pub(crate) fn gcode_line_problem(line: &str) -> Option<String> {
    let t = line.trim();
    if t.starts_with("{%") || t.starts_with('{') && t.ends_with('}') {
        // Jinja statements and expressions are rendered before Klipper parses the line; their
        // own text (an error message in action_raise_error) never reaches the G-code parser.
        return None;
    }
    t.find([';', '#', '*']).map(|i| {
        format!(
            "`{}` at column {} ends the command for Klipper",
            &t[i..=i],
            i + 1
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::is_user_error;
    use serde_json::json;

    const BED: ArgSpec = bed_arg("bed temperature");
    const LAYOUT: ArgSpec = arg(
        "layout",
        ArgKind::Choice(&["paper", "full"]),
        "paper",
        "paper or full",
        "",
        "layout",
    );
    const FORCE: ArgSpec = arg("force", ArgKind::Flag, "1", "1 or 0", "0", "force");
    const CYCLES: ArgSpec = arg(
        "cycles",
        ArgKind::Whole { min: 1, max: 50 },
        "5",
        "1..50",
        "",
        "cycles",
    );
    static START: OpSpec = OpSpec::remote(
        "klipcal_x",
        "KLIPCAL_AB_START",
        "x",
        "x",
        &[BED, LAYOUT, FORCE, CYCLES],
    );

    #[test]
    fn macro_arguments_arrive_as_strings_and_are_parsed_with_clear_errors() {
        let a = Args::parse(
            &json!({"bed": "60", "LAYOUT": "FULL", "force": "1", "cycles": 5}),
            &START,
        )
        .unwrap();
        assert_eq!(a.num(&BED).unwrap(), Some(60.0));
        assert_eq!(a.choice(&LAYOUT).unwrap(), Some("full"));
        assert!(a.flag(&FORCE).unwrap());
        assert_eq!(a.int(&CYCLES).unwrap(), Some(5));
        let a = Args::parse(&json!({"bed": "hot"}), &START).unwrap();
        let err = a.num(&BED).unwrap_err();
        assert_eq!(
            err.to_string(),
            "BED=hot is not a number; expected e.g. BED=60"
        );
        assert!(is_user_error(&err));
    }

    #[test]
    fn the_getters_check_the_declared_range_as_they_read() {
        let a = Args::parse(
            &json!({"bed": "200", "cycles": "0", "layout": "wide"}),
            &START,
        )
        .unwrap();
        assert_eq!(
            a.num(&BED).unwrap_err().to_string(),
            "BED=200: expected a bed temperature from 0 (unheated) to 130 °C"
        );
        assert_eq!(
            a.int(&CYCLES).unwrap_err().to_string(),
            "CYCLES=0: expected 1..50"
        );
        assert_eq!(
            a.choice(&LAYOUT).unwrap_err().to_string(),
            "LAYOUT=wide: expected paper or full"
        );
        let a = Args::parse(&json!({"cycles": "2.5"}), &START).unwrap();
        assert!(a.int(&CYCLES).unwrap_err().to_string().contains("whole"));
    }

    #[test]
    fn unknown_arguments_are_refused_by_name_with_what_is_taken() {
        let err = Args::parse(&json!({"bde": 60}), &START).unwrap_err();
        assert_eq!(
            err.to_string(),
            "KLIPCAL_AB_START: unknown argument BDE; it takes BED, LAYOUT, FORCE, CYCLES"
        );
    }

    #[test]
    fn an_argument_given_twice_in_two_cases_is_refused_by_name() {
        let err = Args::parse(&json!({"bed": 60, "BED": 70}), &START).unwrap_err();
        assert_eq!(
            err.to_string(),
            "KLIPCAL_AB_START: argument BED given twice; give it once"
        );
    }

    #[test]
    fn empty_values_count_as_not_given_and_bad_flags_are_refused() {
        let a = Args::parse(&json!({"force": "", "bed": " "}), &START).unwrap();
        assert!(!a.flag(&FORCE).unwrap());
        assert_eq!(a.num(&BED).unwrap(), None);
        let a = Args::parse(&json!({"force": "maybe"}), &START).unwrap();
        assert!(a
            .flag(&FORCE)
            .unwrap_err()
            .to_string()
            .contains("FORCE=maybe"));
    }

    #[test]
    fn a_semicolon_hash_or_star_in_a_gcode_line_is_found_and_jinja_is_not() {
        assert!(gcode_line_problem("RESPOND MSG=\"paused; resumes\"").is_some());
        assert!(gcode_line_problem("RESPOND MSG=\"a # b\"").is_some());
        assert!(gcode_line_problem("RESPOND MSG=\"paused, resumes\"").is_none());
        assert!(gcode_line_problem("{action_raise_error(\"x; y\")}").is_none());
        assert!(gcode_line_problem("{% set a = params.A|default(\"\") %}").is_none());
    }
}
