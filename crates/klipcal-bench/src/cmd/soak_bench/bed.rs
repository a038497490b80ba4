//! The simulated bed of `klipcal bench soak`: a fast heater element on a slow plate under PI
//! control, and what the detector said on it.

use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};
use crate::cmd::soak_families::{information_bound, weakest_threshold};
use crate::cmd::soak_noise::{gauss, uniform};

/// A bed: a fast heater element on a slow plate, both losing heat to ambient, under PI control
/// of a thermistor that reads mostly the heater.
#[derive(Debug, Clone)]
pub(super) struct Bed {
    t_amb_c: f64,
    target_c: f64,
    /// Heat capacities (J/K) and conductances (W/K): heater–plate, plate–air, heater–air.
    c_heater: f64,
    c_plate: f64,
    g_hp: f64,
    g_pa: f64,
    g_ha: f64,
    p_max_w: f64,
    /// The thermistor reads `w·T_heater + (1−w)·T_plate`.
    w: f64,
    kp: f64,
    ki: f64,
    /// The plate's time constant with the heater held (what the decay of power follows).
    tau_plate_s: f64,
    /// Duty at equilibrium.
    final_power: f64,
    noise: Noise,
}

#[derive(Debug, Clone, Copy, Default)]
struct Noise {
    temp_sd_c: f64,
    ar_sd: f64,
    ar_tau_s: f64,
    white_sd: f64,
}

impl Bed {
    pub(super) fn random(rng: &mut fastrand::Rng) -> Bed {
        // Units: power in fractions of the heater's full power (p_max_w = 1), so conductances
        // are in full-power per kelvin and capacities in full-power seconds per kelvin.
        let t_amb_c = uniform(rng, 18.0, 28.0);
        let target_c = uniform(rng, 50.0, 110.0);
        let tau_plate_s = (uniform(rng, 120f64.ln(), 1800f64.ln())).exp();
        let tau_heater_s = uniform(rng, 20.0, 90.0);
        // The heater runs this much hotter than the plate at full power.
        let g_hp = 1.0 / uniform(rng, 10.0, 40.0);
        let c_heater = tau_heater_s * g_hp;
        let w = uniform(rng, 0.8, 1.0);
        let final_power = uniform(rng, 0.15, 0.5);
        // Losses to ambient, split between the plate's top and the heater's underside, scaled
        // so that the equilibrium duty is `final_power`.
        let heater_share = uniform(rng, 0.05, 0.3);
        let equilibrium_power = |loss: f64| {
            let (g_pa, g_ha) = ((1.0 - heater_share) * loss, heater_share * loss);
            // Plate balance: g_hp (th − tp) = g_pa (tp − ta); thermistor at the target.
            let r = g_pa / g_hp;
            let k = (1.0 - w) / (1.0 + r);
            let th = (target_c - k * r * t_amb_c) / (w + k);
            let tp = (th + r * t_amb_c) / (1.0 + r);
            g_ha * (th - t_amb_c) + g_pa * (tp - t_amb_c)
        };
        let (mut lo, mut hi) = (1e-6, 1.0);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if equilibrium_power(mid) < final_power {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let loss = 0.5 * (lo + hi);
        let (g_pa, g_ha) = ((1.0 - heater_share) * loss, heater_share * loss);
        let c_plate = tau_plate_s * (g_hp + g_pa);
        let p_max_w = 1.0;
        // IMC-tuned PI on the heater: closed-loop time constant lambda.
        let lambda_s = uniform(rng, 20.0, 60.0);
        let kp = c_heater / (p_max_w * lambda_s * w);
        let ki = kp / tau_heater_s;
        // A PID's power jitter comes mostly from thermistor noise through its gains (white at
        // the report rate), plus a smaller, slower wobble.
        let noise = Noise {
            temp_sd_c: uniform(rng, 0.02, 0.1),
            ar_sd: uniform(rng, 0.005, 0.02),
            ar_tau_s: uniform(rng, 2.0, 10.0),
            white_sd: uniform(rng, 0.02, 0.05),
        };
        Bed {
            t_amb_c,
            target_c,
            c_heater,
            c_plate,
            g_hp,
            g_pa,
            g_ha,
            p_max_w,
            w,
            kp,
            ki,
            tau_plate_s,
            final_power,
            noise,
        }
    }

    /// Heats from ambient with the target set at t = 0; calls `sample(t_s, power, temp_c)`
    /// once a second until it returns false or `until_s` passes.
    fn run(
        &self,
        noise: Option<Noise>,
        rng: &mut fastrand::Rng,
        until_s: f64,
        mut sample: impl FnMut(f64, f64, f64, f64) -> bool,
    ) {
        const DT: f64 = 0.5;
        let n = noise.unwrap_or_default();
        let (mut th, mut tp) = (self.t_amb_c, self.t_amb_c);
        let mut integ = 0.0;
        let mut dist = 0.0;
        let phi = if n.ar_tau_s > 0.0 {
            (-DT / n.ar_tau_s).exp()
        } else {
            0.0
        };
        let mut step: u64 = 0;
        loop {
            let t = step as f64 * DT;
            if t > until_s {
                return;
            }
            let sensor = self.w * th + (1.0 - self.w) * tp;
            let measured = sensor + n.temp_sd_c * gauss(rng);
            let err = self.target_c - measured;
            let new_integ = integ + err * DT;
            let co = self.kp * err + self.ki * new_integ;
            let bounded = co.clamp(0.0, 1.0);
            if co == bounded {
                integ = new_integ;
            }
            dist = dist * phi + n.ar_sd * (1.0 - phi * phi).sqrt() * gauss(rng);
            let power = (bounded + dist + n.white_sd * gauss(rng)).clamp(0.0, 1.0);
            if step % 2 == 0 && !sample(t, power, measured, tp) {
                return;
            }
            let q_hp = self.g_hp * (th - tp);
            let dth =
                (power * self.p_max_w - q_hp - self.g_ha * (th - self.t_amb_c)) / self.c_heater;
            let dtp = (q_hp - self.g_pa * (tp - self.t_amb_c)) / self.c_plate;
            th += dth * DT;
            tp += dtp * DT;
            step += 1;
        }
    }
}

/// One simulated bed's outcome.
#[derive(Debug, Clone)]
pub(super) struct Outcome {
    pub(super) tau_plate_s: f64,
    /// The last moment the noise-free power was more than 1 % of full power from its final value.
    pub(super) t_one_pct_s: f64,
    /// The last moment the plate (the print surface) was more than 1 K from its final value.
    pub(super) t_surface_s: f64,
    /// First time the (noisy) thermistor was within 2 °C of the target.
    pub(super) t_reach_s: f64,
    pub(super) declared_s: Option<f64>,
    pub(super) power_sd: f64,
    /// The information bound at the detector's own noise at the end of the run (see
    /// `soak_families::information_bound`), with tau_max_s and with it halved, s.
    pub(super) bound_s: f64,
    pub(super) bound_half_s: f64,
    /// The detector's explanation at the end of the run.
    pub(super) why: String,
}

pub(super) fn simulate_bed(bed: &Bed, rng: &mut fastrand::Rng, params: &SoakParams) -> Outcome {
    // Noise-free run: the true power and the 1 % moment.
    let horizon = 14.0 * bed.tau_plate_s + 3600.0;
    let mut t_one = 0.0;
    let mut clean: Vec<f64> = Vec::new();
    let mut plate: Vec<(f64, f64)> = Vec::new();
    bed.run(None, rng, horizon, |t, p, _, tp| {
        if (p - bed.final_power).abs() > 0.01 {
            t_one = t;
        }
        clean.push(p);
        plate.push((t, tp));
        true
    });
    // The surface truth (issue 29): the plate is this bed's print surface.
    let fin = plate.last().map_or(0.0, |p| p.1);
    let t_surface = plate
        .iter()
        .filter(|(_, tp)| (tp - fin).abs() > 1.0)
        .map(|(t, _)| *t)
        .fold(0.0, f64::max);
    // Noisy run through the detector.
    let mut det = SoakDetector::new(params.clone());
    let mut t_reach = f64::NAN;
    let mut declared = None;
    let (mut n, mut sum2) = (0.0, 0.0);
    let mut i = 0;
    let until = 3.0 * t_one + 3600.0;
    bed.run(Some(bed.noise), rng, until, |t, p, temp, _| {
        if t_reach.is_nan() && (temp - bed.target_c).abs() <= 2.0 {
            t_reach = t;
        }
        // The jitter a user sees: noisy power minus the true power, once settled.
        if let Some(c) = clean.get(i) {
            if t > t_reach + 300.0 {
                n += 1.0;
                sum2 += (p - c) * (p - c);
            }
        }
        i += 1;
        if let SoakStatus::Stable { at_s } = det.push(t, p, temp, bed.target_c) {
            declared = Some(at_s);
            return false;
        }
        true
    });
    let var = if n > 0.0 { sum2 / n } else { 0.0 };
    let test_sd = det.fit().map_or(0.0, |f| f.test_sd);
    Outcome {
        tau_plate_s: bed.tau_plate_s,
        t_one_pct_s: t_one,
        t_surface_s: t_surface,
        t_reach_s: t_reach,
        declared_s: declared,
        power_sd: var.sqrt(),
        bound_s: information_bound(
            t_reach,
            test_sd,
            params.tau_max_s,
            weakest_threshold(params),
            params,
        ),
        bound_half_s: information_bound(
            t_reach,
            test_sd,
            params.tau_max_s / 2.0,
            weakest_threshold(params),
            params,
        ),
        why: det.explanation().to_string(),
    }
}
