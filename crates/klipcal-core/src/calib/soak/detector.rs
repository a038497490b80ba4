//! PURE: the soak detector's state: samples into bins, the saturation, overshoot and step-down
//! bookkeeping, the coupling's identification and the status it reports (the test it decides
//! by is in `decide`).

use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use super::chamber::ChamberGate;
use super::coupling::{identify_coupling, Coupling, ID_HOLD_S};
use super::stack::{open_frame_reach, SurfaceReach};
use super::SoakParams;

mod decide;

/// What the detector says after a sample.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum SoakStatus {
    /// The temperature is not (or no longer) within the band around the target.
    Heating,
    /// The temperature is settled; waiting for the power to stop falling.
    Soaking {
        /// Rough fraction of the soak done, 0..1: elapsed / (elapsed + ETA); 0 without an ETA.
        progress: f64,
        /// Predicted seconds until the bed is declared stable, when the fit can tell.
        eta_s: Option<f64>,
        /// What is still being waited for, in words.
        reason: String,
        /// What printing now would cost: the surface warming still possible at 95 %, K
        /// (once the power has been watched long enough to tell).
        print_now_c: Option<f64>,
    },
    /// Equilibrium: the power has stopped falling. Stays so until the target changes.
    Stable {
        /// The sample time at which it was declared.
        at_s: f64,
    },
    /// Unheated bed (target at or below `skip_below_c`): no soak needed.
    Skipped,
}

/// The decay fitted to the bed power since the soak began, summed up as one exponential.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DecayFit {
    /// Time constant τ of what is still to fall (the fitted decays weighted by what each has
    /// left now).
    pub tau_s: f64,
    /// The power the decay tends to, P∞ (fraction of full power).
    pub final_power: f64,
    /// The power still to fall from now to P∞ in the best fit (fraction of full power, ≥ 0);
    /// after a step down, the power still to rise.
    pub remaining: f64,
    /// The largest power still to fall (after a step down: to rise) that the data cannot rule
    /// out (about three standard errors), over every decay up to `tau_max_s`: the bed is
    /// stable once this is below `max_remaining`.
    pub remaining_upper: f64,
    /// The fitted fall from the start of the soak to P∞ (negative when the power rises).
    pub amplitude: f64,
    /// The soak follows a step down to a lower target: the power rises while the
    /// surroundings cool, and `remaining` is a rise.
    pub rising: bool,
    /// Most of what is left sits in the slowest decay allowed: the end is not in sight yet.
    pub tau_unbounded: bool,
    /// Scatter (standard deviation) of the binned power about the fit.
    pub noise_sd: f64,
    /// The bin noise the test ruled `max_remaining` out against (standard deviation): the
    /// scatter at the one-minute scale and beyond, widened while the data are short.
    pub test_sd: f64,
    /// Factor by which slow (correlated) noise widens the test: the scatter at the one-minute
    /// scale over the scatter of single bins (1 for white noise).
    pub noise_inflation: f64,
    /// The power still to fall that the rule allows (budget × coupling).
    pub threshold: f64,
    /// The surface warming still possible (about three standard errors), K: the bed is
    /// stable once this is within `surface_budget_c`.
    pub surface_upper_c: f64,
    /// The surface warming still possible at 95 %, K: what printing now costs.
    pub surface_95_c: f64,
}

impl DecayFit {
    /// How fast the power moves now, % of full power per 10 min (negative: it rises), as a
    /// person is told it: only when the fit is physically plausible — a finite τ, a final
    /// power within 0..1, at most all of full power still to move, and a rate of at most
    /// 100 % per 10 min. Otherwise `None` ("has not settled"): a fit that extrapolates far past
    /// its data once told a user "886742.1 % per 10 min".
    #[must_use]
    pub fn rate_pct_per_10min(&self) -> Option<f64> {
        let plausible = self.tau_s.is_finite()
            && self.tau_s > 0.0
            && self.remaining.is_finite()
            && (0.0..=1.0).contains(&self.remaining)
            && (0.0..=1.0).contains(&self.final_power);
        let rate = self.remaining / self.tau_s * 600.0 * 100.0;
        (plausible && rate <= 100.0).then_some(if self.rising { -rate } else { rate })
    }
}

/// The fastest time constant of the model: 1/60 of `tau_max_s` (one minute at the default),
/// at least two bins.
fn grid_min_s(p: &SoakParams) -> f64 {
    (p.tau_max_s / 60.0).max(2.0 * p.bin_s)
}
/// Decays faster than this many times the grid's fastest may be negative (the controller's
/// undershoot); slower ones are the plate's and its surroundings' and only decay.
const FREE_TAUS: f64 = 2.5;
/// The most a decay may hold at the start of the soak, either way, in `max_power`: the power
/// stays within 0..max_power, so what is still to fall or rise of it is at most max_power,
/// and a controller's swing (a free decay) no more; twice that, as the grid's neighbouring
/// decays share a true one between them.
const DECAY_BOUND: f64 = 2.0;
/// Columns after the decays: the temperature's rate of change (heat into the bed's own
/// capacity, either sign); under MPC also the high-passed temperature (see [`HP_TAUS`]).
const EXTRA_COLS: usize = 1;
/// Under Kalico's MPC the temperature itself moves (an overshoot of 1–2 K for some minutes
/// after the band, then a slow wander of 0.1 K) and the power follows it. A clamped RC
/// network's power answers a step of its thermistor's temperature with the step's share
/// that charges the neighbours, decaying as they catch up (a sum of decays with positive
/// amplitudes, as a heat-up's): so the power's answer to the measured temperature since the
/// band is the temperature high-passed at the network's time constants, each with a
/// coefficient ≥ 0. These columns take the answer to the overshoot and the wander out of the
/// power; what is left is the heat-up's own decays, all positive (see `SoakDetector::free`).
/// Time constants, s.
const HP_TAUS: [f64; 6] = [60.0, 120.0, 240.0, 480.0, 960.0, 1920.0];
/// Ratio between neighbouring time constants of the grid.
const GRID_RATIO: f64 = std::f64::consts::SQRT_2;
/// Consecutive bins out of the band that restart the soak clock (fewer are only skipped).
const OUT_OF_BAND_BINS: u32 = 3;
/// Bins in the shortest noise block (the one-minute scale at the default bin).
const BLOCK_BINS: usize = 6;
/// Fewest blocks a long-run noise estimate rests on.
const MIN_BLOCKS: usize = 10;
/// Fewest bins before a fit is tried.
const MIN_POINTS: usize = 6;
/// Bins kept at most (about 55 h at the default bin); beyond, the soak is far too long to
/// matter and older bins are dropped from the model.
const MAX_POINTS: usize = 20_000;
/// Samples further apart than this are a gap: the earlier value is held this long, not over
/// the whole gap.
const MAX_HOLD_S: f64 = 30.0;
/// Saturation is judged on the mean power over this long.
const SATURATION_WINDOW_S: f64 = 60.0;
/// Readings (power between off and the cap, and temperature) unchanged this long are frozen, s.
const FROZEN_S: f64 = 120.0;
/// A power held this long at one value while heating is the heater's cap (`max_power`), s.
const CAP_RUN_S: f64 = 30.0;
/// A temperature this far over the target counts as an overshoot, °C.
const OVERSHOOT_C: f64 = 0.5;
/// The coldest room a printer runs in, °C: after a warm start, the lowest the print surface
/// can be.
const COLDEST_ROOM_C: f64 = 10.0;

#[derive(Debug, Clone, Copy)]
struct Point {
    t_s: f64,
    power: f64,
    /// The bin's rate of temperature change (°C/s), edge to edge: power that went into the
    /// bed's own heat capacity (a bang-bang heater's on and off, a PID's derivative kick) is
    /// no heat flow to its surroundings, and this column takes it out of the decays.
    rate_c_s: f64,
    /// The temperature since the band was first reached, high-passed at each of [`HP_TAUS`]
    /// (used under MPC only).
    hp: [f64; HP_TAUS.len()],
}

/// A bin being filled: the time-weighted integrals of power, time and temperature.
#[derive(Debug, Clone, Default)]
struct Bin {
    start_s: f64,
    covered_s: f64,
    t_int: f64,
    power_int: f64,
    temp_sum: f64,
    temp_n: u32,
    temp_last: f64,
}

/// One direction's test (see `SoakDetector::test`).
#[derive(Debug, Clone)]
struct DirectionTest {
    /// +1: the power's fall is tested; −1: its rise (the model sees the negated power).
    sign: f64,
    best: Solution,
    white: f64,
    sigma2: f64,
    remaining: f64,
    remaining_upper: f64,
    remaining_95: f64,
    ruled_out: bool,
}

/// The model fitted by least squares with its sign constraints.
#[derive(Debug, Clone)]
struct Solution {
    coef: DVector<f64>,
    sse: f64,
}

/// The thermal soak detector: feed it every heater_bed sample; it says when the bed is at
/// equilibrium. Pure: time comes in with each sample.
#[derive(Debug, Clone)]
pub struct SoakDetector {
    params: SoakParams,
    /// Time constants of the model's decays (column k + 1 of the design).
    taus: Vec<f64>,
    target_c: Option<f64>,
    last: Option<(f64, f64)>,
    bin: Option<Bin>,
    /// Where the last closed bin with a temperature ended, and its last temperature.
    edge: Option<(f64, f64)>,
    /// Mean powers of the latest bins (for the one-minute saturation check).
    recent: Vec<(f64, f64)>,
    band_since_s: Option<f64>,
    soak_t0_s: Option<f64>,
    /// Time origin of the model's exponentials (the first bin of the soak).
    origin_s: Option<f64>,
    points: Vec<Point>,
    /// Each point's row of the model ([`SoakDetector::row`]), one after another: the noise
    /// estimate reads every row on every bin, and a row's decays only change with the origin.
    rows: Vec<f64>,
    /// Normal equations of the model over `points`: XᵀX, Xᵀy, yᵀy.
    xtx: DMatrix<f64>,
    xty: DVector<f64>,
    yty: f64,
    out_of_band_bins: u32,
    excursions: u32,
    last_saturated_s: Option<f64>,
    /// The heater's `max_power` (Klipper caps the pwm there): saturation is measured against it.
    max_power: f64,
    /// `max_power` came from Klipper's config ([`SoakDetector::set_max_power`]); otherwise it
    /// is learnt from the heat-up (see `learn_cap`).
    max_power_set: bool,
    /// The power held at one value while heating, and since when.
    cap_run: Option<(f64, f64)>,
    /// The last reading (power, temperature), and since when readings have not changed.
    reading: Option<(f64, f64)>,
    unchanged_since_s: Option<f64>,
    status: SoakStatus,
    explanation: String,
    fit: Option<DecayFit>,
    /// The progress reported last in this soak (it never goes back).
    progress_floor: f64,
    /// The last bin within the band, and the longest excursion out of it so far.
    last_in_band_s: Option<f64>,
    excursion_len_s: f64,
    /// Since when the temperature has been over the target by more than `OVERSHOOT_C`.
    over_since_s: Option<f64>,
    /// The side the temperature last was on, out of the band, before the soak first began:
    /// `Some(true)` above (a step down), `Some(false)` below (a heat-up).
    approach_above: Option<bool>,
    /// The first temperature seen for this target was above `skip_below_c` and out of the
    /// band: the bed was heated before (a print, another target) and now moves to a new one,
    /// so its plate and surroundings may be in any state. (A bed first seen at its target has
    /// been held there: a daemon primed from Moonraker's store, a second round.)
    warm_start: Option<bool>,
    /// The first temperature seen for this target was at room temperature (at or below
    /// `skip_below_c`): the heat-up can identify the coupling.
    cold_start: Option<(bool, f64)>,
    /// Bins from the first on, `(t_s, power, temp_c, rate_c_s)`, until the coupling is
    /// identified.
    history: Vec<[f64; 4]>,
    /// The coupling the rule uses now, and whether it is final (identified or given up).
    coupling: Coupling,
    coupling_final: bool,
    /// The first time the temperature entered the band for this target.
    first_band_s: Option<f64>,
    /// A chamber thermometer, when the printer has one (see [`super::chamber`]).
    gate: Option<Box<ChamberGate>>,
    /// The lowest temperature seen for this target, °C: the surface, which lags the
    /// thermistor on its way up, was at least there (see [`SoakDetector::surface_reach_c`]).
    lowest_c: Option<f64>,
    /// The print-now cost told last, K: a later one is never higher (the surface's warming
    /// still to come only shrinks while the bed is held), so the figure does not jump.
    print_now_told: Option<f64>,
    /// A coupling identified from an earlier cold heat-up of this bed (see
    /// [`super::carry::CarriedCoupling`]): used on a warm start instead of the fallback.
    carried: Option<Coupling>,
    /// Surface warming reserved out of the budget for the air around the bed, K (a chamber
    /// thermometer's, see [`super::chamber`]; 0 without one).
    reserve_c: f64,
    /// The ETA's projection: when it was made and what it said, s from then (None: beyond
    /// its horizon); see `decide`.
    projection: Option<(f64, Option<f64>)>,
    /// The temperature when the band was first reached and the low-passed temperatures
    /// since (for [`HP_TAUS`]).
    hp_ref: Option<f64>,
    hp_low: [f64; HP_TAUS.len()],
}

impl SoakDetector {
    /// A detector with these thresholds. Values out of range are replaced by their defaults
    /// (check them with [`SoakParams::validate`] when they come from a user).
    pub fn new(params: SoakParams) -> Self {
        let params = if params.validate().is_ok() {
            params
        } else {
            SoakParams::default()
        };
        let mut taus = Vec::new();
        let mut tau = grid_min_s(&params);
        let slowest = params.slowest_s();
        while tau < slowest / 1.1 {
            taus.push(tau);
            tau *= GRID_RATIO;
        }
        taus.push(slowest);
        let k = taus.len() + 1 + extra_cols(&params);
        let coupling = Coupling::fallback(
            &params,
            "not identified yet (from the heat-up, after the first minutes at the target)",
        );
        SoakDetector {
            params,
            taus,
            target_c: None,
            last: None,
            bin: None,
            edge: None,
            recent: Vec::new(),
            band_since_s: None,
            soak_t0_s: None,
            origin_s: None,
            points: Vec::new(),
            rows: Vec::new(),
            xtx: DMatrix::zeros(k, k),
            xty: DVector::zeros(k),
            yty: 0.0,
            out_of_band_bins: 0,
            excursions: 0,
            last_saturated_s: None,
            max_power: 1.0,
            max_power_set: false,
            cap_run: None,
            reading: None,
            unchanged_since_s: None,
            status: SoakStatus::Heating,
            explanation: "no samples yet".into(),
            fit: None,
            progress_floor: 0.0,
            last_in_band_s: None,
            excursion_len_s: 0.0,
            warm_start: None,
            cold_start: None,
            history: Vec::new(),
            coupling,
            coupling_final: false,
            first_band_s: None,
            over_since_s: None,
            approach_above: None,
            gate: None,
            lowest_c: None,
            print_now_told: None,
            carried: None,
            reserve_c: 0.0,
            projection: None,
            hp_ref: None,
            hp_low: [0.0; HP_TAUS.len()],
        }
    }

    /// A coupling identified from this bed's earlier cold heat-up, for a warm start (a bed
    /// reheated after an apply, or first seen at its target): the rule uses it instead of
    /// the preset or the weakest. A cold heat-up seen here is identified as always.
    pub fn carry_coupling(&mut self, coupling: Coupling) {
        if let Some(g) = self.gate.as_mut() {
            g.stack.carry_coupling(coupling.clone());
        }
        self.carried = Some(coupling);
    }

    /// The most the print surface can still warm, K, whatever the fit: from where it can be
    /// now to the target. It was at least at the lowest temperature seen since a cold start
    /// (it lags the thermistor on the way up and warms on); after a warm start the bed's past
    /// is not seen, and the coldest room, [`COLDEST_ROOM_C`], is all that is known.
    #[must_use]
    pub fn surface_reach_c(&self) -> Option<f64> {
        let target = self.target_c?;
        let lowest = self.lowest_c?;
        let from = match self.cold_start {
            Some((true, _)) => lowest,
            _ => lowest.min(COLDEST_ROOM_C),
        };
        Some((target - from).max(0.0))
    }

    /// What printing now costs, K, as told: the fit's 95 % figure, at most
    /// [`SoakDetector::surface_reach_c`] and never above the figure told before.
    fn print_now_bounded(&mut self, surface_95_c: f64) -> f64 {
        let c = surface_95_c
            .max(0.0)
            .min(self.surface_reach_c().unwrap_or(f64::INFINITY))
            .min(self.print_now_told.unwrap_or(f64::INFINITY));
        self.print_now_told = Some(c);
        c
    }

    /// The heater's `max_power` from Klipper's config (0.05–1; Klipper reports the pwm as a
    /// fraction of full power, capped there): a heater at `saturated_power` of it has no
    /// headroom left. Out-of-range values are ignored.
    pub fn set_max_power(&mut self, max_power: f64) {
        if max_power.is_finite() && (0.05..=1.0).contains(&max_power) {
            self.max_power = max_power;
            self.max_power_set = true;
        }
        if let Some(g) = self.gate.as_mut() {
            g.stack.set_max_power(max_power);
        }
    }

    /// The `max_power` saturation is measured against: Klipper's, when given; else 1.0 until
    /// the heat-up shows a lower cap (see [`SoakDetector::push`]).
    #[must_use]
    pub fn max_power(&self) -> f64 {
        self.max_power
    }

    /// Without Klipper's `max_power` (a trace replayed offline), the cap shows in the heat-up:
    /// while the bed is below its band a PID heater sits at exactly `max_power`, and a
    /// watermark heater's "on" is `max_power`. A power held at one value for `CAP_RUN_S` while
    /// heating, below the cap assumed so far, is taken as the cap.
    fn learn_cap(&mut self, t_s: f64, power: f64, temp_c: f64, target_c: f64) {
        let heating = temp_c < target_c - self.params.temp_band_c;
        match self.cap_run {
            Some((v, since)) if heating && (power - v).abs() < 1e-9 => {
                if t_s - since >= CAP_RUN_S && v >= 0.05 && v < self.max_power {
                    self.max_power = v;
                }
            }
            _ => self.cap_run = heating.then_some((power, t_s)),
        }
    }

    /// The thresholds in use.
    pub fn params(&self) -> &SoakParams {
        &self.params
    }

    /// The coupling from thermistor to surface the rule uses now, and where it came from.
    pub fn coupling(&self) -> &Coupling {
        &self.coupling
    }

    /// On an open frame, which decays reach the print surface and how much of them.
    pub fn reach(&self) -> Option<SurfaceReach> {
        open_frame_reach(&self.params.frame, &self.params.bed, self.coupling.charge_s)
    }

    /// Which decays are ruled out and, on an open frame, how much of the slow ones reaches the
    /// surface, in words.
    pub fn slowest_words(&self) -> String {
        let base = self.params.slowest_s();
        let words = self.params.slowest_words();
        match self.reach() {
            Some(r) if r.whole_s < base => {
                let share = if r.slow_share == 0.0 {
                    "with the thermistor in the plate it does not reach the surface".to_string()
                } else if r.slow_share < 1.0 {
                    format!(
                        "with the thermistor in the pad at most {:.0} % of it reaches the \
                         surface",
                        r.slow_share * 100.0
                    )
                } else {
                    "all of it may reach the surface (soak.bed not set, or a bare plate over a \
                     pad)"
                        .to_string()
                };
                format!(
                    "{words}; a decay slower than {:.0} min is the carriage or frame warming: \
                     {share}",
                    r.whole_s / 60.0
                )
            }
            _ => words,
        }
    }

    /// The coupling is settled for this target (identified, or fallen back and said why).
    pub fn coupling_final(&self) -> bool {
        self.coupling_final
    }

    /// The power (fraction of full power) that may still fall when the bed is declared: the
    /// surface budget (less what a chamber's air may still bring) times the coupling (issue
    /// 10's fixed value in the bench's comparison).
    #[must_use]
    pub fn threshold(&self) -> f64 {
        self.params.fixed_remaining.unwrap_or_else(|| {
            ((self.params.surface_budget_c - self.reserve_c) * self.coupling.g)
                .min(0.5 * self.max_power)
        })
    }

    /// Surface kelvin for power still to fall (weighted for the stack's charge, see
    /// `decays_at`): ΔP / G.
    fn surface_c(&self, power: f64) -> f64 {
        power / self.coupling.g
    }

    /// Once the bed has held its band for [`ID_HOLD_S`], the coupling is settled for this
    /// target: the preset or the weakest, capped by what a cold heat-up allows.
    fn update_coupling(&mut self, now_s: f64) {
        if self.coupling_final {
            return;
        }
        let Some(first) = self.first_band_s else {
            return;
        };
        if now_s - first < ID_HOLD_S {
            return;
        }
        self.coupling_final = true;
        let history = std::mem::take(&mut self.history);
        self.coupling = match self.cold_start {
            _ if self.params.no_identify => {
                Coupling::fallback(&self.params, "not identified (the bench's comparison)")
            }
            Some((true, _)) => match identify_coupling(&history, &self.params) {
                Ok(id) => id,
                Err(why) => Coupling::fallback(&self.params, &format!("not identified: {why}")),
            },
            Some((false, _)) | None if self.carried.is_some() => self
                .carried
                .clone()
                .unwrap_or_else(|| Coupling::fallback(&self.params, "not identified")),
            Some((false, temp)) => Coupling::fallback(
                &self.params,
                &format!(
                    "not identified: the bed was first seen at {temp:.1} °C, not heated from \
                     room temperature (a warm start)"
                ),
            ),
            None => Coupling::fallback(&self.params, "not identified: no heat-up seen"),
        };
    }

    /// The latest status (as returned by the last [`push`](Self::push)).
    pub fn status(&self) -> &SoakStatus {
        self.gate.as_ref().map_or(&self.status, |g| &g.status)
    }

    /// Why the detector says what it says, in words: what it waits for, or why it declared.
    pub fn explanation(&self) -> &str {
        self.gate
            .as_ref()
            .map_or(&self.explanation, |g| &g.explanation)
    }

    /// The latest decay fit, once the soak has enough data.
    pub fn fit(&self) -> Option<DecayFit> {
        self.fit
    }

    /// Forgets everything but the thresholds and `max_power` (a new heat-up).
    pub fn reset(&mut self) {
        let (max_power, set) = (self.max_power, self.max_power_set);
        let carried = self.carried.take();
        let gate = self.gate.take().map(|mut g| {
            g.stack.reset();
            g.status = SoakStatus::Heating;
            g
        });
        *self = SoakDetector::new(self.params.clone());
        self.max_power = max_power;
        self.max_power_set = set;
        self.gate = gate;
        self.carried = carried;
    }

    /// Feeds one sample: time `t_s` (any origin, increasing), heater `power` (0..1, held until
    /// the next sample, at most 30 s), bed temperature `temp_c` and target `target_c`. Samples
    /// that are not finite or not later than the previous one are ignored; a change of target
    /// restarts the soak. The status changes at most once per `bin_s`.
    pub fn push(&mut self, t_s: f64, power: f64, temp_c: f64, target_c: f64) -> SoakStatus {
        if let Some(g) = self.gate.as_mut() {
            g.chamber.set_now(t_s);
            // The air's share of the budget, from the chamber's trend so far, for both rules.
            self.reserve_c = g.reserve_c(&self.params, self.coupling.g);
            g.stack.reserve_c = g.reserve_c(&self.params, g.stack.coupling.g);
        }
        let main = self.push_bed(t_s, power, temp_c, target_c);
        match self.gate.take() {
            None => main,
            Some(mut g) => {
                g.stack.push_bed(t_s, power, temp_c, target_c);
                let g_used = self.coupling.g.min(g.stack.coupling.g);
                g.decide(&main, &self.explanation, target_c, g_used);
                let status = g.status.clone();
                self.gate = Some(g);
                status
            }
        }
    }

    /// Reads a chamber thermometer (`name` as Klipper names its object) beside the bed: while
    /// it still warms the soak waits, once it is flat the rule rules out only the bed stack's
    /// own decays (see [`super::chamber`]).
    #[must_use]
    pub fn with_chamber(mut self, name: &str) -> Self {
        let mut stack = SoakDetector::new(SoakParams {
            frame: "open".into(),
            ..self.params.clone()
        });
        if self.max_power_set {
            stack.set_max_power(self.max_power);
        }
        if let Some(c) = &self.carried {
            stack.carry_coupling(c.clone());
        }
        self.gate = Some(Box::new(ChamberGate::new(name, stack)));
        self
    }

    /// A chamber reading (ignored without [`with_chamber`](Self::with_chamber)).
    pub fn push_chamber(&mut self, t_s: f64, temp_c: f64) {
        if let Some(g) = self.gate.as_mut() {
            g.chamber.push(t_s, temp_c);
        }
    }

    /// The chamber thermometer's trend in words, naming it, when there is one.
    #[must_use]
    pub fn chamber_words(&self) -> Option<String> {
        self.gate
            .as_ref()
            .map(|g| g.words(&self.params, self.coupling.g.min(g.stack.coupling.g)))
    }

    /// [`push`](Self::push) without the chamber.
    fn push_bed(&mut self, t_s: f64, power: f64, temp_c: f64, target_c: f64) -> SoakStatus {
        if !(t_s.is_finite() && power.is_finite() && temp_c.is_finite() && target_c.is_finite()) {
            return self.status.clone();
        }
        if self.last.is_some_and(|(last, _)| t_s <= last) {
            return self.status.clone();
        }
        if self.target_c.map_or(true, |t| (t - target_c).abs() > 0.05) {
            let last = self.last;
            self.reset();
            // The new target holds from this sample on; what came before belongs to the old.
            self.last = last.map(|(t, _)| (t, power.clamp(0.0, 1.0)));
            self.target_c = Some(target_c);
        }
        if !self.max_power_set {
            self.learn_cap(t_s, power.clamp(0.0, 1.0), temp_c, target_c);
        }
        if self.reading != Some((power, temp_c)) {
            self.reading = Some((power, temp_c));
            self.unchanged_since_s = Some(t_s);
        }
        if target_c <= self.params.skip_below_c {
            self.last = Some((t_s, power.clamp(0.0, 1.0)));
            self.status = SoakStatus::Skipped;
            self.explanation = format!(
                "target {target_c:.1} °C is at or below {:.1} °C: an unheated bed needs no soak",
                self.params.skip_below_c
            );
            return self.status.clone();
        }
        if let Some((t_prev, p_prev)) = self.last {
            let hold_end = t_s.min(t_prev + MAX_HOLD_S);
            self.accumulate(t_prev, hold_end, p_prev);
        }
        self.roll_bins(t_s);
        self.warm_start.get_or_insert(
            temp_c > self.params.skip_below_c
                && (temp_c - target_c).abs() > self.params.temp_band_c,
        );
        self.cold_start
            .get_or_insert((temp_c <= self.params.skip_below_c, temp_c));
        self.lowest_c = Some(self.lowest_c.map_or(temp_c, |l| l.min(temp_c)));
        if let Some(bin) = self.bin.as_mut() {
            bin.temp_sum += temp_c;
            bin.temp_n += 1;
            bin.temp_last = temp_c;
        }
        self.last = Some((t_s, power.clamp(0.0, 1.0)));
        self.status.clone()
    }

    /// Closes the bins that end at or before `t_s` and opens the one that holds it.
    fn roll_bins(&mut self, t_s: f64) {
        let bin_s = self.params.bin_s;
        match &self.bin {
            None => {
                self.bin = Some(Bin {
                    start_s: t_s,
                    ..Bin::default()
                });
            }
            Some(bin) if t_s >= bin.start_s + bin_s => {
                let bin = bin.clone();
                // A bin needs half its length covered by held samples to count.
                if bin.covered_s >= 0.5 * bin_s {
                    let temp = if bin.temp_n > 0 {
                        bin.temp_sum / f64::from(bin.temp_n)
                    } else {
                        f64::NAN
                    };
                    let rate = match self.edge {
                        Some((start, last))
                            if bin.temp_n > 0 && (start - bin.start_s).abs() < 1e-9 =>
                        {
                            (bin.temp_last - last) / bin_s
                        }
                        _ => 0.0,
                    };
                    self.on_bin(
                        bin.t_int / bin.covered_s,
                        bin.power_int / bin.covered_s,
                        temp,
                        rate,
                    );
                }
                self.edge = (bin.temp_n > 0).then_some((bin.start_s + bin_s, bin.temp_last));
                let skip = ((t_s - bin.start_s) / bin_s).floor();
                self.bin = Some(Bin {
                    start_s: bin.start_s + skip * bin_s,
                    ..Bin::default()
                });
            }
            Some(_) => {}
        }
    }

    /// Adds power `p` held over `[a, b)` to the bins it covers.
    fn accumulate(&mut self, mut a: f64, b: f64, p: f64) {
        let bin_s = self.params.bin_s;
        while a < b {
            self.roll_bins(a);
            let Some(bin) = self.bin.as_mut() else { return };
            let end = b.min(bin.start_s + bin_s);
            let dt = end - a;
            if dt <= 0.0 {
                return;
            }
            bin.covered_s += dt;
            bin.power_int += p * dt;
            bin.t_int += 0.5 * (a + end) * dt;
            a = end;
        }
    }

    /// The model's row for a bin: 1, then each decay, then the temperature's rate of change
    /// (and under MPC the high-passed temperature).
    fn row(&self, p: &Point) -> DVector<f64> {
        let origin = self.origin_s.unwrap_or(p.t_s);
        let dt = (p.t_s - origin).max(0.0);
        let hp = if self.params.heater.mpc {
            &p.hp[..]
        } else {
            &[]
        };
        DVector::from_iterator(
            self.taus.len() + 1 + extra_cols(&self.params),
            std::iter::once(1.0)
                .chain(self.taus.iter().map(|tau| (-dt / tau).exp()))
                .chain([p.rate_c_s])
                .chain(hp.iter().copied()),
        )
    }

    /// The high-passed temperature columns for a bin at `temp_c` (zero before the band).
    fn hp_now(&self, temp_c: f64) -> [f64; HP_TAUS.len()] {
        match self.hp_ref {
            Some(r) => std::array::from_fn(|k| temp_c - r - self.hp_low[k]),
            None => [0.0; HP_TAUS.len()],
        }
    }

    /// Steps the low-passed temperatures by one bin (from the first bin within the band).
    fn hp_step(&mut self, temp_c: f64, target: f64) {
        if !temp_c.is_finite() {
            return;
        }
        if self.hp_ref.is_none() && (temp_c - target).abs() <= self.params.temp_band_c {
            self.hp_ref = Some(temp_c);
        }
        if let Some(r) = self.hp_ref {
            let bin = self.params.bin_s;
            for (low, tau) in self.hp_low.iter_mut().zip(HP_TAUS) {
                *low += (temp_c - r - *low) * (1.0 - (-bin / tau).exp());
            }
        }
    }

    /// The temperature's answer is modelled (MPC) and the bed came up into the band from
    /// below, from room temperature or a lower target: then every decay left is positive.
    fn temp_model(&self) -> bool {
        self.params.heater.mpc && self.approach_above == Some(false)
    }

    fn add_point(&mut self, p: Point) {
        let x = self.row(&p);
        self.xtx.ger(1.0, &x, &x, 1.0);
        self.xty.axpy(p.power, &x, 1.0);
        self.yty += p.power * p.power;
        self.rows.extend(x.iter());
        self.points.push(p);
    }

    /// One smoothed bin: temperature and headroom gates, then the model and the decision.
    fn on_bin(&mut self, t_s: f64, power: f64, temp_c: f64, rate_c_s: f64) {
        if matches!(self.status, SoakStatus::Stable { .. }) {
            return;
        }
        let Some(target) = self.target_c else { return };
        self.hp_step(temp_c, target);
        if !self.coupling_final && temp_c.is_finite() {
            self.history.push([t_s, power, temp_c, rate_c_s]);
        }
        self.recent.push((t_s, power));
        self.recent.retain(|(t, _)| t_s - t < SATURATION_WINDOW_S);
        let band = self.params.temp_band_c;
        if !temp_c.is_finite() || (temp_c - target).abs() > band {
            self.out_of_band_bins += 1;
            if self.last_in_band_s.is_none() && temp_c.is_finite() {
                self.approach_above = Some(temp_c > target);
            }
            // A short excursion (noise, a draught) is skipped. A longer one restarts the soak
            // clock (settling, minimum soak) but keeps the power history: the plate's decay
            // went on meanwhile, and forgetting it would only hide how far it still has to go.
            if self.band_since_s.is_some() && self.out_of_band_bins < OUT_OF_BAND_BINS {
                return;
            }
            if self.band_since_s.is_some() {
                self.excursions += 1;
            }
            self.band_since_s = None;
            self.soak_t0_s = None;
            self.progress_floor = 0.0;
            self.projection = None;
            self.status = SoakStatus::Heating;
            self.explanation = format!(
                "temperature {temp_c:.1} °C is {:+.1} °C from the target {target:.1} °C \
                 (settled within ±{band:.1} °C)",
                temp_c - target
            );
            return;
        }
        self.out_of_band_bins = 0;
        if self.excursions > 0 && self.band_since_s.is_none() {
            if let Some(last) = self.last_in_band_s {
                self.excursion_len_s = self.excursion_len_s.max(t_s - last);
            }
        }
        self.last_in_band_s = Some(t_s);
        // An overshoot inside the band has the same aftermath on its own time scale (unless
        // the temperature's answer is modelled: then the overshoot is in the data).
        if temp_c > target + OVERSHOOT_C && !self.temp_model() {
            let since = *self.over_since_s.get_or_insert(t_s);
            self.excursion_len_s = self.excursion_len_s.max(t_s - since);
        } else {
            self.over_since_s = None;
        }
        let minute = self.recent.iter().map(|(_, p)| p).sum::<f64>() / self.recent.len() as f64;
        if minute >= self.params.saturated_power * self.max_power {
            if self.band_since_s.is_none() {
                self.status = SoakStatus::Heating;
                self.explanation = format!(
                    "heater at {:.0} % of full power over the last minute (max_power {:.2}): \
                     still heating (no headroom left)",
                    minute * 100.0,
                    self.max_power
                );
                return;
            }
            // Once soaking, a saturated stretch is left out of the model and holds the
            // declaration off for the minimum soak.
            self.last_saturated_s = Some(t_s);
            return;
        }
        if self.approach_above == Some(true)
            && self.band_since_s.is_none()
            && minute <= (1.0 - self.params.saturated_power) * self.max_power
        {
            self.status = SoakStatus::Heating;
            self.explanation = format!(
                "heater off over the last minute ({:.1} % of full power) after a step down to \
                 {target:.1} °C: the bed is still cooling",
                minute * 100.0
            );
            return;
        }
        let since = *self.band_since_s.get_or_insert(t_s);
        self.first_band_s.get_or_insert(t_s);
        self.update_coupling(t_s);
        // After an excursion the controller recovers from its own overshoot: twice the settling.
        let settle_s = if self.excursions > 0 {
            2.0 * self.params.settle_s
        } else {
            self.params.settle_s
        };
        if t_s - since < settle_s {
            self.status = SoakStatus::Soaking {
                progress: 0.0,
                eta_s: None,
                print_now_c: None,
                reason: format!(
                    "temperature reached; letting the controller settle ({:.0} of {:.0} s)",
                    t_s - since,
                    settle_s
                ),
            };
            self.explanation = status_reason(&self.status);
            return;
        }
        let soak_t0 = *self.soak_t0_s.get_or_insert(t_s);
        self.origin_s.get_or_insert(t_s);
        let hp = self.hp_now(temp_c);
        self.add_point(Point {
            t_s,
            power,
            rate_c_s,
            hp,
        });
        if self.points.len() > MAX_POINTS {
            let keep = self.points.split_off(MAX_POINTS / 2);
            self.points.clear();
            self.rows.clear();
            let k = self.taus.len() + 1 + extra_cols(&self.params);
            self.xtx = DMatrix::zeros(k, k);
            self.xty = DVector::zeros(k);
            self.yty = 0.0;
            self.origin_s = keep.first().map(|p| p.t_s);
            for p in keep {
                self.add_point(p);
            }
        }
        self.decide(t_s, soak_t0);
    }
}

/// Columns after the decays for these params: the rate, and under MPC [`HP_TAUS`].
fn extra_cols(p: &SoakParams) -> usize {
    EXTRA_COLS + if p.heater.mpc { HP_TAUS.len() } else { 0 }
}

fn status_reason(s: &SoakStatus) -> String {
    match s {
        SoakStatus::Soaking { reason, .. } => reason.clone(),
        other => format!("{other:?}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::soak::test_beds::{run_bed, surface_left, two_node_bed, TARGET_C};

    #[test]
    fn the_power_rate_told_is_plausible_or_not_told() {
        let base = DecayFit {
            tau_s: 1200.0,
            final_power: 0.3,
            remaining: 0.02,
            remaining_upper: 0.03,
            amplitude: 0.2,
            rising: false,
            tau_unbounded: false,
            noise_sd: 0.01,
            test_sd: 0.01,
            noise_inflation: 1.0,
            threshold: 0.01,
            surface_upper_c: 0.5,
            surface_95_c: 0.4,
        };
        // 0.02 of full power over τ = 20 min: 1 % per 10 min.
        let r = base.rate_pct_per_10min().unwrap();
        assert!((r - 1.0).abs() < 1e-12, "{r}");
        assert!(
            (DecayFit {
                rising: true,
                ..base
            }
            .rate_pct_per_10min()
            .unwrap()
                + 1.0)
                .abs()
                < 1e-12
        );
        // What a runaway extrapolation looks like: told as nothing, never as a number.
        for bad in [
            DecayFit {
                remaining: 14.8,
                ..base
            },
            DecayFit {
                tau_s: 0.01,
                ..base
            },
            DecayFit {
                final_power: -3.0,
                ..base
            },
            DecayFit {
                tau_s: f64::NAN,
                ..base
            },
        ] {
            assert_eq!(bad.rate_pct_per_10min(), None, "{bad:?}");
        }
    }

    /// A synthetic bed: full power while the temperature ramps to the target over `heat_s`,
    /// then `P(t) = final + amp·e^(−(t−heat_s)/tau_s)` plus white noise of `noise_sd`, one
    /// sample a second.
    struct Synthetic {
        heat_s: f64,
        tau_s: f64,
        final_power: f64,
        amp: f64,
        noise_sd: f64,
        seed: u64,
    }

    impl Synthetic {
        fn quiet(tau_s: f64) -> Self {
            Synthetic {
                heat_s: 300.0,
                tau_s,
                final_power: 0.3,
                amp: 0.5,
                noise_sd: 0.0,
                seed: 1,
            }
        }

        /// The last moment the noise-free power is more than 1 % of full power above its end.
        fn one_percent_moment_s(&self) -> f64 {
            self.heat_s + self.tau_s * (self.amp / 0.01).ln()
        }

        fn samples(&self, until_s: f64) -> Vec<(f64, f64, f64)> {
            let mut rng = fastrand::Rng::with_seed(self.seed);
            let mut gauss = move || {
                let u = 1.0 - rng.f64();
                let v = rng.f64();
                (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
            };
            (0..=until_s as usize)
                .map(|i| {
                    let t = i as f64;
                    if t < self.heat_s {
                        (t, 1.0, 25.0 + (TARGET_C - 25.0) * t / self.heat_s)
                    } else {
                        let clean =
                            self.final_power + self.amp * (-(t - self.heat_s) / self.tau_s).exp();
                        let p = (clean + self.noise_sd * gauss()).clamp(0.0, 1.0);
                        (t, p, TARGET_C + 0.1 * gauss())
                    }
                })
                .collect()
        }

        /// Feeds the detector until it declares; returns the time, or None.
        fn stable_at(&self, until_s: f64) -> Option<f64> {
            let mut d = SoakDetector::new(SoakParams::default());
            self.samples(until_s).into_iter().find_map(|(t, p, temp)| {
                match d.push(t, p, temp, TARGET_C) {
                    SoakStatus::Stable { at_s } => Some(at_s),
                    _ => None,
                }
            })
        }
    }

    /// The rows kept for the noise estimate are, bit for bit, the model's rows of the points
    /// now (the origin they were worked out from has not moved), and one per point.
    #[test]
    fn the_rows_kept_per_point_are_the_models_rows() {
        let bed = Synthetic {
            noise_sd: 0.02,
            ..Synthetic::quiet(1800.0)
        };
        let mut d = SoakDetector::new(SoakParams::default());
        for (t, p, temp) in bed.samples(3.0 * 3600.0) {
            d.push(t, p, temp, TARGET_C);
        }
        let k = d.taus.len() + 1 + EXTRA_COLS;
        assert!(d.points.len() > 100, "{}", d.points.len());
        assert_eq!(d.rows.len(), k * d.points.len());
        for (p, kept) in d.points.iter().zip(d.rows.chunks_exact(k)) {
            let row = d.row(p);
            assert!(row
                .iter()
                .zip(kept)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
        }
    }

    #[test]
    fn declares_after_the_decay_is_done_and_never_before_the_one_percent_moment() {
        let bed = Synthetic::quiet(600.0);
        let moment = bed.one_percent_moment_s();
        let at = bed.stable_at(4.0 * moment).expect("declared");
        assert!(
            at >= moment,
            "declared at {at} s, before the 1 % moment {moment} s"
        );
        assert!(
            at <= 1.5 * moment + 60.0,
            "declared at {at} s, later than 1.5 × {moment} s + 60 s"
        );
    }

    /// A bed with a controller transient and a slow plate decay, sampled at `rate_hz`:
    /// `P = final + fast·e^(−t/τ_fast) + slow·e^(−t/τ_slow)` after a ramp, white noise.
    #[allow(clippy::too_many_arguments)]
    fn two_decay_samples(
        tau_s: f64,
        amp: f64,
        fast_amp: f64,
        noise_sd: f64,
        rate_hz: f64,
        until_s: f64,
        seed: u64,
    ) -> Vec<(f64, f64, f64)> {
        let heat_s = 300.0;
        let mut rng = fastrand::Rng::with_seed(seed);
        let mut gauss = move || {
            let u = 1.0 - rng.f64();
            let v = rng.f64();
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let n = (until_s * rate_hz) as usize;
        (0..=n)
            .map(|i| {
                let t = i as f64 / rate_hz;
                if t < heat_s {
                    (t, 1.0, 25.0 + (TARGET_C - 25.0) * t / heat_s)
                } else {
                    let dt = t - heat_s;
                    let clean = 0.3 + fast_amp * (-dt / 120.0).exp() + amp * (-dt / tau_s).exp();
                    let p = (clean + noise_sd * gauss()).clamp(0.0, 1.0);
                    (t, p, TARGET_C + 0.1 * gauss())
                }
            })
            .collect()
    }

    /// Runs one grid bed until its true moment; the declaration time if the detector
    /// declared before it.
    fn early_on(
        tau_s: f64,
        amp: f64,
        fast_amp: f64,
        noise_sd: f64,
        rate_hz: f64,
        seed: u64,
    ) -> Option<(f64, f64)> {
        // The statistics' property at a given power threshold (issue 10's 0.8 %, which the
        // grid was drawn around): these beds' heat-ups are ramps, not physics, so no coupling
        // is identified from them (the surface's side of the rule is tested on physical beds).
        let params = SoakParams {
            fixed_remaining: Some(0.008),
            ..SoakParams::default()
        };
        let max_remaining = SoakDetector::new(params.clone()).threshold();
        // The true moment: the noise-free remaining fall of both decays reaches max_remaining.
        let rem = |dt: f64| fast_amp * (-dt / 120.0).exp() + amp * (-dt / tau_s).exp();
        let (mut lo, mut hi) = (0.0, 40.0 * tau_s);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if rem(mid) > max_remaining {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let moment = 300.0 + hi;
        let mut d = SoakDetector::new(params);
        two_decay_samples(tau_s, amp, fast_amp, noise_sd, rate_hz, moment, seed)
            .into_iter()
            .find_map(|(t, p, temp)| match d.push(t, p, temp, TARGET_C) {
                SoakStatus::Stable { at_s } => Some((at_s, moment)),
                _ => None,
            })
    }

    /// Never early on a slow decay the old detector declared early (issue 10 names
    /// case: τ 2700 s, amplitude 0.03 was declared at ~980 s against a moment of 3267 s).
    #[test]
    fn slow_decays_too_long_to_resolve_yet_are_waited_for() {
        let (tau_s, amp) = (2700.0, 0.03);
        let e = early_on(tau_s, amp, 0.0, 0.02, 1.0, 7);
        assert!(
            e.is_none(),
            "τ {tau_s} s, amplitude {amp}: declared early {e:?}"
        );
    }

    /// Never early, as a property over a grid (issue 10): time constants 2–60 min (up to the
    /// default `tau_max_s`), slow amplitudes from 2 % to 30 % of full power, noise 0–6 % at
    /// 1/4–4 Hz, with and without a fast controller transient in front of the slow decay; the
    /// moment is when both decays together have `max_remaining` left (stricter than the
    /// bench's 1 %).
    #[test]
    fn never_early_over_a_grid_of_beds() {
        let mut early = Vec::new();
        let mut seed = 0;
        for tau_s in [120.0, 300.0, 900.0, 1800.0, 2700.0, 3600.0] {
            for amp in [0.02, 0.05, 0.1, 0.3] {
                for (noise_sd, rate_hz) in [
                    (0.0, 1.0),
                    (0.02, 0.25),
                    (0.02, 4.0),
                    (0.04, 1.0),
                    (0.06, 2.0),
                ] {
                    for fast_amp in [0.0, 0.2] {
                        seed += 1;
                        if let Some((at, moment)) =
                            early_on(tau_s, amp, fast_amp, noise_sd, rate_hz, seed)
                        {
                            early.push(format!(
                                "τ {tau_s} s, amp {amp}, fast {fast_amp}, noise {noise_sd}, \
                                 {rate_hz} Hz: declared at {at:.0} s, moment {moment:.0} s"
                            ));
                        }
                    }
                }
            }
        }
        assert!(
            early.is_empty(),
            "{} of 240 beds declared early:\n{}",
            early.len(),
            early.join("\n")
        );
    }

    #[test]
    fn pid_like_noise_does_not_cause_an_early_declaration() {
        for (seed, tau_s) in (0..12).zip([300.0, 900.0, 1500.0].into_iter().cycle()) {
            let bed = Synthetic {
                noise_sd: 0.04,
                seed,
                ..Synthetic::quiet(tau_s)
            };
            let moment = bed.one_percent_moment_s();
            let at = bed.stable_at(4.0 * moment);
            assert!(
                at.is_some_and(|at| at >= moment),
                "seed {seed}, τ {tau_s} s: declared at {at:?}, the 1 % moment is {moment} s"
            );
        }
    }

    /// A watermark (bang-bang) bed: one heat capacity, switched between 0 and full power at
    /// ±1 °C about the target, losing heat to surroundings that warm with a 15-min decay, one
    /// sample a second. Returns the detector after `until_s` and the sd of the raw 10-s bins
    /// of power over the last 10 minutes.
    fn bang_bang_bed(until_s: f64) -> (SoakDetector, f64) {
        // Full power heats the bed by 0.2 °C/s; it loses 1 % of full power per °C over its
        // surroundings (about 0.35 at the target).
        let (heat_c_s, loss_per_c) = (0.2, 0.01);
        let mut temp = 25.0;
        let mut on = true;
        let mut d = SoakDetector::new(SoakParams::default());
        let mut bins: Vec<f64> = Vec::new();
        let mut acc = 0.0;
        let mut t = 0.0;
        while t < until_s {
            let ambient = 25.0 + 10.0 * (1.0 - (-t / 900.0).exp());
            if temp > TARGET_C + 1.0 {
                on = false;
            } else if temp < TARGET_C - 1.0 {
                on = true;
            }
            let power = if on { 1.0 } else { 0.0 };
            d.push(t, power, temp, TARGET_C);
            acc += power;
            if (t as u64 + 1) % 10 == 0 {
                bins.push(acc / 10.0);
                acc = 0.0;
            }
            temp += heat_c_s * (power - loss_per_c * (temp - ambient));
            t += 1.0;
        }
        let last: Vec<f64> = bins[bins.len() - 60..].to_vec();
        let mean = last.iter().sum::<f64>() / last.len() as f64;
        let sd = (last.iter().map(|b| (b - mean).powi(2)).sum::<f64>() / last.len() as f64).sqrt();
        (d, sd)
    }

    /// Power a bang-bang heater puts into the bed's own heat capacity (on: the temperature
    /// climbs; off: it falls) is no heat flow: the temperature's rate takes it out of the
    /// model, so the scatter left is a small part of the 0/1 switching's.
    #[test]
    fn a_bang_bang_heaters_switching_is_taken_out_by_the_temperature_rate() {
        let (d, raw_sd) = bang_bang_bed(5400.0);
        let fit = d.fit().expect("a fit after 90 min");
        assert!(
            raw_sd > 0.1,
            "the bins of a switching heater scatter: {raw_sd}"
        );
        assert!(
            fit.noise_sd < 0.25 * raw_sd,
            "scatter about the fit {:.4} against the raw bins' {raw_sd:.4}: {}",
            fit.noise_sd,
            d.explanation()
        );
    }

    /// A bed held over its target by more than `OVERSHOOT_C` (inside the band) for longer than
    /// `tau_max_s` lets every decay take either sign; the test still bounds what is left
    /// (it found no sign-constrained decay to pin and never declared: "at most inf %").
    #[test]
    fn a_bed_over_its_target_for_longer_than_the_slowest_decay_is_still_declared() {
        let params = SoakParams::default();
        let over_s = params.tau_max_s + 1200.0;
        let mut rng = fastrand::Rng::with_seed(5);
        let mut d = SoakDetector::new(params);
        let mut declared = None;
        for k in 0..6 * 3600 {
            let t = f64::from(k);
            let temp = if t < over_s { TARGET_C + 1.2 } else { TARGET_C };
            let p = 0.3 + 0.005 * (rng.f64() - 0.5);
            if let SoakStatus::Stable { at_s } = d.push(t, p, temp, TARGET_C) {
                declared = Some(at_s);
                break;
            }
        }
        let fit = d.fit().expect("a fit");
        assert!(fit.remaining_upper.is_finite(), "{}", d.explanation());
        assert!(declared.is_some(), "never declared: {}", d.explanation());
    }

    #[test]
    fn a_heater_capped_by_max_power_counts_as_saturated_at_its_cap() {
        // A bed whose max_power is 0.6, in the band, driving 0.6: no headroom, still heating.
        let mut d = SoakDetector::new(SoakParams::default());
        d.set_max_power(0.6);
        for k in 0..30 {
            d.push(f64::from(k) * 10.0, 0.6, TARGET_C, TARGET_C);
        }
        assert_eq!(*d.status(), SoakStatus::Heating, "{}", d.explanation());
        assert!(
            d.explanation().contains("max_power 0.60"),
            "{}",
            d.explanation()
        );
        // Measured against full power the same bed would seem to have headroom.
        let mut full = SoakDetector::new(SoakParams::default());
        for k in 0..30 {
            full.push(f64::from(k) * 10.0, 0.6, TARGET_C, TARGET_C);
        }
        assert_ne!(*full.status(), SoakStatus::Heating);
        // Nonsense is ignored.
        let mut d = SoakDetector::new(SoakParams::default());
        d.set_max_power(7.0);
        d.set_max_power(f64::NAN);
        assert_eq!(d.max_power, 1.0);
    }

    /// A trace replayed without Klipper's config (`klipcal soak-detect`): the heat-up at a
    /// steady 0.6 shows the cap, and the bed at its target still at 0.6 is still heating.
    #[test]
    fn a_cap_below_full_power_is_learnt_from_the_heat_up() {
        let mut d = SoakDetector::new(SoakParams::default());
        for k in 0..600 {
            let t = f64::from(k);
            d.push(t, 0.6, 25.0 + 0.055 * t, TARGET_C);
        }
        assert_eq!(d.max_power(), 0.6);
        for k in 600..900 {
            d.push(f64::from(k), 0.6, TARGET_C, TARGET_C);
        }
        assert_eq!(*d.status(), SoakStatus::Heating, "{}", d.explanation());
        assert!(
            d.explanation().contains("max_power 0.60"),
            "{}",
            d.explanation()
        );
        // A PID's varying output while heating is no cap; Klipper's own value wins.
        let mut varying = SoakDetector::new(SoakParams::default());
        for k in 0..600 {
            let t = f64::from(k);
            varying.push(t, 0.5 + 0.1 * (t / 7.0).sin(), 25.0 + 0.055 * t, TARGET_C);
        }
        assert_eq!(varying.max_power(), 1.0);
        let mut told = SoakDetector::new(SoakParams::default());
        told.set_max_power(0.8);
        for k in 0..600 {
            let t = f64::from(k);
            told.push(t, 0.6, 25.0 + 0.055 * t, TARGET_C);
        }
        assert_eq!(told.max_power(), 0.8);
    }

    /// A stopped Klipper keeps logging its last values (a real klippy.log held pwm 0.365 and
    /// 59.9 °C for 30 min after a shutdown, and the detector called it stable after 8 min):
    /// frozen readings are no settled bed.
    #[test]
    fn readings_frozen_for_minutes_are_not_a_settled_bed() {
        let mut rng = fastrand::Rng::with_seed(9);
        let mut d = SoakDetector::new(SoakParams::default());
        for k in 0..3600 {
            let t = f64::from(k);
            let (p, temp) = if t < 600.0 {
                (
                    0.36 + 0.01 * (rng.f64() - 0.5),
                    TARGET_C + 0.1 * (rng.f64() - 0.5),
                )
            } else {
                (0.365, TARGET_C - 0.1)
            };
            let status = d.push(t, p, temp, TARGET_C);
            assert!(
                !matches!(status, SoakStatus::Stable { .. }),
                "declared at {t} s: {}",
                d.explanation()
            );
        }
        assert!(
            d.explanation().contains("have not changed for"),
            "{}",
            d.explanation()
        );
    }

    #[test]
    fn an_unheated_bed_skips_the_soak() {
        for target in [0.0, 25.0] {
            let mut d = SoakDetector::new(SoakParams::default());
            assert_eq!(d.push(0.0, 0.0, 22.0, target), SoakStatus::Skipped);
            assert_eq!(d.push(1.0, 0.0, 22.0, target), SoakStatus::Skipped);
        }
        // and heating it later starts a soak
        let mut d = SoakDetector::new(SoakParams::default());
        d.push(0.0, 0.0, 22.0, 0.0);
        assert_eq!(d.push(1.0, 1.0, 22.0, TARGET_C), SoakStatus::Heating);
    }

    #[test]
    fn the_eta_shrinks_as_the_decay_proceeds() {
        let bed = Synthetic {
            noise_sd: 0.01,
            ..Synthetic::quiet(900.0)
        };
        let mut d = SoakDetector::new(SoakParams::default());
        let mut seen = Vec::new();
        let mut stable_at = None;
        for (t, p, temp) in bed.samples(4.0 * bed.one_percent_moment_s()) {
            match d.push(t, p, temp, TARGET_C) {
                SoakStatus::Soaking {
                    eta_s: Some(eta),
                    progress,
                    ..
                } if [1500.0, 2100.0, 2700.0, 3300.0].contains(&t) => seen.push((t, eta, progress)),
                SoakStatus::Stable { at_s } => {
                    stable_at = Some(at_s);
                    break;
                }
                _ => {}
            }
        }
        assert_eq!(seen.len(), 4, "an ETA at every check: {seen:?}");
        // The progress never goes back; the ETA may move, but shrinks over the soak.
        for w in seen.windows(2) {
            assert!(w[1].2 >= w[0].2, "progress went back: {seen:?}");
        }
        assert!(seen[3].1 < seen[0].1, "ETA did not shrink: {seen:?}");
        assert!(seen[3].2 > seen[0].2, "progress did not grow: {seen:?}");
        // The ETA late in the soak points near the actual declaration.
        let (t, eta, _) = seen[3];
        let at = stable_at.expect("declared");
        assert!(
            ((t + eta) - at).abs() < 0.25 * at,
            "predicted {} s, declared at {at} s",
            t + eta
        );
    }

    #[test]
    fn a_bed_whose_temperature_has_not_reached_the_target_is_not_stable() {
        // Seed 000 §3.7: the plate must be within ±2 K of the set temperature; 2.5 K below is
        // outside, even with the power perfectly flat.
        let mut d = SoakDetector::new(SoakParams::default());
        for i in 0..7200 {
            let status = d.push(f64::from(i), 0.6, TARGET_C - 2.5, TARGET_C);
            assert_eq!(status, SoakStatus::Heating, "at {i} s");
        }
        assert!(
            d.explanation().contains("from the target"),
            "{}",
            d.explanation()
        );
    }

    #[test]
    fn a_heater_at_full_power_is_still_heating() {
        let mut d = SoakDetector::new(SoakParams::default());
        for i in 0..3600 {
            assert_eq!(
                d.push(f64::from(i), 1.0, TARGET_C, TARGET_C),
                SoakStatus::Heating
            );
        }
    }

    #[test]
    fn a_flat_power_at_temperature_is_declared_after_settling_and_the_minimum_soak() {
        let params = SoakParams::default();
        let earliest = params.settle_s + params.min_soak_s;
        // Quiet power: the slope is known at once, declared right after the minimum soak.
        let quiet = Synthetic {
            heat_s: 0.0,
            amp: 0.0,
            noise_sd: 0.0005,
            ..Synthetic::quiet(600.0)
        };
        let at = quiet.stable_at(7200.0).expect("declared");
        assert!(at >= earliest, "declared at {at} s, before {earliest} s");
        assert!(at <= earliest + 600.0, "quiet: declared at {at} s");
        // PID-like noise: the time it takes to rule out the slowest decay allowed, no more.
        let noisy = Synthetic {
            noise_sd: 0.02,
            ..quiet
        };
        let at_noisy = noisy.stable_at(3.0 * 3600.0).expect("declared");
        assert!(at_noisy > at, "noisy {at_noisy} s, quiet {at} s");
        assert!(
            at_noisy <= earliest + 3600.0,
            "noisy: declared at {at_noisy} s"
        );
    }

    #[test]
    fn a_new_target_restarts_the_soak() {
        let bed = Synthetic::quiet(300.0);
        let mut d = SoakDetector::new(SoakParams::default());
        let mut last_t = 0.0;
        for (t, p, temp) in bed.samples(6000.0) {
            d.push(t, p, temp, TARGET_C);
            last_t = t;
        }
        assert!(matches!(d.status(), SoakStatus::Stable { .. }));
        let status = d.push(last_t + 1.0, 1.0, TARGET_C, TARGET_C + 20.0);
        assert_eq!(status, SoakStatus::Heating);
        assert!(d.fit().is_none());
    }

    /// A step down from 100 °C to the target: 10 min coming down with the heater off, then
    /// the power goes towards 0.3 by `change` (positive: it falls, the surroundings still
    /// warming; negative: it rises, they cool) with a 20-min time constant, 1 % noise, 1 Hz.
    /// Returns the declaration and the explanation at the end.
    fn after_a_step_down(change: f64, seed: u64) -> (Option<f64>, String) {
        let mut rng = fastrand::Rng::with_seed(seed);
        let mut gauss = move || {
            let u = 1.0 - rng.f64();
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.f64()).cos()
        };
        let mut d = SoakDetector::new(SoakParams::default());
        for i in 0..=6 * 3600 {
            let t = f64::from(i);
            let (p, temp) = if t < 600.0 {
                (0.0, 100.0 - (100.0 - TARGET_C) * t / 600.0)
            } else {
                let clean = 0.3 + change * (-(t - 600.0) / 1200.0).exp();
                (
                    (clean + 0.01 * gauss()).clamp(0.0, 1.0),
                    TARGET_C + 0.1 * gauss(),
                )
            };
            if let SoakStatus::Stable { at_s } = d.push(t, p, temp, TARGET_C) {
                return (Some(at_s), d.explanation().to_string());
            }
        }
        (None, d.explanation().to_string())
    }

    #[test]
    fn after_a_step_down_the_power_is_waited_for_whichever_way_it_goes() {
        for change in [-0.1, 0.1] {
            // The last moment the noise-free power is 1 % of full power from its end.
            let moment = 600.0 + 1200.0 * (0.1f64 / 0.01).ln();
            for seed in 1..=3 {
                let (at, why) = after_a_step_down(change, seed);
                let at = at.unwrap_or_else(|| panic!("change {change}: never declared: {why}"));
                assert!(
                    at >= moment,
                    "change {change}: declared at {at} s, before {moment} s: {why}"
                );
                assert!(
                    at < 3.0 * moment,
                    "change {change}: declared at {at} s: {why}"
                );
                let word = if change < 0.0 {
                    "stopped rising"
                } else {
                    "stopped falling"
                };
                assert!(why.contains(word), "change {change}: {why}");
            }
        }
    }

    #[test]
    fn samples_that_are_not_finite_or_go_back_in_time_are_ignored() {
        let bed = Synthetic::quiet(300.0);
        let mut d = SoakDetector::new(SoakParams::default());
        let mut reference = SoakDetector::new(SoakParams::default());
        for (t, p, temp) in bed.samples(3000.0) {
            let expected = reference.push(t, p, temp, TARGET_C);
            assert_eq!(d.push(f64::NAN, p, temp, TARGET_C), d.status().clone());
            assert_eq!(d.push(t, f64::INFINITY, temp, TARGET_C), d.status().clone());
            assert_eq!(d.push(t, p, temp, TARGET_C), expected);
            assert_eq!(d.push(t - 5.0, 0.0, 0.0, TARGET_C), expected);
        }
    }

    /// An open-frame bed whose stack settles in about 8 min (steel on a magnet over a
    /// pad-sensed plate): with soak.frame = "open" the rule rules out decays up to 20 min, not
    /// 60, so it declares sooner, still with the surface within the budget, and says which.
    #[test]
    fn an_open_frame_rules_out_the_bed_stacks_own_decays_and_says_so() {
        for seed in 0..3 {
            // Surface node: c_s / (G + h_s) = 21.6 / 0.045 = 480 s.
            let bed = two_node_bed(
                1.0 / 30.0,
                0.4,
                21.6,
                0.002,
                0.012,
                0.05,
                4.0 * 3600.0,
                seed,
            );
            let unknown = SoakParams {
                bed: "steel-pad".into(),
                ..SoakParams::default()
            };
            let open = SoakParams {
                frame: "open".into(),
                ..unknown.clone()
            };
            let (_, before) = run_bed(unknown, &bed, 0);
            let (d, after) = run_bed(open, &bed, 0);
            let (before, after) = (before.expect("declared"), after.expect("declared"));
            assert!(
                after + 300.0 < before,
                "seed {seed}: open {after} s, unknown {before} s"
            );
            let left = surface_left(&bed, after);
            assert!(left <= 1.0, "seed {seed}: {left} K left at {after} s");
            let why = d.explanation();
            assert!(
                why.contains("up to 20 min") && why.contains("soak.frame = \"open\""),
                "{why}"
            );
        }
    }

    /// On an open frame a decay slower than the stack and the air (a carriage warming on its
    /// mounts, 15 min here, holding 40 % of full power) draws its heat from the plate: with the
    /// thermistor in the plate it does not reach the surface and is not waited for; in the pad
    /// it reaches it in part and is waited for until that part is within the budget; with the
    /// frame not known it is waited for whole.
    #[test]
    fn on_an_open_frame_a_slow_decay_is_weighed_by_how_much_of_it_reaches_the_surface() {
        let bed = Synthetic {
            heat_s: 300.0,
            tau_s: 900.0,
            final_power: 0.3,
            amp: 0.4,
            noise_sd: 0.02,
            seed: 5,
        };
        let run = |bed_name: &str, frame: &str| {
            let mut d = SoakDetector::new(SoakParams {
                bed: bed_name.into(),
                frame: frame.into(),
                ..SoakParams::default()
            });
            let at = bed
                .samples(6.0 * 3600.0)
                .into_iter()
                .find_map(|(t, p, temp)| match d.push(t, p, temp, TARGET_C) {
                    SoakStatus::Stable { at_s } => Some(at_s),
                    _ => None,
                });
            (at.expect("declared"), d)
        };
        let left = |at: f64| bed.amp * (-(at - bed.heat_s) / bed.tau_s).exp();
        let (plate, d_plate) = run("steel-plate", "open");
        let (pad, d_pad) = run("steel-pad", "open");
        let (enclosed, d_enclosed) = run("steel-pad", "");
        // The plate-sensed bed is declared while the slow decay still holds more than the
        // surface's budget of power (it cannot reach the surface).
        assert!(
            left(plate) > 1.5 * d_plate.threshold(),
            "plate-sensed: declared at {plate} s with {} left (allowed {})",
            left(plate),
            d_plate.threshold()
        );
        // The pad-sensed one waits until the share that reaches the surface is within it.
        let share = d_pad.reach().expect("open frame").slow_share;
        assert!(share > 0.3 && share < 1.0, "share {share}");
        assert!(
            share * left(pad) <= d_pad.threshold(),
            "pad-sensed: declared at {pad} s with {} of the share left (allowed {})",
            share * left(pad),
            d_pad.threshold()
        );
        assert!(plate + 300.0 < pad, "plate {plate} s, pad {pad} s");
        // An unknown frame waits for all of it.
        assert!(d_enclosed.reach().is_none());
        assert!(
            left(enclosed) <= d_enclosed.threshold(),
            "frame not known: declared at {enclosed} s with {} left",
            left(enclosed)
        );
        assert!(pad < enclosed, "pad {pad} s, frame not known {enclosed} s");
        assert!(
            d_plate.explanation().contains("does not reach the surface"),
            "{}",
            d_plate.explanation()
        );
    }

    /// A decay holds at most `DECAY_BOUND` × max_power at the start of the soak (the power
    /// stays within 0..max_power): on an open frame with the thermistor in the plate only
    /// decays up to 5 min reach the surface, and one of those still holding the budget's power
    /// 17.5 min into the soak would have held more than that at its start. So even power far
    /// too noisy for the statistics to tell anything is declared by then: the bounds rule out
    /// what the heater cannot give.
    /// A detector for an open frame with `soak.bed = "steel-plate"`, its coupling the preset's
    /// (not identified) and `max_power` 1.
    fn open_plate_sensed_steel() -> SoakDetector {
        let mut d = SoakDetector::new(SoakParams {
            bed: "steel-plate".into(),
            frame: "open".into(),
            no_identify: true,
            ..SoakParams::default()
        });
        d.set_max_power(1.0);
        d
    }

    #[test]
    fn what_the_heater_cannot_give_is_ruled_out_whatever_the_noise() {
        let bed = Synthetic {
            heat_s: 300.0,
            tau_s: 600.0,
            final_power: 0.3,
            amp: 0.0,
            noise_sd: 0.5,
            seed: 9,
        };
        let mut d = open_plate_sensed_steel();
        let at = bed
            .samples(3.0 * 3600.0)
            .into_iter()
            .find_map(|(t, p, temp)| match d.push(t, p, temp, TARGET_C) {
                SoakStatus::Stable { at_s } => Some(at_s),
                _ => None,
            })
            .expect("declared");
        let fit = d.fit().expect("a fit");
        // The noise alone would keep the test from ruling the budget out for hours.
        assert!(fit.test_sd > 2.0 * d.threshold(), "{fit:?}");
        // The soak starts 180 s after the band (reached at 300 s); by 1050 s more, a 5-min
        // decay (and the grid's 4-min one) holding the budget now would have held more than
        // twice full power at that start.
        let start = bed.heat_s + d.params().settle_s;
        assert!(
            at <= start + 1050.0,
            "declared at {at} s: {}",
            d.explanation()
        );
        assert!(at >= start + d.params().min_soak_s, "declared at {at} s");
    }

    /// A small overshoot (under `OVERSHOOT_C`, so no excursion is counted) that the
    /// controller recovers from slowly dips the power, which then rises back while the surface's
    /// own decay still falls: the sum looks flat for a while. The rise must not hide the fall.
    #[test]
    fn a_slow_recovery_from_a_small_overshoot_does_not_hide_the_surface_decay() {
        let mut rng = fastrand::Rng::with_seed(21);
        for dip in [0.05, 0.1, 0.2, 0.3] {
            for dip_tau in [90.0, 120.0, 150.0, 200.0, 300.0] {
                for amp in [0.1, 0.3, 0.6] {
                    let mut d = open_plate_sensed_steel();
                    let heat = 300.0;
                    let mut at = None;
                    for i in 0..=7200 {
                        let t = f64::from(i);
                        let (p, temp) = if t < heat {
                            (1.0, 25.0 + (TARGET_C - 25.0) * t / heat)
                        } else {
                            let u = t - heat;
                            let clean =
                                0.25 + amp * (-u / 240.0).exp() - dip * (-u / dip_tau).exp();
                            let over = 0.45 * (-u / dip_tau).exp();
                            let g = rng.f64() - 0.5;
                            (
                                (clean + 0.05 * g).clamp(0.0, 1.0),
                                TARGET_C + over + 0.02 * g,
                            )
                        };
                        if let SoakStatus::Stable { at_s } = d.push(t, p, temp, TARGET_C) {
                            at = Some(at_s);
                            break;
                        }
                    }
                    let at = at.expect("declared");
                    // What the surface's decay still held, weighted as the rule weighs it.
                    let tau: f64 = 240.0;
                    let left =
                        amp * (-(at - heat) / tau).exp() * (1.0 + d.coupling().charge_s / tau);
                    assert!(
                        left <= d.threshold(),
                        "dip {dip} τ {dip_tau} amp {amp}: declared at {at} s with {left} left (allowed {})",
                        d.threshold()
                    );
                }
            }
        }
    }

    #[test]
    fn print_now_states_its_cost_from_the_band_on() {
        let bed = two_node_bed(1.0 / 30.0, 0.4, 6.0, 0.002, 0.012, 0.05, 3600.0, 3);
        let mut d = SoakDetector::new(SoakParams::default());
        let mut costs = Vec::new();
        for s in &bed {
            if let SoakStatus::Soaking {
                print_now_c: Some(c),
                ..
            } = d.push(s[0], s[1], s[2], TARGET_C)
            {
                costs.push((s[0], c, surface_left(&bed, s[0])));
            }
        }
        assert!(!costs.is_empty(), "no print-now cost stated");
        // The cost covers what the surface really still had to go, and it falls.
        for (t, c, left) in &costs {
            assert!(
                *c + 0.3 >= *left,
                "at {t} s cost {c:.2} K, surface had {left:.2} K"
            );
        }
        assert!(costs.last().unwrap().1 < costs.first().unwrap().1);
    }

    /// Issue 38 item 8: a user once read "printing now costs up to 295.7 K" and then 1354.0 K
    /// on a 60 °C bed, figures 30 s apart jumping both ways. The cost told is at most the
    /// distance from where the surface can be to the target, and never rises.
    #[test]
    fn the_print_now_cost_is_physically_possible_and_never_jumps_up() {
        // Beds from weakly to strongly coupled, with the weakest coupling assumed (defaults):
        // early fits divided by a weak G give hundreds of kelvin unbounded.
        for (seed, g) in [(1, 1.0 / 120.0), (2, 1.0 / 60.0), (5, 1.0 / 30.0)] {
            let bed = two_node_bed(g, 0.4, 6.0, 0.002, 0.012, 0.08, 3600.0, seed);
            let mut d = SoakDetector::new(SoakParams::default());
            let start_c = bed[0][2];
            let mut told: Vec<f64> = Vec::new();
            for s in &bed {
                if let SoakStatus::Soaking {
                    print_now_c: Some(c),
                    ..
                } = d.push(s[0], s[1], s[2], TARGET_C)
                {
                    told.push(c);
                }
            }
            assert!(!told.is_empty(), "seed {seed}: no cost stated");
            let reach = TARGET_C - start_c + 0.5;
            assert!(
                told.iter()
                    .all(|c| c.is_finite() && *c >= 0.0 && *c <= reach),
                "seed {seed}: a cost beyond {reach:.1} K: {told:?}"
            );
            assert!(
                told.windows(2).all(|w| w[1] <= w[0]),
                "seed {seed}: the cost rose between updates"
            );
        }
        // A warm start (a bed first seen at its target) is bounded from the coldest room.
        let mut d = SoakDetector::new(SoakParams::default());
        d.push(0.0, 0.3, TARGET_C, TARGET_C);
        assert_eq!(d.surface_reach_c(), Some(TARGET_C - COLDEST_ROOM_C));
    }

    /// A bed whose controller overshoots by about 1.5 K for some minutes after the band and
    /// then wanders (a PI whose integral winds up during the heat-up, as MPC's dip and limit
    /// cycle do): `(t, power, reading, surface)` once a second.
    fn overshooting_bed(g: f64, c_s: f64, seed: u64) -> Vec<[f64; 4]> {
        let mut rng = fastrand::Rng::with_seed(seed);
        let (amb, dt, c_th, h_th, h_s) = (22.0, 0.25, 1.5, 0.001, 0.004);
        let (mut th, mut ts, mut integ, mut power) = (amb, amb, 0.0, 1.0);
        let mut out = Vec::new();
        for i in 0..(4 * 7200) {
            let t = f64::from(i) * dt;
            if i % 4 == 0 {
                let reading = th + 0.02 * (rng.f64() - 0.5);
                let err = TARGET_C - reading;
                // The integral winds up while the power is capped: the overshoot.
                integ = (integ + err).clamp(-2000.0, 3000.0);
                power = (0.08 * err + 0.0002 * integ + 0.03 * (rng.f64() - 0.5)).clamp(0.0, 1.0);
                out.push([t, power, reading, ts]);
            }
            let q = g * (th - ts);
            th += dt * (power - q - h_th * (th - amb)) / c_th;
            ts += dt * (q - h_s * (ts - amb)) / c_s;
        }
        out
    }

    /// Under MPC (Kalico's `control: mpc`) the power's answer to the measured temperature is
    /// modelled instead of freeing every decay up to the overshoot's length: on beds whose
    /// temperature overshoots by about 1.5 K, never declared while the surface can still warm
    /// by more than the budget, and sooner than with the overshoot's free decays.
    #[test]
    fn an_overshoot_under_mpc_is_taken_out_by_the_temperature_and_never_early() {
        let mut faster = 0;
        let mut runs = 0;
        for (k, (g, c_s)) in [(0.02, 1.0), (0.03, 2.0), (0.05, 3.0), (0.02, 2.0)]
            .into_iter()
            .enumerate()
        {
            let bed = overshooting_bed(g, c_s, 40 + k as u64);
            let peak = bed.iter().map(|s| s[2]).fold(f64::MIN, f64::max);
            assert!(peak > TARGET_C + 1.0, "the bed overshoots: {peak}");
            let params = |mpc| SoakParams {
                bed: "steel-pad".into(),
                frame: "open".into(),
                heater: if mpc {
                    crate::calib::soak::HeaterFacts::mpc(None, None)
                } else {
                    crate::calib::soak::HeaterFacts::default()
                },
                ..SoakParams::default()
            };
            let (_, with) = run_bed(params(true), &bed, 0);
            let (_, without) = run_bed(params(false), &bed, 0);
            let at = with.expect("declared under MPC");
            let left = surface_left(&bed, at);
            assert!(
                left <= 1.0,
                "bed {k}: declared at {at} s with {left:.2} K to go"
            );
            runs += 1;
            if without.map_or(true, |w| at < w) {
                faster += 1;
            }
        }
        assert!(faster * 2 > runs, "sooner on {faster} of {runs}");
    }
}
