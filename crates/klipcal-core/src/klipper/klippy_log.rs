//! PURE: the heated bed's history in a klippy.log. Klipper writes a `Stats <eventtime>: …` line
//! about once a second (`heater_bed: target=60 temp=59.8 pwm=0.400` among its sections) and, at
//! each start, the printer's config between `===== Config file =====` and a line of `=`; from
//! that dump come the bed's `max_power` and `control`. Text in, data out: no file is read here.

/// One `Stats` line's bed values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BedStat {
    /// Klipper's eventtime (s, monotonic within one start of Klipper).
    pub eventtime_s: f64,
    /// `heater_bed` target, °C.
    pub target_c: f64,
    /// Bed temperature, °C.
    pub temp_c: f64,
    /// Heater power, fraction of full power (already capped at `max_power` by Klipper).
    pub pwm: f64,
}

/// One start of Klipper in the log: its bed settings and bed stats.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogSession {
    /// `[heater_bed] max_power` from the config dump, when it sets one.
    pub max_power: Option<f64>,
    /// `[heater_bed] control` from the config dump (`pid`, `watermark`, …).
    pub control: Option<String>,
    /// A config dump was seen for this start (`[heater_bed]` without `max_power` then means
    /// Klipper's default, 1.0).
    pub has_config: bool,
    /// The bed's stats, eventtime increasing.
    pub stats: Vec<BedStat>,
}

const CONFIG_START: &str = "===== Config file =====";

/// Why a log gave no bed history, when the log itself says: Kalico's `[danger_options]
/// minimal_logging: True` (or `log_statistics: False`) leaves out the `Stats` lines, and
/// `log_config_file_at_startup: False` the config dump. `None` when the log has Stats lines, or
/// nothing tells why it has none.
#[must_use]
pub fn why_no_stats(text: &str) -> Option<String> {
    let has_stats = text
        .lines()
        .any(|l| l.contains("Stats ") && l.contains(": gcodein="));
    if has_stats {
        return None;
    }
    let kalico = text.contains("App Name: Kalico") || text.contains("Welcome to Kalico");
    let started = text.contains("Starting Klippy...");
    let config = text.contains(CONFIG_START);
    if kalico {
        Some(format!(
            "this Kalico log has no Stats lines{}: Kalico's [danger_options] minimal_logging: \
             True (or log_statistics: False) leaves them out; set log_statistics: True{} under \
             [danger_options] and restart Klipper, then soak the bed again",
            if config { "" } else { " and no config dump" },
            if config {
                ""
            } else {
                " and log_config_file_at_startup: True"
            },
        ))
    } else if started {
        Some(
            "Klipper started in this log but logged no Stats lines (it writes them about once \
             a second while it runs; a log cut short, or a logging setup that drops them?)"
                .to_string(),
        )
    } else {
        None
    }
}

/// Reads every start of Klipper in `text` that logged bed stats or a config. Lines may carry a
/// timestamp before `Stats` (as some logging setups add); Stats lines without a `heater_bed:`
/// section, or whose eventtime does not move forward, are skipped.
#[must_use]
pub fn parse(text: &str) -> Vec<LogSession> {
    let mut sessions: Vec<LogSession> = Vec::new();
    let mut in_config = false;
    let mut section = String::new();
    for raw in text.lines() {
        let line = raw.trim_end();
        if line.contains(CONFIG_START) {
            sessions.push(LogSession {
                has_config: true,
                ..LogSession::default()
            });
            in_config = true;
            section.clear();
            continue;
        }
        if in_config {
            let t = line.trim();
            if !t.is_empty() && t.chars().all(|c| c == '=') {
                in_config = false;
                continue;
            }
            if let Some(name) = t.strip_prefix('[').and_then(|r| r.strip_suffix(']')) {
                section = name.trim().to_ascii_lowercase();
                continue;
            }
            if section == "heater_bed" && !raw.starts_with([' ', '\t']) {
                if let Some((key, value)) = t.split_once([':', '=']) {
                    let value = value.split('#').next().unwrap_or("").trim();
                    let session = sessions.last_mut().expect("pushed at the config start");
                    match key.trim().to_ascii_lowercase().as_str() {
                        "max_power" => session.max_power = value.parse().ok(),
                        "control" => session.control = Some(value.to_ascii_lowercase()),
                        _ => {}
                    }
                }
            }
            continue;
        }
        let Some(stat) = bed_stat(line) else { continue };
        if sessions.is_empty() {
            sessions.push(LogSession::default());
        }
        let session = sessions.last_mut().expect("pushed above");
        if session
            .stats
            .last()
            .is_some_and(|s| stat.eventtime_s <= s.eventtime_s)
        {
            continue;
        }
        session.stats.push(stat);
    }
    sessions.retain(|s| s.has_config || !s.stats.is_empty());
    sessions
}

/// The bed values of one `Stats` line, if it is one and has them.
fn bed_stat(line: &str) -> Option<BedStat> {
    let at = line.find("Stats ")?;
    let rest = &line[at + "Stats ".len()..];
    let (time, body) = rest.split_once(':')?;
    let eventtime_s: f64 = time.trim().parse().ok()?;
    let bed = body.split_once("heater_bed:")?.1;
    let (mut target, mut temp, mut pwm) = (None, None, None);
    for token in bed.split_whitespace() {
        if token.ends_with(':') {
            break;
        }
        let Some((key, value)) = token.split_once('=') else {
            continue;
        };
        let value: Option<f64> = value.parse().ok().filter(|v: &f64| v.is_finite());
        match key {
            "target" => target = value,
            "temp" => temp = value,
            "pwm" => pwm = value,
            _ => {}
        }
    }
    Some(BedStat {
        eventtime_s,
        target_c: target?,
        temp_c: temp?,
        pwm: pwm?.clamp(0.0, 1.0),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOG: &str = "\
Starting Klippy...
===== Config file =====
[printer]
kinematics = corexy

[heater_bed]
heater_pin = PA1
control = pid
max_power: 0.6   # capped pad
pid_kp = 38.7
=======================
Stats 100.0: gcodein=0  mcu: mcu_awake=0.003 bytes_write=1 heater_bed: target=0 temp=21.3 pwm=0.000 sysload=0.1
Stats 101.0: gcodein=0  heater_bed: target=100 temp=21.4 pwm=0.600 extruder: target=0 temp=22.0 pwm=0.000
12:25:06.344: Stats 102.0: gcodein=0 heater_bed: target=100 temp=21.9 pwm=0.600
Stats 102.0: gcodein=0 heater_bed: target=100 temp=22.0 pwm=0.600
Stats 103.0: gcodein=0 mcu: mcu_awake=0.003
Restarting printer
===== Config file =====
[heater_bed]
control: watermark
=======================
Stats 5.0: gcodein=0 heater_bed: target=60 temp=58.0 pwm=1.000
";

    #[test]
    fn stats_and_the_beds_settings_are_read_per_start_of_klipper() {
        let s = parse(LOG);
        assert_eq!(s.len(), 2);
        assert_eq!(s[0].max_power, Some(0.6));
        assert_eq!(s[0].control.as_deref(), Some("pid"));
        // The timestamped line is read; the repeated eventtime and the line without a bed are not.
        let times: Vec<f64> = s[0].stats.iter().map(|b| b.eventtime_s).collect();
        assert_eq!(times, vec![100.0, 101.0, 102.0]);
        assert_eq!(
            s[0].stats[1],
            BedStat {
                eventtime_s: 101.0,
                target_c: 100.0,
                temp_c: 21.4,
                pwm: 0.6
            }
        );
        // After a restart: a new eventtime origin, the default max_power, the new control.
        assert_eq!(s[1].max_power, None);
        assert!(s[1].has_config);
        assert_eq!(s[1].control.as_deref(), Some("watermark"));
        assert_eq!(s[1].stats.len(), 1);
    }

    #[test]
    fn a_kalico_log_with_minimal_logging_says_why_it_has_no_stats() {
        // The head of a real Kalico 2026.10 klippy.log (the bench's, `[danger_options]
        // minimal_logging: True`): its start, no config dump, no Stats line.
        let text = "Starting Klippy...\nArgs: ['kalico', 'printer.cfg']\nApp Name: Kalico\n\
                    Git version: 'v2026.10.0'\nWelcome to Kalico\n";
        assert!(parse(text).is_empty());
        let why = why_no_stats(text).unwrap();
        assert!(
            why.contains("minimal_logging") && why.contains("log_statistics: True"),
            "{why}"
        );
        assert!(why.contains("log_config_file_at_startup: True"), "{why}");
        let with_stats = "Stats 10.0: gcodein=0  heater_bed: target=0 temp=20.0 pwm=0.000\n";
        assert_eq!(why_no_stats(&format!("{text}{with_stats}")), None);
        assert_eq!(why_no_stats("some other text\n"), None);
    }

    #[test]
    fn a_log_without_bed_stats_or_config_gives_nothing() {
        assert!(parse("Starting Klippy...\nStats 1.0: gcodein=0 mcu: a=1\n").is_empty());
        assert!(parse("").is_empty());
        // A broken bed section is skipped, not guessed.
        let s = parse("Stats 1.0: heater_bed: target=60 temp=x pwm=0.5\n");
        assert!(s.is_empty(), "{s:?}");
    }
}
