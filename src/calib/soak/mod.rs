//! PURE: thermal soak detection from the bed heater's power (paper 000 §3.1): the bed is at
//! equilibrium when its power has stopped decreasing. No I/O and no clock: every sample carries
//! its own time.
//!
//! How it decides. The power is averaged over bins of `bin_s`, each sample held until the next
//! (so 1–4 Hz reports, gaps and a bang-bang heater's 0/max switching all give the true duty). A
//! bin counts once the temperature is within `temp_band_c` of the target and the heater has
//! headroom over the last minute (below `saturated_power` of its `max_power`); after `settle_s`
//! for the controller, every bin goes into the model of what a bed's power can do while its
//! temperature is held: a constant plus decaying exponentials with time constants on a grid
//! from one minute to `tau_max_s` (a temperature-clamped network of heat capacities draws a sum
//! of decays with positive amplitudes; the fastest, the controller's, may have either sign).
//! The bed is stable when the data rule out, by a likelihood-ratio test at about three standard
//! errors, every such model whose power still to fall now is `max_remaining` or more — whatever
//! its time constant up to `tau_max_s`. A decay too slow to resolve yet is one of those models,
//! so it is waited for, not ignored: the test needs the slope to be known well enough that even
//! the slowest allowed decay could not hide `max_remaining` in it. The model also has a column
//! for the temperature's rate of change over each bin: power that went into the bed's own heat
//! capacity (a bang-bang heater's on and off, a PID's derivative kick) is no heat flow to the
//! surroundings, so it is taken out instead of counted as noise. The noise level comes from
//! the scatter about the best fit, taken at the one-minute scale too, so correlated controller
//! noise and bang-bang cycling widen the test instead of fooling it.
//!
//! A long temperature excursion restarts the soak clock (with twice the settling) but keeps the
//! power history; a new target forgets everything. After an overshoot (out of the band, or
//! `OVERSHOOT_C` over the target inside it) the controller's integral winds back and lifts the
//! power for a while before the slow decay goes on: decays up to the overshoot's length may then
//! take either sign, so the rise cannot pass for "nothing left to fall". Only from equilibrium
//! are a clamped network's decays all positive: a bed first seen warm and out of the band (held
//! at another target before, perhaps long at full power) may have its plate ahead of its
//! surroundings, so decays up to a sixth of `tau_max_s` (the plate's) may then take either sign.
//!
//! After a step down (the temperature came into the band from above) the surroundings may be
//! warmer than they will be at the new target (the power rises while they cool) or still
//! colder (it falls): the same test is run on the negated power too, and both a rise and a fall
//! of `max_remaining` must be ruled out; so for a bed first seen inside the band. A heater off
//! over the last minute after a step down means the bed is still cooling.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Thresholds of the soak detector. Every field has a default (see [`SoakParams::default`]),
/// so a `[soak]` table in the daemon's TOML may name only the keys it changes.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct SoakParams {
    /// The temperature counts as settled within ± this of the target. Default 2.0 °C
    /// (the paper's condition, 000 §3.7: plate within ±2 K of the set temperature).
    pub temp_band_c: f64,
    /// A target at or below this is an unheated bed: the soak is skipped. Default 30.0 °C.
    pub skip_below_c: f64,
    /// Mean power over the last minute at or above this fraction of the heater's `max_power`
    /// means it has no headroom left: the bed is still heating, whatever the temperature.
    /// Default 0.97.
    pub saturated_power: f64,
    /// Time after the temperature first enters the band that is left out of the model (the
    /// controller's overshoot and settling); twice this after the temperature left the band
    /// for more than three bins. Default 180 s.
    pub settle_s: f64,
    /// Samples are averaged over bins of this length before anything else. Default 10 s.
    pub bin_s: f64,
    /// Shortest soak (after `settle_s`) before the bed may be declared stable. Default 300 s.
    pub min_soak_s: f64,
    /// The print surface may still warm by at most this after the print starts, K. The power
    /// still to fall is turned into surface warming through the bed's coupling from thermistor
    /// to surface (see [`Coupling`]). Default 1.0 (1.2 µm/100 mm on steel, 2.3 on aluminium:
    /// half the paper's ±2 K).
    pub surface_budget_c: f64,
    /// The bed's build, whose coupling the rule uses (capped at the most a cold heat-up of this
    /// bed allows, which bounds it only from above): one of [`BED_PRESETS`] by name, or ""
    /// (unknown: the weakest coupling is assumed). Default "".
    pub bed: String,
    /// The slowest time constant the bed and its surroundings (plate, enclosure) may have: a
    /// decay this slow is ruled out before the bed is declared stable, so a longer value waits
    /// longer on every bed (on an open frame, `frame = "open"` caps it at the bed stack's own
    /// bound). Default 3600 s (1 h: a plate and an enclosure).
    pub tau_max_s: f64,
    /// The printer's frame: "open" (no enclosure: nothing around the bed warms for hours, so
    /// the slowest decay ruled out is the bed stack's own, [`OPEN_FRAME_TAU_MAX_S`], when that
    /// is below `tau_max_s`), "enclosed", or "" (unknown). "enclosed" and "" use `tau_max_s`.
    /// Default "".
    pub frame: String,
    /// Issue 10's rule, for the bench's comparison only: stable once this much power (fraction
    /// of full power) is ruled out, whatever the surface. Not a setting.
    #[serde(skip)]
    pub(crate) fixed_remaining: Option<f64>,
    /// The bench's comparison only: never identify the coupling (as after a warm start).
    #[serde(skip)]
    pub(crate) no_identify: bool,
}

impl Default for SoakParams {
    fn default() -> Self {
        SoakParams {
            temp_band_c: 2.0,
            skip_below_c: 30.0,
            saturated_power: 0.97,
            settle_s: 180.0,
            bin_s: 10.0,
            min_soak_s: 300.0,
            surface_budget_c: 1.0,
            bed: String::new(),
            tau_max_s: 3600.0,
            frame: String::new(),
            fixed_remaining: None,
            no_identify: false,
        }
    }
}

/// `[soak]` keys of earlier versions that the detector no longer has (its statistics are no
/// longer knobs): read and ignored, with a warning, so an old settings file still loads.
pub(crate) const RETIRED_KEYS: &[&str] = &[
    "span_taus",
    "fit_taus",
    "trend_window_s",
    "max_drop_se",
    "max_window_drop",
    "tau_min_s",
    "max_remaining",
];

/// A bed's build, as a user names it in `soak.bed`: what its materials allow of its coupling
/// from thermistor to print surface, and how long its stack takes to charge.
///
/// G = 1/(R·A·q) in full power per K, where R is the stack's resistance per m² between the
/// thermistor and the surface, A the bed's area and q = P/A its heater's power per m²; and the
/// bed's whole heat capacity, in full power·s/K, is C = c·A/P = c/q with c its heat capacity per
/// m². Two bounds follow from the materials alone, per m² (see [`StackLimits`]):
/// - the weakest coupling such a build can have: G ≥ 1/(R_max·q_max), whatever the bed;
/// - for this bed, from its own heat-up (which gives C): G = C/(R·c) ≥ C/(R_max·c_max), the
///   "G ≈ 1/(τ × full-power heating rate)" of issue 29 with τ = R_max·c_max the build's
///   slowest stack time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct BedPreset {
    /// The name in `soak.bed`.
    pub name: &'static str,
    /// What it is, in words.
    pub words: &'static str,
    /// Coupling G from the thermistor to the surface, full power per K: the weak end of such
    /// beds, 1/(R_max·q_max) (a weaker coupling waits longer).
    pub g: f64,
    /// R_max·c_max: the most the stack's resistance times the bed's heat capacity can be, s.
    pub rc_s: f64,
    /// What a layer behind the one a heat-up shows may add to R·c, s: a sheet on its magnet,
    /// whose own lag is a few seconds. None where the layer behind may be as slow as the one
    /// in front (glass over the plate) and merge with it: then the heat-up's lag tells nothing
    /// of the rest.
    pub hidden_s: Option<f64>,
    /// The stack's own charge time between thermistor and surface, s (the transient right
    /// after the bed reaches its band): its clamped time constants add up to at most
    /// Σ C_i·R_i ≤ R·C (see [`OPEN_FRAME_TAU_MAX_S`]), so `rc_s`.
    pub charge_s: f64,
}

/// Per-m² limits of real bed stacks, from their materials.
pub(crate) struct StackLimits;

impl StackLimits {
    /// Heater power per m², at most: 1 W/cm² (a 250 mm bed with a 625 W mains heater).
    pub(crate) const Q_MAX_W_M2: f64 = 10_000.0;
    /// Heat capacity per m², J/m²K: a 1.5 mm silicone pad (1.2 g/cm³, 1.3 J/gK) ...
    pub(crate) const C_PAD: f64 = 2_340.0;
    /// ... a 10 mm aluminium plate (2.7 g/cm³, 0.9 J/gK) ...
    pub(crate) const C_PLATE: f64 = 24_300.0;
    /// ... 0.8 mm spring steel (7.85, 0.46) with PEI on a 1 mm magnet sheet (3.6, 0.9) ...
    pub(crate) const C_STEEL: f64 = 2_890.0 + 3_240.0;
    /// ... or 5 mm borosilicate glass (2.23, 0.83).
    pub(crate) const C_GLASS: f64 = 9_250.0;
    /// Resistance per m², m²K/W: the pad's thermistor through 1 mm of silicone (0.3 W/mK) ...
    pub(crate) const R_PAD: f64 = 0.001 / 0.3;
    /// ... a 1 mm magnet sheet at 0.4 W/mK and half 0.5 mm of steel (20 W/mK) ...
    pub(crate) const R_STEEL: f64 = 0.001 / 0.4 + 0.000_25 / 20.0;
    /// ... glass on clips over an air gap of up to 0.4 mm (0.03 W/mK) and half 5 mm of glass
    /// (1.1 W/mK) ...
    pub(crate) const R_GLASS: f64 = 0.0004 / 0.03 + 0.0025 / 1.1;
    /// ... a bare plate's own half thickness and a 0.1 mm PEI film (0.22 W/mK).
    pub(crate) const R_BARE: f64 = 0.0005;
}

/// The beds `soak.bed` may name, strongest coupling first. The last is the weakest coupling,
/// assumed when the bed is neither identified nor named.
pub(crate) const BED_PRESETS: &[BedPreset] = &[
    preset(
        "bare-plate",
        "bare aluminium plate, thermistor in the plate",
        StackLimits::R_BARE,
        StackLimits::C_PAD + StackLimits::C_PLATE,
        Some(0.0),
    ),
    preset(
        "steel-plate",
        "steel sheet on a magnet, thermistor in the plate",
        StackLimits::R_STEEL,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL,
        Some(
            StackLimits::R_STEEL
                * (StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL),
        ),
    ),
    preset(
        "bare-pad",
        "bare aluminium plate, thermistor in the heater pad",
        StackLimits::R_PAD + StackLimits::R_BARE,
        StackLimits::C_PAD + StackLimits::C_PLATE,
        Some(0.0),
    ),
    preset(
        "steel-pad",
        "steel sheet on a magnet, thermistor in the heater pad",
        StackLimits::R_PAD + StackLimits::R_STEEL,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL,
        Some(
            StackLimits::R_STEEL
                * (StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL),
        ),
    ),
    preset(
        "glass-plate",
        "glass on clips, thermistor in the plate",
        StackLimits::R_GLASS,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_GLASS,
        None,
    ),
    preset(
        "glass-pad",
        "glass on clips, thermistor in the heater pad",
        StackLimits::R_PAD + StackLimits::R_GLASS,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_GLASS,
        None,
    ),
];

/// A preset from its stack's limits: resistance `r` m²K/W and heat capacity `c` J/m²K.
const fn preset(
    name: &'static str,
    words: &'static str,
    r: f64,
    c: f64,
    hidden_s: Option<f64>,
) -> BedPreset {
    BedPreset {
        name,
        words,
        g: 1.0 / (r * StackLimits::Q_MAX_W_M2),
        rc_s: r * c,
        hidden_s,
        charge_s: r * c,
    }
}

/// The slowest decay the rule rules out on an open frame (`soak.frame = "open"`), s: 20 min.
///
/// With the thermistor's node held, the bed is a network of heat capacities C_i joined by
/// conductances to that node and to the room; its slowest time constant is at most the trace
/// of K⁻¹C, Σ C_i R_i, where R_i is node i's resistance to ground (the held node or the room;
/// taking the room's path away only raises it). Per m², the slowest stacks of real beds:
/// - thermistor in a 1.5 mm silicone pad, 1 mm of silicone and 0.2 mm of adhesive (0.2 W/mK)
///   to the plate: R = 0.006 m²K/W; a 10 mm aluminium plate (24.3 kJ/m²K): 146 s;
/// - 1 mm magnet sheet (2.9 kJ/m²K) behind 0.2 mm of adhesive and half its 0.4 W/mK:
///   R = 0.0083, 24 s; a 1.5 mm steel sheet (5.4 kJ/m²K) on it with 0.002 m²K/W of contact,
///   R = 0.0115: 62 s; so 232 s (3.9 min) for steel on a magnet over a 10 mm plate;
/// - 5 mm glass (10.5 kJ/m²K) on clips over a 0.5 mm air gap (0.03 W/mK) and half its own
///   1 W/mK: R = 0.025, 264 s; with the plate 410 s (6.8 min);
/// - insulation under the pad: 6 mm cork (2.4 kJ/m²K, 0.04 W/mK, its underside at 5 W/m²K):
///   R = 0.086, 206 s; 10 mm of foam, 46 s.
///
/// The worst open stack (pad-sensed, 10 mm plate, 5 mm glass on a poor gap, cork) is thus at
/// most 616 s (10.3 min) however weak its convection (h only lowers R). Beside it, the
/// carriage or frame the bed is screwed to (a 6 mm aluminium Y plate of 250 mm, 0.9 kJ/K,
/// cooled on both faces at 5–10 W/m²K) settles in about 12 min, through spacers that carry a
/// few watts. Twice the stack's bound covers both: 20 min. Not covered: an enclosure, or a
/// frame built in a box (the air warms for hours: that is what `tau_max_s` is for).
pub(crate) const OPEN_FRAME_TAU_MAX_S: f64 = 1200.0;

/// What `soak.frame` accepts, for its error.
const FRAME_NAMES: &str = "\"\" (unknown: up to tau_max_s), \"open\" (no enclosure: up to 20 min) \
                           or \"enclosed\" (up to tau_max_s)";

/// What `soak.bed` accepts, for its error.
const BED_NAMES: &str = "\"\" (unknown), \"bare-plate\", \"steel-plate\", \"bare-pad\", \
                         \"steel-pad\", \"glass-plate\" or \"glass-pad\"";

/// Thermal expansion that turns surface kelvin into µm per 100 mm: steel and aluminium.
pub(crate) const UM_PER_100MM_K_STEEL: f64 = 1.2;
/// See [`UM_PER_100MM_K_STEEL`].
pub(crate) const UM_PER_100MM_K_ALUMINIUM: f64 = 2.3;

/// Kelvin of surface warming in words with what they cost in µm/100 mm.
#[must_use]
pub(crate) fn kelvin_words(k: f64) -> String {
    format!(
        "{k:.1} K ({:.1} µm/100 mm on steel, {:.1} on aluminium)",
        k * UM_PER_100MM_K_STEEL,
        k * UM_PER_100MM_K_ALUMINIUM
    )
}

/// Where the coupling the rule uses came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum CouplingSource {
    /// Identified from this bed's own data, lower end included. A heat-up bounds the coupling
    /// only from above (see `bounded_by_heat_up`), so the rule does not use this today.
    Identified,
    /// The user's `soak.bed` preset.
    Preset,
    /// Neither: the weakest coupling of any bed.
    Weakest,
}

/// The coupling G from the thermistor to the print surface, in full power per K: while the
/// thermistor is held at its target, each unit of power the heater no longer gives is a unit
/// less flowing through the stack to the surface, so the surface still warms by ΔP / G.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Coupling {
    /// The value the rule uses: the conservative (low) end.
    pub g: f64,
    /// The interval it lies in (identified: the 95 % interval; preset or weakest: the value).
    pub low: f64,
    /// See `low`.
    pub high: f64,
    /// The stack's own charge time between thermistor and surface, s.
    pub charge_s: f64,
    /// Where it came from.
    pub source: CouplingSource,
    /// Which, and why, in words.
    pub why: String,
}

impl Coupling {
    /// [`Coupling::short`], and why it was not identified when it was not.
    #[must_use]
    pub(crate) fn short_why(&self) -> String {
        match self.why.find("not identified") {
            Some(i) if self.source != CouplingSource::Identified => {
                format!("{} ({})", self.short(), &self.why[i..])
            }
            _ => self.short(),
        }
    }

    /// The coupling in a few words, for a status line: its value, interval and source.
    #[must_use]
    pub(crate) fn short(&self) -> String {
        match self.source {
            CouplingSource::Identified => format!(
                "G identified from the heat-up: 1/{:.0} ({})",
                1.0 / self.g,
                if self.high.is_finite() {
                    format!("1/{:.0}–1/{:.0}", 1.0 / self.low, 1.0 / self.high)
                } else {
                    format!("at least 1/{:.0}", 1.0 / self.low)
                }
            ),
            CouplingSource::Preset => {
                format!("G 1/{:.0} from soak.bed, not identified", 1.0 / self.g)
            }
            CouplingSource::Weakest => {
                format!("G 1/{:.0}, the weakest, not identified", 1.0 / self.g)
            }
        }
    }

    /// From `soak.bed`, else the weakest coupling; `not_identified` says why the bed's own
    /// heat-up did not give it.
    #[must_use]
    pub(crate) fn fallback(params: &SoakParams, not_identified: &str) -> Self {
        let weakest = BED_PRESETS[BED_PRESETS.len() - 1];
        match BED_PRESETS.iter().find(|b| b.name == params.bed) {
            Some(b) => Coupling {
                g: b.g,
                low: b.g,
                high: b.g,
                charge_s: b.charge_s,
                source: CouplingSource::Preset,
                why: format!(
                    "coupling 1/{:.0} of full power per K from soak.bed = \"{}\" ({}); \
                     {not_identified}",
                    1.0 / b.g,
                    b.name,
                    b.words
                ),
            },
            None => Coupling {
                g: weakest.g,
                low: weakest.g,
                high: weakest.g,
                charge_s: weakest.charge_s,
                source: CouplingSource::Weakest,
                why: format!(
                    "the weakest coupling, 1/{:.0} of full power per K ({}), as soak.bed is \
                     not set; {not_identified}",
                    1.0 / weakest.g,
                    weakest.words
                ),
            },
        }
    }
}

/// Hold after the band is reached that the identification takes in, s (its "first minutes").
pub(crate) const ID_HOLD_S: f64 = 480.0;
/// Fewest heat-up bins the identification needs.
const ID_MIN_HEAT_BINS: usize = 12;

/// One τ's least-squares fit of the identification.
struct IdFit {
    tau: f64,
    coef: DVector<f64>,
    sse: f64,
    inv: DMatrix<f64>,
    res: Vec<f64>,
}

/// The heat-up's lag longer than this is no bed stack's (see [`OPEN_FRAME_TAU_MAX_S`]: the
/// slowest stack's modes add up to at most 10 min, a single layer's to about 5), s.
pub(crate) const LAG_MAX_S: f64 = 300.0;

/// Why [`lag_fit`] gave no lag.
#[derive(Debug)]
enum LagError {
    /// The best lag is longer than any bed stack's, s.
    TooSlow(f64),
    /// Anything else, in words.
    Other(String),
}

impl From<String> for LagError {
    fn from(s: String) -> Self {
        LagError::Other(s)
    }
}

impl From<&str> for LagError {
    fn from(s: &str) -> Self {
        LagError::Other(s.to_string())
    }
}

/// The first layer beyond the thermistor, as a heat-up shows it.
#[derive(Debug, Clone, Copy)]
struct Lag {
    /// Its coupling's 95 % interval, full power per K: the low end is the layer's own
    /// (β·G), the high end the most the heat-up allows to the surface (h + G).
    low: f64,
    high: f64,
}

/// The one-lag fit of a cold heat-up and the first minutes of hold, binned:
/// `(t_s, power, temp_c, rate_c_s)` from the first bin on (the bed at room temperature).
///
/// The model is two nodes: the thermistor's, with heat capacity C and losses h, and the
/// stack beyond it, which follows the thermistor through a first-order lag of time constant
/// τ (its heat capacity over G + its own losses h_s). The power balance at the thermistor,
/// `P = C·dT/dt + (h + G)·(T − T₀) − G·β·F_τ(T − T₀)` with F_τ the lag filter and
/// β = G / (G + h_s), is linear in C, a = h + G and b = G·β for each τ: so G lies in [b, a].
/// τ is scanned on a grid; every τ whose fit is within the 95 % profile of the best counts,
/// and the interval is the profile's: at each τ, b and a may move until the fit is worse than
/// the best by 2² σ² (σ from the scatter at the one-minute scale, so a PID's correlated noise
/// widens it). A layer behind the first one whose lag is short or whose share is small (a
/// steel sheet on its magnet) does not show: it only lowers G below b, by at most what its
/// build allows ([`BedPreset::hidden_s`]).
fn lag_fit(bins: &[[f64; 4]]) -> Result<Lag, LagError> {
    let n = bins.len();
    if n < ID_MIN_HEAT_BINS + 6 {
        return Err(format!("too short a heat-up to identify the coupling ({n} bins)").into());
    }
    let t0 = bins[0][2];
    let rise = bins.iter().map(|b| b[2]).fold(f64::NEG_INFINITY, f64::max) - t0;
    if rise.is_nan() || rise <= 10.0 {
        return Err(format!(
            "the bed rose only {rise:.1} K from its start: too little to identify the coupling"
        )
        .into());
    }
    // The lag filter of T − T₀ for time constant τ, exact for a linear change within a bin.
    let filtered = |tau: f64| -> Vec<f64> {
        let mut f = 0.0;
        let mut out = Vec::with_capacity(n);
        for (i, b) in bins.iter().enumerate() {
            if i > 0 {
                let dt = b[0] - bins[i - 1][0];
                let x = 0.5 * (b[2] + bins[i - 1][2]) - t0;
                f += (1.0 - (-dt / tau).exp()) * (x - f);
            }
            out.push(f);
        }
        out
    };
    let fit = |tau: f64| -> Option<IdFit> {
        let f = filtered(tau);
        let x = DMatrix::from_fn(n, 3, |i, j| match j {
            0 => bins[i][3],
            1 => bins[i][2] - t0,
            _ => -f[i],
        });
        let y = DVector::from_iterator(n, bins.iter().map(|b| b[1]));
        let xtx = x.transpose() * &x;
        let inv = xtx.clone().try_inverse()?;
        let coef = &inv * (x.transpose() * &y);
        let res: Vec<f64> = (0..n)
            .map(|i| y[i] - x.row(i).dot(&coef.transpose()))
            .collect();
        let sse = res.iter().map(|r| r * r).sum::<f64>();
        coef.iter().all(|c| c.is_finite()).then_some(IdFit {
            tau,
            coef,
            sse,
            inv,
            res,
        })
    };
    let mut taus = Vec::new();
    let mut tau = 10.0;
    while tau <= 3600.0 {
        taus.push(tau);
        tau *= 1.25;
    }
    let fits: Vec<IdFit> = taus.iter().filter_map(|tau| fit(*tau)).collect();
    let best = fits
        .iter()
        .min_by(|a, b| a.sse.total_cmp(&b.sse))
        .ok_or("the heat-up does not fit a bed's heat balance")?;
    if best.tau > LAG_MAX_S {
        return Err(LagError::TooSlow(best.tau));
    }
    // One lag must do: a stack of two layers that show apart (a plate under glass, sensed in
    // the pad) fits a second lag clearly better, and then the first lag is the nearer layer,
    // not the surface: its coupling would be too strong to be safe.
    let two_lags = |t1: f64, t2: f64| -> Option<(f64, Vec<f64>)> {
        let (f1, f2) = (filtered(t1), filtered(t2));
        let x = DMatrix::from_fn(n, 4, |i, j| match j {
            0 => bins[i][3],
            1 => bins[i][2] - t0,
            2 => -f1[i],
            _ => -f2[i],
        });
        let y = DVector::from_iterator(n, bins.iter().map(|b| b[1]));
        let coef = (x.transpose() * &x).try_inverse()? * (x.transpose() * &y);
        let r = &y - &x * &coef;
        coef.iter()
            .all(|c| c.is_finite())
            .then(|| (r.dot(&r), r.iter().copied().collect()))
    };
    let mut two: Option<(f64, Vec<f64>)> = None;
    for (i, t1) in taus.iter().enumerate().step_by(2) {
        for t2 in taus.iter().skip(i + 2).step_by(2) {
            if let Some(v) = two_lags(*t1, *t2) {
                if two.as_ref().map_or(true, |b| v.0 < b.0) {
                    two = Some(v);
                }
            }
        }
    }
    // Noise at the one-minute scale (blocks of 6 bins) and beyond: a PID's noise is
    // correlated, and single bins would understate it. It is taken about the richer fit (two
    // lags), so a one-lag model that misses a layer cannot hide its own misfit in the noise
    // it is judged by.
    let (sse2, res) = two.unwrap_or_else(|| (best.sse, best.res.clone()));
    let white = sse2 / (n - 4) as f64;
    let m = 6;
    let blocks: Vec<f64> = res
        .chunks_exact(m)
        .map(|c| c.iter().sum::<f64>() / m as f64)
        .collect();
    let long = if blocks.len() >= 4 {
        m as f64 * blocks.iter().map(|b| b * b).sum::<f64>() / blocks.len() as f64
    } else {
        white
    };
    let sigma2 = white.max(long);
    if best.sse - sse2 > Z * Z * sigma2 {
        return Err(format!(
            "the heat-up shows more than one layer between the thermistor and the surface (two \
             lags fit it better by {:.0} σ²)",
            (best.sse - sse2) / sigma2
        )
        .into());
    }
    let (mut low, mut high) = (f64::INFINITY, f64::NEG_INFINITY);
    for IdFit {
        coef: c, sse, inv, ..
    } in &fits
    {
        // The 95 % profile: a fit worse than the best by more than 2² σ² is ruled out.
        if (sse - best.sse) > 4.0 * sigma2 {
            continue;
        }
        // The exact profile at this τ (the model is linear in the rest): b may move until the
        // fit has spent what is left of the 2² σ².
        let slack = (4.0 * sigma2 - (sse - best.sse)).max(0.0);
        let half = |k: usize| (slack * inv[(k, k)]).max(0.0).sqrt();
        low = low.min(c[2] - half(2));
        high = high.max(c[1] + half(1));
    }
    if !(low > 0.0 && high.is_finite()) {
        return Err(format!(
            "the heat-up's lag does not show (its low end {low:.4} is not above 0)"
        )
        .into());
    }
    Ok(Lag { low, high })
}

/// The bed's whole heat capacity, full power·s/K, at its low end, from the energy of a cold
/// heat-up and the first minutes of hold (binned as in [`lag_fit`]): what went in, less the
/// most that can have been lost, over the thermistor's rise. The losses are at most the last
/// two minutes' power per kelvin of rise (the power is still falling then) times the
/// integral of the thermistor's rise; the stack beyond a pad's thermistor is cooler than it
/// and not yet quite charged, so dividing by the thermistor's rise only lowers the answer.
fn heat_capacity_low(bins: &[[f64; 4]]) -> Result<f64, String> {
    let n = bins.len();
    let t0 = bins[0][2];
    let end = bins[n - 1][0];
    let tail: Vec<&[f64; 4]> = bins.iter().filter(|b| end - b[0] < 120.0).collect();
    let p_end = tail.iter().map(|b| b[1]).sum::<f64>() / tail.len() as f64;
    let rise_end = tail.iter().map(|b| b[2]).sum::<f64>() / tail.len() as f64 - t0;
    let (mut energy, mut rise_s) = (0.0, 0.0);
    for w in bins.windows(2) {
        let dt = w[1][0] - w[0][0];
        energy += w[1][1] * dt;
        rise_s += 0.5 * (w[0][2] + w[1][2] - 2.0 * t0) * dt;
    }
    let c = (energy - p_end / rise_end * rise_s) / rise_end;
    if !(c.is_finite() && c > 0.0) {
        return Err(format!(
            "the heat-up's energy gives no heat capacity ({c:.2} full power·s/K)"
        ));
    }
    Ok(c)
}

/// Identifies the coupling from a cold heat-up and the first minutes of hold, binned:
/// `(t_s, power, temp_c, rate_c_s)` from the first bin on (the bed at room temperature), for
/// the build `soak.bed` names (or the weakest, unnamed).
///
/// Its low end is the strongest of three lower bounds, each from the build's materials
/// ([`BedPreset`]): the weakest G such a build can have; C/(R·c)_max with C the bed's own heat
/// capacity ([`heat_capacity_low`]); and, where the layer a heat-up cannot show is a quick one
/// (a sheet on its magnet), the heat-up's own lag plus that layer, 1/(1/b + hidden/C). Its
/// high end is the lag's (h + G). A lag longer than any bed stack's (a plant this does not
/// describe) is not identified.
///
/// # Errors
/// Why the heat-up does not give the coupling, in words.
pub(crate) fn identify_coupling(
    bins: &[[f64; 4]],
    params: &SoakParams,
) -> Result<Coupling, String> {
    let lag = match lag_fit(bins) {
        Ok(l) => Some(l),
        Err(LagError::TooSlow(tau)) => {
            return Err(format!(
                "the heat-up shows a lag of {:.1} min, longer than any bed stack's ({:.0} min): \
                 something slower than the bed is in it",
                tau / 60.0,
                LAG_MAX_S / 60.0
            ))
        }
        Err(LagError::Other(why))
            if why.starts_with("too short") || why.starts_with("the bed rose") =>
        {
            return Err(why)
        }
        Err(LagError::Other(_)) => None,
    };
    let c = heat_capacity_low(bins)?;
    let named = BED_PRESETS.iter().find(|b| b.name == params.bed);
    let build = *named.unwrap_or(&BED_PRESETS[BED_PRESETS.len() - 1]);
    let from_c = c / build.rc_s;
    let from_lag = match (lag, build.hidden_s) {
        (Some(l), Some(h)) => 1.0 / (1.0 / l.low + h / c),
        _ => 0.0,
    };
    let high = lag.map_or(f64::INFINITY, |l| l.high);
    let mut low = build.g.max(from_c).max(from_lag);
    let mut note = String::new();
    if low > high {
        // The heat-up allows less than the build can have: the build is not what soak.bed
        // says (or this is not a bed stack); the heat-up's upper end is all that is left.
        low = high;
        note = format!(
            "; the heat-up allows at most 1/{:.0}, less than a {} can have: is soak.bed right?",
            1.0 / high,
            build.words
        );
    }
    let how = if low == from_lag && from_lag > 0.0 {
        format!(
            "its lag plus at most {:.0} s for a sheet on its magnet",
            build.hidden_s.unwrap_or(0.0)
        )
    } else if low == from_c {
        format!(
            "its heat capacity over the {:.0} s a {} takes at most",
            build.rc_s, build.words
        )
    } else if low == high {
        "the heat-up's upper end".to_string()
    } else {
        format!(
            "no more than the weakest {} (its heat-up allows no better)",
            build.words
        )
    };
    Ok(Coupling {
        g: low,
        low,
        high,
        charge_s: build.charge_s,
        source: CouplingSource::Identified,
        why: format!(
            "G identified from the heat-up: at least 1/{:.0} of full power per K ({}; bed heat \
             capacity {c:.1} full power·s/K{}), up to {}; the low end is used{note}",
            1.0 / low,
            how,
            if named.is_some() {
                format!(", soak.bed = \"{}\"", build.name)
            } else {
                ", soak.bed not set: any build".to_string()
            },
            if high.is_finite() {
                format!("1/{:.0}", 1.0 / high)
            } else {
                "an upper end the heat-up does not show".to_string()
            }
        ),
    })
}

/// A [`SoakParams`] value out of range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("soak.{key} = {value}: expected {expected}")]
pub struct SoakParamsError {
    /// The key, e.g. `bin_s`.
    pub key: &'static str,
    /// The value found, as written.
    pub value: String,
    /// What would be accepted.
    pub expected: &'static str,
}

impl SoakParams {
    /// Checks every value's range.
    ///
    /// # Errors
    /// The first key out of range, with its value and what is expected.
    pub(crate) fn validate(&self) -> Result<(), SoakParamsError> {
        let check = |key, value: f64, ok: bool, expected| {
            if ok && value.is_finite() {
                Ok(())
            } else {
                Err(SoakParamsError {
                    key,
                    value: value.to_string(),
                    expected,
                })
            }
        };
        let p = self;
        check("temp_band_c", p.temp_band_c, p.temp_band_c > 0.0, "> 0 °C")?;
        check("skip_below_c", p.skip_below_c, true, "a temperature in °C")?;
        check(
            "saturated_power",
            p.saturated_power,
            p.saturated_power > 0.0 && p.saturated_power <= 1.0,
            "a fraction of full power above 0, at most 1",
        )?;
        check("settle_s", p.settle_s, p.settle_s >= 0.0, ">= 0 s")?;
        check(
            "bin_s",
            p.bin_s,
            p.bin_s > 0.0 && p.bin_s <= 60.0,
            "between 0 and 60 s",
        )?;
        check("min_soak_s", p.min_soak_s, p.min_soak_s >= 0.0, ">= 0 s")?;
        check(
            "surface_budget_c",
            p.surface_budget_c,
            p.surface_budget_c >= 0.1 && p.surface_budget_c <= 10.0,
            "between 0.1 and 10 K",
        )?;
        if !(p.bed.is_empty() || BED_PRESETS.iter().any(|b| b.name == p.bed)) {
            return Err(SoakParamsError {
                key: "bed",
                value: format!("{:?}", p.bed),
                expected: BED_NAMES,
            });
        }
        check(
            "tau_max_s",
            p.tau_max_s,
            p.tau_max_s >= 20.0 * p.bin_s && p.tau_max_s <= 14_400.0,
            "at least 20 bins (bin_s) and at most 14400 s (4 h)",
        )?;
        if !["", "open", "enclosed"].contains(&p.frame.as_str()) {
            return Err(SoakParamsError {
                key: "frame",
                value: format!("{:?}", p.frame),
                expected: FRAME_NAMES,
            });
        }
        Ok(())
    }

    /// The slowest decay the rule rules out, s: `tau_max_s`, or on an open frame the bed
    /// stack's own bound when that is shorter.
    #[must_use]
    pub(crate) fn slowest_s(&self) -> f64 {
        if self.frame == "open" {
            self.tau_max_s.min(OPEN_FRAME_TAU_MAX_S)
        } else {
            self.tau_max_s
        }
    }

    /// Which slowest decay is ruled out, and why, in words.
    #[must_use]
    pub(crate) fn slowest_words(&self) -> String {
        let m = self.slowest_s() / 60.0;
        // Whole minutes for real beds; a test bench's seconds-long settings stay readable.
        let min = if m < 10.0 {
            format!("{m:.1}")
        } else {
            format!("{m:.0}")
        };
        match self.frame.as_str() {
            "open" if self.slowest_s() < self.tau_max_s => format!(
                "ruling out decays up to {min} min, the bed stack's own on an open frame \
                 (soak.frame = \"open\"; in an enclosure this may be early)"
            ),
            "open" => format!(
                "ruling out decays up to {min} min (soak.tau_max_s, already below the open \
                 frame's {:.0} min)",
                OPEN_FRAME_TAU_MAX_S / 60.0
            ),
            "enclosed" => format!(
                "ruling out decays up to {min} min (soak.tau_max_s; soak.frame = \"enclosed\")"
            ),
            _ => format!(
                "ruling out decays up to {min} min (soak.tau_max_s, for a plate and an \
                 enclosure; soak.frame = \"open\" shortens it to {:.0} min on an open frame)",
                OPEN_FRAME_TAU_MAX_S / 60.0
            ),
        }
    }
}

/// What the detector says after a sample.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub(crate) enum SoakStatus {
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
pub(crate) struct DecayFit {
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
    pub(crate) fn rate_pct_per_10min(&self) -> Option<f64> {
        let plausible = self.tau_s.is_finite()
            && self.tau_s > 0.0
            && self.remaining.is_finite()
            && (0.0..=1.0).contains(&self.remaining)
            && (0.0..=1.0).contains(&self.final_power);
        let rate = self.remaining / self.tau_s * 600.0 * 100.0;
        (plausible && rate <= 100.0).then_some(if self.rising { -rate } else { rate })
    }
}

/// Likelihood-ratio threshold of the test in standard errors: a remaining fall of
/// `max_remaining` is ruled out once it costs the fit more than Z² σ².
pub(crate) const Z: f64 = 3.0;
/// The fastest time constant of the model: 1/60 of `tau_max_s` (one minute at the default),
/// at least two bins.
fn grid_min_s(p: &SoakParams) -> f64 {
    (p.tau_max_s / 60.0).max(2.0 * p.bin_s)
}
/// Decays faster than this many times the grid's fastest may be negative (the controller's
/// undershoot); slower ones are the plate's and its surroundings' and only decay.
const FREE_TAUS: f64 = 2.5;
/// Columns after the decays: the temperature's rate of change (heat into the bed's own
/// capacity, either sign).
const EXTRA_COLS: usize = 1;
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

#[derive(Debug, Clone, Copy)]
struct Point {
    t_s: f64,
    power: f64,
    /// The bin's rate of temperature change (°C/s), edge to edge: power that went into the
    /// bed's own heat capacity (a bang-bang heater's on and off, a PID's derivative kick) is
    /// no heat flow to its surroundings, and this column takes it out of the decays.
    rate_c_s: f64,
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
}

impl SoakDetector {
    /// A detector with these thresholds. Values out of range are replaced by their defaults
    /// (check them with [`SoakParams::validate`] when they come from a user).
    pub(crate) fn new(params: SoakParams) -> Self {
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
        let k = taus.len() + 1 + EXTRA_COLS;
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
        }
    }

    /// The heater's `max_power` from Klipper's config (0.05–1; Klipper reports the pwm as a
    /// fraction of full power, capped there): a heater at `saturated_power` of it has no
    /// headroom left. Out-of-range values are ignored.
    pub(crate) fn set_max_power(&mut self, max_power: f64) {
        if max_power.is_finite() && (0.05..=1.0).contains(&max_power) {
            self.max_power = max_power;
            self.max_power_set = true;
        }
    }

    /// The `max_power` saturation is measured against: Klipper's, when given; else 1.0 until
    /// the heat-up shows a lower cap (see [`SoakDetector::push`]).
    #[cfg(test)]
    #[must_use]
    pub(crate) fn max_power(&self) -> f64 {
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
    pub(crate) fn params(&self) -> &SoakParams {
        &self.params
    }

    /// The coupling from thermistor to surface the rule uses now, and where it came from.
    pub(crate) fn coupling(&self) -> &Coupling {
        &self.coupling
    }

    /// The coupling is settled for this target (identified, or fallen back and said why).
    pub(crate) fn coupling_final(&self) -> bool {
        self.coupling_final
    }

    /// The power (fraction of full power) that may still fall when the bed is declared: the
    /// surface budget times the coupling (issue 10's fixed value in the bench's comparison).
    #[must_use]
    pub(crate) fn threshold(&self) -> f64 {
        self.params.fixed_remaining.unwrap_or_else(|| {
            (self.params.surface_budget_c * self.coupling.g).min(0.5 * self.max_power)
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
    pub(crate) fn status(&self) -> &SoakStatus {
        &self.status
    }

    /// Why the detector says what it says, in words: what it waits for, or why it declared.
    pub(crate) fn explanation(&self) -> &str {
        &self.explanation
    }

    /// The latest decay fit, once the soak has enough data.
    pub(crate) fn fit(&self) -> Option<DecayFit> {
        self.fit
    }

    /// Forgets everything but the thresholds and `max_power` (a new heat-up).
    pub(crate) fn reset(&mut self) {
        let (max_power, set) = (self.max_power, self.max_power_set);
        *self = SoakDetector::new(self.params.clone());
        self.max_power = max_power;
        self.max_power_set = set;
    }

    /// Feeds one sample: time `t_s` (any origin, increasing), heater `power` (0..1, held until
    /// the next sample, at most 30 s), bed temperature `temp_c` and target `target_c`. Samples
    /// that are not finite or not later than the previous one are ignored; a change of target
    /// restarts the soak. The status changes at most once per `bin_s`.
    pub(crate) fn push(&mut self, t_s: f64, power: f64, temp_c: f64, target_c: f64) -> SoakStatus {
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

    /// The model's row for a bin: 1, then each decay, then the temperature's rate of change.
    fn row(&self, p: &Point) -> DVector<f64> {
        let origin = self.origin_s.unwrap_or(p.t_s);
        let dt = (p.t_s - origin).max(0.0);
        DVector::from_iterator(
            self.taus.len() + 1 + EXTRA_COLS,
            std::iter::once(1.0)
                .chain(self.taus.iter().map(|tau| (-dt / tau).exp()))
                .chain([p.rate_c_s]),
        )
    }

    fn add_point(&mut self, p: Point) {
        let x = self.row(&p);
        self.xtx.ger(1.0, &x, &x, 1.0);
        self.xty.axpy(p.power, &x, 1.0);
        self.yty += p.power * p.power;
        self.points.push(p);
    }

    /// One smoothed bin: temperature and headroom gates, then the model and the decision.
    fn on_bin(&mut self, t_s: f64, power: f64, temp_c: f64, rate_c_s: f64) {
        if matches!(self.status, SoakStatus::Stable { .. }) {
            return;
        }
        let Some(target) = self.target_c else { return };
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
        // An overshoot inside the band has the same aftermath on its own time scale.
        if temp_c > target + OVERSHOOT_C {
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
        self.add_point(Point {
            t_s,
            power,
            rate_c_s,
        });
        if self.points.len() > MAX_POINTS {
            let keep = self.points.split_off(MAX_POINTS / 2);
            self.points.clear();
            let k = self.taus.len() + 1 + EXTRA_COLS;
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

    /// The directions the power may still go, as the sign the model sees it with: after a
    /// heat-up (the temperature came up into the band) its surroundings only warm and the
    /// power only falls (+1). After a step down they may be warmer than they will be (the bed
    /// was held long at the higher target: the power rises while they cool) or still colder
    /// (it was not: the power falls), and so may a bed first seen already in the band: both
    /// are tested, the rise on the negated power (−1), and both must be ruled out.
    fn directions(&self) -> &'static [f64] {
        if self.approach_above == Some(false) {
            &[1.0]
        } else {
            &[1.0, -1.0]
        }
    }

    /// Which coefficients may take either sign: the constant and the controller's fast decays;
    /// on a bed first seen warm also the plate's (up to a sixth of `tau_max_s`). Only from
    /// equilibrium does a clamped RC network's power fall as a sum of decays that are all
    /// positive; a bed heated before may start with its plate ahead of its surroundings, and
    /// then the plate's part of the power rises while the surroundings' still falls.
    fn free(&self) -> Vec<bool> {
        let warm_free_s = if self.warm_start == Some(true) {
            self.params.tau_max_s / 6.0
        } else {
            0.0
        };
        std::iter::once(true)
            .chain(self.taus.iter().map(|tau| {
                *tau < FREE_TAUS * grid_min_s(&self.params)
                            // An excursion's aftermath (the controller's integral winding back
                            // after an overshoot lifts the power) may go either way, on the
                            // excursion's own time scale.
                            || *tau <= self.excursion_len_s
                            || *tau <= warm_free_s
            }))
            .chain([true; EXTRA_COLS])
            .collect()
    }

    /// Least squares on `sign`·power with the decays' sign constraints; with `pin` = (g, θ),
    /// also g·c = θ.
    fn solve(&self, sign: f64, pin: Option<(&DVector<f64>, f64)>) -> Option<Solution> {
        let xty = &self.xty * sign;
        let coef = nnls(&self.xtx, &xty, &self.free(), pin)?;
        let sse = (self.yty - 2.0 * coef.dot(&xty) + coef.dot(&(&self.xtx * &coef))).max(0.0);
        (sse.is_finite() && coef.iter().all(|c| c.is_finite())).then_some(Solution { coef, sse })
    }

    /// Noise variance of a bin about the fit: (white, long-run, blocks behind the long-run
    /// estimate). The long-run variance is the one the test needs (the decision rests on the
    /// slow part of the signal): bins' residuals are averaged over blocks as long as the data
    /// allow with at least `MIN_BLOCKS` of them, and the variance of those means is scaled back
    /// to one bin. A PID loop suppresses slow power noise (that is lower), a wandering or
    /// cycling heater has more of it (that is higher).
    fn noise(&self, sign: f64, coef: &DVector<f64>) -> (f64, f64, usize) {
        let residuals: Vec<f64> = self
            .points
            .iter()
            .map(|p| sign * p.power - self.row(p).dot(coef))
            .collect();
        let n = residuals.len();
        let used = coef.iter().filter(|c| **c != 0.0).count();
        let white =
            residuals.iter().map(|r| r * r).sum::<f64>() / (n.saturating_sub(used)).max(1) as f64;
        let mut m = BLOCK_BINS;
        while n / (2 * m) >= MIN_BLOCKS {
            m *= 2;
        }
        let blocks: Vec<f64> = residuals
            .chunks_exact(m)
            .map(|c| c.iter().sum::<f64>() / m as f64)
            .collect();
        if blocks.len() < MIN_BLOCKS {
            return (white, white, blocks.len());
        }
        let long = m as f64 * blocks.iter().map(|b| b * b).sum::<f64>() / blocks.len() as f64;
        (white, long, blocks.len())
    }

    /// The decays' values at `t_s` (the constant's entry 0): g·c is the power still to fall.
    fn decays_at(&self, t_s: f64) -> DVector<f64> {
        let mut g = self.row(&Point {
            t_s,
            power: 0.0,
            rate_c_s: 0.0,
        });
        g[0] = 0.0;
        // Right after the band is reached the stack is still charging: the surface lags the
        // power by its charge time, so a decay of time constant τ still holds (1 + charge/τ)
        // times more surface warming than its power says (the first-order lag's gain on a
        // decay, to first order); slow decays hold what ΔP / G says.
        if self.params.fixed_remaining.is_none() {
            let charge = self.coupling.charge_s;
            for (k, tau) in self.taus.iter().enumerate() {
                g[k + 1] *= 1.0 + charge / tau;
            }
        }
        g
    }

    /// The likelihood-ratio test in one direction (`sign` +1: what is still to fall; −1: what
    /// is still to rise): the best model, and how much worse the best one is that still has
    /// `max_remaining` to go now.
    fn test(&self, sign: f64, now_s: f64) -> Option<DirectionTest> {
        let best = self.solve(sign, None)?;
        let (white, long, blocks) = self.noise(sign, &best.coef);
        // Few blocks make the one-minute scatter itself uncertain: widen it while they are few.
        let sigma2 = long * (1.0 + 2.0 / (blocks.max(1) as f64).sqrt());
        let g = self.decays_at(now_s);
        let r_hat = g.dot(&best.coef);
        let theta = self.threshold();
        let cost = if r_hat >= theta {
            0.0
        } else {
            self.solve(sign, Some((&g, theta)))
                .map_or(0.0, |s| (s.sse - best.sse).max(0.0))
        };
        // The upper bound, from the cost of θ (exact for a linear model without active
        // constraints: cost = (θ − R̂)² / var R̂).
        let sd_r = if cost > 0.0 {
            (theta - r_hat) * sigma2.sqrt() / cost.sqrt()
        } else {
            f64::INFINITY
        };
        let remaining = r_hat.max(0.0);
        let remaining_upper = if r_hat >= theta {
            r_hat
        } else {
            (r_hat + Z * sd_r).max(remaining)
        };
        // What printing now may cost at 95 % (one-sided): the spread from the cost of a pin
        // above the best fit when θ itself is below it.
        let sd_95 = if sd_r.is_finite() {
            sd_r
        } else {
            let pin = r_hat.max(0.0) + theta;
            self.solve(sign, Some((&g, pin)))
                .map(|s| (s.sse - best.sse).max(0.0))
                .filter(|c| *c > 0.0)
                .map_or(f64::INFINITY, |c| (pin - r_hat) * sigma2.sqrt() / c.sqrt())
        };
        let remaining_95 = (r_hat + 1.645 * sd_95).max(remaining);
        Some(DirectionTest {
            sign,
            best,
            white,
            sigma2,
            remaining,
            remaining_upper,
            remaining_95,
            ruled_out: cost > Z * Z * sigma2,
        })
    }

    fn decide(&mut self, now_s: f64, t0: f64) {
        let p = self.params.clone();
        let span = now_s - t0;
        if self.points.len() < MIN_POINTS {
            self.status = SoakStatus::Soaking {
                progress: 0.0,
                eta_s: None,
                print_now_c: None,
                reason: format!(
                    "collecting power readings ({} of {MIN_POINTS} bins of {:.0} s)",
                    self.points.len(),
                    p.bin_s
                ),
            };
            self.explanation = status_reason(&self.status);
            return;
        }
        let tests: Option<Vec<DirectionTest>> = self
            .directions()
            .iter()
            .map(|sign| self.test(*sign, now_s))
            .collect();
        let Some(tests) = tests else {
            self.status = SoakStatus::Soaking {
                progress: 0.0,
                eta_s: None,
                print_now_c: None,
                reason: "power readings do not fit a decay yet".into(),
            };
            self.explanation = status_reason(&self.status);
            return;
        };
        let ruled_out = tests.iter().all(|t| t.ruled_out);
        // What is reported: a direction still waited for, and of those (or of all, once
        // both are ruled out) the one that fits the data better.
        let Some(t) = tests.into_iter().max_by(|a, b| {
            (!a.ruled_out)
                .cmp(&!b.ruled_out)
                .then(b.best.sse.total_cmp(&a.best.sse))
        }) else {
            return;
        };
        let DirectionTest {
            sign,
            best,
            white,
            sigma2,
            remaining,
            remaining_upper,
            remaining_95,
            ..
        } = t;
        let theta = self.threshold();
        let g = self.decays_at(now_s);
        let contrib: Vec<(f64, f64)> = self
            .taus
            .iter()
            .enumerate()
            .map(|(k, tau)| (*tau, best.coef[k + 1] * g[k + 1]))
            .collect();
        let left: f64 = contrib.iter().map(|(_, c)| c.max(0.0)).sum();
        let tau_s = if left > 0.0 {
            contrib.iter().map(|(tau, c)| tau * c.max(0.0)).sum::<f64>() / left
        } else {
            // Nothing left: the τ of the largest decay fitted.
            self.taus
                .iter()
                .zip(best.coef.iter().skip(1))
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map_or(grid_min_s(&self.params), |(tau, _)| *tau)
        };
        let slowest = contrib.last().map_or(0.0, |(_, c)| *c);
        let rising = sign < 0.0;
        let (fall, falling) = if rising {
            ("rise", "rising")
        } else {
            ("fall", "falling")
        };
        let fit = DecayFit {
            tau_s,
            final_power: sign * best.coef[0],
            remaining,
            remaining_upper,
            amplitude: sign * best.coef.iter().skip(1).take(self.taus.len()).sum::<f64>(),
            rising,
            tau_unbounded: slowest > 0.5 * remaining.max(theta),
            noise_sd: white.sqrt(),
            test_sd: sigma2.sqrt(),
            noise_inflation: (sigma2 / white.max(1e-18)).sqrt().max(1.0),
            threshold: theta,
            surface_upper_c: self.surface_c(remaining_upper),
            surface_95_c: self.surface_c(remaining_95),
        };
        self.fit = Some(fit);
        let budget = p.surface_budget_c;
        let span_ok = span >= p.min_soak_s;
        // A heater between off and its cap always moves a little, and so does a thermistor's
        // reading: readings frozen for minutes are a stopped Klipper (a shutdown keeps logging
        // its last values), not a settled bed.
        let frozen_s = match (self.unchanged_since_s, self.reading) {
            (Some(since), Some((power, _)))
                if power > 0.0 && power < self.params.saturated_power * self.max_power =>
            {
                now_s - since
            }
            _ => 0.0,
        };
        let frozen = frozen_s >= FROZEN_S;
        let saturated_recently = self
            .last_saturated_s
            .is_some_and(|t| now_s - t < p.min_soak_s);
        // Early in a soak (or on a bed whose power wanders) the best fit can head for a power
        // the heater cannot give; its numbers would only confuse: say so in words instead.
        let plausible = (-0.05..=self.max_power + 0.05).contains(&fit.final_power)
            && remaining <= self.max_power
            && remaining_upper <= self.max_power;
        let surface = if rising { "cool" } else { "warm" };
        let fit_words = if plausible {
            format!(
                "the print surface can still {surface} by at most {:.2} K (budget {budget:.1} K); \
                 power best fit {:.2} % still to {fall} (τ {:.1} min, towards {:.1} %), at most \
                 {:.2} % (allowed {:.2} %; power noise {:.2} %); {}; {}",
                fit.surface_upper_c,
                remaining * 100.0,
                tau_s / 60.0,
                fit.final_power * 100.0,
                remaining_upper * 100.0,
                theta * 100.0,
                sigma2.sqrt() * 100.0,
                self.coupling.why,
                p.slowest_words()
            )
        } else {
            format!(
                "the power is still changing too much to tell where it settles (stable once less \
                 than {:.2} % can still {fall}, the surface's budget of {budget:.1} K; power \
                 noise {:.2} %); {}; {}",
                theta * 100.0,
                sigma2.sqrt() * 100.0,
                self.coupling.why,
                p.slowest_words()
            )
        };
        if span_ok && ruled_out && !saturated_recently && !frozen {
            self.status = SoakStatus::Stable { at_s: now_s };
            self.explanation = format!(
                "surface settled, power stopped {falling}: temperature within ±{:.1} °C of {:.1} \
                 °C, soaked {:.1} min; {fit_words}",
                p.temp_band_c,
                self.target_c.unwrap_or(f64::NAN),
                span / 60.0
            );
            return;
        }
        let mut waits = Vec::new();
        if !ruled_out {
            if plausible && fit.tau_unbounded && remaining > theta {
                waits.push(format!(
                    "power still {falling} steadily ({:.3} %/min); the end of the decay is not \
                     in sight yet ({fit_words})",
                    remaining / tau_s * 6000.0
                ));
            } else {
                waits.push(format!("power may still {fall}: {fit_words}"));
            }
        }
        if frozen {
            waits.push(format!(
                "the bed's power and temperature have not changed for {:.0} s: are Klipper and \
                 its heater still running?",
                frozen_s
            ));
        }
        if span < p.min_soak_s {
            waits.push(format!(
                "minimum soak: {:.1} of {:.1} min",
                span / 60.0,
                p.min_soak_s / 60.0
            ));
        }
        if saturated_recently {
            waits.push(if self.max_power < 1.0 {
                format!(
                    "the heater was at its max_power ({:.2}) within the minimum soak",
                    self.max_power
                )
            } else {
                "the heater was at full power within the minimum soak".into()
            });
        }
        // ETA: the best fit's fall to θ, and the span the test needs to rule out
        // the slowest decay allowed: its slope θ/τ_max known to ± θ/(Z·τ_max) at this noise
        // (n bins over a span W give the slope to ± σ·√(12/n)/W).
        let physical = Some(if remaining > theta {
            tau_s * (remaining / theta).ln()
        } else {
            0.0
        });
        let statistical = if ruled_out {
            Some(0.0)
        } else {
            let need = (Z * p.slowest_s() * sigma2.sqrt() * (12.0 * p.bin_s).sqrt() / theta)
                .powf(2.0 / 3.0);
            Some((need - span).max(0.0).min(4.0 * p.slowest_s()))
        };
        let eta_s = match (physical, statistical) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (Some(a), None) if a > 0.0 => Some(a),
            (None, Some(b)) => Some(b),
            _ => None,
        }
        .map(|e| e.max(p.min_soak_s - span).max(p.bin_s));
        // The progress a user sees never goes back within a soak (the ETA may).
        let progress = eta_s
            .map_or(0.0, |eta| (span / (span + eta)).clamp(0.0, 1.0))
            .max(self.progress_floor);
        self.progress_floor = progress;
        let print_now_c = (plausible && fit.surface_95_c.is_finite()).then_some(fit.surface_95_c);
        self.status = SoakStatus::Soaking {
            progress,
            eta_s,
            print_now_c,
            reason: waits.join("; "),
        };
        self.explanation = status_reason(&self.status);
    }
}

fn status_reason(s: &SoakStatus) -> String {
    match s {
        SoakStatus::Soaking { reason, .. } => reason.clone(),
        other => format!("{other:?}"),
    }
}

/// Solves the least-squares problem restricted to the indices where `mask` is set (the others
/// 0), with `pin` = (g, θ) under gᵀx = θ (the KKT system, solved by LU).
fn solve_masked(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    mask: &[bool],
    pin: Option<(&DVector<f64>, f64)>,
) -> Option<DVector<f64>> {
    let idx: Vec<usize> = (0..mask.len()).filter(|i| mask[*i]).collect();
    let mut x = DVector::zeros(mask.len());
    if idx.is_empty() {
        return Some(x);
    }
    let m = idx.len();
    let extra = usize::from(pin.is_some());
    let mut kkt = DMatrix::zeros(m + extra, m + extra);
    let mut rhs = DVector::zeros(m + extra);
    // A tiny ridge: neighbouring decays of the grid are nearly collinear.
    let ridge = 1e-13 * (0..m).map(|i| h[(idx[i], idx[i])]).fold(1e-300, f64::max);
    for i in 0..m {
        for j in 0..m {
            kkt[(i, j)] = h[(idx[i], idx[j])];
        }
        kkt[(i, i)] += ridge;
        rhs[i] = b[idx[i]];
    }
    if let Some((g, theta)) = pin {
        for i in 0..m {
            kkt[(i, m)] = g[idx[i]];
            kkt[(m, i)] = g[idx[i]];
        }
        rhs[m] = theta;
    }
    let s = kkt
        .clone()
        .lu()
        .solve(&rhs)
        .filter(|s| s.iter().all(|v| v.is_finite()));
    let s = match s {
        Some(s) => s,
        None => kkt.svd(true, true).solve(&rhs, 1e-14).ok()?,
    };
    for (k, i) in idx.iter().enumerate() {
        x[*i] = s[k];
    }
    Some(x)
}

/// Least squares from the normal equations (`h` = XᵀX, `b` = Xᵀy) with `x[i] ≥ 0` wherever
/// `free[i]` is false, and with `pin` = (g, θ) also gᵀx = θ: Lawson and Hanson's active-set
/// method, started from a feasible point (with a pin: all of θ in the constrained decay that
/// has most left).
fn nnls(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    free: &[bool],
    pin: Option<(&DVector<f64>, f64)>,
) -> Option<DVector<f64>> {
    let k = b.len();
    let mut passive: Vec<bool> = free.to_vec();
    let mut x = DVector::zeros(k);
    if free.iter().all(|f| *f) {
        // Nothing constrained (after an excursion longer than the slowest decay every decay
        // may take either sign): plain least squares, with the pin if any.
        return solve_masked(h, b, free, pin);
    }
    if let Some((g, theta)) = pin {
        let j = (0..k)
            .filter(|i| !free[*i])
            .max_by(|a, c| g[*a].total_cmp(&g[*c]))?;
        if g[j] <= 0.0 {
            return None;
        }
        x[j] = theta / g[j];
        passive[j] = true;
    }
    let tol = 1e-10 * h.diagonal().max().max(1.0) * 1e-3;
    let mut first = true;
    for _ in 0..4 * k {
        if !first {
            // The gradient of the Lagrangian: with a pin, its multiplier is the one that makes
            // the passive components' gradients zero (their mean, as they are all equal).
            let mut w = b - h * &x;
            if let Some((g, _)) = pin {
                let (mut num, mut den) = (0.0, 0.0);
                for i in (0..k).filter(|i| passive[*i]) {
                    num += w[i] * g[i];
                    den += g[i] * g[i];
                }
                if den > 0.0 {
                    let lambda = num / den;
                    w.axpy(-lambda, g, 1.0);
                }
            }
            let pick = (0..k)
                .filter(|i| !passive[*i])
                .max_by(|a, c| w[*a].total_cmp(&w[*c]));
            let Some(j) = pick.filter(|j| w[*j] > tol) else {
                break;
            };
            passive[j] = true;
        }
        first = false;
        for _ in 0..4 * k {
            let s = solve_masked(h, b, &passive, pin)?;
            let bad: Vec<usize> = (0..k)
                .filter(|i| passive[*i] && !free[*i] && s[*i] <= 0.0)
                .collect();
            if bad.is_empty() {
                x = s;
                break;
            }
            let alpha = bad
                .iter()
                .map(|i| x[*i] / (x[*i] - s[*i]))
                .fold(1.0, f64::min)
                .clamp(0.0, 1.0);
            x += (s - &x) * alpha;
            for i in 0..k {
                if passive[i] && !free[i] && x[i] <= 1e-15 {
                    passive[i] = false;
                    x[i] = 0.0;
                }
            }
        }
    }
    Some(x)
}

#[cfg(test)]
mod tests {
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

    use super::*;

    const TARGET_C: f64 = 60.0;

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

    /// Every field's doc comment states its default, and states the one the code uses.
    #[test]
    fn the_doc_comments_state_the_real_defaults() {
        let src = include_str!("soak.rs");
        let start = src.find("pub struct SoakParams {").unwrap();
        let end = start + src[start..].find("\n}").unwrap();
        let defaults = serde_json::to_value(SoakParams::default()).unwrap();
        let mut doc = String::new();
        let mut checked = 0;
        for line in src[start..end].lines().skip(1) {
            let t = line.trim();
            if let Some(d) = t.strip_prefix("///") {
                doc.push_str(d);
                doc.push(' ');
            } else if let Some(field) = t.strip_prefix("pub ").and_then(|r| r.split(':').next()) {
                match defaults[field].as_str() {
                    // A text setting: its doc says `Default "…"`.
                    Some(text) => assert!(
                        doc.contains(&format!("Default {text:?}")),
                        "soak.{field}: doc does not say Default {text:?}"
                    ),
                    None => {
                        let stated: f64 = doc
                            .split("Default ")
                            .nth(1)
                            .and_then(|r| r.split_whitespace().next())
                            .map(|n| n.trim_end_matches(['.', ',', ')']))
                            .and_then(|n| n.parse().ok())
                            .unwrap_or_else(|| {
                                panic!("soak.{field}: no \"Default N\" in its doc comment")
                            });
                        let real = defaults[field].as_f64().unwrap();
                        assert!(
                            (stated - real).abs() < 1e-12,
                            "soak.{field}: doc says {stated}, code {real}"
                        );
                    }
                }
                checked += 1;
                doc.clear();
            }
        }
        assert_eq!(checked, defaults.as_object().unwrap().len());
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

    #[test]
    fn soak_params_read_from_toml_with_defaults_for_missing_keys() {
        let p: SoakParams =
            toml::from_str("surface_budget_c = 0.5\ntemp_band_c = 1.5\nbed = \"glass-pad\"\n")
                .unwrap();
        assert_eq!(p.surface_budget_c, 0.5);
        assert_eq!(p.bed, "glass-pad");
        assert_eq!(p.temp_band_c, 1.5);
        assert_eq!(p.min_soak_s, SoakParams::default().min_soak_s);
        assert!(toml::from_str::<SoakParams>("max_remainder = 0.005").is_err());
    }

    #[test]
    fn out_of_range_params_name_the_key_and_what_is_expected() {
        let p = SoakParams {
            bin_s: 0.0,
            ..SoakParams::default()
        };
        let err = p.validate().unwrap_err();
        assert_eq!(err.key, "bin_s");
        assert!(err.to_string().contains("soak.bin_s = 0"), "{err}");
        assert!(SoakParams::default().validate().is_ok());
    }

    /// A bed of two nodes in full-power units: the thermistor's (heat capacity `c_th`, losses
    /// `h_th`) and the print surface beyond it (capacity `c_s`, coupling `g`, losses `h_s`),
    /// from 22 °C under a PI controller on the thermistor with `noise_c` of reading noise.
    /// Returns `(t, power, reading, surface)` once a second for `until_s`.
    #[allow(clippy::too_many_arguments)]
    fn two_node_bed(
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
    fn run_bed(params: SoakParams, bed: &[[f64; 4]], from: usize) -> (SoakDetector, Option<f64>) {
        let mut d = SoakDetector::new(params);
        for s in &bed[from..] {
            if let SoakStatus::Stable { at_s } = d.push(s[0], s[1], s[2], TARGET_C) {
                return (d, Some(at_s));
            }
        }
        (d, None)
    }

    /// The surface's distance from its final temperature at `t_s`, K.
    fn surface_left(bed: &[[f64; 4]], t_s: f64) -> f64 {
        let last = bed.last().unwrap()[3];
        let now = bed.iter().find(|s| s[0] >= t_s).unwrap()[3];
        last - now
    }

    #[test]
    fn a_cold_heat_up_identifies_the_coupling_within_its_interval_and_questions_a_wrong_preset() {
        // Beds with a stack beyond the thermistor: couplings 1/10–1/40 (R·C 64–256 s).
        for (k, g) in [0.1, 1.0 / 20.0, 1.0 / 40.0].into_iter().enumerate() {
            let bed = two_node_bed(g, 0.4, 6.0, 0.002, 0.012, 0.05, 4.0 * 3600.0, k as u64);
            let (d, at) = run_bed(SoakParams::default(), &bed, 0);
            let c = d.coupling().clone();
            assert_eq!(c.source, CouplingSource::Identified, "G {g}: {}", c.why);
            assert!(
                c.low <= g && g <= c.high && c.g == c.low,
                "G {g} outside [{}, {}]",
                c.low,
                c.high
            );
            // Not weaker than the weakest build allows, and said with its interval.
            assert!(c.low >= BED_PRESETS[BED_PRESETS.len() - 1].g);
            assert!(
                c.why.starts_with("G identified from the heat-up: "),
                "{}",
                c.why
            );
            assert!(c
                .short()
                .contains(&format!("1/{:.0}–1/{:.0}", 1.0 / c.low, 1.0 / c.high)));
            let at = at.unwrap_or_else(|| panic!("G {g} never declared: {}", d.explanation()));
            let left = surface_left(&bed, at);
            assert!(
                left <= 1.0,
                "G {g}: declared at {at} s with {left:.2} K to go"
            );
            // A build stronger than the heat-up allows (a bare plate's 1/5 on these beds) is
            // not believed: the heat-up's upper end is used, and the user is asked.
            let strong = SoakParams {
                bed: "bare-plate".into(),
                ..SoakParams::default()
            };
            let (d, _) = run_bed(strong, &bed, 0);
            let p = d.coupling();
            assert_eq!(p.source, CouplingSource::Identified);
            assert!(p.g <= c.high + 1e-12, "G {g}: used {} over {}", p.g, c.high);
            if c.high < 0.2 {
                assert!(p.why.contains("is soak.bed right?"), "{}", p.why);
            }
        }
    }

    /// A bed whose surface lags its heater by 25 min, far more than any bed stack: the first
    /// minutes of hold cannot show such a lag, its energy shows only the part that charged
    /// (a low heat capacity, which only lowers the low end), and the interval still holds its
    /// G, at the weakest build's low end.
    #[test]
    fn a_heat_up_slower_than_any_bed_stack_still_gets_an_interval_that_holds_its_g() {
        let g = 0.02;
        let bed = two_node_bed(g, 0.4, 48.0, 0.002, 0.012, 0.05, 2.0 * 3600.0, 4);
        let (d, _) = run_bed(SoakParams::default(), &bed, 0);
        let c = d.coupling();
        assert!(c.low <= g && g <= c.high, "{}", c.why);
        assert!(
            c.source == CouplingSource::Weakest
                || (c.low - BED_PRESETS[BED_PRESETS.len() - 1].g).abs() < 1e-12,
            "{}",
            c.why
        );
    }

    #[test]
    fn a_warm_start_falls_back_to_the_preset_or_the_weakest_coupling_and_says_so() {
        let bed = two_node_bed(0.05, 0.4, 6.0, 0.002, 0.012, 0.05, 3.0 * 3600.0, 7);
        // First seen at its target (a daemon primed from the temperature store).
        let from = bed
            .iter()
            .position(|s| (s[2] - TARGET_C).abs() < 0.5)
            .unwrap();
        let (d, _) = run_bed(SoakParams::default(), &bed, from);
        let c = d.coupling();
        assert_eq!(c.source, CouplingSource::Weakest);
        assert!(c.why.contains("warm start"), "{}", c.why);
        assert!(
            d.explanation().contains("warm start"),
            "{}",
            d.explanation()
        );
        let preset = SoakParams {
            bed: "steel-pad".into(),
            ..SoakParams::default()
        };
        let (d, _) = run_bed(preset, &bed, from);
        assert_eq!(d.coupling().source, CouplingSource::Preset);
        let steel_pad = BED_PRESETS
            .iter()
            .find(|b| b.name == "steel-pad")
            .unwrap()
            .g;
        assert!((d.coupling().g - steel_pad).abs() < 1e-12);
        assert!(d.coupling().short().contains("not identified"));
        assert!(
            d.coupling().why.contains("soak.bed = \"steel-pad\""),
            "{}",
            d.coupling().why
        );
        assert!((d.threshold() - steel_pad).abs() < 1e-12);
    }

    #[test]
    fn soak_frame_is_read_and_refused_by_name_when_not_a_frame() {
        let p: SoakParams = toml::from_str("frame = \"open\"\n").expect("parses");
        assert_eq!(p.frame, "open");
        assert!(p.validate().is_ok());
        assert_eq!(p.slowest_s(), OPEN_FRAME_TAU_MAX_S);
        // A shorter tau_max_s still wins; "enclosed" and unknown keep tau_max_s.
        let short = SoakParams {
            tau_max_s: 900.0,
            ..p.clone()
        };
        assert_eq!(short.slowest_s(), 900.0);
        for frame in ["", "enclosed"] {
            let q = SoakParams {
                frame: frame.into(),
                ..SoakParams::default()
            };
            assert!(q.validate().is_ok());
            assert_eq!(q.slowest_s(), 3600.0);
        }
        for bad in ["Open", "opne", "closed"] {
            let q = SoakParams {
                frame: bad.into(),
                ..SoakParams::default()
            };
            let e = q.validate().expect_err(bad);
            assert_eq!(e.key, "frame");
            assert_eq!(e.value, format!("{bad:?}"));
            let msg = e.to_string();
            assert!(
                msg.starts_with("soak.frame = ")
                    && msg.contains("\"open\"")
                    && msg.contains("\"enclosed\""),
                "{msg}"
            );
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

    #[test]
    fn the_new_settings_are_refused_by_name_when_out_of_range() {
        for (p, key) in [
            (
                SoakParams {
                    surface_budget_c: 0.0,
                    ..SoakParams::default()
                },
                "surface_budget_c",
            ),
            (
                SoakParams {
                    surface_budget_c: f64::NAN,
                    ..SoakParams::default()
                },
                "surface_budget_c",
            ),
            (
                SoakParams {
                    surface_budget_c: 11.0,
                    ..SoakParams::default()
                },
                "surface_budget_c",
            ),
            (
                SoakParams {
                    bed: "granite".into(),
                    ..SoakParams::default()
                },
                "bed",
            ),
        ] {
            let e = p.validate().unwrap_err();
            assert_eq!(e.key, key);
            assert!(e.to_string().starts_with(&format!("soak.{key} = ")), "{e}");
        }
        let e = SoakParams {
            bed: "granite".into(),
            ..SoakParams::default()
        }
        .validate()
        .unwrap_err();
        assert!(e.to_string().contains("\"steel-plate\""), "{e}");
        for b in BED_PRESETS {
            let p = SoakParams {
                bed: b.name.into(),
                ..SoakParams::default()
            };
            assert!(p.validate().is_ok(), "{}", b.name);
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
}
