//! Following: `klipcal_mesh_follow` loads the profile for the frame temperature when the
//! model says it matters (`calib::mesh_follow`), and the loop that does it.

use super::*;

impl Mesh {
    /// The newest finished capture (`done`: its profiles are the ones written) and its fit. A
    /// capture still running is waited for; a newer one that failed or was cancelled wrote
    /// nothing (a failed write is rolled back), so the one before it rules.
    pub(super) fn model(&self) -> anyhow::Result<(Session, cm::DirectionalSelection)> {
        if let Some((id, s)) = self.core.latest_of::<Session>(KIND)? {
            if !s.state.is_final() {
                return Err(user(format!(
                    "thermal mesh session {id} is {}; wait for it to finish (or KLIPCAL_CANCEL)",
                    s.state.name().replace('_', " ")
                )));
            }
        }
        let Some((_, s)) = self
            .core
            .latest_of_in::<Session>(KIND, &State::Done.name())?
        else {
            return Err(user(
                "no thermal mesh captured yet; run KLIPCAL_MESH_CAPTURE first",
            ));
        };
        let sel = fit_session(&s)?;
        Ok((s, sel))
    }

    /// Whether the user had following on (the model's session says so). Without a finished
    /// capture, the usual start, it answers without building [`Mesh::model`]'s error: an
    /// error captures a backtrace when RUST_BACKTRACE is set, which reads the unwind tables
    /// into memory (0.4 MiB of the daemon's RSS, `klipcal bench footprint`).
    pub(super) fn following_was_on(&self) -> bool {
        let done = self
            .core
            .latest_of_in::<Session>(KIND, &State::Done.name())
            .ok()
            .flatten();
        done.is_some_and(|(_, s)| s.following) && self.model().is_ok_and(|(s, _)| s.following)
    }

    pub(super) async fn stop_following(&self, why: &str) {
        let t = self.follow.lock().ok().and_then(|mut f| f.take());
        if let Some(t) = t {
            t.cancel();
            if let Ok(mut st) = self.follow_status.lock() {
                *st = FollowStatus::stopped(why);
            }
            self.core
                .console(&format!("{TITLE}: following stopped ({why})"))
                .await;
        }
    }

    /// `klipcal_mesh_follow`: starts or stops following the frame temperature.
    pub(super) async fn follow_cmd(&self, enable: bool) -> anyhow::Result<Following> {
        if !enable {
            self.stop_following("KLIPCAL_MESH_FOLLOW ENABLE=0").await;
            if let Ok((s, _)) = self.model() {
                if s.following {
                    self.update(s.id, |d| {
                        d.following = false;
                        Ok(())
                    })
                    .await?;
                }
            }
            return Ok(Following {
                following: false,
                session: None,
                message: "thermal mesh following is off".into(),
            });
        }
        let (s, sel) = self.model()?;
        let temps = s
            .result
            .as_ref()
            .map(|r| r.profiles_c.clone())
            .unwrap_or_default();
        // The cooling profiles, when the session wrote them (the fit is the same: the same
        // captures and tolerance).
        let cooling = match (
            sel.cooling,
            s.result.as_ref().and_then(|r| r.cooling.as_ref()),
        ) {
            (Some(c), Some(doc)) if !doc.profiles_c.is_empty() => Some(Branch {
                phase: Phase::Cooling,
                fit: c.fit,
                temps_c: doc.profiles_c.clone(),
            }),
            _ => None,
        };
        if temps.is_empty() {
            return Err(user(
                "the last capture wrote no profiles; run KLIPCAL_MESH_CAPTURE again",
            ));
        }
        let cf = self.core.m().configfile().await?;
        let bm = cf.settings.bed_mesh.unwrap_or_default();
        let (fade_start, fade_end) = (bm.fade_start, bm.fade_end);
        if fade_end > fade_start {
            return Err(user(format!(
                "[bed_mesh] fades the mesh out from {fade_start} to {fade_end} mm: a profile loaded mid-print \
                 would be faded differently from the one it replaces (VGB: IMPORTANT). Set fade_end: 0 in \
                 [bed_mesh] (or remove fade_start/fade_end), restart, then KLIPCAL_MESH_FOLLOW ENABLE=1"
            )));
        }
        let offset_note = if self.kept_offset().await.is_some() {
            format!(
                "; an offset set with {OFFSET_MACRO} X= Y= is set again after each load (a plain \
                 BED_MESH_OFFSET is dropped by the next load)"
            )
        } else {
            self.core
                .console_error(&format!(
                    "{TITLE}: klipcal.cfg has no {OFFSET_MACRO} (update klipcal.cfg): each profile \
                     load drops a BED_MESH_OFFSET and klipcal cannot set it again"
                ))
                .await;
            String::new()
        };
        self.stop_following("restarted").await;
        let token = self.core.shutdown().child_token();
        if let Ok(mut f) = self.follow.lock() {
            *f = Some(token.clone());
        }
        let me = self.clone();
        let sensor = s.options.frame_sensor.clone();
        let policy = self.settings.follow_policy();
        let directions = if cooling.is_some() {
            " (klipcal_* while the frame warms, klipcal_cool_* while it cools)"
        } else {
            ""
        };
        let heating = Branch {
            phase: Phase::Heating,
            fit: sel.heating.fit,
            temps_c: temps,
        };
        self.core.spawn(async move {
            me.follow_loop(token, sensor, policy, heating, cooling)
                .await;
        });
        if !s.following {
            self.update(s.id, |d| {
                d.following = true;
                Ok(())
            })
            .await?;
        }
        let msg = format!(
            "{TITLE}: following the frame temperature with the profiles of session {}{directions}{offset_note}",
            s.id
        );
        Ok(Following {
            following: true,
            session: Some(s.id),
            message: msg,
        })
    }

    /// Follows the frame sensor once a second until cancelled: each reading pushed to the
    /// follower, and what it decides done (a profile loaded, following stopped).
    pub(super) async fn follow_loop(
        &self,
        token: CancellationToken,
        sensor: String,
        policy: crate::calib::mesh_follow::FollowPolicy,
        heating: Branch,
        cooling: Option<Branch>,
    ) {
        let t0 = Instant::now();
        let fresh = || Follower::with_directions(policy, heating.clone(), cooling.clone(), None);
        let mut f = fresh();
        let mut offset_mm = (0.0, 0.0);
        loop {
            tokio::select! {
                () = token.cancelled() => return,
                () = tokio::time::sleep(Duration::from_secs(1)) => {}
            }
            let t = t0.elapsed().as_secs_f64();
            // A Klipper restart (or a manual load) replaces the mesh the follower loaded: start
            // over, so the right profile is loaded again.
            if self.mesh_changed_under(&f).await {
                info!("the active mesh changed under the follower (Klipper restarted?); reloading");
                f = fresh();
            }
            let busy = self.busy().await;
            let d = match self.frame_temp(&sensor).await {
                Ok(temp) => {
                    let d = f.push(t, temp, busy);
                    self.show_reading(&f, temp, offset_mm, &d);
                    d
                }
                // Moonraker away (longer than a call waits for it): no reading is not a stale
                // sensor. Wait for it, then start over from the next reading; the profile
                // loaded stays in Klipper meanwhile.
                Err(e) if self.core.unreachable(&e) => {
                    info!(error = %format!("{e:#}"), "Moonraker unreachable; following waits for it");
                    tokio::select! {
                        () = token.cancelled() => return,
                        back = self.core.wait_back() => if !back { return },
                    }
                    f = fresh();
                    continue;
                }
                Err(_) => match f.tick(t) {
                    Some(d) => d,
                    None => continue,
                },
            };
            match d {
                Decision::Keep { .. } => {}
                Decision::Load {
                    phase,
                    temp_c,
                    residual_um,
                    ..
                } => {
                    if let Some(kept) = self.load_profile(phase, temp_c, residual_um).await {
                        offset_mm = kept;
                    }
                }
                Decision::RefuseJump {
                    phase,
                    index,
                    jump_um,
                } => {
                    let set = if phase == Phase::Cooling {
                        cooling.as_ref().unwrap_or(&heating)
                    } else {
                        &heating
                    };
                    self.refuse_jump(set, phase, index, jump_um, policy.jump_limit_um)
                        .await;
                    return;
                }
                Decision::Stopped { reason } => {
                    self.follower_stopped(&reason).await;
                    return;
                }
            }
        }
    }

    /// A Klipper restart (or a manual load) replaced the mesh the follower loaded.
    async fn mesh_changed_under(&self, f: &Follower) -> bool {
        let Some((phase, temp_c)) = f.loaded() else {
            return false;
        };
        let active = self
            .core
            .m()
            .bed_mesh(&["profile_name"])
            .await
            .ok()
            .and_then(|bm| bm.profile_name);
        active.is_some_and(|a| a != direction_profile_name(phase, temp_c))
    }

    /// The follower's status (the page's and STATUS's): the reading, the trend, the profile
    /// loaded, the offset kept and the residual of the decision `d`.
    fn show_reading(&self, f: &Follower, temp: f64, offset_mm: (f64, f64), d: &Decision) {
        if let Ok(mut st) = self.follow_status.lock() {
            let residual_um = match d {
                Decision::Keep { residual_um, .. } | Decision::Load { residual_um, .. } => {
                    Some(*residual_um)
                }
                _ => None,
            };
            *st = FollowStatus {
                following: true,
                stopped: None,
                reading: Some(FollowReading {
                    frame_c: temp,
                    trend: f.trend(),
                    loaded: f.loaded().map(|(p, t)| direction_profile_name(p, t)),
                    offset_mm: [offset_mm.0, offset_mm.1],
                    residual_um,
                }),
            };
        }
    }

    /// Loads the profile for `temp_c` in `phase`. The load drops BED_MESH_OFFSET: the one kept
    /// by KLIPCAL_MESH_OFFSET is set again in the same script. Returns that offset when the
    /// profile was loaded.
    async fn load_profile(
        &self,
        phase: Phase,
        temp_c: f64,
        residual_um: f64,
    ) -> Option<(f64, f64)> {
        let name = direction_profile_name(phase, temp_c);
        let kept = self.kept_offset().await.unwrap_or((0.0, 0.0));
        match bed_mesh::load_script(&name, kept) {
            Ok(script) => match self.core.m().gcode(&script).await {
                Ok(()) => {
                    info!(profile = %name, residual_um, offset_x_mm = kept.0,
                          offset_y_mm = kept.1, "mesh profile loaded");
                    Some(kept)
                }
                Err(e) => {
                    warn!(profile = %name, error = %e, "mesh profile load failed");
                    None
                }
            },
            Err(e) => {
                self.core
                    .console_error(&format!(
                        "{TITLE}: {OFFSET_MACRO} holds an offset klipcal cannot send \
                         ({e}); {name} not loaded"
                    ))
                    .await;
                None
            }
        }
    }

    /// A profile `index` of `set` would change the mesh by more than the limit: said on the
    /// console, and following stops.
    async fn refuse_jump(
        &self,
        set: &Branch,
        phase: Phase,
        index: usize,
        jump_um: f64,
        limit_um: f64,
    ) {
        let name = set
            .temps_c
            .get(index)
            .map_or_else(String::new, |&t| direction_profile_name(phase, t));
        self.core
            .console_error(&format!(
                "{TITLE}: loading {} would change the mesh by {jump_um:.0} µm (limit {:.0} µm, \
                 mesh.jump_limit_um): following stopped — was it switched on mid-print, or did the \
                 frame sensor jump?",
                name, limit_um
            ))
            .await;
        self.stop_following("a jump over the limit").await;
    }

    /// The follower stopped itself (`reason` on the console and in its status).
    async fn follower_stopped(&self, reason: &str) {
        self.core.console_error(&format!("{TITLE}: {reason}")).await;
        if let Ok(mut st) = self.follow_status.lock() {
            *st = FollowStatus::stopped(reason);
        }
        if let Ok(mut fl) = self.follow.lock() {
            fl.take();
        }
    }

    /// The offset `KLIPCAL_MESH_OFFSET` keeps, mm (X, Y); `None` when klipcal.cfg lacks the
    /// macro. A variable that is not a number counts as 0.
    pub(super) async fn kept_offset(&self) -> Option<(f64, f64)> {
        let obj = format!("gcode_macro {OFFSET_MACRO}");
        let st = self
            .core
            .m()
            .objects_query(json!({ obj.clone(): ["x", "y"] }))
            .await
            .ok()?;
        // Klipper answers an object it does not have with `{}`.
        let vars = st.get(&obj).filter(|v| v.get("x").is_some())?;
        let num = |k: &str| vars[k].as_f64().filter(|v| v.is_finite()).unwrap_or(0.0);
        Some((num("x"), num("y")))
    }

    /// Homing or probing in progress (never load a mesh then).
    pub(super) async fn busy(&self) -> bool {
        match self
            .core
            .m()
            .objects_query(json!({"idle_timeout": ["state"]}))
            .await
        {
            Ok(st) => {
                // "Printing" in idle_timeout means busy executing G-code (a move, a probe);
                // during a print the mesh is loaded between moves by Klipper's queue, which
                // is safe, so only an active print_stats print counts as not busy.
                let it = st["idle_timeout"]["state"].as_str().unwrap_or("");
                let ps = self
                    .core
                    .m()
                    .objects_query(json!({"print_stats": ["state"]}))
                    .await
                    .ok()
                    .and_then(|s| s["print_stats"]["state"].as_str().map(str::to_string))
                    .unwrap_or_default();
                it == "Printing" && ps != "printing"
            }
            Err(_) => true,
        }
    }
}
