//! The capture: `klipcal_mesh_capture`, the preflight, the runner (soak, the meshes as the
//! frame warms, each stored as it completes) and the profile write (backup, restart, verify,
//! roll back).

use super::*;

impl Mesh {
    /// `klipcal_mesh_capture`: starts a capture.
    pub(super) async fn capture(&self, bed_c: Option<f64>) -> anyhow::Result<SessionAnswer> {
        let mut options = self.settings.clone();
        if let Some(b) = bed_c {
            options.bed_temp_c = b;
        }
        self.core.refuse_other_kind(KIND)?;
        self.core.printer_idle().await?;
        self.preflight(&options).await?;
        self.stop_following("a capture starts").await;
        // The mesh the user has loaded now, to load again after each capture mesh.
        let user_mesh = self
            .core
            .m()
            .bed_mesh(&["profile_name"])
            .await?
            .profile_name
            .unwrap_or_default();
        let mut doc = Session::new(
            State::Preflight,
            "starting",
            MeshBody {
                options,
                params: None,
                captures: Vec::new(),
                started_unix: None,
                result: None,
                user_mesh: Some(user_mesh),
                imported: false,
                following: false,
            },
        );
        let id = self.core.create(KIND, &mut doc, |d, id| d.id = id).await?;
        self.spawn_runner(id);
        let o = &doc.options;
        let every = format!(
            "a mesh is taken each time the frame moves {} °C or every {:.0} min until it settles",
            o.step_c,
            o.interval_s / 60.0
        );
        let msg = if o.bed_temp_c > 0.0 {
            format!(
                "thermal mesh capture started (session {id}): the bed heats to {} °C, then {every}",
                o.bed_temp_c
            )
        } else {
            // Issue 26 A.7: with nothing heated the frame stays where it is, and the fit needs
            // meshes at different frame temperatures; said now, not after the meshes are taken.
            format!(
                "thermal mesh capture started (session {id}) with BED=0: klipcal heats nothing, \
                 so the frame does not warm unless something else heats it (a chamber heater). \
                 Without that every mesh is taken at the same frame temperature and the capture \
                 fails after {} meshes: it needs {} °C between the coldest and the \
                 hottest. To warm the frame, KLIPCAL_CANCEL and KLIPCAL_MESH_CAPTURE BED=<°C>. \
                 Otherwise {every}",
                o.min_meshes,
                cm::MIN_SPAN_C
            )
        };
        Ok(SessionAnswer {
            session: id,
            state: State::Preflight.name(),
            message: msg,
        })
    }

    /// Refuses when the printer lacks what a capture needs, naming it.
    pub(super) async fn preflight(&self, o: &MeshConfig) -> anyhow::Result<()> {
        let objects = self.core.m().objects_list().await?;
        let mut missing = Vec::new();
        let sensor = format!("temperature_sensor {}", o.frame_sensor);
        if !objects.contains(&sensor) {
            missing.push(format!(
                "[{sensor}] (the frame thermistor; mesh.frame_sensor names it)"
            ));
        }
        if !objects.iter().any(|x| x == "bed_mesh") {
            missing.push("[bed_mesh]".to_string());
        }
        if !objects.iter().any(|x| {
            x == "probe"
                || x.starts_with("bltouch")
                || x.starts_with("probe_eddy")
                || x.starts_with("beacon")
                || x.starts_with("cartographer")
        }) {
            missing.push("a probe ([probe], [bltouch], …)".to_string());
        }
        if o.bed_temp_c > 0.0 && !objects.iter().any(|x| x == "heater_bed") {
            missing.push("[heater_bed] (or capture with BED=0)".to_string());
        }
        if !missing.is_empty() {
            return Err(user(format!(
                "the printer lacks what a thermal mesh capture needs: {}",
                missing.join(", ")
            )));
        }
        Ok(())
    }

    pub(super) fn spawn_runner(&self, id: i64) {
        let (me, me2) = (self.clone(), self.clone());
        self.core.spawn_session(
            id,
            TITLE,
            move || {
                let me = me.clone();
                async move { me.run(id).await }
            },
            move |msg| async move {
                me2.core
                    .fail_session::<State, MeshBody>(id, TITLE, &msg, false, |_| {})
                    .await;
            },
        );
    }

    /// Runs the session's steps; when one fails, the user's mesh is loaded again before the
    /// error goes on.
    pub(super) async fn run(&self, id: i64) -> anyhow::Result<()> {
        let r = self.run_steps(id).await;
        if r.is_err() {
            if let Ok(s) = self.core.load::<Session>(id) {
                self.put_back_user_mesh(&s, true).await;
            }
        }
        r
    }

    pub(super) async fn run_steps(&self, id: i64) -> anyhow::Result<()> {
        loop {
            let s: Session = self.core.load(id)?;
            match s.state {
                State::Preflight => {
                    if s.options.bed_temp_c > 0.0 {
                        BedSoak::heat(
                            &self.core,
                            s.options.bed_temp_c,
                            s.options.soak_max_s + crate::jobs::soak::BOUND_SLACK_S,
                        )
                        .await?;
                    }
                    self.set_state(id, State::Soaking, "heating the bed")
                        .await?;
                }
                State::Soaking => self.soak_bed(&s).await?,
                State::Capturing => self.capture_loop(s).await?,
                State::Writing => self.write_profiles(s).await?,
                _ => return Ok(()),
            }
        }
    }

    pub(super) async fn soak_bed(&self, s: &Session) -> anyhow::Result<()> {
        if s.options.bed_temp_c > 0.0 {
            // The bed was heated before this state was stored; if its target is no longer
            // the capture's (Klipper restarted, an emergency stop), the soak ends saying so
            // rather than heating it again behind the user's back.
            let params = self.soak.for_soak(&self.core, "thermal mesh").await;
            let mut soak = BedSoak::new(
                params,
                s.options.bed_temp_c,
                s.options.soak_max_s,
                "mesh.soak_max_s",
            )
            .before_no_print();
            loop {
                match soak.poll(&self.core, "thermal mesh").await? {
                    SoakUpdate::Stable { .. } => break,
                    SoakUpdate::TooLong { minutes, .. } => {
                        return Err(user(format!(
                            "the bed had not settled after {minutes:.0} min (mesh.soak_max_s); \
                             the meshes would drift with it"
                        )))
                    }
                    SoakUpdate::Heating => {}
                    SoakUpdate::Soaking { text, .. } => {
                        let _ = self
                            .update(s.id, |d| {
                                d.progress = text;
                                Ok(())
                            })
                            .await;
                    }
                }
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
        // Between meshes the printer idles: Klipper's idle timeout must not end the capture,
        // yet still turns the heaters off if klipcal stops (at most an interval later).
        self.core
            .hold_heaters_for(s.options.interval_s + 600.0)
            .await?;
        let now = now_unix();
        self.update(s.id, |d| {
            d.state = State::Capturing;
            d.started_unix.get_or_insert(now);
            d.progress = "bed stable; taking the first mesh".into();
            Ok(())
        })
        .await
    }

    /// Loads the mesh that was active when the capture started (clears the mesh when none
    /// was), so klipcal's capture mesh never stays in use; `last` also drops the capture
    /// profile from Klipper's memory (and from what a SAVE_CONFIG would write). Nothing for a
    /// session that did not record the user's mesh (an import). Failures are logged: the
    /// capture's own outcome is what the user hears about.
    pub(super) async fn put_back_user_mesh(&self, s: &Session, last: bool) {
        let Some(user_mesh) = &s.user_mesh else {
            return;
        };
        let load = if user_mesh.is_empty() || user_mesh == CAPTURE_PROFILE {
            Ok("BED_MESH_CLEAR".to_string())
        } else {
            crate::klipper::GcodeCmd::new("BED_MESH_PROFILE")
                .word("LOAD", user_mesh)
                .build()
        };
        let mut script = match load {
            Ok(l) => l,
            Err(e) => {
                warn!(profile = %user_mesh, error = %e, "the mesh active before the capture cannot be loaded by name");
                "BED_MESH_CLEAR".to_string()
            }
        };
        if last {
            let kept = self
                .core
                .m()
                .bed_mesh(&["profiles"])
                .await
                .map_or(true, |bm| bm.profiles.contains_key(CAPTURE_PROFILE));
            if kept {
                script.push_str(&format!("\nBED_MESH_PROFILE REMOVE={CAPTURE_PROFILE}"));
            }
        }
        if let Err(e) = self
            .core
            .m()
            .gcode_within(&script, Duration::from_secs(900))
            .await
        {
            warn!(session = s.id, error = %e, "loading the mesh active before the capture again");
        }
    }

    pub(super) async fn homed(&self) -> anyhow::Result<()> {
        let st = self
            .core
            .m()
            .objects_query(json!({"toolhead": ["homed_axes"]}))
            .await?;
        if st["toolhead"]["homed_axes"].as_str().unwrap_or("") != "xyz" {
            self.core
                .m()
                .gcode_within("G28", Duration::from_secs(300))
                .await?;
        }
        Ok(())
    }

    /// One BED_MESH_CALIBRATE with the frame sampled while it runs.
    pub(super) async fn take_mesh(&self, s: &Session) -> anyhow::Result<(CaptureDoc, MeshParams)> {
        self.homed().await?;
        let sensor = s.options.frame_sensor.clone();
        let me = self.clone();
        let stop = self.core.shutdown().child_token();
        let stop2 = stop.clone();
        let sampler = tokio::spawn(async move {
            let t0 = Instant::now();
            let mut out: Vec<(f64, f64)> = Vec::new();
            loop {
                if let Ok(t) = me.frame_temp(&sensor).await {
                    out.push((t0.elapsed().as_secs_f64(), t));
                }
                tokio::select! {
                    () = stop2.cancelled() => break,
                    () = tokio::time::sleep(Duration::from_millis(250)) => {}
                }
            }
            if let Ok(t) = me.frame_temp(&sensor).await {
                out.push((t0.elapsed().as_secs_f64(), t));
            }
            out
        });
        let calibrate = crate::klipper::GcodeCmd::new("BED_MESH_CALIBRATE")
            .word("PROFILE", CAPTURE_PROFILE)
            .build()
            .map_err(|e| anyhow!("{e}"))?;
        let done = self
            .core
            .m()
            .gcode_within(&calibrate, Duration::from_secs(900))
            .await;
        stop.cancel();
        let samples = sampler.await.unwrap_or_default();
        done.context("BED_MESH_CALIBRATE")?;
        let bm = self
            .core
            .m()
            .bed_mesh(&["probed_matrix", "profiles", "profile_name"])
            .await?;
        self.put_back_user_mesh(s, false).await;
        let rows = bm.probed_matrix;
        let params = bm
            .profiles
            .get(CAPTURE_PROFILE)
            .map(|p| p.mesh_params.clone())
            .ok_or_else(|| {
                anyhow!("bed_mesh reports no mesh_params for profile {CAPTURE_PROFILE}")
            })?;
        if rows.len() != params.y_count || rows.iter().any(|r| r.len() != params.x_count) {
            return Err(anyhow!(
                "the probed mesh is not {}×{}",
                params.x_count,
                params.y_count
            ));
        }
        let temps = point_temps(&samples, params.x_count, params.y_count);
        if temps.iter().any(|t| !t.is_finite()) {
            return Err(user(format!(
                "the frame sensor [temperature_sensor {}] gave no reading during the mesh",
                s.options.frame_sensor
            )));
        }
        let first = samples.first().map_or(f64::NAN, |s| s.1);
        let last = samples.last().map_or(f64::NAN, |s| s.1);
        let prev = s
            .captures
            .last()
            .map(|c| c.temps_c.iter().sum::<f64>() / c.temps_c.len().max(1) as f64);
        let heating = match prev {
            Some(p) => (first + last) / 2.0 >= p,
            None => last >= first,
        };
        Ok((
            CaptureDoc {
                n: s.captures.len() + 1,
                at_unix: now_unix(),
                temps_c: temps,
                points_mm: rows.into_iter().flatten().collect(),
                heating,
            },
            params,
        ))
    }

    pub(super) async fn capture_loop(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let o = s.options.clone();
        let started = s.started_unix.unwrap_or_else(now_unix);
        if s.captures.is_empty() {
            self.mesh_now(id).await?;
        }
        loop {
            let s: Session = self.core.load(id)?;
            if let Some(why) = capture_done(&s.captures, now_unix(), started, &o) {
                self.core
                    .heaters_off_reported("mesh capture complete")
                    .await;
                self.put_back_user_mesh(&s, true).await;
                // An unheated bed (BED=0) had no heater on: "heaters off" said nothing there.
                let off = if o.bed_temp_c > 0.0 {
                    "; heaters off"
                } else {
                    ""
                };
                let msg = format!("{TITLE}: capture complete, {why}{off}; fitting");
                self.core.console(&msg).await;
                self.set_state(id, State::Writing, &msg).await?;
                return Ok(());
            }
            self.bed_still_ours(&s).await?;
            let last = s.captures.last().ok_or_else(|| anyhow!("no mesh"))?;
            let last_t = last.temps_c.iter().sum::<f64>() / last.temps_c.len().max(1) as f64;
            let now_t = self.frame_temp(&o.frame_sensor).await?;
            if mesh_due(last_t, now_t, now_unix() - last.at_unix, &o) {
                self.mesh_now(id).await?;
            } else {
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }

    /// Fails when the bed's target is no longer the capture's (Klipper restarted, or the
    /// heaters were turned off): meshes of a cooling bed must not join the heating ones, and
    /// klipcal does not heat again behind the user's back.
    async fn bed_still_ours(&self, s: &Session) -> anyhow::Result<()> {
        if s.options.bed_temp_c <= 0.0 {
            return Ok(());
        }
        let bed = self.core.m().heater("heater_bed", &["target"]).await?;
        match bed.target {
            Some(now_c) if (now_c - s.options.bed_temp_c).abs() > 0.5 => Err(anyhow!(
                "the bed's target is now {now_c:.0} °C instead of the capture's {:.0} °C \
                 (Klipper restarted, or the heaters were turned off by its idle timeout or by \
                 hand); the {} meshes stored are kept",
                s.options.bed_temp_c,
                s.captures.len()
            )),
            _ => Ok(()),
        }
    }

    pub(super) async fn mesh_now(&self, id: i64) -> anyhow::Result<()> {
        let s: Session = self.core.load(id)?;
        let (cap, params) = self.take_mesh(&s).await?;
        let n = cap.n;
        let mean = cap.temps_c.iter().sum::<f64>() / cap.temps_c.len().max(1) as f64;
        if let Some(p) = &s.params {
            if p.x_count != params.x_count || p.y_count != params.y_count {
                return Err(user(format!(
                    "mesh {n} is {}×{} but the first was {}×{}: the [bed_mesh] settings changed during the capture",
                    params.x_count, params.y_count, p.x_count, p.y_count
                )));
            }
        }
        let msg = format!("{TITLE}: mesh {n} stored at frame {mean:.2} °C");
        self.update(id, |d| {
            d.captures.push(cap);
            d.params.get_or_insert(params);
            d.progress = msg.clone();
            Ok(())
        })
        .await?;
        self.core.console(&msg).await;
        Ok(())
    }

    /// Fits, plans the profiles and writes them into the SAVE_CONFIG block; rolls back when
    /// Klipper does not come back ready with every profile.
    pub(super) async fn write_profiles(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let (profiles, mut result) = plan_session(&s)?;
        self.core.printer_idle().await?;
        let (backup, replaced) = self.write_block(&profiles).await?;
        result.backup = Some(backup);
        result.replaced = replaced;
        let (lo, hi) = result.range_c;
        let cooling_words = match &result.cooling {
            Some(c) => format!(
                " and {} for cooling over {:.2}–{:.2} °C (model {})",
                super::profiles_words(crate::calib::mesh::Phase::Cooling, &c.profiles_c),
                c.range_c.0,
                c.range_c.1,
                c.model
            ),
            None => String::new(),
        };
        let replaced_words = if result.replaced.is_empty() {
            String::new()
        } else {
            format!(
                "; they replace the {} klipcal profiles of before ({}), kept in the backup {}",
                result.replaced.len(),
                result.replaced.join(", "),
                result.backup.as_deref().unwrap_or("")
            )
        };
        let msg = format!(
            "{TITLE}: {} written for {lo:.2}–{hi:.2} °C (model {}, worst step {:.1} \
             µm){cooling_words}; {}{replaced_words}; KLIPCAL_MESH_FOLLOW ENABLE=1 follows the \
             frame",
            super::profiles_words(crate::calib::mesh::Phase::Heating, &result.profiles_c),
            result.model,
            result.max_quantisation_um,
            result.directions
        );
        self.update(id, |d| {
            d.result = Some(result);
            d.state = State::Done;
            d.progress = msg.clone();
            Ok(())
        })
        .await?;
        self.core.console(&msg).await;
        Ok(())
    }

    /// Replaces the klipcal profiles in printer.cfg's SAVE_CONFIG block: backup, upload,
    /// restart, verify each profile is known; on failure the backup goes back. The backup's
    /// path and the klipcal profiles replaced.
    pub(super) async fn write_block(
        &self,
        profiles: &[MeshProfile],
    ) -> anyhow::Result<(String, Vec<String>)> {
        let files = self.core.files();
        let old = files
            .download("config", "printer.cfg")
            .await
            .context("reading printer.cfg")?;
        let text =
            String::from_utf8(old.clone()).map_err(|_| anyhow!("printer.cfg is not UTF-8"))?;
        let new =
            bed_mesh::replace_klipcal_profiles(&text, profiles).map_err(|e| user(e.to_string()))?;
        let replaced = bed_mesh::klipcal_profile_names(&text);
        let stamp = crate::jobs::core::printer_config::stamp(now_unix() as u64);
        let backup_dir = format!("klipcal_backups/{stamp}");
        let writes = [FileWrite {
            rel: "printer.cfg".into(),
            old: Some(old),
            new: new.into_bytes(),
        }];
        crate::jobs::core::printer_config::transact(
            self.core.m(),
            files,
            &writes,
            &backup_dir,
            "RESTART",
            || self.verify_profiles(profiles),
        )
        .await?;
        Ok((format!("config/{backup_dir}/printer.cfg"), replaced))
    }

    /// After the restart with new profiles: every profile is known to Klipper and loads
    /// (`BED_MESH_PROFILE LOAD=`, which builds the mesh as a print would and applies
    /// `[bed_mesh]`'s fade checks); the mesh active before is put back. `Some(why)` names the
    /// first profile Klipper refused, in Klipper's words.
    pub(super) async fn verify_profiles(
        &self,
        profiles: &[MeshProfile],
    ) -> anyhow::Result<Option<String>> {
        let m = self.core.m();
        let bm = m.bed_mesh(&["profiles", "profile_name"]).await?;
        if let Some(p) = profiles.iter().find(|p| !bm.profiles.contains_key(&p.name)) {
            return Ok(Some(format!(
                "Klipper did not read profile {} from printer.cfg",
                p.name
            )));
        }
        let active = bm.profile_name.unwrap_or_default();
        let mut refused = None;
        for p in profiles {
            let load = crate::klipper::GcodeCmd::new("BED_MESH_PROFILE")
                .word("LOAD", &p.name)
                .build()
                .map_err(|e| anyhow!("{e}"))?;
            match m.gcode(&load).await {
                Ok(()) => {}
                Err(e) if e.is_refusal() => {
                    refused = Some(format!(
                        "Klipper refused to load profile {}: {}",
                        p.name,
                        klipper_message(&e)
                    ));
                    break;
                }
                Err(e) => return Err(e).context(format!("loading profile {}", p.name)),
            }
        }
        // Leave the mesh as the restart left it.
        let back = crate::klipper::GcodeCmd::new("BED_MESH_PROFILE")
            .word("LOAD", &active)
            .build()
            .ok()
            .filter(|_| !active.is_empty())
            .unwrap_or_else(|| "BED_MESH_CLEAR".to_string());
        if let Err(e) = m.gcode(&back).await {
            warn!(error = %e, "putting the mesh back after verifying the profiles");
        }
        Ok(refused)
    }
}
