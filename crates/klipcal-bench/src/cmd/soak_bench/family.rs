//! One four-node family's report in `klipcal bench soak`: klipcal's rule judged on the
//! simulated surface beside its information bound, the named build and frame, a chamber
//! sensor, the coupling, the other rules and the ETA's error.

use crate::calib::soak::SoakParams;
use crate::cmd::soak_families::information_bound;
use crate::cmd::soak_four_node::{preset_name, BedResult, Control, Kind};

use super::{median, pass, quantile};

/// A rule's declaration on a bed (None: not within the run).
type Rule<'f> = &'f dyn Fn(&BedResult) -> Option<f64>;

/// One family's beds and what the report needs to judge them.
pub(super) struct Family<'a> {
    pub control: Control,
    pub kind: Kind,
    pub res: &'a [BedResult],
    pub params: &'a SoakParams,
    pub per_kind: usize,
}

/// Minutes in words ("never (median)" for a median that never came).
fn words(m: f64) -> String {
    if m >= 1e8 {
        "never (median)".to_string()
    } else {
        format!("{m:.1} min")
    }
}

/// The open-frame steel target (≤ 20 min after the band): PASS, or by how much it is missed.
fn steel_target(m: f64) -> String {
    if m <= 20.0 {
        "   target ≤ 20 min   PASS".to_string()
    } else {
        format!("   target ≤ 20 min   MISS by {:.1} min", m - 20.0)
    }
}

/// `a` of `b` in %.
fn pct(a: usize, b: usize) -> f64 {
    100.0 * a as f64 / b.max(1) as f64
}

/// Within 1.5 × the surface moment + 5 min (and not before it).
fn in_window(r: &BedResult, at: f64) -> bool {
    at >= r.moment_s && at <= 1.5 * r.moment_s + 300.0
}

impl Family<'_> {
    /// The family's whole report; true when every target with a verdict passed.
    pub(super) fn report(&self) -> bool {
        let mut ok = self.report_rule();
        if self.kind.enclosed {
            ok &= self.report_enclosed();
        } else {
            ok &= self.report_preset_open();
        }
        ok &= self.report_frame_open();
        ok &= self.report_coupling();
        self.report_beside();
        ok &= self.report_eta();
        ok
    }

    fn budget(&self) -> f64 {
        self.params.surface_budget_c
    }

    /// Open-frame steel beds: the timeliness target applies.
    fn steel_open(&self) -> bool {
        !self.kind.enclosed && !self.kind.glass
    }

    /// How many beds the rule declared before their surface moment.
    fn early(&self, f: Rule) -> usize {
        self.res
            .iter()
            .filter(|r| f(r).is_some_and(|d| d < r.moment_s))
            .count()
    }

    /// The rule's median soak after reaching the target, min (1e9 for never).
    fn soak_min(&self, f: Rule) -> f64 {
        median(
            self.res
                .iter()
                .map(|r| f(r).map_or(1e9, |d| (d - r.reach_s) / 60.0))
                .map(|x| if x.is_finite() { x } else { 1e9 })
                .collect(),
        )
    }

    /// "target 0" and its verdict (none for air that warms for hours, which the bed's power
    /// cannot show: only the chamber's runs have a target there).
    fn target0(&self, n: usize) -> String {
        if self.kind.slow_air {
            "no target without a chamber sensor".to_string()
        } else {
            format!("target 0   {}", pass(n == 0))
        }
    }

    /// The information bound of this rule on a bed, s: the earliest a 3 σ test knowing all but
    /// the final power could rule out a tau_max_s decay still holding the budget's power (the
    /// budget times `g`), from the end of the settling on, at the detector's own noise.
    fn bound_at(&self, r: &BedResult, g: f64) -> f64 {
        let p = self.params;
        information_bound(
            r.reach_s + p.settle_s,
            r.sigma,
            p.tau_max_s,
            self.budget() * g,
            p,
        )
        .max(r.reach_s + p.settle_s + p.min_soak_s)
    }

    /// The header, klipcal's line, its information bound and how often it is in time; true
    /// when it was never early (where that has a target).
    fn report_rule(&self) -> bool {
        let (res, budget) = (self.res, self.budget());
        let e = self.early(&|r| r.rule);
        let surf = median(
            res.iter()
                .map(|r| (r.moment_s - r.reach_s) / 60.0)
                .collect(),
        );
        let bound_min = |g: &dyn Fn(&BedResult) -> f64| {
            median(
                res.iter()
                    .map(|r| (self.bound_at(r, g(r)) - r.reach_s) / 60.0)
                    .collect(),
            )
        };
        let (bound_true, bound_used) = (bound_min(&|r| r.g_true), bound_min(&|r| r.g_used));
        let bound_within = res
            .iter()
            .filter(|r| self.bound_at(r, r.g_used) <= 1.5 * r.moment_s + 300.0)
            .count();
        let soak = self.soak_min(&|r| r.rule);
        println!(
            "    {}, {} ({} of {} beds tuned; surface within {budget:.1} K after {:.1} min past \
             reaching the target, median):",
            self.kind.name(),
            self.control.name(),
            res.len(),
            self.per_kind,
            surf
        );
        println!(
            "      klipcal: early {e} ({:.0} %)   {}; soak after reaching the target {}{}",
            pct(e, res.len()),
            self.target0(e),
            words(soak),
            if self.steel_open() {
                steel_target(soak)
            } else {
                String::new()
            },
        );
        println!(
            "      information bound of the rule (a 3 σ test that knew all but the final power, \
             ruling out a tau_max_s decay still holding the budget's power at the detector's \
             noise, after the settling and minimum soak): {:.1} min with the true G, {:.1} min \
             with the G used (median); klipcal is {:.1} min past the latter",
            bound_true,
            bound_used,
            soak - bound_used
        );
        self.report_within(bound_within);
        e == 0 || self.kind.slow_air
    }

    /// How often klipcal's rule is within 1.5 × the surface moment + 5 min.
    fn report_within(&self, bound_within: usize) {
        let res = self.res;
        let in_time = |r: &BedResult| r.rule.is_some_and(|d| in_window(r, d));
        let ident: Vec<&BedResult> = res.iter().filter(|r| r.identified).collect();
        let within = ident.iter().filter(|r| in_time(r)).count();
        let within_all = res.iter().filter(|r| in_time(r)).count();
        println!(
            "      within 1.5 × surface moment + 5 min: {within_all} of {} beds ({:.0} %); the \
             information bound of the rule (G used) within it on {bound_within} (no test of this \
             rule can be within it where the bound is not); where G is identified: {}",
            res.len(),
            pct(within_all, res.len()),
            if ident.is_empty() {
                "no bed (see the coupling), target ≥ 90 % not applicable".to_string()
            } else {
                format!(
                    "{within} of {} ({:.0} %)   target ≥ 90 %   {}",
                    ident.len(),
                    pct(within, ident.len()),
                    pass(pct(within, ident.len()) >= 90.0)
                )
            }
        );
    }

    /// Enclosed beds with soak.bed named, and with a chamber sensor; true when neither was
    /// early (where that has a target).
    fn report_enclosed(&self) -> bool {
        let kind = self.kind;
        let preset = preset_name(kind);
        let pe = self.early(&|r| r.with_preset);
        let soak = self.soak_min(&|r| r.rule);
        println!(
            "      with soak.bed = \"{preset}\" (and soak.frame = \"enclosed\", which rules out \
             what an unknown frame does): early {pe}   {}; soak after reaching the target {} \
             (defaults: {})",
            self.target0(pe),
            words(self.soak_min(&|r| r.with_preset)),
            words(soak),
        );
        let ce = self.early(&|r| r.chamber) + self.early(&|r| r.chamber_preset);
        let named = SoakParams {
            bed: preset.into(),
            ..self.params.clone()
        };
        println!(
            "      with a chamber sensor (temperature_sensor chamber in the enclosure's air; the \
             soak waits while it warms by more than {:.2} K/h with the defaults, {:.2} with \
             soak.bed named: what the air may still rise in {:.0} h would warm the surface by \
             more than {:.0} % of the budget; then rules out the stack's own decays against the \
             rest): early {ce} (defaults and soak.bed = \"{preset}\")   target 0   {}; soak {} \
             with the defaults, {} with soak.bed named",
            crate::calib::soak::flat_k_per_h(self.params, f64::INFINITY),
            crate::calib::soak::flat_k_per_h(&named, f64::INFINITY),
            crate::calib::soak::CHAMBER_TAU_MAX_S / 3600.0,
            crate::calib::soak::CHAMBER_BUDGET_SHARE * 100.0,
            pass(ce == 0),
            words(self.soak_min(&|r| r.chamber)),
            words(self.soak_min(&|r| r.chamber_preset)),
        );
        (pe == 0 || kind.slow_air) && ce == 0
    }

    /// Open frames with soak.bed named: never early, its coupling's interval and the G used;
    /// true when all hold.
    fn report_preset_open(&self) -> bool {
        let res = self.res;
        let preset = preset_name(self.kind);
        let pe = self.early(&|r| r.with_preset);
        let ps = self.soak_min(&|r| r.with_preset);
        let pid = res.iter().filter(|r| r.preset_identified).count();
        let pcov = res
            .iter()
            .filter(|r| r.preset_identified && r.preset_covered)
            .count();
        let psafe = res.iter().filter(|r| r.preset_g_safe).count();
        let pcov_ok = pid == 0 || pct(pcov, pid) >= 95.0;
        println!(
            "      with soak.bed = \"{preset}\" (its weakest G 1/{:.0}; identified from the \
             heat-up on {pid} of {} beds, the true G in the interval on {pcov} ({:.0} %)   target \
             ≥ 95 %   {}; the G used at or below the true G on {psafe} of {}   target all   {}): \
             early {pe}   target 0   {}; soak after reaching the target {}{}",
            1.0 / crate::calib::soak::BED_PRESETS
                .iter()
                .find(|b| b.name == preset)
                .map_or(f64::NAN, |b| b.g),
            res.len(),
            pct(pcov, pid),
            if pid == 0 {
                "not applicable"
            } else {
                pass(pcov_ok)
            },
            res.len(),
            pass(psafe == res.len()),
            pass(pe == 0),
            words(ps),
            if self.steel_open() {
                steel_target(ps)
            } else {
                String::new()
            }
        );
        pe == 0 && pcov_ok && psafe == res.len()
    }

    /// The information bound of the open frame's rule with the preset on a bed, s: the decays
    /// up to the stack's and the air's time whole, the slower ones up to the open frame's bound
    /// at their share (see `open_frame_reach`), whichever a test needs longer for.
    fn open_bound_at(&self, r: &BedResult) -> f64 {
        let p = self.params;
        let with = SoakParams {
            bed: preset_name(self.kind).into(),
            frame: "open".into(),
            ..p.clone()
        };
        let charge = crate::calib::soak::BED_PRESETS
            .iter()
            .find(|b| b.name == with.bed)
            .map_or(0.0, |b| b.charge_s);
        let reach = crate::calib::soak::open_frame_reach(&with.frame, &with.bed, charge);
        let from = r.reach_s + p.settle_s;
        let theta = self.budget() * r.preset_g_used;
        let mut at = from + p.min_soak_s;
        if let Some(reach) = reach {
            at = at.max(information_bound(
                from,
                r.sigma,
                reach.whole_s,
                theta,
                &with,
            ));
            if reach.slow_share > 0.0 {
                at = at.max(information_bound(
                    from,
                    r.sigma,
                    with.slowest_s(),
                    theta / reach.slow_share,
                    &with,
                ));
            }
        }
        at
    }

    /// soak.frame = "open": right on open frames (never early, the timeliness target), a
    /// user's error on enclosed ones (how early, on the surface); true when an open frame's
    /// runs were never early.
    fn report_frame_open(&self) -> bool {
        let (res, budget) = (self.res, self.budget());
        let open_s = crate::calib::soak::OPEN_FRAME_TAU_MAX_S;
        let oe = self.early(&|r| r.open);
        let op = self.early(&|r| r.open_preset);
        let os = self.soak_min(&|r| r.open);
        let slowest = res.iter().map(|r| r.slowest_s).fold(0.0, f64::max);
        if self.kind.enclosed {
            let worst = res
                .iter()
                .filter(|r| {
                    r.open.is_some_and(|d| d < r.moment_s)
                        || r.open_preset.is_some_and(|d| d < r.moment_s)
                })
                .map(|r| r.open_left_c)
                .fold(0.0, f64::max);
            println!(
                "      soak.frame = \"open\" set on this enclosed bed (a user's error; slowest \
                 clamped mode {:.0} min, rule up to {:.0} min): early {oe} of {}{}, the surface \
                 up to {worst:.2} K short of its final temperature at the declaration (budget \
                 {budget:.1} K); soak {}",
                slowest / 60.0,
                open_s / 60.0,
                res.len(),
                if self.steel_open() {
                    format!(", with the preset {op}")
                } else {
                    String::new()
                },
                words(os),
            );
            return true;
        }
        let ps = self.soak_min(&|r| r.open_preset);
        let fe = self.early(&|r| r.open_fixed) + self.early(&|r| r.open_preset_fixed);
        let target = |m: f64| {
            if self.steel_open() {
                steel_target(m)
            } else {
                String::new()
            }
        };
        let open_bound = median(
            res.iter()
                .map(|r| (self.open_bound_at(r) - r.reach_s) / 60.0)
                .collect(),
        );
        // Where even the information bound falls outside the window of "within 1.5 × the
        // surface moment + 5 min", no detector of this rule can be within it.
        let win = res
            .iter()
            .filter(|r| r.open_preset.is_some_and(|d| in_window(r, d)))
            .count();
        let win_bound = res
            .iter()
            .filter(|r| in_window(r, self.open_bound_at(r).max(r.moment_s)))
            .count();
        println!(
            "      with soak.frame = \"open\" (decays up to {:.0} min; these beds' slowest \
             clamped mode {:.1} min at most   target ≤ {:.0} min   {}): early {oe}   target 0   \
             {}; soak after reaching the target {}{}; with soak.bed = \"{}\" too: early {op}   \
             target 0   {}; soak {}{} (information bound of this rule {:.1} min, klipcal {:.1} \
             min past it; within 1.5 × surface moment + 5 min on {win} of {} beds, the \
             information bound itself on {win_bound}); not identified (a warm start: the G of \
             soak.bed, else the weakest): soak {} with soak.bed, {} without (early {fe}   target \
             0   {})",
            open_s / 60.0,
            slowest / 60.0,
            open_s / 60.0,
            pass(slowest <= open_s),
            pass(oe == 0),
            words(os),
            target(os),
            preset_name(self.kind),
            pass(op == 0),
            words(ps),
            target(ps),
            open_bound,
            ps - open_bound,
            res.len(),
            words(self.soak_min(&|r| r.open_preset_fixed)),
            words(self.soak_min(&|r| r.open_fixed)),
            pass(fe == 0),
        );
        oe == 0 && op == 0 && slowest <= open_s && fe == 0
    }

    /// The coupling: identified, the G used never above the true one, the interval holding
    /// it; true when those with a target pass.
    fn report_coupling(&self) -> bool {
        let res = self.res;
        let ident = res.iter().filter(|r| r.identified).count();
        let bounded: Vec<&BedResult> = res.iter().filter(|r| r.bounded).collect();
        let covered = bounded.iter().filter(|r| r.covered).count();
        let safe = res.iter().filter(|r| r.g_safe).count();
        println!(
            "      coupling: identified (lower end from the bed's own heat-up) on {ident} of {} \
             beds; the G used at or below the true G on {safe} of {}   target all   {}; {}",
            res.len(),
            res.len(),
            pass(safe == res.len()),
            if bounded.is_empty() {
                "no heat-up gave an upper end (the surface's lag does not show: the G used is \
                 the preset's or the weakest), coverage target not applicable"
                    .to_string()
            } else {
                format!(
                    "the heat-up gave an upper end on {} beds, and the true G lay between the G \
                     used and it on {covered} ({:.0} %)   target ≥ 95 %   {}",
                    bounded.len(),
                    pct(covered, bounded.len()),
                    pass(pct(covered, bounded.len()) >= 95.0)
                )
            }
        );
        safe == res.len() && (bounded.is_empty() || pct(covered, bounded.len()) >= 95.0)
    }

    /// The other rules on the same beds: today's, the fixed preheats, the pwm slope and the
    /// R-statistic.
    fn report_beside(&self) {
        let fixed = |m: f64| {
            self.res
                .iter()
                .filter(|r| r.reach_s + m * 60.0 < r.moment_s)
                .count()
        };
        println!(
            "      beside it: today's rule (0.8 % of power) early {} soak {}; fixed 10 min early \
             {}; fixed 15 min early {}; pwm slope (< 2 points over 2 min) early {} soak {}; \
             R-statistic (Cao–Rhinehart, R < 2) early {} soak {}",
            self.early(&|r| r.today),
            words(self.soak_min(&|r| r.today)),
            fixed(10.0),
            fixed(15.0),
            self.early(&|r| r.slope),
            words(self.soak_min(&|r| r.slope)),
            self.early(&|r| r.r_stat),
            words(self.soak_min(&|r| r.r_stat)),
        );
    }

    /// The ETA's error at 25/50/75 % of the soak (stated minus true time left): the median
    /// and 90th percentile of its size, with the defaults and with the build (and frame)
    /// named, beside [`ETA_TARGET`]; true when it is met.
    fn report_eta(&self) -> bool {
        let mut ok = true;
        let mut eta = |f: &dyn Fn(&BedResult) -> [f64; 3]| {
            (0..3)
                .map(|k| {
                    let v: Vec<f64> = self.res.iter().map(|r| f(r)[k]).collect();
                    let none = v.iter().filter(|x| !x.is_finite()).count();
                    let abs: Vec<f64> = v.iter().map(|x| x.abs()).collect();
                    let (m, p90) = (median(abs.clone()), quantile(abs, 0.9));
                    let bias = median(v);
                    if none == self.res.len() {
                        return "none stated (still settling then)".to_string();
                    }
                    let met = m <= ETA_TARGET.0 && p90 <= ETA_TARGET.1;
                    ok &= met;
                    format!(
                        "{m:.1} / {p90:.1} (median {bias:+.1}{}) {}",
                        if none > 0 {
                            format!(", none stated on {none}")
                        } else {
                            String::new()
                        },
                        pass(met)
                    )
                })
                .collect::<Vec<_>>()
                .join("; ")
        };
        let defaults = eta(&|r| r.eta_err);
        let named = eta(&|r| r.preset_eta_err);
        println!(
            "      ETA error at 25 / 50 / 75 % of the soak (|stated − true time left|, min: \
             median / 90th percentile, and the signed median)   target ≤ {:.0} / {:.0} min: \
             defaults {defaults}; soak.bed named{} {named}",
            ETA_TARGET.0,
            ETA_TARGET.1,
            if self.kind.enclosed {
                ""
            } else {
                " and soak.frame = \"open\""
            },
        );
        ok
    }
}

/// The ETA's target, min: the median and the 90th percentile of its error's size at 25, 50
/// and 75 % of a soak. The fixed preheat a user compares klipcal with is 10–15 min, a guess
/// any user can make without klipcal: an ETA is worth reading when half the time it is off by
/// less than that guess's own step (10 min) and nine times in ten by less than two of them.
pub(super) const ETA_TARGET: (f64, f64) = (10.0, 20.0);
