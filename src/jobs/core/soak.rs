//! The shared heat-and-soak step: the bed is watched through Moonraker and the pure detector
//! ([`crate::calib::soak`]) says when its power has stopped falling (paper 000 §3.1). Any
//! calibration that needs a soaked bed (A/B, thermal mesh) polls one [`BedSoak`]; the step
//! also writes the console's progress lines: one when soaking starts, one a minute with a
//! percentage that never goes backwards, and "bed stable after N min" at the end.

use std::time::Instant;

use serde_json::json;

use super::session::Core;
use super::user;
use crate::calib::soak::ask;
use crate::calib::soak::{cost_words, kelvin_words, SoakDetector, SoakParams, SoakStatus};
use crate::klipper::gcode_cmd;

/// The `[soak]` settings a soak starts with: as klipcal.toml says when the soak starts, so an
/// edit (in Mainsail's or Fluidd's file editor, say) applies to the next soak without a
/// restart; as klipcal started when the file no longer loads. Every calibration shares one
/// (its clones share the file's path, which the soak question may create).
#[derive(Debug, Clone, Default)]
pub(crate) struct SoakSettings {
    /// `[soak]` as klipcal started with it.
    pub started: SoakParams,
    /// The settings file klipcal read (none: the embedded defaults, until an answer to the
    /// soak question writes one).
    path: std::sync::Arc<std::sync::Mutex<Option<std::path::PathBuf>>>,
}

impl SoakSettings {
    /// `[soak]` and the file it came from, from the loaded settings.
    #[must_use]
    pub(crate) fn of(config: &crate::config::Config) -> Self {
        Self {
            started: config.soak.clone(),
            path: std::sync::Arc::new(std::sync::Mutex::new(config.path.clone())),
        }
    }

    fn path(&self) -> Option<std::path::PathBuf> {
        self.path
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// The settings file an answer goes to: the one klipcal read, else the conventional
    /// `~/printer_data/config/klipcal.toml`.
    #[must_use]
    pub(crate) fn file(&self) -> std::path::PathBuf {
        self.path().unwrap_or_else(crate::config::default_path)
    }

    /// An answer was written to `path`: `[soak]` is read from it from now on.
    pub(crate) fn written_to(&self, path: &std::path::Path) {
        *self
            .path
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(path.to_path_buf());
    }

    /// `[soak]` as the file says now, or as klipcal started with why not (the file no longer
    /// reads or a value is out of range: the whole file is refused, not half of it).
    pub(crate) fn now(&self) -> (SoakParams, Option<String>) {
        let Some(path) = self.path() else {
            return (self.started.clone(), None);
        };
        match crate::config::Config::load(Some(&path)) {
            Ok(c) => (c.soak, None),
            Err(e) => (
                self.started.clone(),
                Some(format!(
                    "{e}; this soak uses the [soak] settings klipcal started with"
                )),
            ),
        }
    }

    /// [`SoakSettings::now`] for a soak starting now, saying on the console (as `title`) why
    /// the file was not used when it was not.
    pub(crate) async fn for_soak(&self, core: &Core, title: &str) -> SoakParams {
        let (params, unread) = self.now();
        if let Some(why) = unread {
            core.console(&format!("{title}: {why}")).await;
        }
        params
    }
}

/// What the start of a soak says when `soak.bed` or `soak.frame` is not set: what klipcal
/// assumes instead, what naming them buys, and that the next soak reads them.
#[must_use]
pub(crate) fn unset_build_words(p: &SoakParams) -> Option<String> {
    let (bed, frame) = (ask::not_named(&p.bed), ask::not_named(&p.frame));
    let unset: Vec<&str> = [("soak.bed", bed), ("soak.frame", frame)]
        .into_iter()
        .filter_map(|(k, unset)| unset.then_some(k))
        .collect();
    if unset.is_empty() {
        return None;
    }
    Some(format!(
        "{} not set in klipcal.toml (or answered \"don't know\"), so this soak assumes {}; \
         answering klipcal's question (KLIPCAL_SOAK_BED SURFACE=… SENSOR=… FRAME=…) names {} \
         and this soak uses it at once (an edit of [soak] by hand is read by the next soak; docs/bed-soak.md): on \
         an open-frame steel bed about {} min instead of about {} min",
        unset.join(" and "),
        match (bed, frame) {
            (true, true) => "the weakest bed (glass on clips) and an enclosure",
            (true, false) => "the weakest bed (glass on clips)",
            _ => "an enclosure",
        },
        if unset.len() == 2 { "them" } else { "it" },
        ask::Minutes::STEEL_OPEN,
        ask::Minutes::DEFAULTS_OPEN
    ))
}

/// What `[heater_bed]` tells the soak rule: Kalico's `control: mpc` and its calibration.
fn heater_facts(
    h: &crate::moonraker::answers::HeaterSettings,
) -> Option<crate::calib::soak::HeaterFacts> {
    (h.control == Some(crate::moonraker::answers::HeaterControl::Mpc))
        .then(|| crate::calib::soak::HeaterFacts::mpc(h.block_heat_capacity, h.heater_power))
}

/// What one poll saw.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum SoakUpdate {
    /// The bed is still heating towards its target.
    Heating,
    /// Heated; waiting for the power to settle. `text` is the progress in words.
    Soaking {
        /// Fraction done, 0..1, never lower than an earlier poll's.
        progress: f64,
        /// Seconds left, when the fit can tell.
        eta_s: Option<f64>,
        /// Progress in words.
        text: String,
        /// What printing now would cost: the surface warming still possible at 95 %, K.
        print_now_c: Option<f64>,
    },
    /// The soak ran past its longest wait with the bed at its target but its power still
    /// moving: the caller asks the user (print now / wait / cancel) instead of failing.
    TooLong {
        /// Minutes since the target was set.
        minutes: f64,
        /// Seconds since the bed reached its target (the soak proper), when it did.
        at_target_s: Option<f64>,
        /// How fast the power still falls, % of full power per 10 min, when the fit can tell
        /// (negative: it still rises, after a step down to a lower target).
        falling_pct_per_10min: Option<f64>,
    },
    /// Stable (or skipped: unheated bed); `why` is the detector's explanation.
    Stable {
        /// The detector's explanation.
        why: String,
    },
}

/// One bed soak in progress.
pub(crate) struct BedSoak {
    detector: SoakDetector,
    start: Instant,
    target_c: f64,
    max_s: f64,
    max_setting: &'static str,
    best_progress: f64,
    /// The wait told to the user (smoothed and bounded).
    eta_shown: EtaShown,
    /// The last plausible print-now cost, K: shown until a newer one replaces it, so the offer
    /// does not flicker off the page when one poll's fit is not trusted.
    last_print_now_c: Option<f64>,
    soaking_since_s: Option<f64>,
    last_console_s: f64,
    primed: bool,
    /// Klipper's idle timeout must be set again to the soak's remaining time (at the first
    /// poll, and after [`BedSoak::extend`]).
    rebound: bool,
    /// The coupling the rule settled on has been told on the console.
    coupling_told: bool,
    /// A print follows the soak (A/B): its lines offer to print now and state what that costs.
    /// A mesh capture prints nothing and its lines say nothing of printing.
    prints: bool,
    /// The chamber thermometer read beside the bed (`soak.chamber_sensor`, else the first one
    /// Klipper's config has), as Klipper names its object.
    chamber: Option<String>,
    /// Every sample fed to the detector (time, power, temperature, target): replayed into a new
    /// detector when an answer to the soak question changes `[soak]` mid-soak.
    samples: Vec<[f64; 4]>,
    /// Klipper's `max_power` of the bed, once read.
    max_power: Option<f64>,
    /// The soak question's count of answers this soak's settings include.
    generation: u64,
    /// The core, once polled: the soak question ends with the soak.
    core: Option<Core>,
    /// A coupling identified from this bed's earlier cold heat-up, used on a warm start.
    carried: Option<crate::calib::soak::Coupling>,
}

impl Drop for BedSoak {
    fn drop(&mut self) {
        if let Some(core) = &self.core {
            super::soak_ask::soak_ended(core);
        }
    }
}

/// Beyond the soak's own limit, how long Klipper's idle timeout leaves the bed on (klipcal's
/// next look at it, and its question to the user, come well within it).
pub(crate) const BOUND_SLACK_S: f64 = 60.0;

/// A wait in words: minutes, or hours and minutes for a bed that needs hours (where a soak
/// before a print offers to print now, `prints`, the words say so).
#[must_use]
pub(crate) fn eta_words(eta_s: f64, prints: bool) -> String {
    let min = (eta_s / 60.0).ceil();
    if min >= 90.0 {
        format!(
            "{:.0} h {:.0} min{}",
            (min / 60.0).floor(),
            min % 60.0,
            if prints {
                " (this bed needs hours: print now is offered)"
            } else {
                ""
            }
        )
    } else {
        format!("{min:.0} min")
    }
}

/// How often the console hears of the soak.
const CONSOLE_EVERY_S: f64 = 60.0;

/// The wait a user is told, from the detector's estimate: smoothed (the estimate of the end
/// moves towards a new one with a 2-minute time constant, so a refit's jump from 3 to 15 min
/// shows as a steady rise, not a leap), never beyond what is left of the soak's limit, and no
/// "about 1 min left" over and over when the end is due but not yet confirmed.
#[derive(Debug, Clone, Default)]
pub(crate) struct EtaShown {
    /// The smoothed end, s (the soak's clock), and when it was last moved.
    end: Option<(f64, f64)>,
}

/// What [`EtaShown`] says.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Eta {
    /// About this long, s.
    Left(f64),
    /// Due now: the detector is confirming that the power has stopped falling.
    Confirming,
    /// Later than the soak's limit, which is this far off, s.
    BeyondLimit(f64),
    /// No estimate.
    Unknown,
}

/// The smoothed end's time constant, s.
const ETA_SMOOTHING_S: f64 = 120.0;

impl EtaShown {
    /// The wait to say at `t_s`, from the detector's `raw` estimate, with `left_s` of the
    /// soak's limit left.
    pub(crate) fn update(&mut self, t_s: f64, raw: Option<f64>, left_s: f64) -> Eta {
        let Some(raw) = raw.filter(|r| r.is_finite() && *r >= 0.0) else {
            return Eta::Unknown;
        };
        let new_end = t_s + raw;
        let end = match self.end {
            Some((end, at)) => {
                let a = 1.0 - (-(t_s - at).max(0.0) / ETA_SMOOTHING_S).exp();
                end + a * (new_end - end)
            }
            None => new_end,
        };
        self.end = Some((end, t_s));
        let eta = (end - t_s).max(0.0);
        if eta > left_s {
            Eta::BeyondLimit(left_s.max(0.0))
        } else if eta < 60.0 {
            Eta::Confirming
        } else {
            Eta::Left(eta)
        }
    }
}

impl BedSoak {
    /// Starts watching a bed heated to `target_c`; fails after `max_s` (named as the setting
    /// `max_setting` in the error).
    #[must_use]
    pub(crate) fn new(
        params: SoakParams,
        target_c: f64,
        max_s: f64,
        max_setting: &'static str,
    ) -> Self {
        Self {
            detector: SoakDetector::new(params),
            start: Instant::now(),
            target_c,
            max_s,
            max_setting,
            best_progress: 0.0,
            eta_shown: EtaShown::default(),
            last_print_now_c: None,
            soaking_since_s: None,
            last_console_s: f64::NEG_INFINITY,
            primed: false,
            rebound: true,
            coupling_told: false,
            prints: true,
            chamber: None,
            samples: Vec::new(),
            max_power: None,
            generation: 0,
            core: None,
            carried: None,
        }
    }

    /// Feeds one sample to the detector, keeping it for a replay.
    fn push(&mut self, t_s: f64, power: f64, temp_c: f64, target_c: f64) -> SoakStatus {
        self.samples.push([t_s, power, temp_c, target_c]);
        self.detector.push(t_s, power, temp_c, target_c)
    }

    /// An answer to the soak question was written since this soak read `[soak]`: the soak goes
    /// on with the new settings at once, its samples replayed into a detector that has them.
    async fn reread(&mut self, core: &Core, title: &str) {
        let (generation, settings) = {
            let st = core.ask_state();
            (st.generation, st.settings.clone())
        };
        if generation == self.generation {
            return;
        }
        self.generation = generation;
        let Some(settings) = settings else { return };
        let (mut params, unread) = settings.now();
        if let Some(why) = unread {
            core.console(&format!("{title}: {why}")).await;
            return;
        }
        params.fixed_remaining = self.detector.params().fixed_remaining;
        params.no_identify = self.detector.params().no_identify;
        params.heater = self.detector.params().heater;
        if params == *self.detector.params() {
            return;
        }
        let mut d = SoakDetector::new(params);
        if let Some(p) = self.max_power {
            d.set_max_power(p);
        }
        if let Some(name) = &self.chamber {
            d = d.with_chamber(name);
        }
        if let Some(c) = &self.carried {
            d.carry_coupling(c.clone());
        }
        for [t, p, temp, target] in &self.samples {
            d.push(*t, *p, *temp, *target);
        }
        self.detector = d;
        self.best_progress = 0.0;
        self.eta_shown = EtaShown::default();
        self.last_print_now_c = None;
        self.coupling_told = false;
        let p = self.detector.params();
        core.console(&format!(
            "{title}: this soak now uses soak.bed = \"{}\" and soak.frame = \"{}\": {}; {}",
            p.bed,
            p.frame,
            self.detector.coupling().why,
            self.detector.slowest_words()
        ))
        .await;
    }

    /// A soak no print follows (a mesh capture): its console lines and progress neither offer
    /// to print now nor state what printing now would cost (issue 26 B.7).
    #[must_use]
    pub(crate) fn before_no_print(mut self) -> Self {
        self.prints = false;
        self
    }

    /// Once per soak, before the first live sample: the bed's `max_power` from Klipper's
    /// settings (saturation is measured against it), the chamber thermometer, a coupling
    /// identified from this bed's earlier cold heat-up (for a warm start), and the detector
    /// primed with the bed's history at this target (klipcal's own, merged from Moonraker's
    /// temperature store: [`super::bed_log`]), so a daemon restarted mid-soak, or a round
    /// started on a bed held at its target since the apply, goes on from what the bed did
    /// instead of starting from zero (issue 38 item 6). Returns how many samples were replayed.
    async fn prime(&mut self, core: &Core) -> usize {
        self.primed = true;
        if let Ok(cf) = core.m().configfile().await {
            if let Some(facts) = cf.settings.heater_bed.as_ref().and_then(heater_facts) {
                let params = SoakParams {
                    heater: facts,
                    ..self.detector.params().clone()
                };
                self.detector = SoakDetector::new(params);
            }
            if let Some(p) = cf.settings.heater_bed.as_ref().and_then(|h| h.max_power) {
                self.detector.set_max_power(p);
                self.max_power = Some(p);
            }
            self.chamber = self
                .detector
                .params()
                .chamber_sensor_from(&cf.settings.chamber_sensors);
            if let Some(name) = &self.chamber {
                let fresh = SoakDetector::new(self.detector.params().clone());
                let d = std::mem::replace(&mut self.detector, fresh);
                self.detector = d.with_chamber(name);
            }
        }
        self.carried = super::bed_log::carried_coupling(core, self.detector.params());
        if let Some(c) = &self.carried {
            self.detector.carry_coupling(c.clone());
        }
        let skip = self.detector.params().skip_below_c;
        let read = match super::bed_log::record(core, skip).await {
            Ok(r) => r,
            Err(e) => {
                tracing::debug!(error = %e, "no bed history to prime the soak with");
                return 0;
            }
        };
        let history = read.log.at_target(self.target_c);
        let Some(first) = history.first().map(|s| s[0]) else {
            tracing::debug!(
                target = self.target_c,
                "no bed history at this soak's target"
            );
            return 0;
        };
        // The soak's clock starts where the history does; its limit still counts from now.
        let ago = (read.now_unix - first).max(0.0);
        if let Some(start) = Instant::now().checked_sub(std::time::Duration::from_secs_f64(ago)) {
            self.start = start;
            self.max_s += ago;
        }
        for s in history {
            let t = s[0] - first;
            if let Some(name) = &self.chamber {
                if let Some(c) = super::bed_log::chamber_at(&read.store, name, read.now_unix, s[0])
                {
                    self.detector.push_chamber(t, c);
                }
            }
            self.push(t, s[1], s[2], s[3]);
        }
        history.len()
    }

    /// The heater was just set with [`BedSoak::heat`], whose bound covers this soak: the first
    /// poll does not set Klipper's idle timeout again (issue 40: two `SET_IDLE_TIMEOUT` rows
    /// per start). A soak resumed after a restart keeps the first poll's bound.
    #[must_use]
    pub(crate) fn bound_just_set(mut self) -> Self {
        self.rebound = false;
        self
    }

    /// A soak resumed after a restart goes on from the progress it had said (`done`, 0..1):
    /// the replayed history may project a longer wait, but the percentage never goes back.
    #[must_use]
    pub(crate) fn resumed_from(mut self, done: Option<f64>) -> Self {
        if let Some(d) = done.filter(|d| d.is_finite()) {
            self.best_progress = d.clamp(0.0, 0.99);
        }
        self
    }

    /// Allows `extra_s` more from now (the user chose to wait).
    pub(crate) fn extend(&mut self, extra_s: f64) {
        self.max_s = self.start.elapsed().as_secs_f64() + extra_s;
        self.rebound = true;
    }

    /// Sets the bed's target through Klipper, once Klipper's idle timeout bounds it to
    /// `bound_s` from now (the phase's limit): the bed is never on, even for a moment, with
    /// only Klipper's configured timeout to turn it off should klipcal stop.
    ///
    /// # Errors
    /// Moonraker failures.
    pub(crate) async fn heat(core: &Core, target_c: f64, bound_s: f64) -> anyhow::Result<()> {
        // A bed already at this target (heated again after an apply so that the next round
        // starts warm, or an unheated bed left off) is not sent its target a second time: the
        // console showed SET_HEATER_TEMPERATURE twice (issue 26 B.7).
        if let Ok(bed) = core.m().heater("heater_bed", &["target"]).await {
            match bed.target {
                Some(now) if (now - target_c).abs() < 0.05 => {
                    if target_c > 0.0 {
                        core.hold_heaters_for(bound_s).await?;
                    }
                    return Ok(());
                }
                // No heated bed (BED=0 on a printer without one): nothing to set.
                None if target_c <= 0.0 => return Ok(()),
                _ => {}
            }
        }
        let set = gcode_cmd::set_heater_temperature("heater_bed", target_c)?;
        if target_c > 0.0 {
            // The bound first, in the same script (one console row).
            core.hold_heaters_with(bound_s, &set).await?;
        } else {
            core.m().gcode(&set).await?;
        }
        Ok(())
    }

    /// Reads the bed once and feeds the detector; says progress on the console when due.
    ///
    /// # Errors
    /// The soak took longer than allowed (a user error naming the setting), or Moonraker failed.
    pub(crate) async fn poll(&mut self, core: &Core, title: &str) -> anyhow::Result<SoakUpdate> {
        if !self.primed {
            self.core = Some(core.clone());
            self.generation = core.ask_state().generation;
            let n = self.prime(core).await;
            if n > 0 {
                tracing::debug!(
                    samples = n,
                    "soak detector primed from Moonraker's temperature store"
                );
            }
            if self.target_c > self.detector.params().skip_below_c {
                super::soak_ask::ask(core, false).await;
            }
        }
        self.reread(core, title).await;
        let t_s = self.start.elapsed().as_secs_f64();
        if self.rebound && self.target_c > 0.0 {
            // Klipper owns the heated bed for the rest of the soak: if klipcal or Moonraker is
            // gone longer than that, Klipper's idle timeout turns the heaters off.
            core.hold_heaters_for((self.max_s - t_s).max(0.0) + BOUND_SLACK_S)
                .await?;
            self.rebound = false;
        }
        if t_s > self.max_s {
            if matches!(self.detector.status(), SoakStatus::Heating) {
                return Err(user(format!(
                    "the bed did not reach its target of {:.0} °C within {:.0} s ({}): {}",
                    self.target_c,
                    self.max_s,
                    self.max_setting,
                    self.detector.explanation()
                )));
            }
            return Ok(SoakUpdate::TooLong {
                minutes: t_s / 60.0,
                at_target_s: self.soaking_since_s.map(|since| t_s - since),
                falling_pct_per_10min: self.detector.fit().and_then(|f| f.rate_pct_per_10min()),
            });
        }
        let hb = core
            .m()
            .heater("heater_bed", &["temperature", "power", "target"])
            .await?;
        if let Some(now_c) = hb.target {
            if self.target_c > 0.0 && (now_c - self.target_c).abs() > 0.5 {
                // Not this soak's bed any more (e.g. Klipper restarted during an outage): a
                // soak cannot go on from it, and printing would waste the round.
                return Err(anyhow::anyhow!(
                    "the bed's target is now {now_c:.0} °C instead of this soak's {:.0} °C \
                     (Klipper restarted, or the heaters were turned off by its idle timeout or \
                     by hand)",
                    self.target_c
                ));
            }
        }
        if let Some(name) = self.chamber.clone() {
            // A chamber reading that fails is left out (the soak then holds to the rule
            // without it once its window has no readings), logged.
            match core.m().heater(&name, &["temperature"]).await {
                Ok(c) => {
                    if let Some(temp) = c.temperature {
                        self.detector.push_chamber(t_s, temp);
                    }
                }
                Err(e) => tracing::warn!(sensor = %name, error = %e, "chamber sensor not read"),
            }
        }
        let status = self.push(
            t_s,
            hb.power.unwrap_or(0.0),
            hb.temperature.unwrap_or(0.0),
            hb.target.unwrap_or(self.target_c),
        );
        Ok(match status {
            SoakStatus::Stable { .. } | SoakStatus::Skipped => {
                super::soak_ask::soak_ended(core);
                let why = self.detector.explanation().to_string();
                if let Some(since) = self.soaking_since_s {
                    core.console(&format!(
                        "{title}: bed stable after {:.0} min of soaking",
                        (t_s - since) / 60.0
                    ))
                    .await;
                }
                SoakUpdate::Stable { why }
            }
            SoakStatus::Heating => SoakUpdate::Heating,
            SoakStatus::Soaking {
                eta_s,
                progress,
                print_now_c,
                ..
            } => {
                self.soaking(core, title, t_s, eta_s, progress, print_now_c)
                    .await
            }
        })
    }
}

impl BedSoak {
    /// The soak's first line: what klipcal waits for, about how long, how to shorten it (the
    /// derivation goes to STATUS and the page, [`BedSoak::derivation`]).
    fn first_line(&self, title: &str) -> String {
        let p = self.detector.params();
        let named = !(ask::not_named(&p.bed) || ask::not_named(&p.frame));
        let mut shorten = Vec::new();
        let chamber = self.detector.chamber_words();
        if let Some(w) = &chamber {
            shorten.push(w.as_str());
        }
        if !named {
            shorten.push("naming your bed and frame shortens it (KLIPCAL_SOAK_BED)");
        }
        if self.prints {
            shorten.push("KLIPCAL_SOAK_CHOICE CHOICE=print prints now");
        }
        format!(
            "{title}: the bed is at {:.0} °C; klipcal waits until its print surface can warm by \
             at most {:.1} K more, typically about {} min {}{}; KLIPCAL_STATUS and klipcal's page \
             say how this is worked out",
            self.target_c,
            p.surface_budget_c,
            ask::typical_minutes(&p.bed, &p.frame),
            if named {
                "for this bed"
            } else {
                "for a bed not named"
            },
            if shorten.is_empty() {
                String::new()
            } else {
                format!("; {}", shorten.join("; "))
            }
        )
    }

    /// How the rule was worked out: the coupling and where it came from, the slowest decay
    /// ruled out, what is assumed for what is not named.
    fn derivation(&self) -> String {
        let p = self.detector.params();
        format!(
            "waiting until the print surface can warm by at most {}: {}; {}{}{}",
            kelvin_words(p.surface_budget_c),
            self.detector.coupling().why,
            self.detector.slowest_words(),
            self.detector
                .chamber_words()
                .map(|w| format!("; {w}"))
                .unwrap_or_default(),
            unset_build_words(p)
                .map(|w| format!("; {w}"))
                .unwrap_or_default()
        )
    }

    /// A poll while the bed soaks at its target: the progress line (the one the console, the
    /// session's progress, STATUS and the page all show) and the live view.
    async fn soaking(
        &mut self,
        core: &Core,
        title: &str,
        t_s: f64,
        eta_s: Option<f64>,
        progress: f64,
        print_now_c: Option<f64>,
    ) -> SoakUpdate {
        if self.soaking_since_s.is_none() {
            self.soaking_since_s = Some(t_s);
            // A question closed without an answer is asked again now (once).
            super::soak_ask::ask(core, true).await;
            core.console(&self.first_line(title)).await;
            tracing::info!(derivation = %self.derivation(), "{title}: bed soak begins");
            self.last_console_s = t_s;
        }
        // 100 % is said when the bed is stable, not while it is being confirmed.
        self.best_progress = self.best_progress.max(progress.clamp(0.0, 0.99));
        let done = self.best_progress * 100.0;
        let shown = self
            .eta_shown
            .update(t_s, eta_s, (self.max_s - t_s).max(0.0));
        let eta_s = match shown {
            Eta::Left(s) => Some(s),
            _ => None,
        };
        let mut text = match shown {
            Eta::Left(eta) => format!(
                "bed soaking: {done:.0} % done, about {} left",
                eta_words(eta, self.prints)
            ),
            Eta::Confirming => format!(
                "bed soaking: {done:.0} % done, due to settle now: confirming that its power \
                 has stopped falling"
            ),
            Eta::BeyondLimit(left) => format!(
                "bed soaking: {done:.0} % done; it may not settle within {} ({} of it left): {}",
                self.max_setting,
                eta_words(left, self.prints),
                if self.prints {
                    "you will be asked then whether to print or wait"
                } else {
                    "the capture stops then"
                }
            ),
            Eta::Unknown => {
                let p = self.detector.params();
                format!(
                    "bed soaking: watching the bed's power (the first estimate comes after a \
                     few minutes; typically about {} min)",
                    ask::typical_minutes(&p.bed, &p.frame)
                )
            }
        };
        if self.detector.coupling_final() {
            if !self.coupling_told {
                self.coupling_told = true;
                // Kept when identified here, not when carried (its age counts from the
                // heat-up that identified it).
                if self.carried.as_ref() != Some(self.detector.coupling()) {
                    super::bed_log::keep_coupling(
                        core,
                        self.detector.coupling(),
                        self.detector.params(),
                    );
                }
                core.console(&format!("{title}: {}", self.detector.coupling().why))
                    .await;
            }
            text.push_str(&format!("; {}", self.detector.coupling().short()));
        }
        if print_now_c.is_some() {
            self.last_print_now_c = print_now_c;
        }
        let print_now_c = self.last_print_now_c;
        if let Some(c) = print_now_c.filter(|_| self.prints) {
            text.push_str(&format!(
                "; printing now: the surface may still warm by up to {} (95 %)",
                cost_words(c)
            ));
        }
        if t_s - self.last_console_s >= CONSOLE_EVERY_S {
            self.last_console_s = t_s;
            core.console(&format!("{title}: {text}")).await;
        }
        self.publish(core, &text, eta_s, print_now_c);
        SoakUpdate::Soaking {
            progress: self.best_progress,
            eta_s,
            print_now_c,
            text,
        }
    }

    /// What this soak says now, for STATUS, the page and its plot (the same line and ETA as the
    /// console's).
    fn publish(&self, core: &Core, text: &str, eta_s: Option<f64>, print_now_c: Option<f64>) {
        let fit = self.detector.fit().map(|f| crate::plots::DecayCurve {
            now_s: 0.0,
            tau_s: f.tau_s,
            final_power: f.final_power,
            remaining: f.remaining,
        });
        core.ask_state().live = Some(LiveSoak {
            progress: text.to_string(),
            derivation: self.derivation(),
            eta_s,
            print_now_c: print_now_c.filter(|_| self.prints),
            fit,
            at: Instant::now(),
        });
    }
}

/// What the soak running now says, as STATUS and the page show it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub(crate) struct LiveSoak {
    /// The progress line: how far, about how long, what printing now costs.
    pub progress: String,
    /// How the rule was worked out (coupling, slowest decay, what is assumed).
    pub derivation: String,
    /// The wait told, s (the console's).
    pub eta_s: Option<f64>,
    /// What printing now costs, K (a soak before a print).
    pub print_now_c: Option<f64>,
    /// The detector's fitted decay, its `now_s` at [`LiveSoak::at`].
    #[serde(skip)]
    pub fit: Option<crate::plots::DecayCurve>,
    /// When it was said.
    #[serde(skip)]
    pub at: Instant,
}

/// The bed since its current heat-up began, as far as Moonraker's temperature store goes back
/// (1 Hz; 20 min by default, `temperature_store_size`), as an SVG plot titled with the span it
/// shows, with the soak detector's fit replayed over the same samples.
///
/// # Errors
/// Moonraker unreachable, no heater_bed, or nothing to plot (the message says which).
pub(crate) async fn soak_picture(
    m: &crate::moonraker::Moonraker,
    params: &SoakParams,
    live: Option<LiveSoak>,
) -> Result<String, String> {
    let store = m
        .call(
            "server.temperature_store",
            json!({"include_monitors": false}),
        )
        .await
        .map_err(|e| format!("Moonraker's temperature store: {e}"))?;
    let (samples, mut fit, mut eta) = crate::plots::replay_soak(&store["heater_bed"], params)
        .ok_or("the printer has no heater_bed in Moonraker's temperature store")?;
    if let (Some(live), Some(last)) = (live, samples.last()) {
        // The soak under way says the ETA and the fit: the plot shows the same as the console
        // (issue 38 item 4), not a replay of its own. The store's last sample is now.
        let ago = live.at.elapsed().as_secs_f64();
        eta = live.eta_s.map(|e| (e - ago).max(0.0));
        fit = live.fit.map(|f| crate::plots::DecayCurve {
            now_s: last.t_s - ago,
            ..f
        });
    }
    crate::plots::soak_svg(&samples, fit, eta, &crate::plots::soak_title(&samples))
}

/// Saves [`soak_picture`] under the config root; returns its name for the user.
pub(crate) async fn save_soak_picture(
    core: &Core,
    params: &SoakParams,
    path: &str,
) -> Option<String> {
    let svg = soak_picture(core.m(), params, None).await.ok()?;
    core.save_picture(path, svg).await
}

#[cfg(test)]
mod eta_tests {
    use super::{Eta, EtaShown};

    #[test]
    fn the_wait_told_rises_steadily_is_bounded_by_the_limit_and_is_not_repeated_at_the_end() {
        // A refit moves the end from 3 to 15 min away: the wait told rises over minutes, by at
        // most ~6 min in the first minute (polls every 5 s).
        let mut e = EtaShown::default();
        assert_eq!(e.update(0.0, Some(180.0), 3600.0), Eta::Left(180.0));
        let mut told = Vec::new();
        for k in 1..=12 {
            let t = 5.0 * f64::from(k);
            if let Eta::Left(s) = e.update(t, Some(900.0), 3600.0 - t) {
                told.push(s);
            }
        }
        assert!(told.windows(2).all(|w| w[1] >= w[0]), "{told:?}");
        let after_a_minute = *told.last().unwrap();
        assert!(
            (300.0..=540.0).contains(&after_a_minute),
            "3 min jumped to {after_a_minute:.0} s within a minute"
        );
        // Beyond what is left of soak_max_s: said so, never "about 105 min left".
        let mut e = EtaShown::default();
        assert_eq!(
            e.update(2400.0, Some(6300.0), 1200.0),
            Eta::BeyondLimit(1200.0)
        );
        // Due now but not confirmed: no "about 1 min left" over and over.
        let mut e = EtaShown::default();
        for k in 0..30 {
            let t = 5.0 * f64::from(k);
            assert_eq!(e.update(t, Some(40.0), 3600.0), Eta::Confirming);
        }
        assert_eq!(e.update(200.0, None, 3600.0), Eta::Unknown);
    }
}

#[cfg(test)]
mod settings_tests {
    use super::{unset_build_words, SoakParams, SoakSettings};

    /// A soak reads `[soak]` from the file as it is when the soak starts; a file that no
    /// longer loads is refused whole and the settings klipcal started with are used, saying why.
    #[test]
    fn a_soak_reads_the_settings_file_again_and_keeps_the_started_ones_when_it_is_broken() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("klipcal.toml");
        std::fs::write(&path, "[soak]\nbed = \"steel-pad\"\n").unwrap();
        let config = crate::config::Config::load(Some(&path)).unwrap();
        let settings = SoakSettings::of(&config);
        assert_eq!(settings.now(), (config.soak.clone(), None));
        std::fs::write(&path, "[soak]\nbed = \"steel-pad\"\nframe = \"open\"\n").unwrap();
        let (now, why) = settings.now();
        assert_eq!(
            (now.bed.as_str(), now.frame.as_str(), why),
            ("steel-pad", "open", None)
        );
        // One value out of range: the whole file is refused, not half of it.
        std::fs::write(&path, "[soak]\nframe = \"open\"\nbin_s = 0\n").unwrap();
        let (now, why) = settings.now();
        assert_eq!(now, config.soak);
        let why = why.expect("why the file was not used");
        assert!(
            why.contains("bin_s") && why.contains("klipcal started with"),
            "{why}"
        );
        // No file (the embedded defaults): nothing to read again.
        let none = SoakSettings::of(&crate::config::Config::default());
        assert_eq!(none.now(), (SoakParams::default(), None));
    }

    #[test]
    fn an_unset_bed_or_frame_is_named_with_what_is_assumed_instead() {
        let both = unset_build_words(&SoakParams::default()).unwrap();
        assert!(
            both.starts_with("soak.bed and soak.frame not set in klipcal.toml")
                && both.contains("the weakest bed (glass on clips) and an enclosure"),
            "{both}"
        );
        let frame = unset_build_words(&SoakParams {
            bed: "steel-pad".into(),
            ..SoakParams::default()
        })
        .unwrap();
        assert!(
            frame.starts_with("soak.frame not set") && frame.contains("assumes an enclosure"),
            "{frame}"
        );
        assert_eq!(
            unset_build_words(&SoakParams {
                bed: "steel-pad".into(),
                frame: "open".into(),
                ..SoakParams::default()
            }),
            None
        );
    }
}
