//! Klipper's heater control ported line by line from klippy/extras (`heaters.ControlPID`,
//! `Heater.set_pwm`, `pid_calibrate.ControlAutoTune`) on a four-node bed, and the check of the
//! port against the bench venv's own klippy.

use super::{read, step, FourNode, Kind};

/// Klipper's `PID_PARAM_BASE`, `MAX_HEAT_TIME`, `TUNE_PID_DELTA` and the thermistor's report
/// time.
const PID_PARAM_BASE: f64 = 255.0;
const MAX_HEAT_TIME: f64 = 5.0;
const TUNE_PID_DELTA: f64 = 5.0;
const REPORT_S: f64 = 0.3;
/// Klipper's default `smooth_time`.
const SMOOTH_TIME: f64 = 1.0;

/// Klipper's heater with its control: `Heater.set_pwm` and `ControlPID` or `ControlAutoTune`.
struct Klipper {
    max_power: f64,
    target: f64,
    next_pwm_time: f64,
    last_pwm_value: f64,
    // ControlPID
    kp: f64,
    ki: f64,
    kd: f64,
    temp_integ_max: f64,
    prev_temp: f64,
    prev_temp_time: f64,
    prev_temp_deriv: f64,
    prev_temp_integ: f64,
}

impl Klipper {
    fn new(max_power: f64, gains: (f64, f64, f64)) -> Self {
        let (kp, ki, kd) = (
            gains.0 / PID_PARAM_BASE,
            gains.1 / PID_PARAM_BASE,
            gains.2 / PID_PARAM_BASE,
        );
        Klipper {
            max_power,
            target: 0.0,
            next_pwm_time: 0.0,
            last_pwm_value: 0.0,
            kp,
            ki,
            kd,
            temp_integ_max: if ki != 0.0 { max_power / ki } else { 0.0 },
            // AMBIENT_TEMP
            prev_temp: 25.0,
            prev_temp_time: 0.0,
            prev_temp_deriv: 0.0,
            prev_temp_integ: 0.0,
        }
    }

    /// heaters.Heater.set_pwm (pwm_delay left out: it only shifts the schedule).
    fn set_pwm(&mut self, read_time: f64, value: f64) {
        let value = if self.target <= 0.0 { 0.0 } else { value };
        if (read_time < self.next_pwm_time || self.last_pwm_value == 0.0)
            && (value - self.last_pwm_value).abs() < 0.05
        {
            return;
        }
        self.next_pwm_time = read_time + REPORT_S + 0.75 * MAX_HEAT_TIME;
        self.last_pwm_value = value;
    }

    /// heaters.ControlPID.temperature_update.
    fn pid_update(&mut self, read_time: f64, temp: f64) {
        let time_diff = read_time - self.prev_temp_time;
        let temp_diff = temp - self.prev_temp;
        let temp_deriv = if time_diff >= SMOOTH_TIME {
            temp_diff / time_diff
        } else {
            (self.prev_temp_deriv * (SMOOTH_TIME - time_diff) + temp_diff) / SMOOTH_TIME
        };
        let temp_err = self.target - temp;
        let temp_integ =
            (self.prev_temp_integ + temp_err * time_diff).clamp(0.0, self.temp_integ_max);
        let co = self.kp * temp_err + self.ki * temp_integ - self.kd * temp_deriv;
        let bounded_co = co.clamp(0.0, self.max_power);
        self.set_pwm(read_time, bounded_co);
        self.prev_temp = temp;
        self.prev_temp_time = read_time;
        self.prev_temp_deriv = temp_deriv;
        if co == bounded_co {
            self.prev_temp_integ = temp_integ;
        }
    }
}

/// One reading Klipper's control saw and the pwm it set after it: `(read_time, temp, pwm)`.
pub(crate) type Trace = Vec<(f64, f64, f64)>;

/// PID gains (Kp, Ki, Kd) in Klipper's units.
type Gains = (f64, f64, f64);

/// pid_calibrate.ControlAutoTune on the bed from room temperature at its target: the PID
/// gains (Klipper's units) a user's PID_CALIBRATE would write, or None if it did not finish.
#[must_use]
pub(crate) fn autotune(bed: &FourNode, rng: &mut fastrand::Rng) -> Option<(f64, f64, f64)> {
    autotune_traced(bed, rng, None)
}

/// [`autotune`], recording every reading and the pwm set after it into `trace`.
pub(crate) fn autotune_traced(
    bed: &FourNode,
    rng: &mut fastrand::Rng,
    mut trace: Option<&mut Trace>,
) -> Option<(f64, f64, f64)> {
    let mut t = [bed.room_c; 4];
    let mut k = Klipper::new(1.0, (0.0, 0.0, 0.0));
    let calibrate_temp = bed.target_c;
    k.target = calibrate_temp;
    let (mut heating, mut peak, mut peak_time) = (false, 0.0, 0.0);
    let mut peaks: Vec<(f64, f64)> = Vec::new();
    let mut time = 0.0;
    // The pwm the heater runs at: Klipper's set_pwm schedules a new value pwm_delay (the
    // report time) after the reading it answers.
    let mut applied = 0.0;
    while time < 4.0 * 3600.0 {
        time += REPORT_S;
        step(bed, &mut t, applied, REPORT_S);
        let temp = read(bed, &t, rng);
        applied = k.last_pwm_value;
        let target_temp = k.target;
        if heating && temp >= target_temp {
            heating = false;
            peaks.push((peak, peak_time));
            peak = -9_999_999.0;
            k.target = calibrate_temp - TUNE_PID_DELTA;
        } else if !heating && temp <= target_temp {
            heating = true;
            peaks.push((peak, peak_time));
            peak = 9_999_999.0;
            k.target = calibrate_temp;
        }
        if heating {
            k.set_pwm(time, k.max_power);
            if temp < peak {
                peak = temp;
                peak_time = time;
            }
        } else {
            k.set_pwm(time, 0.0);
            if temp > peak {
                peak = temp;
                peak_time = time;
            }
        }
        if let Some(tr) = trace.as_deref_mut() {
            tr.push((time, temp, k.last_pwm_value));
        }
        if !heating && peaks.len() >= 12 {
            break;
        }
    }
    if peaks.len() < 12 {
        return None;
    }
    // calc_final_pid: the median cycle time's position; calc_pid there.
    let mut cycles: Vec<(f64, usize)> = (4..peaks.len())
        .map(|pos| (peaks[pos].1 - peaks[pos - 2].1, pos))
        .collect();
    cycles.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let pos = cycles[cycles.len() / 2].1;
    let temp_diff = peaks[pos].0 - peaks[pos - 1].0;
    let time_diff = peaks[pos].1 - peaks[pos - 2].1;
    let amplitude = 0.5 * temp_diff.abs();
    let ku = 4.0 * k.max_power / (std::f64::consts::PI * amplitude);
    let tu = time_diff;
    let ti = 0.5 * tu;
    let td = 0.125 * tu;
    let kp = 0.6 * ku * PID_PARAM_BASE;
    Some((kp, kp / ti, kp * td))
}

/// A heat-up from room temperature under Klipper's PID with these gains: `(t_s, power,
/// reading, target, surface, air)` once a second for `until_s`.
#[must_use]
pub(crate) fn heat_up(
    bed: &FourNode,
    gains: (f64, f64, f64),
    until_s: f64,
    rng: &mut fastrand::Rng,
) -> Vec<[f64; 6]> {
    heat_up_traced(bed, gains, until_s, rng, None)
}

/// [`heat_up`], recording every reading and the pwm set after it into `trace`.
pub(crate) fn heat_up_traced(
    bed: &FourNode,
    gains: (f64, f64, f64),
    until_s: f64,
    rng: &mut fastrand::Rng,
    mut trace: Option<&mut Trace>,
) -> Vec<[f64; 6]> {
    let mut t = [bed.room_c; 4];
    let mut k = Klipper::new(1.0, gains);
    k.target = bed.target_c;
    let mut out = Vec::with_capacity(until_s as usize + 1);
    let mut time = 0.0;
    let mut next_out = 0.0;
    let mut temp = bed.room_c;
    let mut applied = 0.0;
    while time <= until_s {
        if time >= next_out {
            // The power Klipper reports is the last value it set.
            out.push([time, k.last_pwm_value, temp, bed.target_c, t[2], t[3]]);
            next_out += 1.0;
        }
        time += REPORT_S;
        step(bed, &mut t, applied, REPORT_S);
        temp = read(bed, &t, rng);
        applied = k.last_pwm_value;
        k.pid_update(time, temp);
        if let Some(tr) = trace.as_deref_mut() {
            tr.push((time, temp, k.last_pwm_value));
        }
    }
    out
}

/// The klippy venv's python (`$KLIPCAL_BENCH_HOME`, else the checkout's `.bench`, as
/// tests/bench/setup.sh installs it) and the checker script, from a source checkout.
///
/// # Errors
/// Where they were looked for, and how to install them.
pub(crate) fn klippy_python() -> Result<(std::path::PathBuf, std::path::PathBuf), String> {
    let repo = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."));
    let home = std::env::var_os("KLIPCAL_BENCH_HOME")
        .map_or_else(|| repo.join(".bench"), std::path::PathBuf::from);
    let python = home.join("venv-klippy/bin/python");
    let script = repo.join("tests/bench/klipper_control_check.py");
    if !python.exists() {
        return Err(format!(
            "no klippy venv at {} (run tests/bench/setup.sh, or set KLIPCAL_BENCH_HOME)",
            python.display()
        ));
    }
    if !script.exists() {
        return Err(format!("{} is missing", script.display()));
    }
    Ok((python, script))
}

/// The port checked against Klipper's own Python on the same readings (`klipcal bench soak`).
#[derive(Debug, Clone, Default)]
pub(crate) struct KlipperCheck {
    /// Runs compared (an autotune and a PID heat-up per bed).
    pub runs: usize,
    /// Readings replayed, and those after which the pwm differed by more than `PWM_TOL`.
    pub updates: usize,
    /// See `updates`.
    pub pwm_mismatches: usize,
    /// The largest pwm difference seen.
    pub max_pwm_diff: f64,
    /// The largest relative difference of the autotune gains (Kp, Ki, Kd).
    pub max_gain_rel: f64,
    /// Autotunes where one side finished and the other did not, or at another reading.
    pub autotune_mismatches: usize,
}

/// The pwm tolerance of [`klipper_check`]: both sides compute the same f64 expressions in
/// the same order, so anything above rounding is a difference in the port.
pub(crate) const PWM_TOL: f64 = 1e-9;
/// The relative tolerance on the autotune gains.
pub(crate) const GAIN_TOL: f64 = 1e-9;

/// Runs Klipper's own heaters.py / pid_calibrate.py (`python`, the klippy venv's, on
/// `script`, tests/bench/klipper_control_check.py) on the readings of `beds` four-node beds
/// (one of each kind in turn): the autotune and `heat_s` of PID heat-up each, and compares
/// the pwm after every reading and the gains with the port's.
///
/// # Errors
/// Python could not run or answered something unreadable.
pub(crate) fn klipper_check(
    python: &std::path::Path,
    script: &std::path::Path,
    beds: usize,
    heat_s: f64,
    seed: u64,
) -> anyhow::Result<KlipperCheck> {
    use anyhow::Context;
    let mut rng = fastrand::Rng::with_seed(seed);
    let kinds = Kind::all();
    let mut runs = Vec::new();
    let mut expect: Vec<(Trace, Option<Gains>)> = Vec::new();
    for i in 0..beds {
        let bed = FourNode::random(kinds[i % kinds.len()], &mut rng);
        let mut tr = Trace::new();
        let gains = autotune_traced(&bed, &mut rng, Some(&mut tr));
        let readings: Vec<[f64; 2]> = tr.iter().map(|x| [x.0, x.1]).collect();
        runs.push(serde_json::json!({
            "mode": "autotune", "max_power": 1.0, "smooth_time": SMOOTH_TIME,
            "pwm_delay": REPORT_S, "target": bed.target_c, "readings": readings,
        }));
        expect.push((tr, gains));
        // Gains as a user's config holds them (PID_CALIBRATE writes 3 decimals).
        let g = gains.unwrap_or((50.0, 1.0, 300.0));
        let g = (
            (g.0 * 1e3).round() / 1e3,
            (g.1 * 1e3).round() / 1e3,
            (g.2 * 1e3).round() / 1e3,
        );
        let mut tr = Trace::new();
        heat_up_traced(&bed, g, heat_s, &mut rng, Some(&mut tr));
        let readings: Vec<[f64; 2]> = tr.iter().map(|x| [x.0, x.1]).collect();
        runs.push(serde_json::json!({
            "mode": "pid", "max_power": 1.0, "smooth_time": SMOOTH_TIME,
            "pwm_delay": REPORT_S, "target": bed.target_c, "gains": [g.0, g.1, g.2],
            "readings": readings,
        }));
        expect.push((tr, None));
    }
    let input = serde_json::json!({ "runs": runs }).to_string();
    let v = run_python(python, script, input)?;
    let answers = v["runs"].as_array().context("no runs in the answer")?;
    anyhow::ensure!(
        answers.len() == expect.len(),
        "runs answered: {}",
        answers.len()
    );
    let mut r = KlipperCheck {
        runs: expect.len(),
        ..KlipperCheck::default()
    };
    for ((tr, gains), a) in expect.iter().zip(answers) {
        let pwm: Vec<f64> = a["pwm"]
            .as_array()
            .context("no pwm")?
            .iter()
            .map(|x| x.as_f64().unwrap_or(f64::NAN))
            .collect();
        if pwm.len() != tr.len() {
            r.autotune_mismatches += 1;
        }
        for (x, p) in tr.iter().zip(&pwm) {
            let d = (x.2 - p).abs();
            r.updates += 1;
            if d.is_nan() || d > PWM_TOL {
                r.pwm_mismatches += 1;
            }
            r.max_pwm_diff = r
                .max_pwm_diff
                .max(if d.is_nan() { f64::INFINITY } else { d });
        }
        let theirs = a["gains"].as_array().map(|g| {
            g.iter()
                .map(|x| x.as_f64().unwrap_or(f64::NAN))
                .collect::<Vec<f64>>()
        });
        if a.get("gains").is_some_and(|g| !g.is_null()) || gains.is_some() {
            match (gains, theirs) {
                (Some(ours), Some(t)) if t.len() == 3 => {
                    for (o, k) in [ours.0, ours.1, ours.2].iter().zip(&t) {
                        let rel = ((o - k) / k).abs();
                        r.max_gain_rel =
                            r.max_gain_rel
                                .max(if rel.is_nan() { f64::INFINITY } else { rel });
                    }
                }
                _ => r.autotune_mismatches += 1,
            }
        }
    }
    Ok(r)
}

/// Runs `script` under `python` with `input` on its stdin and reads its stdout as JSON.
///
/// # Errors
/// Python could not run, failed, or answered something unreadable.
pub(crate) fn run_python(
    python: &std::path::Path,
    script: &std::path::Path,
    input: String,
) -> anyhow::Result<serde_json::Value> {
    use anyhow::Context;
    use std::io::Write;
    let mut child = std::process::Command::new(python)
        .arg(script)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .with_context(|| format!("cannot run {}", python.display()))?;
    let mut stdin = child.stdin.take().context("python's stdin")?;
    let writer = std::thread::spawn(move || stdin.write_all(input.as_bytes()));
    let out = child.wait_with_output()?;
    writer
        .join()
        .map_err(|_| anyhow::anyhow!("writing to python"))??;
    if !out.status.success() {
        anyhow::bail!(
            "{} failed: {}",
            script.display(),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    serde_json::from_slice(&out.stdout).with_context(|| format!("{}'s answer", script.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The port against Klipper's own Python (the bench venv's klippy, which the test command
    /// installs first): the same readings give the same pwm and the same autotune gains.
    #[test]
    fn the_port_matches_klippers_own_heaters_py_on_the_same_readings() {
        let (python, script) = klippy_python().unwrap_or_else(|e| panic!("{e}"));
        let r = klipper_check(&python, &script, 2, 900.0, 5).expect("the check ran");
        assert_eq!(r.runs, 4);
        assert!(r.updates > 5000, "{r:?}");
        assert_eq!(r.pwm_mismatches, 0, "{r:?}");
        assert_eq!(r.autotune_mismatches, 0, "{r:?}");
        assert!(
            r.max_pwm_diff <= PWM_TOL && r.max_gain_rel <= GAIN_TOL,
            "{r:?}"
        );
    }

    #[test]
    fn klippers_autotune_gives_gains_that_hold_the_bed_at_its_target() {
        let mut rng = fastrand::Rng::with_seed(3);
        for kind in Kind::all() {
            let bed = FourNode::random(kind, &mut rng);
            let gains = autotune(&bed, &mut rng).expect("autotune finished");
            assert!(gains.0 > 0.0 && gains.1 > 0.0 && gains.2 > 0.0, "{gains:?}");
            let s = heat_up(&bed, gains, 3600.0, &mut rng);
            let tail = &s[s.len() - 600..];
            let mean = tail.iter().map(|x| x[2]).sum::<f64>() / tail.len() as f64;
            let (lo, hi) = tail
                .iter()
                .fold((f64::MAX, f64::MIN), |a, x| (a.0.min(x[2]), a.1.max(x[2])));
            // Klipper holds an overpowered bed in a small limit cycle (its pwm updates under
            // 0.05 are held): within 1 K on average.
            assert!(
                (mean - bed.target_c).abs() < 1.0,
                "{}: {mean} in {lo}..{hi}, target {}, gains {gains:?}, P {}",
                kind.name(),
                bed.target_c,
                bed.p_max_w
            );
            // Klipper reports 0.01 °C steps.
            assert!(tail
                .iter()
                .all(|x| ((x[2] * 100.0).round() - x[2] * 100.0).abs() < 1e-6));
            // The surface below the target, warming.
            assert!(tail[599][4] < bed.target_c + 0.01 && tail[599][4] >= tail[0][4] - 0.05);
            assert!(bed.g_true() > 0.0 && bed.p_max_w >= 150.0 && bed.p_max_w <= 900.0);
        }
    }
}
