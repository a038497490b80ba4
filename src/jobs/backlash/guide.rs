//! The guided measurement: the camera point (`KLIPCAL_BACKLASH_SET_POINT`), the start
//! (`KLIPCAL_BACKLASH_START`), the jog buttons that walk `calib::backlash_guide`, the moves
//! and prompts, and the results in words.

use super::*;

/// What the measurement of one axis starts with ([`Backlash::begin_axis`]).
pub(super) struct AxisStart {
    pub(super) progress: String,
    pub(super) point: [f64; 3],
    /// The guide, for the guided measurement.
    pub(super) guide: Option<Guide>,
    pub(super) printer: AxisPrinter,
}

impl Backlash {
    pub(super) async fn detect(&self) -> anyhow::Result<(Detection, ConfigFile)> {
        let help = self.core.m().call("printer.gcode.help", json!({})).await?;
        let cf = self.core.m().configfile().await?;
        Ok((kb::detect(&help, &cf.config)?, cf))
    }

    /// Starts measuring an axis, guided or by camera: in the session that has measured other
    /// axes (`measured`), or in a new one; refused while an axis is being measured.
    pub(super) async fn begin_axis(&self, a: AxisStart) -> anyhow::Result<Session> {
        let existing = {
            let _g = self.core.lock().await;
            match self.active()? {
                Some(mut s) if s.state == State::Measured => {
                    let p = &a.printer;
                    s.state = State::Measuring;
                    s.progress = a.progress.clone();
                    s.guide = a.guide.clone();
                    s.point = a.point;
                    s.detection = p.detection.clone();
                    s.active_mm.extend(p.active_mm.clone());
                    s.carriage = p.carriage;
                    s.kinematics = p.kinematics.clone();
                    set_step(&mut s.step_mm, p);
                    self.core.save(s.id, &s)?;
                    Some(s)
                }
                Some(s) => {
                    return Err(user(format!(
                        "session {} is {}; finish the axis in progress or KLIPCAL_CANCEL",
                        s.id,
                        s.state.name()
                    )))
                }
                None => None,
            }
        };
        if let Some(s) = existing {
            return Ok(s);
        }
        let mut step_mm = BTreeMap::new();
        set_step(&mut step_mm, &a.printer);
        let p = a.printer;
        let mut s = Session::new(
            State::Measuring,
            a.progress,
            BacklashBody {
                point: a.point,
                detection: p.detection,
                active_mm: p.active_mm,
                guide: a.guide,
                cycles: BTreeMap::new(),
                max_accel_mm_s2: p.max_accel_mm_s2,
                carriage: p.carriage,
                kinematics: p.kinematics,
                camera: BTreeMap::new(),
                step_mm,
            },
        );
        s.id = self.core.create(KIND, &mut s, |s, id| s.id = id).await?;
        Ok(s)
    }

    /// What compensation is active while measuring (measurements are residuals to it): the
    /// seed's values as its command reports them (with the carriage's own under `key`), or
    /// PR 7157's `[backlash]` numbers.
    pub(super) async fn active_values(
        &self,
        detection: &Detection,
        cf: &ConfigFile,
        axis: GuideAxis,
        carriage: Option<u32>,
        key: &str,
    ) -> anyhow::Result<BTreeMap<String, f64>> {
        let mut active_mm = BTreeMap::new();
        match detection.branch {
            Branch::Seed => {
                let r = self.seed_values().await?;
                active_mm.insert("x".into(), r.x_mm);
                active_mm.insert("y".into(), r.y_mm);
                active_mm.insert("z".into(), r.z_mm);
                if carriage.is_some() {
                    let own = match axis {
                        GuideAxis::Y => r.y_mm,
                        _ => r.x_mm,
                    };
                    active_mm.insert(key.to_string(), own);
                }
            }
            Branch::Pr7157 { .. } => {
                if let Some(o) = &cf.settings.backlash {
                    active_mm.extend(o.iter().map(|(k, v)| (k.clone(), *v)));
                }
            }
            Branch::Neither => {}
        }
        Ok(active_mm)
    }

    /// The G-code console lines since the last call, newest last (for command replies).
    pub(super) async fn console_tail(&self) -> anyhow::Result<String> {
        let store = self
            .core
            .m()
            .call("server.gcode_store", json!({"count": 30}))
            .await?;
        Ok(store["gcode_store"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|e| e["message"].as_str())
            .collect::<Vec<_>>()
            .join("\n"))
    }

    /// PR 7259's values now: the bare command's reply.
    pub(super) async fn seed_values(&self) -> anyhow::Result<kb::BacklashReply> {
        self.core.m().gcode(kb::SET_CMD).await?;
        Ok(kb::parse_reply(&self.console_tail().await?)?)
    }

    pub(super) async fn homed(&self, axis: GuideAxis) -> anyhow::Result<()> {
        let st = self
            .core
            .m()
            .objects_query(json!({"toolhead": ["homed_axes"]}))
            .await?;
        let homed = st["toolhead"]["homed_axes"].as_str().unwrap_or("");
        let need = match axis {
            GuideAxis::Z => "xyz",
            _ => "xy",
        };
        if need.chars().all(|c| homed.contains(c)) {
            Ok(())
        } else {
            Err(user(format!(
                "the printer is not homed ({need} needed, homed: '{homed}'); run G28 first"
            )))
        }
    }

    pub(super) async fn move_along(&self, s: &Session, step: &Step) -> anyhow::Result<()> {
        let Some(g) = &s.guide else { return Ok(()) };
        for &along in &step.moves_mm {
            self.go(g.axis.point_at(s.point, along)).await?;
        }
        Ok(())
    }

    /// The jog dialog for `step`. `page` ([`Core::page_road`]) is named in the approach's
    /// dialog: a phone shows the dialog full screen over the camera, the page has the same
    /// buttons beside the live picture (issue 40 item 2). Said inside a line the dialog has
    /// anyway: each dialog line is a console row, and a jog sends one dialog per press.
    pub(super) fn prompt_for(s: &Session, step: &Step, page: Option<&str>) -> Prompt {
        let Some(g) = &s.guide else {
            return Prompt::default();
        };
        let (sign, dir) = if step.phase == Phase::Minus {
            ("-", "−")
        } else {
            ("+", "+")
        };
        let axis = g.axis.name().to_uppercase();
        if step.crossing {
            // After Centred: each press says what the nozzle looks like there and jogs fine
            // on (issue 27: every answer is counted, so an early or late "looks centred" of a
            // noisy eye is not where the reading stops).
            let first = if step.past_once {
                "Past once: look again after that jog. Still past? Press Past again to end the approach; otherwise say what you see."
                    .to_string()
            } else {
                format!(
                    "At each fine jog {axis}{sign}, say what the nozzle looks like now: Short (of the mark), Centred, or Past. Past twice in a row ends the approach."
                )
            };
            return Prompt {
                title: title_for(&axis, dir, s.carriage, step.cycle, g.params.cycles),
                lines: vec![
                    first,
                    format!(
                        "Fine {} mm. Every answer counts: the reading is halfway between where it stops looking short and where it starts looking past, so answer each look as it comes, even if it looks short again.",
                        g.fine_mm()
                    ),
                ],
                buttons: vec![
                    Button::new("Short", "_KLIPCAL_BACKLASH_JOG PRESS=short", "secondary"),
                    Button::new("Centred", "_KLIPCAL_BACKLASH_JOG PRESS=centred", "primary"),
                    Button::new("Past", "_KLIPCAL_BACKLASH_JOG PRESS=past", "primary"),
                    Button::new(
                        "Overshot - start over",
                        "_KLIPCAL_BACKLASH_JOG PRESS=overshot",
                        "warning",
                    ),
                ],
                footer: vec![Button::cancel_asking()],
            };
        }
        Prompt {
            title: title_for(&axis, dir, s.carriage, step.cycle, g.params.cycles),
            lines: vec![
                format!(
                    "Jog {axis}{sign} toward the camera mark, never back; fine jogs near it. At the first fine jog where the nozzle no longer looks short of the mark, say what you see: Centred, or Past if that one jog took it through the whole mark."
                ),
                format!(
                    "Coarse {} mm, fine {} mm. Past the mark after a coarse jog, or centred where the approach began? Press Overshot: it starts the approach over from {} mm back.{}",
                    g.params.coarse_mm,
                    g.fine_mm(),
                    g.params.approach_mm,
                    page.map(|p| format!(" The same buttons beside the live camera: {p}."))
                        .unwrap_or_default()
                ),
            ],
            buttons: vec![
                Button::new(
                    &format!("Coarse {axis}{sign}"),
                    "_KLIPCAL_BACKLASH_JOG PRESS=coarse",
                    "secondary",
                ),
                Button::new(
                    &format!("Fine {axis}{sign}"),
                    "_KLIPCAL_BACKLASH_JOG PRESS=fine",
                    "secondary",
                ),
                Button::new("Centred", "_KLIPCAL_BACKLASH_JOG PRESS=centred", "primary"),
                Button::new("Past", "_KLIPCAL_BACKLASH_JOG PRESS=past", "primary"),
                Button::new(
                    "Overshot - start over",
                    "_KLIPCAL_BACKLASH_JOG PRESS=overshot",
                    "warning",
                ),
            ],
            footer: vec![Button::cancel_asking()],
        }
    }

    pub(super) fn results(&self, s: &Session) -> anyhow::Result<BTreeMap<String, AxisResult>> {
        let params = self.settings.params();
        s.cycles
            .iter()
            .map(|(axis, c)| {
                // Camera cycles are read to the camera's precision, not a jog's.
                // Jogged cycles carry the motor's microstep lattice.
                let p = s.camera.get(axis).map_or_else(
                    || crate::calib::backlash::BacklashParams {
                        step_mm: s.step_mm.get(axis).copied().unwrap_or(0.0),
                        ..params.clone()
                    },
                    |r| r.params(&params),
                );
                Ok((axis.clone(), analyse(axis, c, s.max_accel_mm_s2, &p)?))
            })
            .collect()
    }

    pub(super) fn result_lines(&self, s: &Session) -> anyhow::Result<Vec<String>> {
        Ok(result_text(s, &self.results(s)?))
    }

    /// The seed's CoreXY question answered from the results (CoreXY printers only).
    pub(super) fn corexy_answer(
        s: &Session,
        results: &BTreeMap<String, AxisResult>,
    ) -> Option<String> {
        (s.kinematics == "corexy")
            .then(|| crate::calib::backlash::corexy_xy_answer(results))
            .flatten()
    }

    /// `klipcal_backlash_set_point`: the current toolhead position becomes the camera point.
    ///
    /// # Errors
    /// A measurement in progress, a printer that is printing or not homed.
    pub(crate) async fn set_point(&self) -> anyhow::Result<PointSaved> {
        // The point is what every reading of a measurement is taken against (issue 27's walk).
        if let Some(s) = self.active()? {
            if matches!(s.state, State::Measuring | State::Applying) {
                return Err(user(format!(
                    "backlash session {} is {}: the camera point cannot move during it; \
                     finish the axis or KLIPCAL_CANCEL first",
                    s.id,
                    s.state.name()
                )));
            }
        }
        self.core.printer_idle().await?;
        self.homed(GuideAxis::X).await?;
        let st = self
            .core
            .m()
            .objects_query(json!({"gcode_move": ["position"]}))
            .await?;
        let pos = &st["gcode_move"]["position"];
        let p = [0, 1, 2].map(|i| pos[i].as_f64().unwrap_or(f64::NAN));
        if p.iter().any(|v| !v.is_finite()) {
            return Err(anyhow!("Klipper reports no toolhead position: {pos}"));
        }
        self.core
            .store()
            .set_value(POINT_KEY, &serde_json::to_value(PointDoc { point: p })?)?;
        let msg = format!(
            "camera point saved: X{:.3} Y{:.3} Z{:.3}; KLIPCAL_BACKLASH_START AXIS=X begins",
            p[0], p[1], p[2]
        );
        Ok(PointSaved {
            point: p,
            message: msg,
        })
    }

    /// `klipcal_backlash_start`: measures one axis (a new session, or the next axis of a
    /// measured one).
    ///
    /// # Errors
    /// Bad arguments, no camera point, another calibration running, a printing or unhomed
    /// printer, or A/B on a printer that is not CoreXY.
    pub(crate) async fn start(&self, req: &StartRequest) -> anyhow::Result<AxisStarted> {
        let axis = req.axis;
        let mut params = self.settings.guide();
        if let Some(c) = req.cycles {
            params.cycles = c;
        }
        params.validate().map_err(|e| user(e.to_string()))?;
        self.core.refuse_other_kind(KIND)?;
        self.core.printer_idle().await?;
        self.homed(axis).await?;
        let point = self
            .saved_point()?
            .ok_or_else(|| {
                user("no camera point saved: centre the nozzle on the camera mark, then KLIPCAL_BACKLASH_SET_POINT")
            })?;
        let printer = self.axis_printer(axis, req.carriage).await?;
        let key = printer.key.clone();
        let carriage = printer.carriage;
        let (guide, step) = Guide::start(axis, axis.coord(point), params, dither_seed())
            .map_err(|e| user(e.to_string()))?;
        let s = self
            .begin_axis(AxisStart {
                progress: format!("measuring {}", axis.name()),
                point,
                guide: Some(guide),
                printer,
            })
            .await?;
        self.move_along(&s, &step).await?;
        self.core
            .prompt(&Self::prompt_for(
                &s,
                &step,
                self.core.page_road().as_deref(),
            ))
            .await;
        let msg = format!(
            "{TITLE} session {}: {} from {} mm in −, jog only in + until centred{}",
            s.id,
            key_words(&key),
            s.guide.as_ref().map_or(1.0, |g| g.params.approach_mm),
            start_note(&s.detection)
        );
        Ok(AxisStarted {
            session: s.id,
            state: State::Measuring.name(),
            axis: axis.name(),
            carriage,
            webcam: None,
            message: msg,
        })
    }

    /// `klipcal_backlash_jog PRESS=coarse|fine|centred|past|short|overshot`.
    ///
    /// # Errors
    /// No axis being measured, a bad PRESS, a jog the procedure refuses (said why), a print
    /// running or the axis not homed.
    pub(crate) async fn jog(&self, press: Press) -> anyhow::Result<Jogged> {
        // A press moves the machine, from the dialog or from the page: never while a print
        // runs, never along an axis that is not homed (a restart since the start unhomes it).
        if let Some(g) = self.active()?.and_then(|s| s.body.guide) {
            self.core.printer_idle().await?;
            self.homed(g.axis).await?;
        }
        // The press and its reading are saved before the machine moves.
        let (s, step) = {
            let _g = self.core.lock().await;
            let mut s =
                match self.active()? {
                    Some(s) if s.state == State::Measuring => s,
                    _ => return Err(user(
                        "no backlash axis is being measured; KLIPCAL_BACKLASH_START AXIS=X first",
                    )),
                };
            let g = s
                .body
                .guide
                .as_mut()
                .ok_or_else(|| anyhow!("measuring without a guide"))?;
            let step = g.press(press).map_err(|e| user(e.to_string()))?;
            if step.phase == Phase::Done {
                let key = result_key(g.axis, s.body.carriage);
                let cycles = g.cycles.clone();
                s.cycles.insert(key.clone(), cycles);
                s.camera.remove(&key);
                s.guide = None;
                s.carriage = None;
                s.state = State::Measured;
                s.progress = format!(
                    "{} measured; {}",
                    key_words(&key),
                    next_line(&s.detection, "KLIPCAL_BACKLASH_START")
                );
            }
            self.core.save(s.id, &s)?;
            (s, step)
        };
        if step.phase == Phase::Done {
            self.core.prompt_end().await;
            let lines = self.result_lines(&s)?;
            let text = format!(
                "{TITLE}: {}\n{}",
                lines.join("\n"),
                next_line(&s.detection, "KLIPCAL_BACKLASH_START")
            );
            return Ok(Jogged::Measured {
                session: s.id,
                state: State::Measured.name(),
                results: self.results(&s)?,
                message: text,
            });
        }
        self.move_along(&s, &step).await?;
        self.core
            .prompt_unless_closed(&Self::prompt_for(
                &s,
                &step,
                self.core.page_road().as_deref(),
            ))
            .await;
        // A jog answers nothing on the console (the camera shows it); a recorded position and a
        // new approach are said in one line.
        let message = match (step.recorded, press) {
            (Some(v), _) => format!(
                "{TITLE}: {v:.4} mm recorded; now cycle {}, moving only {}",
                step.cycle,
                if step.phase == Phase::Minus {
                    "−"
                } else {
                    "+"
                }
            ),
            (None, Press::Overshot) => format!(
                "{TITLE}: approaching again from {} mm back",
                s.guide.as_ref().map_or(1.0, |g| g.params.approach_mm)
            ),
            (None, _) => String::new(),
        };
        Ok(Jogged::Step {
            session: s.id,
            state: State::Measuring.name(),
            recorded: step.recorded,
            phase: format!("{:?}", step.phase),
            crossing: step.crossing,
            past_once: step.past_once,
            cycle: step.cycle,
            message,
        })
    }
}

/// The result lines of a session's measured axes, as the console says them.
pub(super) fn result_text(s: &Session, results: &BTreeMap<String, AxisResult>) -> Vec<String> {
    let mut out = Vec::new();
    let corexy = Backlash::corexy_answer(s, results);
    for (axis, r) in results {
        let active = s.active_mm.get(axis).copied().unwrap_or(0.0);
        out.push(format!(
            "{}: {:.4} mm ± {:.4} over {} cycles{}{} — {}",
            key_words(axis),
            r.backlash_mm,
            r.uncertainty_mm,
            r.cycles,
            if r.outliers.is_empty() {
                String::new()
            } else {
                format!(" (outlier cycles {:?})", r.outliers)
            },
            if active > 0.0 {
                format!(" left with {active} mm compensation active")
            } else {
                String::new()
            },
            if r.compensate && !matches!(s.detection.branch, Branch::Pr7157 { .. }) {
                format!(
                    "compensate; smooth_time {:.4} s adds {:.0} mm/s²",
                    r.smooth_time_s, r.extra_accel_mm_s2
                )
            } else if r.compensate {
                // PR 7157's [backlash] has no smooth_time: nothing to advise.
                "compensate".to_string()
            } else {
                "no compensation needed".to_string()
            }
        ));
        if let Some(more) = r.more_cycles(MORE_CYCLES_TARGET_U_MM, 50) {
            let last = out.len() - 1;
            out[last].push_str(&match more {
                MoreCycles::Within(n, u) => format!(
                    "; ± above {MORE_CYCLES_TARGET_U_MM}: measuring again with CYCLES={n} would \
                     bring it to about ± {u:.4}"
                ),
                MoreCycles::Short(n, u) => format!(
                    "; ± above {MORE_CYCLES_TARGET_U_MM}: even CYCLES={n} would leave about \
                     ± {u:.4} (the cycles scatter widely: check the camera mark and the nozzle)"
                ),
                MoreCycles::Never(fixed) => format!(
                    "; ± above {MORE_CYCLES_TARGET_U_MM}, and more cycles would not bring it \
                     within: ± {fixed:.4} of it repeats in every cycle{}",
                    match s.step_mm.get(axis) {
                        // Jogged cycles whose repeating part is mostly the motor's microstep:
                        // the pictures read the nozzle itself, wherever the motor stops.
                        Some(&step)
                            if !s.camera.contains_key(axis)
                                && step / 12f64.sqrt() >= 0.8 * fixed =>
                        {
                            format!(
                                " (every jog lands on the motor's {step:.4} mm microstep; \
                                 KLIPCAL_BACKLASH_CAMERA, or KLIPCAL_BACKLASH_CLICK on \
                                 snapshots, reads the nozzle itself)"
                            )
                        }
                        _ => String::new(),
                    }
                ),
            });
        }
    }
    if let Some(t) = corexy {
        out.push(format!("CoreXY, x_backlash = y_backlash? {t}"));
    }
    out
}

/// The motor's microstep along a jogged axis, mm, from Klipper's settings (`rotation_distance
/// / (full_steps_per_rotation · microsteps · gear_ratio)`): cartesian X, Y and Z their own
/// stepper's; CoreXY A and B (motor directions) stepper_x's and stepper_y's, and X or Y, which
/// both motors move, the larger over √2 (the two motors' step errors average); the dual
/// carriage's own section for carriage 1. None where the settings do not say or the
/// kinematics is another.
pub(super) fn step_along(
    settings: &crate::moonraker::answers::Settings,
    kin: &str,
    axis: GuideAxis,
    carriage: Option<u32>,
) -> Option<f64> {
    let step = |section: &str| -> Option<f64> {
        let sec = settings.section(section)?;
        let num = |k: &str| sec.get(k).and_then(Value::as_f64);
        let rd = num("rotation_distance")?;
        let ms = num("microsteps")?;
        let fs = num("full_steps_per_rotation").unwrap_or(200.0);
        let gear: f64 = sec
            .get("gear_ratio")
            .and_then(Value::as_array)
            .map_or(1.0, |pairs| {
                pairs
                    .iter()
                    .filter_map(|p| {
                        let p = p.as_array()?;
                        Some(p.first()?.as_f64()? / p.get(1)?.as_f64()?)
                    })
                    .product()
            });
        let v = rd / (fs * ms * gear);
        (v.is_finite() && v > 0.0).then_some(v)
    };
    let primary = |name: &str| {
        if carriage.is_some_and(|n| n >= 1) {
            step("dual_carriage")
        } else {
            step(name)
        }
    };
    match (kin, axis) {
        ("cartesian", GuideAxis::X) => primary("stepper_x"),
        ("cartesian", GuideAxis::Y) => primary("stepper_y"),
        ("cartesian" | "corexy", GuideAxis::Z) => step("stepper_z"),
        ("corexy", GuideAxis::A) => step("stepper_x"),
        ("corexy", GuideAxis::B) => step("stepper_y"),
        ("corexy", GuideAxis::X | GuideAxis::Y) => {
            Some(step("stepper_x")?.max(step("stepper_y")?) / std::f64::consts::SQRT_2)
        }
        _ => None,
    }
}

/// The microstep along the axis into the session's map (removed where the settings do not
/// say: a value from an earlier measurement of the key must not stay).
fn set_step(step_mm: &mut BTreeMap<String, f64>, p: &AxisPrinter) {
    match p.step_mm {
        Some(v) => step_mm.insert(p.key.clone(), v),
        None => step_mm.remove(&p.key),
    };
}

/// A seed for the guide's dither that differs between measurements: the clock's nanoseconds.
fn dither_seed() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::backlash::{BacklashParams, Cycle};

    fn session(branch: Branch, why: &str) -> Session {
        let mut s = Session::new(
            State::Measured,
            "",
            BacklashBody {
                point: [100.0, 100.0, 0.0],
                detection: Detection {
                    branch,
                    dual_carriage: false,
                    why: why.into(),
                },
                active_mm: BTreeMap::new(),
                guide: None,
                cycles: BTreeMap::new(),
                max_accel_mm_s2: Some(3000.0),
                carriage: None,
                kinematics: "cartesian".into(),
                camera: BTreeMap::new(),
                step_mm: BTreeMap::new(),
            },
        );
        s.id = 1;
        s
    }

    /// Five cycles of `b` mm, every other one `spread` mm more.
    fn alternating(b: f64, spread: f64) -> Vec<Cycle> {
        (0..5)
            .map(|i| Cycle {
                x1_mm: b + spread * f64::from(i % 2),
                x2_mm: 0.0,
                fine_mm: None,
            })
            .collect()
    }

    fn results(b: f64) -> BTreeMap<String, AxisResult> {
        let c = alternating(b, 0.001);
        let r = crate::calib::backlash::analyse("x", &c, Some(3000.0), &BacklashParams::default())
            .unwrap();
        assert!(r.compensate);
        BTreeMap::from([("x".to_string(), r)])
    }

    #[test]
    fn smooth_time_is_advised_only_where_the_module_has_one() {
        // PR 7259 has smooth_time; PR 7157's [backlash] has none (issue 27's walk).
        let seed = result_text(&session(Branch::Seed, ""), &results(0.08)).join("\n");
        assert!(seed.contains("smooth_time"), "{seed}");
        let pr = result_text(
            &session(Branch::Pr7157 { corexy: false }, ""),
            &results(0.08),
        )
        .join("\n");
        assert!(
            pr.contains("compensate") && !pr.contains("smooth_time"),
            "{pr}"
        );
    }

    #[test]
    fn the_result_says_what_more_cycles_would_buy_only_when_the_plus_minus_is_wide() {
        // Cycles 1 µm apart: ± within 2.5 µm, nothing offered.
        let tight = result_text(&session(Branch::Seed, ""), &results(0.08)).join("\n");
        assert!(!tight.contains("CYCLES="), "{tight}");
        // Cycles 10 µm apart: ± above it, and a number of cycles that brings it within.
        let c = alternating(0.08, 0.01);
        let r = crate::calib::backlash::analyse("x", &c, None, &BacklashParams::default()).unwrap();
        assert!(r.uncertainty_mm > MORE_CYCLES_TARGET_U_MM, "{r:?}");
        let wide = result_text(
            &session(Branch::Seed, ""),
            &BTreeMap::from([("x".to_string(), r)]),
        )
        .join("\n");
        assert!(
            wide.contains("measuring again with CYCLES=") && wide.contains("would bring it to"),
            "{wide}"
        );
    }

    #[test]
    fn a_coarse_microstep_that_keeps_the_plus_minus_wide_names_the_picture_flows() {
        // 16 microsteps on a 40 mm pulley: 12.5 µm, of which q/√12 = 3.6 µm repeats in every
        // jogged cycle, above the 2.5 µm the more-cycles offer aims at.
        let step = 0.0125;
        let c = alternating(0.08, 0.0005);
        let p = BacklashParams {
            step_mm: step,
            ..BacklashParams::default()
        };
        let r = crate::calib::backlash::analyse("x", &c, None, &p).unwrap();
        let one = |r: &AxisResult| BTreeMap::from([("x".to_string(), r.clone())]);
        let mut s = session(Branch::Seed, "");
        s.step_mm.insert("x".into(), step);
        let text = result_text(&s, &one(&r)).join("\n");
        assert!(
            text.contains("would not bring it within")
                && text.contains("0.0125 mm microstep")
                && text.contains("KLIPCAL_BACKLASH_CLICK"),
            "{text}"
        );
        // Without the microstep known the repeating part is not put down to it.
        s.step_mm.clear();
        let text = result_text(&s, &one(&r)).join("\n");
        assert!(
            text.contains("would not bring it within") && !text.contains("microstep"),
            "{text}"
        );
    }

    #[test]
    fn the_microstep_along_an_axis_comes_from_klippers_settings() {
        let cf = crate::moonraker::ConfigFile::parse(serde_json::json!({"settings": {
            "stepper_x": {"rotation_distance": 40, "microsteps": 16,
                          "full_steps_per_rotation": 200},
            "stepper_y": {"rotation_distance": 40, "microsteps": 32, "gear_ratio": [[80, 20]]},
            "stepper_z": {"rotation_distance": 8, "microsteps": 16},
            "dual_carriage": {"rotation_distance": 40, "microsteps": 64},
        }}))
        .unwrap();
        let st = &cf.settings;
        let close = |v: Option<f64>, want: f64| v.is_some_and(|v| (v - want).abs() < 1e-12);
        // 40 mm / (200 · 16): 12.5 µm; 40 / (200 · 32 · 4): 1.5625 µm; Z 8 / 3200: 2.5 µm.
        assert!(close(
            step_along(st, "cartesian", GuideAxis::X, None),
            0.0125
        ));
        assert!(close(
            step_along(st, "cartesian", GuideAxis::Y, None),
            0.0015625
        ));
        assert!(close(step_along(st, "corexy", GuideAxis::Z, None), 0.0025));
        // The dual carriage's own stepper for carriage 1, stepper_x for carriage 0.
        assert!(close(
            step_along(st, "cartesian", GuideAxis::X, Some(1)),
            0.003125
        ));
        assert!(close(
            step_along(st, "cartesian", GuideAxis::X, Some(0)),
            0.0125
        ));
        // CoreXY: A is stepper_x's motor; X moves both, the larger step over √2.
        assert!(close(step_along(st, "corexy", GuideAxis::A, None), 0.0125));
        assert!(close(
            step_along(st, "corexy", GuideAxis::X, None),
            0.0125 / std::f64::consts::SQRT_2
        ));
        // Other kinematics, or a stepper the settings do not describe: unknown.
        assert_eq!(step_along(st, "delta", GuideAxis::X, None), None);
        let bare = crate::moonraker::ConfigFile::parse(serde_json::json!({"settings": {
            "stepper_x": {"rotation_distance": 40}}}))
        .unwrap();
        assert_eq!(
            step_along(&bare.settings, "cartesian", GuideAxis::X, None),
            None
        );
    }
}
