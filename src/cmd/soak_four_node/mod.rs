//! The four-node family of `klipcal bench soak` (issue 29): heater pad, aluminium plate, print
//! surface (steel sheet on a magnet, or glass on clips) and the air and frame around the bed
//! (open frame, or an enclosure that warms over hours), in physical units from real materials
//! and sizes (220–400 mm beds, 150–900 W), with the thermistor in the pad or in the plate.
//!
//! Control is Klipper's own, ported line by line from klippy/extras in the bench venv:
//! `heaters.ControlPID.temperature_update` (integral clamp, derivative over `smooth_time`,
//! integral frozen while the output is clamped), `Heater.set_pwm` (updates under 0.05 held up
//! to 0.75 × MAX_HEAT_TIME; the power Klipper reports is the last value set), and the gains come
//! from `pid_calibrate.ControlAutoTune` run on the same bed first (relay between the target and
//! target − 5 °C at max_power, Åström–Hägglund Ku/Tu at the median cycle, Ziegler–Nichols). The
//! thermistor is read every 0.3 s (Klipper's report time) with ADC noise and 0.01 °C rounding.
//!
//! Truth is the surface: its final temperature is the steady state with the thermistor's node
//! held at the target, and a declaration is early when the surface was still more than the
//! budget below it.

use super::soak_noise::{gauss, uniform};
use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};

/// Klipper's `PID_PARAM_BASE`, `MAX_HEAT_TIME`, `TUNE_PID_DELTA` and the thermistor's report
/// time.
const PID_PARAM_BASE: f64 = 255.0;
const MAX_HEAT_TIME: f64 = 5.0;
const TUNE_PID_DELTA: f64 = 5.0;
const REPORT_S: f64 = 0.3;
/// Klipper's default `smooth_time`.
const SMOOTH_TIME: f64 = 1.0;

/// One bed: nodes pad, plate, surface, air; conductances W/K; capacities J/K.
#[derive(Debug, Clone)]
pub(crate) struct FourNode {
    /// What it is, for the report.
    pub kind: Kind,
    c: [f64; 4],
    k_pad_plate: f64,
    k_plate_surf: f64,
    h_surf_air: f64,
    h_pad_air: f64,
    h_air_room: f64,
    p_max_w: f64,
    room_c: f64,
    /// Target, °C.
    pub target_c: f64,
    /// ADC noise, °C (sd).
    pub noise_c: f64,
}

/// A family of four-node beds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Kind {
    /// Glass on clips (else a steel sheet on a magnet).
    pub glass: bool,
    /// Thermistor in the pad (else in the plate).
    pub pad_sensed: bool,
    /// Enclosed (else open frame).
    pub enclosed: bool,
}

impl Kind {
    /// Its name in the report.
    #[must_use]
    pub(crate) fn name(&self) -> String {
        format!(
            "{} {}, thermistor in the {}",
            if self.enclosed {
                "enclosed"
            } else {
                "open-frame"
            },
            if self.glass {
                "glass on clips"
            } else {
                "steel on magnet"
            },
            if self.pad_sensed { "pad" } else { "plate" }
        )
    }

    /// All eight.
    #[must_use]
    pub(crate) fn all() -> Vec<Kind> {
        let mut v = Vec::new();
        for enclosed in [false, true] {
            for glass in [false, true] {
                for pad_sensed in [false, true] {
                    v.push(Kind {
                        glass,
                        pad_sensed,
                        enclosed,
                    });
                }
            }
        }
        v
    }
}

/// The grid's knobs, each 0..1 within its physical range (coupling, plate thickness,
/// enclosure time constant, noise), or drawn at random.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Knobs {
    /// Surface contact (0 poor, 1 good).
    pub coupling: f64,
    /// Plate thickness (0 thin, 1 thick).
    pub plate: f64,
    /// Enclosure air+frame heat capacity (0 small, 1 large).
    pub enclosure: f64,
    /// ADC noise (0 quiet, 1 noisy).
    pub noise: f64,
}

impl FourNode {
    /// A bed of `kind` from the knobs, with the rest drawn.
    #[must_use]
    pub(crate) fn new(kind: Kind, k: Knobs, rng: &mut fastrand::Rng) -> Self {
        let side = uniform(rng, 0.22, 0.40);
        let a = side * side;
        // Heater: 0.35–1 W/cm², within 150–900 W.
        let p_max_w = (a * uniform(rng, 3500.0, 10_000.0)).clamp(150.0, 900.0);
        // Silicone pad 1.5 mm (1.2 g/cm³, 1.3 J/gK); plate 3–8 mm aluminium (2.7, 0.9).
        let c_pad = a * 0.0015 * 1200.0 * 1300.0;
        let t_plate = 0.003 + 0.005 * k.plate;
        let c_plate = a * t_plate * 2700.0 * 900.0;
        // The pad's thermistor sits in silicone (0.3 W/mK) about 0.5–1 mm from the plate.
        let k_pad_plate = a * 0.3 / uniform(rng, 0.0005, 0.001);
        let (c_surf, k_plate_surf) = if kind.glass {
            // 3–4 mm borosilicate (2.23 g/cm³, 0.83 J/gK, 1.1 W/mK) on clips over an air gap of
            // 0.05–0.4 mm (0.03 W/mK).
            let t = uniform(rng, 0.003, 0.004);
            let gap = 0.0004 - 0.00035 * k.coupling;
            let u = 1.0 / (gap / 0.03 + t / 2.0 / 1.1);
            (a * t * 2230.0 * 830.0, a * u)
        } else {
            // 0.5 mm spring steel (7.85, 0.46) with PEI on a 1 mm magnetic sheet (3.6, 0.9,
            // 0.4–1.2 W/mK).
            let c = a * (0.0005 * 7850.0 * 460.0 + 0.001 * 3600.0 * 0.9e3);
            let km = 0.4 + 0.8 * k.coupling;
            (c, a / (0.001 / km + 0.0005 / 20.0))
        };
        // Surface to air: convection 5–9 W/m²K and radiation (ε 0.9, ~7 W/m²K at 60–100 °C);
        // the pad's underside 2–8 W/m²K (insulated or not).
        let h_surf_air = a * uniform(rng, 12.0, 16.0);
        let h_pad_air = a * uniform(rng, 2.0, 8.0);
        // Air and frame: open frame, a small mass well coupled to the room (minutes, a degree
        // or two); enclosed, the air, extrusions and panels (12–40 kJ/K: ~5 kg of aluminium
        // frame, ~5 kg of panels) behind 1.5–3 m² of acrylic or polycarbonate panels at
        // 4–6 W/m²K (6–18 W/K): from about 10 min to 2 h.
        let (c_air, h_air_room) = if kind.enclosed {
            (12_000.0 + 28_000.0 * k.enclosure, uniform(rng, 6.0, 18.0))
        } else {
            (2_000.0 + 3_000.0 * k.enclosure, uniform(rng, 30.0, 80.0))
        };
        FourNode {
            kind,
            c: [c_pad, c_plate, c_surf, c_air],
            k_pad_plate,
            k_plate_surf,
            h_surf_air,
            h_pad_air,
            h_air_room,
            p_max_w,
            room_c: uniform(rng, 18.0, 26.0),
            target_c: if kind.glass {
                uniform(rng, 55.0, 75.0)
            } else {
                uniform(rng, 55.0, 100.0)
            },
            // Klipper averages 8 ADC samples a report: 0.01–0.05 °C of noise on a bed.
            noise_c: 0.01 + 0.04 * k.noise,
        }
    }

    /// A random bed of `kind`.
    #[must_use]
    pub(crate) fn random(kind: Kind, rng: &mut fastrand::Rng) -> Self {
        let k = Knobs {
            coupling: rng.f64(),
            plate: rng.f64(),
            enclosure: rng.f64(),
            noise: rng.f64(),
        };
        Self::new(kind, k, rng)
    }

    fn sensor_node(&self) -> usize {
        usize::from(!self.kind.pad_sensed)
    }

    /// The true coupling from the thermistor's node to the surface, full power per K.
    #[must_use]
    pub(crate) fn g_true(&self) -> f64 {
        let w = if self.kind.pad_sensed {
            1.0 / (1.0 / self.k_pad_plate + 1.0 / self.k_plate_surf)
        } else {
            self.k_plate_surf
        };
        w / self.p_max_w
    }

    /// The time constants of the bed with the thermistor's node held (and the heater's power
    /// free): the modes the power decays with and the surface relaxes with, s, slowest first.
    #[must_use]
    pub(crate) fn clamped_taus_s(&self) -> Vec<f64> {
        let s = self.sensor_node();
        let k = |i: usize, j: usize| -> f64 {
            match (i.min(j), i.max(j)) {
                (0, 1) => self.k_pad_plate,
                (1, 2) => self.k_plate_surf,
                (2, 3) => self.h_surf_air,
                (0, 3) => self.h_pad_air,
                _ => 0.0,
            }
        };
        let free: Vec<usize> = (0..4).filter(|i| *i != s).collect();
        // Symmetric form C^-1/2 K C^-1/2 of the conductance matrix over the free nodes (the
        // held node and the room are fixed: their conductances sit on the diagonal).
        let m = nalgebra::DMatrix::from_fn(free.len(), free.len(), |a, b| {
            let (i, j) = (free[a], free[b]);
            let kij = if i == j {
                (0..4).map(|n| k(i, n)).sum::<f64>() + if i == 3 { self.h_air_room } else { 0.0 }
            } else {
                -k(i, j)
            };
            kij / (self.c[i] * self.c[j]).sqrt()
        });
        let mut taus: Vec<f64> = m
            .symmetric_eigen()
            .eigenvalues
            .iter()
            .map(|l| 1.0 / l)
            .collect();
        taus.sort_by(|a, b| b.total_cmp(a));
        taus
    }

    /// Heat flows into each node at temperatures `t` and heater power `p` (W).
    fn flows(&self, t: &[f64; 4], p_w: f64) -> [f64; 4] {
        let q_pp = self.k_pad_plate * (t[0] - t[1]);
        let q_ps = self.k_plate_surf * (t[1] - t[2]);
        let q_sa = self.h_surf_air * (t[2] - t[3]);
        let q_pa = self.h_pad_air * (t[0] - t[3]);
        let q_ar = self.h_air_room * (t[3] - self.room_c);
        [
            p_w - q_pp - q_pa,
            q_pp - q_ps,
            q_ps - q_sa,
            q_sa + q_pa - q_ar,
        ]
    }

    /// The surface's final temperature with the thermistor's node held at the target: the
    /// other three nodes' steady state (Gauss–Seidel on the linear balance).
    #[must_use]
    pub(crate) fn surface_final_c(&self) -> f64 {
        let s = self.sensor_node();
        let mut t = [self.target_c; 4];
        t[3] = self.room_c;
        for _ in 0..20_000 {
            // Each free node at the conductance-weighted mean of its neighbours.
            if s == 0 {
                t[1] = (self.k_pad_plate * t[0] + self.k_plate_surf * t[2])
                    / (self.k_pad_plate + self.k_plate_surf);
            } else {
                // The plate held: the pad runs hotter by what the plate passes on.
                t[0] = t[1] + self.k_plate_surf * (t[1] - t[2]) / self.k_pad_plate;
            }
            t[2] = (self.k_plate_surf * t[1] + self.h_surf_air * t[3])
                / (self.k_plate_surf + self.h_surf_air);
            t[3] = (self.h_surf_air * t[2] + self.h_pad_air * t[0] + self.h_air_room * self.room_c)
                / (self.h_surf_air + self.h_pad_air + self.h_air_room);
        }
        t[2]
    }
}

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

/// The thermistor's reading: ADC noise and Klipper's 0.01 °C.
fn read(bed: &FourNode, t: &[f64; 4], rng: &mut fastrand::Rng) -> f64 {
    let raw = t[bed.sensor_node()] + bed.noise_c * gauss(rng);
    (raw * 100.0).round() / 100.0
}

/// Steps the plant by `dt` at power fraction `p`.
fn step(bed: &FourNode, t: &mut [f64; 4], p: f64, dt: f64) {
    // Sub-steps keep explicit Euler stable on the fast pad and surface.
    let n = 3;
    let h = dt / f64::from(n);
    for _ in 0..n {
        let f = bed.flows(t, p * bed.p_max_w);
        for i in 0..4 {
            t[i] += h * f[i] / bed.c[i];
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
/// reading, target, surface)` once a second for `until_s`.
#[must_use]
pub(crate) fn heat_up(
    bed: &FourNode,
    gains: (f64, f64, f64),
    until_s: f64,
    rng: &mut fastrand::Rng,
) -> Vec<[f64; 5]> {
    heat_up_traced(bed, gains, until_s, rng, None)
}

/// [`heat_up`], recording every reading and the pwm set after it into `trace`.
pub(crate) fn heat_up_traced(
    bed: &FourNode,
    gains: (f64, f64, f64),
    until_s: f64,
    rng: &mut fastrand::Rng,
    mut trace: Option<&mut Trace>,
) -> Vec<[f64; 5]> {
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
            out.push([time, k.last_pwm_value, temp, bed.target_c, t[2]]);
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
    let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
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
    use std::io::Write;
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
    let v: serde_json::Value =
        serde_json::from_slice(&out.stdout).context("klipper_control_check.py's answer")?;
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

/// What each rule said on one bed, s (None: not within the run).
#[derive(Debug, Clone, Default)]
pub(crate) struct BedResult {
    /// The surface moment: the last time the surface was more than the budget from its final
    /// temperature (∞ when still so at the end of the run).
    pub moment_s: f64,
    /// First reading within 2 °C of the target.
    pub reach_s: f64,
    /// klipcal's rule, issue 10's rule, the pwm-slope rule, the R-statistic test.
    pub rule: Option<f64>,
    /// See `rule`.
    pub today: Option<f64>,
    /// See `rule`.
    pub slope: Option<f64>,
    /// See `rule`.
    pub r_stat: Option<f64>,
    /// The coupling was identified (its lower end from the bed's own data).
    pub identified: bool,
    /// The heat-up gave an upper end of the coupling (identified, or bounding the fallback).
    pub bounded: bool,
    /// The reported interval (the G used to the upper end) held the true G.
    pub covered: bool,
    /// The G the rule used was at or below the true one (the conservative side).
    pub g_safe: bool,
    /// The true G and the G the rule used, full power per K.
    pub g_true: f64,
    /// See `g_true`.
    pub g_used: f64,
    /// The bin noise the detector's test used at its declaration (or the run's end).
    pub sigma: f64,
    /// klipcal's rule with `soak.bed` set to this kind's preset, when asked for.
    pub with_preset: Option<f64>,
    /// With the preset: the coupling was identified, its interval held the true G, and the G
    /// used was at or below it.
    pub preset_identified: bool,
    /// See `preset_identified`.
    pub preset_covered: bool,
    /// See `preset_identified`.
    pub preset_g_safe: bool,
    /// Surface left at klipcal's declaration, K.
    pub left_c: f64,
    /// klipcal's rule with `soak.frame = "open"` (on an enclosed bed: the user's error),
    /// without and with the kind's preset (when asked for).
    pub open: Option<f64>,
    /// See `open`.
    pub open_preset: Option<f64>,
    /// `open` and `open_preset` with the coupling not identified (the preset's or the
    /// weakest G, as after a warm start), when the preset is asked for.
    pub open_fixed: Option<f64>,
    /// See `open_fixed`.
    pub open_preset_fixed: Option<f64>,
    /// Surface left at the `open` and `open_preset` declarations, K (0 when not early).
    pub open_left_c: f64,
    /// The bed's slowest clamped time constant, s.
    pub slowest_s: f64,
}

/// Runs the detector over the samples; the declaration and the detector.
fn detector(samples: &[[f64; 5]], params: &SoakParams) -> (Option<f64>, SoakDetector) {
    let mut d = SoakDetector::new(params.clone());
    for s in samples {
        if let SoakStatus::Stable { at_s } = d.push(s[0], s[1], s[2], s[3]) {
            return (Some(at_s), d);
        }
    }
    (None, d)
}

/// Every rule on one bed.
#[must_use]
pub(crate) fn judge(bed: &FourNode, samples: &[[f64; 5]], params: &SoakParams) -> BedResult {
    let fin = bed.surface_final_c();
    let budget = params.surface_budget_c;
    let moment_s = match samples.iter().rposition(|s| fin - s[4] > budget) {
        Some(i) if i + 1 == samples.len() => f64::INFINITY,
        Some(i) => samples[i][0],
        None => 0.0,
    };
    let reach_s = samples
        .iter()
        .find(|s| (s[2] - s[3]).abs() <= 2.0)
        .map_or(f64::INFINITY, |s| s[0]);
    let (rule, d) = detector(samples, params);
    let c = d.coupling();
    let g = bed.g_true();
    let identified = c.source == crate::calib::soak::CouplingSource::Identified;
    let today = detector(
        samples,
        &SoakParams {
            fixed_remaining: Some(0.008),
            ..params.clone()
        },
    )
    .0;
    // 10-s means of the power after the target is reached.
    let bins: Vec<(f64, f64)> = samples
        .chunks(10)
        .filter(|c| c[0][0] >= reach_s)
        .map(|c| {
            (
                c[c.len() - 1][0],
                c.iter().map(|s| s[1]).sum::<f64>() / c.len() as f64,
            )
        })
        .collect();
    // pwm slope: the last minute's mean within 2 points of the mean two minutes before.
    let slope = (18..bins.len()).find_map(|i| {
        let m = |a: usize| bins[a - 5..=a].iter().map(|b| b.1).sum::<f64>() / 6.0;
        ((m(i) - m(i - 12)).abs() < 0.02).then_some(bins[i].0)
    });
    // Cao–Rhinehart R statistic on the 10-s means (λ1 0.2, λ2 = λ3 0.1; steady below 2.0,
    // after the filters have run for 5 min).
    let r_stat = {
        let (l1, l2, l3, crit) = (0.2, 0.1, 0.1, 2.0);
        let mut out = None;
        if let Some(&(_, first)) = bins.first() {
            let (mut xf, mut v2, mut d2, mut prev) = (first, 0.0, 0.0, first);
            for (i, &(t, x)) in bins.iter().enumerate().skip(1) {
                v2 = l2 * (x - xf).powi(2) + (1.0 - l2) * v2;
                xf = l1 * x + (1.0 - l1) * xf;
                d2 = l3 * (x - prev).powi(2) + (1.0 - l3) * d2;
                prev = x;
                if i >= 30 && d2 > 0.0 && (2.0 - l1) * v2 / d2 < crit {
                    out = Some(t);
                    break;
                }
            }
        }
        out
    };
    let left_at = |at: Option<f64>| {
        at.map_or(0.0, |at| {
            samples
                .iter()
                .find(|s| s[0] >= at)
                .map_or(0.0, |s| fin - s[4])
        })
    };
    let left_c = left_at(rule);
    let open = detector(
        samples,
        &SoakParams {
            frame: "open".into(),
            ..params.clone()
        },
    )
    .0;
    BedResult {
        moment_s,
        reach_s,
        rule,
        today,
        slope,
        r_stat,
        identified,
        bounded: identified || c.high > c.g,
        covered: c.low <= g && g <= c.high,
        g_safe: c.g <= g,
        g_true: g,
        g_used: c.g,
        sigma: d.fit().map_or(0.0, |f| f.test_sd),
        with_preset: None,
        preset_identified: false,
        preset_covered: false,
        preset_g_safe: false,
        left_c,
        open,
        open_preset: None,
        open_fixed: None,
        open_preset_fixed: None,
        open_left_c: left_at(open),
        slowest_s: bed.clamped_taus_s()[0],
    }
}

/// The `soak.bed` preset a user of this kind of bed would set.
#[must_use]
pub(crate) fn preset_name(kind: Kind) -> &'static str {
    match (kind.glass, kind.pad_sensed) {
        (false, false) => "steel-plate",
        (false, true) => "steel-pad",
        (true, false) => "glass-plate",
        (true, true) => "glass-pad",
    }
}

/// One bed of `kind` from the knobs (random when None), tuned and run for `until_s`; with
/// `preset`, klipcal's rule is also run with `soak.bed` set to the kind's preset.
#[must_use]
pub(crate) fn run_bed(
    kind: Kind,
    knobs: Option<Knobs>,
    until_s: f64,
    params: &SoakParams,
    preset: bool,
    rng: &mut fastrand::Rng,
) -> Option<BedResult> {
    let bed = match knobs {
        Some(k) => FourNode::new(kind, k, rng),
        None => FourNode::random(kind, rng),
    };
    let gains = autotune(&bed, rng)?;
    let samples = heat_up(&bed, gains, until_s, rng);
    let mut r = judge(&bed, &samples, params);
    if preset {
        let with = SoakParams {
            bed: preset_name(kind).into(),
            ..params.clone()
        };
        let (at, d) = detector(&samples, &with);
        r.with_preset = at;
        let c = d.coupling();
        r.preset_identified = c.source == crate::calib::soak::CouplingSource::Identified;
        r.preset_covered = c.low <= r.g_true && r.g_true <= c.high;
        r.preset_g_safe = c.g <= r.g_true;
        let open = detector(
            &samples,
            &SoakParams {
                frame: "open".into(),
                ..with
            },
        )
        .0;
        r.open_preset = open;
        let fixed = |p: SoakParams| {
            detector(
                &samples,
                &SoakParams {
                    frame: "open".into(),
                    no_identify: true,
                    ..p
                },
            )
            .0
        };
        r.open_preset_fixed = fixed(SoakParams {
            bed: preset_name(kind).into(),
            ..params.clone()
        });
        r.open_fixed = fixed(params.clone());
        if let Some(at) = open {
            let fin = bed.surface_final_c();
            let left = samples
                .iter()
                .find(|s| s[0] >= at)
                .map_or(0.0, |s| fin - s[4]);
            r.open_left_c = r.open_left_c.max(left);
        }
    }
    Some(r)
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

    /// soak.frame = "open" rules out decays up to `OPEN_FRAME_TAU_MAX_S`: every open-frame
    /// bed of this family, at every corner of the knobs, settles within it; the enclosed ones
    /// do not all (which is why the setting is not the default).
    #[test]
    fn open_frame_beds_have_their_slowest_clamped_mode_within_the_open_frame_bound() {
        let mut rng = fastrand::Rng::with_seed(11);
        let (mut open_max, mut enclosed_max) = (0.0f64, 0.0f64);
        for kind in Kind::all() {
            for corner in 0..16u32 {
                let f = |b: u32| f64::from((corner >> b) & 1);
                let knobs = Knobs {
                    coupling: f(0),
                    plate: f(1),
                    enclosure: f(2),
                    noise: f(3),
                };
                for _ in 0..8 {
                    let bed = FourNode::new(kind, knobs, &mut rng);
                    let slowest = bed.clamped_taus_s()[0];
                    if kind.enclosed {
                        enclosed_max = enclosed_max.max(slowest);
                    } else {
                        open_max = open_max.max(slowest);
                    }
                }
            }
        }
        assert!(
            open_max <= crate::calib::soak::OPEN_FRAME_TAU_MAX_S,
            "open frame: slowest clamped mode {open_max} s"
        );
        assert!(
            enclosed_max > crate::calib::soak::OPEN_FRAME_TAU_MAX_S,
            "enclosed: {enclosed_max} s"
        );
    }

    /// The presets are the weak end of their builds: every bed of this family (random, and at
    /// every corner of the knobs) has a coupling at or above its kind's preset and a stack
    /// time R·C within the preset's, so neither bound the identification uses is above the
    /// true G. (Before, the presets held typical values: 1/30 for steel-pad was above the true
    /// G of 9 of 24 open-frame beds, 1/150 above one open glass-pad bed.)
    #[test]
    fn every_bed_of_the_family_is_within_its_presets_physical_bounds() {
        let mut rng = fastrand::Rng::with_seed(21);
        for kind in Kind::all() {
            let p = crate::calib::soak::BED_PRESETS
                .iter()
                .find(|b| b.name == preset_name(kind))
                .unwrap();
            for i in 0..400u32 {
                let bed = if i < 16 {
                    let f = |b: u32| f64::from((i >> b) & 1);
                    let knobs = Knobs {
                        coupling: f(0),
                        plate: f(1),
                        enclosure: f(2),
                        noise: f(3),
                    };
                    FourNode::new(kind, knobs, &mut rng)
                } else {
                    FourNode::random(kind, &mut rng)
                };
                let g = bed.g_true();
                let rc = (bed.c[0] + bed.c[1] + bed.c[2]) / bed.p_max_w / g;
                assert!(
                    g >= p.g,
                    "{}: G 1/{:.0} below the preset's 1/{:.0}",
                    kind.name(),
                    1.0 / g,
                    1.0 / p.g
                );
                assert!(
                    rc <= p.rc_s,
                    "{}: R·C {rc:.0} s over the preset's {:.0}",
                    kind.name(),
                    p.rc_s
                );
            }
        }
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
