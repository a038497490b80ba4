//! G-code command lines built from typed values: checked names, numbers without exponents,
//! quoted text that Klipper's parser reads back unchanged. PURE; never pastes unchecked text.
//!
//! Klipper's rules this follows (klippy/gcode.py 0.12): an extended command line is
//! `NAME args` where everything from the first `#`, `*` or `;` is a comment or checksum, and the
//! args are split with Python `shlex` (posix) into `KEY=value` words; a double-quoted value may
//! hold spaces and `'` but a `"` or `\` inside would change the quoting. RESPOND
//! (klippy/extras/respond.py) takes `TYPE=echo|echo_no_space|command|error`, `PREFIX=` and `MSG=`.

use super::Error;

/// Decimals used by [`GcodeCmd::num`]: enough for µm on mm values and 1e-6 on ratios.
pub const DEFAULT_DECIMALS: u8 = 6;

/// The prefix klipcal's console messages carry (`RESPOND PREFIX=klipcal MSG="..."`).
pub const RESPOND_PREFIX: &str = "klipcal";

/// A G-code command line under construction. Methods chain; the first error is kept and
/// returned by [`GcodeCmd::build`].
///
/// ```
/// use klipcal_core::klipper::gcode_cmd::GcodeCmd;
/// let line = GcodeCmd::new("SET_HEATER_TEMPERATURE")
///     .word("HEATER", "heater_bed")
///     .num("TARGET", 60.0)
///     .build()
///     .unwrap();
/// assert_eq!(line, "SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=60");
/// ```
#[derive(Debug)]
#[must_use = "call .build() to get the line"]
pub struct GcodeCmd {
    line: String,
    error: Option<Error>,
}

impl GcodeCmd {
    /// Starts a command; `name` must match `[A-Za-z0-9_.-]+`.
    pub fn new(name: &str) -> GcodeCmd {
        let mut cmd = GcodeCmd {
            line: String::new(),
            error: None,
        };
        match check_name("command name", name) {
            Ok(()) => cmd.line.push_str(name),
            Err(e) => cmd.error = Some(e),
        }
        cmd
    }

    /// `KEY=value` with at most [`DEFAULT_DECIMALS`] decimals.
    pub fn num(self, key: &str, value: f64) -> GcodeCmd {
        self.num_decimals(key, value, DEFAULT_DECIMALS)
    }

    /// `KEY=value` with at most `max_decimals` decimals (trailing zeros dropped).
    pub fn num_decimals(self, key: &str, value: f64, max_decimals: u8) -> GcodeCmd {
        self.param(key, || {
            format_num(value, max_decimals).map_err(|e| with_key(e, key))
        })
    }

    /// `KEY=value` for an integer.
    #[cfg(test)]
    pub fn int(self, key: &str, value: i64) -> GcodeCmd {
        self.param(key, || Ok(value.to_string()))
    }

    /// `KEY=a,b,c` (as `SET_SKEW XY=` takes), each with at most [`DEFAULT_DECIMALS`] decimals.
    pub fn nums(self, key: &str, values: &[f64]) -> GcodeCmd {
        self.param(key, || {
            let parts: Result<Vec<String>, Error> = values
                .iter()
                .map(|v| format_num(*v, DEFAULT_DECIMALS).map_err(|e| with_key(e, key)))
                .collect();
            Ok(parts?.join(","))
        })
    }

    /// `KEY=value` where the value is a name (`heater_bed`, `command`): `[A-Za-z0-9_.-]+`.
    pub fn word(self, key: &str, value: &str) -> GcodeCmd {
        self.param(key, || {
            check_name("value", value)?;
            Ok(value.to_string())
        })
    }

    /// `KEY="text"`; refuses text Klipper would not read back unchanged (see [`check_text`]).
    pub fn text(self, key: &str, value: &str) -> GcodeCmd {
        self.param(key, || {
            check_text(value).map_err(|reason| Error::BadText {
                key: key.to_string(),
                value: value.to_string(),
                reason,
            })?;
            Ok(format!("\"{value}\""))
        })
    }

    /// `KEY="text"` after [`sanitize_text`] (for text that came from elsewhere, e.g. a file name).
    pub fn text_lossy(self, key: &str, value: &str) -> GcodeCmd {
        let clean = sanitize_text(value);
        self.text(key, &clean)
    }

    /// A classic axis word, ` X12.5` (for `G1`, `G0`, `G92`…): `letter` must be A–Z.
    pub fn axis(mut self, letter: char, value: f64) -> GcodeCmd {
        if self.error.is_some() {
            return self;
        }
        if !letter.is_ascii_uppercase() {
            self.error = Some(Error::BadName {
                what: "axis letter".into(),
                name: letter.to_string(),
            });
            return self;
        }
        match format_num(value, DEFAULT_DECIMALS) {
            Ok(v) => {
                self.line.push(' ');
                self.line.push(letter);
                self.line.push_str(&v);
            }
            Err(e) => self.error = Some(with_key(e, &letter.to_string())),
        }
        self
    }

    /// The finished line (no newline).
    ///
    /// # Errors
    /// The first [`Error::BadName`], [`Error::BadNumber`] or [`Error::BadText`] met.
    pub fn build(self) -> Result<String, Error> {
        match self.error {
            Some(e) => Err(e),
            None => Ok(self.line),
        }
    }

    fn param(mut self, key: &str, value: impl FnOnce() -> Result<String, Error>) -> GcodeCmd {
        if self.error.is_some() {
            return self;
        }
        let result = check_name("parameter name", key).and_then(|()| value());
        match result {
            Ok(v) => {
                self.line.push(' ');
                self.line.push_str(key);
                self.line.push('=');
                self.line.push_str(&v);
            }
            Err(e) => self.error = Some(e),
        }
        self
    }
}

/// Formats a finite number with at most `max_decimals` decimals, trailing zeros and a
/// trailing `.` removed, never an exponent; `-0` is written `0`.
///
/// # Errors
/// [`Error::BadNumber`] for NaN or infinity.
pub fn format_num(value: f64, max_decimals: u8) -> Result<String, Error> {
    if !value.is_finite() {
        return Err(Error::BadNumber {
            key: String::new(),
            value,
        });
    }
    let mut s = format!("{:.*}", usize::from(max_decimals), value);
    if s.contains('.') {
        let trimmed = s.trim_end_matches('0').trim_end_matches('.').len();
        s.truncate(trimmed);
    }
    if s == "-0" {
        s = "0".to_string();
    }
    Ok(s)
}

/// Why `text` cannot be sent inside `"..."` unchanged, or Ok when it can: no control
/// characters (line breaks end the command), no `"` or `\` (they change shlex quoting), no
/// `#`, `*` or `;` (Klipper cuts the line there).
///
/// # Errors
/// A sentence naming the offending character.
pub fn check_text(text: &str) -> Result<(), String> {
    for c in text.chars() {
        let why = match c {
            c if c.is_control() => "control characters such as line breaks end the command",
            '"' | '\\' => "'\"' and '\\' would change the quoting",
            '#' | '*' | ';' => "Klipper reads '#', '*' and ';' as the end of the command",
            _ => continue,
        };
        return Err(format!("{c:?} is not allowed: {why}"));
    }
    Ok(())
}

/// Replaces what [`check_text`] refuses: control characters → space, `"` → `'`, `\` → `/`,
/// `#` → space, `*` → `x`, `;` → `,`.
pub fn sanitize_text(text: &str) -> String {
    text.chars()
        .map(|c| match c {
            c if c.is_control() => ' ',
            '"' => '\'',
            '\\' => '/',
            '#' => ' ',
            '*' => 'x',
            ';' => ',',
            c => c,
        })
        .collect()
}

/// `SET_SKEW XY=<ac>,<bd>,<ad>`: the measured diagonal and side lengths of the skew test
/// square in mm (klippy/extras/skew_correction.py).
///
/// # Errors
/// [`Error::BadNumber`] for a non-finite length.
pub fn set_skew_xy(ac_mm: f64, bd_mm: f64, ad_mm: f64) -> Result<String, Error> {
    GcodeCmd::new("SET_SKEW")
        .nums("XY", &[ac_mm, bd_mm, ad_mm])
        .build()
}

/// `RESPOND PREFIX=klipcal MSG="..."`: a console message from klipcal.
///
/// # Errors
/// [`Error::BadText`] when `msg` fails [`check_text`].
#[cfg(test)]
pub fn respond(msg: &str) -> Result<String, Error> {
    GcodeCmd::new("RESPOND")
        .word("PREFIX", RESPOND_PREFIX)
        .text("MSG", msg)
        .build()
}

/// `RESPOND TYPE=command MSG="action:<action>"`: a host action, e.g. the Mainsail/Fluidd
/// prompt actions `prompt_begin Title`, `prompt_text ...`, `prompt_button Label|GCODE|primary`,
/// `prompt_show`, `prompt_end`.
///
/// # Errors
/// [`Error::BadText`] when the text fails [`check_text`].
pub fn respond_action(action: &str) -> Result<String, Error> {
    GcodeCmd::new("RESPOND")
        .word("TYPE", "command")
        .text("MSG", &format!("action:{action}"))
        .build()
}

/// `SET_IDLE_TIMEOUT TIMEOUT=<s>`.
///
/// # Errors
/// [`Error::BadNumber`] for a non-finite timeout.
pub fn set_idle_timeout(timeout_s: f64) -> Result<String, Error> {
    GcodeCmd::new("SET_IDLE_TIMEOUT")
        .num_decimals("TIMEOUT", timeout_s, 0)
        .build()
}

/// What Kalico's `[idle_timeout] timeout: 0` means (never time out) said the only way
/// `SET_IDLE_TIMEOUT` takes it: its TIMEOUT must be above 0, so ten years, longer than any
/// Klipper runs between restarts.
pub const IDLE_TIMEOUT_NEVER_S: f64 = 10.0 * 365.0 * 86_400.0;

/// The command that puts Klipper's idle timeout back to its configured `timeout` (s): that
/// value, or for Kalico's `timeout: 0` (disabled; the 2023 Klipper refuses 0 in the config)
/// [`IDLE_TIMEOUT_NEVER_S`], which Klipper accepts where it refuses `TIMEOUT=0`.
///
/// # Errors
/// [`Error::BadNumber`] for a non-finite timeout.
pub fn restore_idle_timeout(configured_s: f64) -> Result<String, Error> {
    if configured_s > 0.0 || !configured_s.is_finite() {
        set_idle_timeout(configured_s)
    } else {
        set_idle_timeout(IDLE_TIMEOUT_NEVER_S)
    }
}

/// `SET_HEATER_TEMPERATURE HEATER=<heater> TARGET=<°C>`.
///
/// # Errors
/// [`Error::BadName`] for a heater name outside `[A-Za-z0-9_.-]`, [`Error::BadNumber`].
pub fn set_heater_temperature(heater: &str, target_c: f64) -> Result<String, Error> {
    GcodeCmd::new("SET_HEATER_TEMPERATURE")
        .word("HEATER", heater)
        .num_decimals("TARGET", target_c, 2)
        .build()
}

fn check_name(what: &str, name: &str) -> Result<(), Error> {
    let ok = !name.is_empty()
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '-'));
    if ok {
        Ok(())
    } else {
        Err(Error::BadName {
            what: what.to_string(),
            name: name.to_string(),
        })
    }
}

fn with_key(e: Error, key: &str) -> Error {
    match e {
        Error::BadNumber { value, .. } => Error::BadNumber {
            key: key.to_string(),
            value,
        },
        other => other,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Klipper's extended-parameter parsing (gcode.py `extended_r` + shlex), enough to read
    /// back `KEY=value` and `KEY="quoted value"` words.
    fn klipper_params(line: &str) -> Vec<(String, String)> {
        let cut = line.find(['#', '*', ';']).unwrap_or(line.len());
        let args = line[..cut].split_once(' ').map_or("", |(_, a)| a);
        let mut out = Vec::new();
        let mut word = String::new();
        let mut quoted = false;
        let mut words = Vec::new();
        for c in args.chars() {
            match c {
                '"' => quoted = !quoted,
                ' ' if !quoted => {
                    if !word.is_empty() {
                        words.push(std::mem::take(&mut word));
                    }
                }
                c => word.push(c),
            }
        }
        if !word.is_empty() {
            words.push(word);
        }
        for w in words {
            let (k, v) = w.split_once('=').unwrap();
            out.push((k.to_uppercase(), v.to_string()));
        }
        out
    }

    #[test]
    fn numbers_have_no_exponent_and_no_trailing_zeros() {
        assert_eq!(format_num(1e-7, 6).unwrap(), "0");
        assert_eq!(format_num(1.5e9, 6).unwrap(), "1500000000");
        assert_eq!(format_num(40.102_891_7, 4).unwrap(), "40.1029");
        assert_eq!(format_num(-0.000_000_1, 3).unwrap(), "0");
        assert_eq!(format_num(-2.5, 3).unwrap(), "-2.5");
        assert_eq!(format_num(60.0, 2).unwrap(), "60");
        assert!(matches!(
            format_num(f64::NAN, 3),
            Err(Error::BadNumber { .. })
        ));
    }

    #[test]
    fn set_skew_lists_the_three_lengths() {
        let line = set_skew_xy(140.4, 142.0, 99.8).unwrap();
        assert_eq!(line, "SET_SKEW XY=140.4,142,99.8");
        assert_eq!(
            klipper_params(&line),
            vec![("XY".into(), "140.4,142,99.8".into())]
        );
        assert!(set_skew_xy(f64::INFINITY, 1.0, 1.0).is_err());
    }

    #[test]
    fn respond_messages_read_back_unchanged_through_klipper_parsing() {
        let msg = "Pylon pair A: d2-d1 = 140.012 mm (it's fine)";
        let line = respond(msg).unwrap();
        assert_eq!(line, format!("RESPOND PREFIX=klipcal MSG=\"{msg}\""));
        assert_eq!(
            klipper_params(&line),
            vec![
                ("PREFIX".into(), "klipcal".into()),
                ("MSG".into(), msg.into())
            ]
        );
    }

    #[test]
    fn prompt_actions_use_respond_type_command() {
        let line = respond_action("prompt_begin klipcal: measure pylons").unwrap();
        assert_eq!(
            line,
            "RESPOND TYPE=command MSG=\"action:prompt_begin klipcal: measure pylons\""
        );
        let button = respond_action("prompt_button Continue|KLIPCAL_CONTINUE|primary").unwrap();
        assert_eq!(
            klipper_params(&button)[1].1,
            "action:prompt_button Continue|KLIPCAL_CONTINUE|primary"
        );
    }

    #[test]
    fn text_that_would_break_the_line_is_refused_or_replaced() {
        for bad in [
            "two\nlines",
            "say \"hi\"",
            "a;b",
            "50% # done",
            "a*b",
            "back\\slash",
            "cr\r",
        ] {
            let r = respond(bad);
            assert!(matches!(r, Err(Error::BadText { .. })), "{bad:?}: {r:?}");
        }
        let line = GcodeCmd::new("RESPOND")
            .text_lossy("MSG", "file \"a;b\"\nnext")
            .build()
            .unwrap();
        assert_eq!(line, "RESPOND MSG=\"file 'a,b' next\"");
        assert_eq!(
            klipper_params(&line),
            vec![("MSG".into(), "file 'a,b' next".into())]
        );
    }

    #[test]
    fn a_disabled_idle_timeout_is_restored_as_never_not_as_a_refused_zero() {
        assert_eq!(
            restore_idle_timeout(600.0).unwrap(),
            "SET_IDLE_TIMEOUT TIMEOUT=600"
        );
        assert_eq!(
            restore_idle_timeout(0.0).unwrap(),
            "SET_IDLE_TIMEOUT TIMEOUT=315360000"
        );
        assert!(restore_idle_timeout(f64::NAN).is_err());
    }

    #[test]
    fn idle_timeout_and_heater_commands() {
        assert_eq!(
            set_idle_timeout(3600.0).unwrap(),
            "SET_IDLE_TIMEOUT TIMEOUT=3600"
        );
        assert_eq!(
            set_heater_temperature("heater_bed", 60.004).unwrap(),
            "SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=60"
        );
        assert!(matches!(
            set_heater_temperature("heater bed", 60.0),
            Err(Error::BadName { .. })
        ));
    }

    #[test]
    fn names_outside_the_allowed_characters_are_refused() {
        assert!(matches!(
            GcodeCmd::new("G1;M112").build(),
            Err(Error::BadName { .. })
        ));
        assert!(matches!(
            GcodeCmd::new("").build(),
            Err(Error::BadName { .. })
        ));
        let r = GcodeCmd::new("SET_X").num("A B", 1.0).build();
        assert!(matches!(r, Err(Error::BadName { .. })), "{r:?}");
        let r = GcodeCmd::new("SET_X").word("K", "x=1").build();
        assert!(matches!(r, Err(Error::BadName { .. })), "{r:?}");
    }

    #[test]
    fn the_first_error_is_kept_and_names_the_parameter() {
        let err = GcodeCmd::new("SET_X")
            .num("SPEED", f64::NAN)
            .word("BAD NAME", "x")
            .build()
            .unwrap_err();
        assert!(
            matches!(err, Error::BadNumber { ref key, .. } if key == "SPEED"),
            "{err}"
        );
    }

    #[test]
    fn classic_moves_use_axis_words() {
        let line = GcodeCmd::new("G1")
            .axis('X', 10.5)
            .axis('Y', -0.25)
            .axis('F', 3600.0)
            .build()
            .unwrap();
        assert_eq!(line, "G1 X10.5 Y-0.25 F3600");
        assert!(GcodeCmd::new("G1").axis('x', 1.0).build().is_err());
        assert_eq!(
            GcodeCmd::new("M400").int("N", -3).build().unwrap(),
            "M400 N=-3"
        );
    }
}
