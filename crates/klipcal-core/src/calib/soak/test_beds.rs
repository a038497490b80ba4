//! Beds simulated for the soak's tests, shared by the detector's and the coupling's.

use super::{SoakDetector, SoakParams, SoakStatus};

pub(super) const TARGET_C: f64 = 60.0;

/// A bed of two nodes in full-power units: the thermistor's (heat capacity `c_th`, losses
/// `h_th`) and the print surface beyond it (capacity `c_s`, coupling `g`, losses `h_s`),
/// from 22 °C under a PI controller on the thermistor with `noise_c` of reading noise.
/// Returns `(t, power, reading, surface)` once a second for `until_s`.
#[allow(clippy::too_many_arguments)]
pub(super) fn two_node_bed(
    g: f64,
    c_th: f64,
    c_s: f64,
    h_th: f64,
    h_s: f64,
    noise_c: f64,
    until_s: f64,
    seed: u64,
) -> Vec<[f64; 4]> {
    let mut rng = fastrand::Rng::with_seed(seed);
    let mut gauss = move || {
        let u = 1.0 - rng.f64();
        let v = rng.f64();
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let (amb, dt) = (22.0, 0.25);
    let (mut th, mut ts, mut integ) = (amb, amb, 0.0);
    let (kp, ki) = (c_th / 20.0, c_th / 20.0 / 60.0);
    let mut out = Vec::new();
    let mut t: f64 = 0.0;
    let mut power = 1.0;
    while t <= until_s {
        if (t.fract()).abs() < 1e-9 {
            let reading = th + noise_c * gauss();
            let err = TARGET_C - reading;
            let co = kp * err + ki * (integ + err);
            power = co.clamp(0.0, 1.0);
            if (co - power).abs() < 1e-12 {
                integ += err;
            }
            out.push([t, power, reading, ts]);
        }
        let q = g * (th - ts);
        th += dt * (power - q - h_th * (th - amb)) / c_th;
        ts += dt * (q - h_s * (ts - amb)) / c_s;
        t += dt;
    }
    out
}

/// Runs the detector over a bed; returns it and the declaration time.
pub(super) fn run_bed(
    params: SoakParams,
    bed: &[[f64; 4]],
    from: usize,
) -> (SoakDetector, Option<f64>) {
    let mut d = SoakDetector::new(params);
    for s in &bed[from..] {
        if let SoakStatus::Stable { at_s } = d.push(s[0], s[1], s[2], TARGET_C) {
            return (d, Some(at_s));
        }
    }
    (d, None)
}

/// The surface's distance from its final temperature at `t_s`, K.
pub(super) fn surface_left(bed: &[[f64; 4]], t_s: f64) -> f64 {
    let last = bed.last().unwrap()[3];
    let now = bed.iter().find(|s| s[0] >= t_s).unwrap()[3];
    last - now
}
