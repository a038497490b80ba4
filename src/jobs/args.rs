//! Remote-method arguments, read at the boundary: macros send every parameter as a string
//! (`BED="60"`), HTTP callers send JSON numbers; names arrive in any case. Each calibration
//! parses its calls into typed requests with these readers, so the messages are the same from
//! a macro, the HTTP API or Moonraker's `/server/extensions/request`. Unknown names are refused
//! by name.

use std::collections::BTreeMap;

use serde_json::Value;

use super::user;

/// One call's arguments, names lower-cased.
#[derive(Debug, Clone, Default)]
pub struct Args {
    map: BTreeMap<String, Value>,
}

impl Args {
    /// Reads `args` (an object, or null for none), refusing names not in `allowed` with the
    /// list of what `command` takes.
    ///
    /// # Errors
    /// Not an object, or an unknown argument.
    pub fn parse(args: &Value, command: &str, allowed: &[&str]) -> anyhow::Result<Self> {
        let obj = match args {
            Value::Null => return Ok(Self::default()),
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
            if !allowed.contains(&key.as_str()) {
                let names: Vec<String> = allowed.iter().map(|a| a.to_uppercase()).collect();
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
        Ok(Self { map })
    }

    /// The raw value, when given and not empty.
    #[must_use]
    pub fn raw(&self, key: &str) -> Option<&Value> {
        match self.map.get(key) {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) if s.trim().is_empty() => None,
            Some(v) => Some(v),
        }
    }

    /// A number (`60`, `"60"`), when given.
    ///
    /// # Errors
    /// A value that is not a finite number, named with an example.
    pub fn num(&self, key: &str, example: &str) -> anyhow::Result<Option<f64>> {
        let bad = |shown: &str| {
            user(format!(
                "{}={shown} is not a number; expected e.g. {}={example}",
                key.to_uppercase(),
                key.to_uppercase()
            ))
        };
        match self.raw(key) {
            None => Ok(None),
            Some(Value::Number(n)) => n.as_f64().map(Some).ok_or_else(|| bad(&n.to_string())),
            Some(Value::String(s)) => s
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .map(Some)
                .ok_or_else(|| bad(s)),
            Some(other) => Err(bad(&other.to_string())),
        }
    }

    /// A whole number, when given.
    ///
    /// # Errors
    /// Not a whole number.
    pub fn int(&self, key: &str, example: &str) -> anyhow::Result<Option<i64>> {
        match self.num(key, example)? {
            None => Ok(None),
            Some(v) if v.fract() == 0.0 && v.abs() < 1e15 => Ok(Some(v as i64)),
            Some(v) => Err(user(format!(
                "{}={v} is not a whole number; expected e.g. {}={example}",
                key.to_uppercase(),
                key.to_uppercase()
            ))),
        }
    }

    /// A word or text, trimmed, when given.
    #[must_use]
    pub fn text(&self, key: &str) -> Option<String> {
        match self.raw(key)? {
            Value::String(s) => Some(s.trim().to_string()),
            Value::Number(n) => Some(n.to_string()),
            Value::Bool(b) => Some(b.to_string()),
            other => Some(other.to_string()),
        }
    }

    /// A yes/no flag: `1`/`0`, `true`/`false`, `yes`/`no`; absent is no.
    ///
    /// # Errors
    /// Any other value.
    pub fn flag(&self, key: &str) -> anyhow::Result<bool> {
        match self.raw(key) {
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
                    _ => Err(user(format!("{}={t}: expected 1 or 0", key.to_uppercase()))),
                }
            }
        }
    }

    /// One of `choices` (case-insensitive), when given.
    ///
    /// # Errors
    /// Anything else, with the choices.
    pub fn choice(&self, key: &str, choices: &[&str]) -> anyhow::Result<Option<String>> {
        match self.text(key) {
            None => Ok(None),
            Some(t) => choices
                .iter()
                .find(|c| c.eq_ignore_ascii_case(&t))
                .map(|c| Some((*c).to_string()))
                .ok_or_else(|| {
                    user(format!(
                        "{}={t}: expected {}",
                        key.to_uppercase(),
                        choices.join(" or ")
                    ))
                }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::is_user_error;
    use serde_json::json;

    #[test]
    fn macro_arguments_arrive_as_strings_and_are_parsed_with_clear_errors() {
        let a = Args::parse(
            &json!({"bed": "60", "EXTRUDER": 215, "layout": "FULL", "force": "1"}),
            "KLIPCAL_AB_START",
            &["bed", "extruder", "layout", "force"],
        )
        .unwrap();
        assert_eq!(a.num("bed", "60").unwrap(), Some(60.0));
        assert_eq!(a.num("extruder", "215").unwrap(), Some(215.0));
        assert_eq!(
            a.choice("layout", &["paper", "full"]).unwrap().as_deref(),
            Some("full")
        );
        assert!(a.flag("force").unwrap());
        let a = Args::parse(&json!({"bed": "hot"}), "X", &["bed"]).unwrap();
        let err = a.num("bed", "60").unwrap_err();
        assert_eq!(
            err.to_string(),
            "BED=hot is not a number; expected e.g. BED=60"
        );
        assert!(is_user_error(&err));
    }

    #[test]
    fn unknown_arguments_are_refused_by_name_with_what_is_taken() {
        let err = Args::parse(
            &json!({"bde": 60}),
            "KLIPCAL_AB_START",
            &["bed", "extruder"],
        )
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "KLIPCAL_AB_START: unknown argument BDE; it takes BED, EXTRUDER"
        );
    }

    #[test]
    fn an_argument_given_twice_in_two_cases_is_refused_by_name() {
        let err = Args::parse(&json!({"bed": 60, "BED": 70}), "C", &["bed"]).unwrap_err();
        assert_eq!(err.to_string(), "C: argument BED given twice; give it once");
    }

    #[test]
    fn empty_values_count_as_not_given_and_bad_flags_are_refused() {
        let a = Args::parse(&json!({"force": "", "x": "maybe"}), "C", &["force", "x"]).unwrap();
        assert!(!a.flag("force").unwrap());
        assert!(a.flag("x").unwrap_err().to_string().contains("X=maybe"));
    }
}
