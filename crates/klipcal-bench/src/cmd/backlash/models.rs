//! The simulated mechanics and people of `klipcal bench backlash`: the axis models with their
//! true lost motion, the person at the camera, the play axis the camera procedure moves, the
//! time a press or a look costs, and the p95 and coverage figures the lines report.

pub(super) fn gauss(rng: &mut fastrand::Rng) -> f64 {
    let u = 1.0 - rng.f64();
    let v = rng.f64();
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// The mechanics of one axis and the camera's mark; the person is a [`Person`].
#[derive(Debug, Clone, Copy)]
pub(super) struct Model {
    pub(super) name: &'static str,
    /// Per reversal, the play taken up varies by this sd (mm).
    pub(super) play_sd_mm: f64,
    /// Stick-slip: after each move the nozzle stops up to this short of where the play
    /// operator puts it (mm), uniformly.
    pub(super) slip_mm: f64,
    /// The camera mark's random walk per look (mm).
    pub(super) drift_mm: f64,
    /// The person's sd when judging the nozzle against the mark (mm).
    pub(super) eye_sd_mm: f64,
    /// Probability that an intended fine jog is clicked as coarse.
    pub(super) misclick: f64,
    /// Probability per look of clicking "centred" while still away (a lapse).
    pub(super) lapse: f64,
    /// The motor moves in whole microsteps of this size (0: continuously): a jog smaller
    /// than a step moves the nozzle only when the commanded position passes half a step.
    pub(super) step_mm: f64,
}

impl Model {
    /// The lost motion between the two approaches that compensation must cancel, mm: the
    /// mean of what one cycle measures on this model. Each reversal takes up a play of
    /// h = max(b/2 + play_sd·g, 0) per side (g normal), and each stop falls short by
    /// slip·U (U uniform 0–1) in the direction of travel, so the approach from below stops at
    /// −(h + slip·U) and the one from above at +(h' + slip·U'): the difference has the mean
    /// 2·E[h] + slip. A compensation of that size leaves each approach's error centred; the
    /// rest varies from reversal to reversal and cannot be compensated.
    pub(super) fn lost_motion_mm(&self, b_mm: f64) -> f64 {
        let (mu, sd) = (b_mm / 2.0, self.play_sd_mm);
        let half = if sd > 0.0 {
            // E[max(X, 0)] for X ~ N(mu, sd²).
            let z = mu / sd;
            mu * normal_cdf(z) + sd * (-0.5 * z * z).exp() / (std::f64::consts::TAU).sqrt()
        } else {
            mu.max(0.0)
        };
        2.0 * half + self.slip_mm
    }
}

/// The standard normal's distribution function (Abramowitz–Stegun 7.1.26, error < 1.5e-7).
fn normal_cdf(z: f64) -> f64 {
    let x = z.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erf = 1.0 - poly * (-x * x).exp();
    0.5 * (1.0 + if z >= 0.0 { erf } else { -erf })
}

pub(super) const MODELS: [Model; 2] = [
    Model {
        name: "ideal play, careful eye",
        play_sd_mm: 0.0,
        slip_mm: 0.0,
        drift_mm: 0.0,
        eye_sd_mm: 0.002,
        misclick: 0.0,
        lapse: 0.0,
        step_mm: 0.0,
    },
    Model {
        name: "stick-slip play, camera drift, misclicks, lapses",
        play_sd_mm: 0.002,
        slip_mm: 0.004,
        drift_mm: 0.0003,
        eye_sd_mm: 0.003,
        misclick: 0.03,
        lapse: 0.002,
        step_mm: 0.0,
    },
];

/// The guided flow's models: the camera's two and one whose axis is built differently, so
/// that the estimator is not fitted to one simulator: the motor moves in whole microsteps
/// (40 mm per turn, 200 full steps, 32 microsteps: 6.25 µm), so many fine jogs move nothing
/// and the next one moves a whole step, on a lattice fixed to the machine that no dither
/// moves; the play varies a little per reversal and the eye is as careful as model 1's.
pub(super) const GUIDED_MODELS: [Model; 3] = [
    MODELS[0],
    MODELS[1],
    Model {
        name: "microstepped motor (6.25 µm steps), varying play",
        play_sd_mm: 0.001,
        slip_mm: 0.0,
        drift_mm: 0.0,
        eye_sd_mm: 0.002,
        misclick: 0.0,
        lapse: 0.0,
        step_mm: 0.00625,
    },
];

/// How the person at the camera decides "centred" (issue 27: the jog-size correction assumed
/// a person who stops late; a person who stops short read 5–13 µm low).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Person {
    /// Calls it centred as soon as the nozzle looks within a few µm (2–8 µm, drawn per axis),
    /// whatever the jog: stops short.
    Short,
    /// Calls it at the nearest jog (a zone of ±half a jog) and reacts a jog late: every answer
    /// is what the previous look showed (in the flow before, whose only answers were Centred
    /// and Past, that was one more fine jog before each): stops late.
    Late,
    /// Either, drawn per approach.
    Mixed,
}

pub(super) const PERSONS: [Person; 3] = [Person::Short, Person::Late, Person::Mixed];

impl Person {
    pub(super) fn name(self) -> &'static str {
        match self {
            Person::Short => "stops short",
            Person::Late => "stops a jog late",
            Person::Mixed => "mixed",
        }
    }
}

/// Realistic time of a guided axis: each press is a look and a tap on a phone (1.5 s) and a
/// move; a move at the jog speed (`JOG_F`, 20 mm/s) plus 0.1 s to start and stop.
pub(super) const PRESS_S: f64 = 1.5;
pub(super) const JOG_MM_S: f64 = 20.0;
pub(super) const MOVE_OVERHEAD_S: f64 = 0.1;
/// A camera look: `camera_settle_s` (0.3 s) and two frames that agree, 0.2 s each.
const LOOK_S: f64 = 0.7;

/// The camera procedure's time per axis at `cycles`: the scale (per axis a move to −1 mm,
/// three 0.5 mm steps with a look each, back to 0: 3 mm, 5 moves) and per cycle −1, 0 (look),
/// +1, 0 (look): 4 mm, 4 moves.
pub(super) fn camera_time_s(cycles: usize) -> f64 {
    let moves = 2 * 5 + 4 * cycles;
    let travel_mm = 2.0 * 3.0 + 4.0 * cycles as f64;
    let looks = 2 * 3 + 2 * cycles;
    moves as f64 * MOVE_OVERHEAD_S + travel_mm / JOG_MM_S + looks as f64 * LOOK_S
}

/// The click flow's time per axis: the camera procedure's moves, with each look replaced by
/// the settle (0.3 s), a snapshot and the person's look and click ([`PRESS_S`]), and one more
/// click that zooms in on the first picture.
pub(super) fn click_time_s(cycles: usize) -> f64 {
    let looks = (2 * 3 + 2 * cycles) as f64;
    camera_time_s(cycles) - looks * LOOK_S + looks * (0.3 + PRESS_S) + PRESS_S
}

/// The stated ± is the standard uncertainty u; ±2u is the 95 % interval whose coverage the
/// benchmark checks ([`coverage`]).
pub(super) const COVER_K: f64 = 2.0;

/// Judges a ±2u that held the truth for `covered` of `n` answers (issue 27: "a ± that covers
/// the error"). It passes at 93 % or more, or short of that by no more than `n` answers
/// explain (the Wilson 95 % interval of the coverage reaches 93 %: 37 of 40 is as likely from
/// a true 95 % as 950 of 1000). Above 97 % the ± is wider than it needs to be, which is said
/// but not failed: the safe side (a motor's microstep counted whole, a camera whose cycles
/// agree to a fraction of a µm). Returns whether it passes and the text for the line.
pub(super) fn coverage(covered: usize, n: usize) -> (bool, String) {
    const MIN_PCT: f64 = 93.0;
    const WIDE_PCT: f64 = 97.0;
    if n == 0 {
        return (true, String::new());
    }
    let (c, nf) = (covered as f64, n as f64);
    let pct = 100.0 * c / nf;
    // Wilson's score interval, z = 1.96.
    let (z, p) = (1.96f64, c / nf);
    let mid = (p + z * z / (2.0 * nf)) / (1.0 + z * z / nf);
    let half = z / (1.0 + z * z / nf) * (p * (1.0 - p) / nf + z * z / (4.0 * nf * nf)).sqrt();
    let (lo, hi) = (100.0 * (mid - half), 100.0 * (mid + half));
    let ok = pct >= MIN_PCT || hi >= MIN_PCT;
    let note = if pct > WIDE_PCT {
        format!(": wider than needed (above {WIDE_PCT:.0} %), the safe side")
    } else if pct < MIN_PCT && ok {
        format!(": short by no more than {n} answers explain, interval {lo:.1}–{hi:.1} %")
    } else {
        String::new()
    };
    (
        ok,
        format!(
            "±2u covers {pct:.1} % of {n} (target ≥ {MIN_PCT:.0} %, nominal 95 %{note}) {}",
            if ok { "PASS" } else { "FAIL" }
        ),
    )
}

pub(super) fn p95(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.iter().map(|x| x.abs()).collect();
    if s.is_empty() {
        return f64::NAN;
    }
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * 0.95).round() as usize]
}

/// One simulated axis with play: the motor at `motor`, the nozzle within ±h of it.
pub(super) struct PlayAxis {
    b_mm: f64,
    play_sd_mm: f64,
    slip_mm: f64,
    motor: f64,
    pub(super) nozzle: f64,
    last_dir: f64,
    h: f64,
}

impl PlayAxis {
    pub(super) fn new(model: &Model, b_mm: f64, rng: &mut fastrand::Rng) -> PlayAxis {
        PlayAxis {
            b_mm,
            play_sd_mm: model.play_sd_mm,
            slip_mm: model.slip_mm,
            motor: 0.0,
            nozzle: if rng.bool() { b_mm / 2.0 } else { -b_mm / 2.0 },
            last_dir: 0.0,
            h: b_mm / 2.0,
        }
    }

    /// The same mechanics as the guided procedure's simulator.
    pub(super) fn move_to(&mut self, m: f64, rng: &mut fastrand::Rng) {
        let dir = (m - self.motor).signum();
        if dir != 0.0 && dir != self.last_dir {
            self.h = (self.b_mm / 2.0 + self.play_sd_mm * gauss(rng)).max(0.0);
            self.last_dir = dir;
        }
        self.nozzle = self.nozzle.clamp(m - self.h, m + self.h);
        if self.slip_mm > 0.0 && dir != 0.0 {
            self.nozzle -= dir * self.slip_mm * rng.f64();
            self.nozzle = self
                .nozzle
                .clamp(m - self.h - self.slip_mm, m + self.h + self.slip_mm);
        }
        self.motor = m;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The truth the camera and click lines are judged against is the simulated axis's own
    /// mean lost motion between the approaches: the mean of many cycles run on `PlayAxis`
    /// (model 2: b + the stick-slip's 4 µm; near b = 0 the play's spread, clamped at 0, adds a
    /// little more).
    #[test]
    fn coverage_passes_what_sampling_explains_and_fails_a_short_one() {
        assert!(coverage(950, 1000).0);
        assert!(coverage(37, 40).0, "{}", coverage(37, 40).1);
        assert!(!coverage(900, 1000).0, "{}", coverage(900, 1000).1);
        assert!(!coverage(30, 40).0, "{}", coverage(30, 40).1);
        let (ok, text) = coverage(999, 1000);
        assert!(ok && text.contains("wider than needed"), "{text}");
    }

    #[test]
    fn the_lost_motion_is_the_mean_of_what_the_simulated_axis_loses_per_cycle() {
        let mut rng = fastrand::Rng::with_seed(9);
        for model in &MODELS {
            for b in [0.0, 0.004, 0.08] {
                let mut ax = PlayAxis::new(model, b, &mut rng);
                let n = 40_000;
                let mut sum = 0.0;
                for _ in 0..n {
                    ax.move_to(-1.0, &mut rng);
                    ax.move_to(0.0, &mut rng);
                    let plus = ax.nozzle;
                    ax.move_to(1.0, &mut rng);
                    ax.move_to(0.0, &mut rng);
                    sum += ax.nozzle - plus;
                }
                let mean = sum / f64::from(n);
                let want = model.lost_motion_mm(b);
                assert!(
                    (mean - want).abs() < 5e-5,
                    "{}: b {b}: cycles lose {mean} on average, lost_motion_mm {want}",
                    model.name
                );
            }
        }
        assert!((MODELS[1].lost_motion_mm(0.08) - 0.084).abs() < 1e-9);
    }
}
