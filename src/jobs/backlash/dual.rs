//! Dual carriage: each carriage measured and applied on its own (park, select, set, check).

use super::*;

impl Backlash {
    /// The carriage an axis is measured on: `None` without a `[dual_carriage]` or for an axis
    /// both carriages share; else CARRIAGE (0 or 1), or the carriage active now.
    pub(super) async fn carriage_for(
        &self,
        detection: &Detection,
        cf: &ConfigFile,
        axis: GuideAxis,
        asked: Option<i64>,
    ) -> anyhow::Result<Option<u32>> {
        if !detection.dual_carriage {
            return match asked {
                Some(n) => Err(user(format!(
                    "CARRIAGE={n}: this printer's config has no [dual_carriage]; leave CARRIAGE out"
                ))),
                None => Ok(None),
            };
        }
        let dc_axis = cf.settings.dual_carriage_axis();
        if axis.name() != dc_axis {
            return match asked {
                Some(n) => Err(user(format!(
                    "CARRIAGE={n}: only {} has two carriages; {} is shared by both, leave \
                     CARRIAGE out",
                    dc_axis.to_uppercase(),
                    axis.name().to_uppercase()
                ))),
                None => Ok(None),
            };
        }
        match asked {
            Some(n @ 0..=1) => Ok(Some(n as u32)),
            Some(n) => Err(user(format!(
                "CARRIAGE={n}: expected 0 or 1, the carriages SET_DUAL_CARRIAGE selects"
            ))),
            None => Ok(Some(self.active_carriage().await?)),
        }
    }

    /// The dual carriage Klipper moves now (`dual_carriage` status: `PRIMARY`).
    pub(super) async fn active_carriage(&self) -> anyhow::Result<u32> {
        let st = self
            .core
            .m()
            .objects_query(json!({"dual_carriage": null}))
            .await?;
        let dc = &st["dual_carriage"];
        Ok(
            if dc["carriage_1"] == "PRIMARY" && dc["carriage_0"] != "PRIMARY" {
                1
            } else {
                0
            },
        )
    }

    pub(super) async fn select_carriage(&self, n: u32) -> anyhow::Result<()> {
        let cmd = GcodeCmd::new("SET_DUAL_CARRIAGE")
            .word("CARRIAGE", &n.to_string())
            .build()?;
        self.core
            .m()
            .gcode(&cmd)
            .await
            .with_context(|| format!("selecting carriage {n} ({cmd})"))
    }

    /// Selects carriage `n` to be measured, the other first parked where it homes (a
    /// carriage may not pass the inactive one, so the camera point is reachable only with
    /// the other out of the way; Klipper's IDEX examples park the same way).
    pub(super) async fn park_and_select(&self, n: u32) -> anyhow::Result<()> {
        let cf = self.core.m().configfile().await?;
        let other = 1 - n.min(1);
        let axis = cf.settings.dual_carriage_axis();
        let section = if other == 0 {
            format!("stepper_{axis}")
        } else {
            "dual_carriage".to_string()
        };
        let park = cf.settings.position_endstop(&section).ok_or_else(|| {
            anyhow!("[{section}] has no position_endstop to park carriage {other} at")
        })?;
        self.select_carriage(other).await?;
        let line = GcodeCmd::new("G1")
            .axis(if axis == "y" { 'Y' } else { 'X' }, park)
            .axis('F', JOG_F * 5.0)
            .build()?;
        self.core
            .m()
            .gcode(&format!("G90\n{line}"))
            .await
            .with_context(|| format!("parking carriage {other} ({line})"))?;
        self.select_carriage(n).await
    }

    /// `SET_BACKLASH_COMPENSATION` with `want`, refused unless Klipper's reply agrees.
    pub(super) async fn set_checked(&self, want: &SetBacklash) -> anyhow::Result<()> {
        let cmd = kb::set_backlash_command(want)?;
        self.core
            .m()
            .gcode(&cmd)
            .await
            .context("SET_BACKLASH_COMPENSATION")?;
        let reply = kb::parse_reply(&self.console_tail().await?)?;
        if !reply.agrees_with(want) {
            return Err(anyhow!("Klipper answered {reply:?} to {cmd}"));
        }
        Ok(())
    }

    /// Each carriage's values as PR 7259 reports them (the active carriage selected again).
    pub(super) async fn carriage_values(&self) -> anyhow::Result<[kb::BacklashReply; 2]> {
        let was = self.active_carriage().await?;
        let mut out = Vec::with_capacity(2);
        for n in 0..2 {
            self.select_carriage(n).await?;
            out.push(self.seed_values().await?);
        }
        self.select_carriage(was).await?;
        let [a, b]: [kb::BacklashReply; 2] = out
            .try_into()
            .map_err(|_| anyhow!("two carriages expected"))?;
        Ok([a, b])
    }

    /// Dual carriage with PR 7259 (the seed's recipe): non-zero values cannot sit in
    /// `[backlash_compensation]`, so each carriage's values are set at run time with the
    /// reply checked, then written into klipcal's `[delayed_gcode]` include (created and
    /// included on first use) through the config transaction, verified per carriage after
    /// the restart. Values not measured now stay as Klipper runs them.
    pub(super) async fn apply_dual(
        &self,
        s: &Session,
        values: &BTreeMap<String, f64>,
        smooth_s: f64,
    ) -> anyhow::Result<Applied> {
        let (_, cf) = self.detect().await?;
        let dc_axis = cf.settings.dual_carriage_axis();
        if let Some(k) = values.keys().find(|k| k.as_str() == dc_axis.as_str()) {
            return Err(user(format!(
                "{} was measured without naming a carriage; measure it again with \
                 KLIPCAL_BACKLASH_START AXIS={} CARRIAGE=0 (and 1)",
                key_words(k),
                dc_axis.to_uppercase()
            )));
        }
        self.set_state(s.id, State::Applying, "applying").await?;
        let outcome = self.apply_dual_values(values, smooth_s, &dc_axis).await;
        self.settle(s.id, values, Some(smooth_s), outcome).await
    }

    pub(super) async fn apply_dual_values(
        &self,
        values: &BTreeMap<String, f64>,
        smooth_s: f64,
        dc_axis: &str,
    ) -> anyhow::Result<String> {
        let now = self.carriage_values().await?;
        let pick = |n: u32, axis: &str, current: f64| -> f64 {
            let own = if axis == dc_axis {
                values.get(&format!("{axis}@{n}"))
            } else {
                values.get(axis)
            };
            own.copied().unwrap_or(current)
        };
        let wanted: Vec<CarriageBacklash> = (0..2u32)
            .map(|n| {
                let r = &now[n as usize];
                CarriageBacklash {
                    carriage: n.to_string(),
                    values: SetBacklash {
                        x_mm: Some(pick(n, "x", r.x_mm)),
                        y_mm: Some(pick(n, "y", r.y_mm)),
                        z_mm: Some(pick(n, "z", r.z_mm)),
                        smooth_time_s: Some(smooth_s),
                    },
                }
            })
            .collect();
        // At run time first, each reply checked; the carriage active before selected again.
        let was = self.active_carriage().await?;
        for c in &wanted {
            self.select_carriage(c.carriage.parse()?).await?;
            self.set_checked(&c.values)
                .await
                .with_context(|| format!("carriage {}", c.carriage))?;
        }
        self.select_carriage(was).await?;
        // Then the include, through the config transaction.
        let include = kb::dual_carriage_include(&wanted[0], &wanted[1])?;
        let pc = printer_config::fetch(self.core.m(), self.core.files()).await?;
        let main = pc
            .config
            .files()
            .first()
            .ok_or_else(|| anyhow!("the config has no files"))?;
        let main_rel = pc.rel(&main.path)?;
        let dir = main_rel.rsplit_once('/').map_or("", |(d, _)| d);
        let inc_rel = if dir.is_empty() {
            kb::DUAL_CARRIAGE_INCLUDE.to_string()
        } else {
            format!("{dir}/{}", kb::DUAL_CARRIAGE_INCLUDE)
        };
        let included = pc
            .config
            .files()
            .iter()
            .any(|f| pc.rel(&f.path).ok().as_deref() == Some(inc_rel.as_str()));
        // A stale include not read now is still put back as it was on a rollback.
        let old_inc = match self.core.files().download("config", &inc_rel).await {
            Ok(b) => Some(b),
            Err(e) if e.to_string().contains("404") => None,
            Err(e) => return Err(e).context(format!("reading {inc_rel}")),
        };
        let mut writes = vec![printer_config::FileWrite {
            rel: inc_rel.clone(),
            old: old_inc,
            new: include.into_bytes(),
        }];
        if !included {
            writes.push(printer_config::FileWrite {
                rel: main_rel.clone(),
                old: Some(main.text.clone().into_bytes()),
                new: crate::klipper::add_include(
                    &main.text,
                    kb::DUAL_CARRIAGE_INCLUDE,
                    "klipcal: per-carriage backlash compensation (dual_carriage, PR 7259)",
                )
                .into_bytes(),
            });
        }
        let stamp = printer_config::stamp(now_unix() as u64);
        let backup_dir = format!("klipcal_backups/{stamp}");
        printer_config::transact(
            self.core.m(),
            self.core.files(),
            &writes,
            &backup_dir,
            "FIRMWARE_RESTART",
            || async {
                // The [delayed_gcode] runs 0.1 s after ready.
                tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
                let after = self.carriage_values().await?;
                for (c, got) in wanted.iter().zip(after.iter()) {
                    if !got.agrees_with(&c.values) {
                        return Ok(Some(format!(
                            "after the restart carriage {} reports {got:?}, not the values \
                             written to {inc_rel}",
                            c.carriage
                        )));
                    }
                }
                Ok(None)
            },
        )
        .await?;
        Ok(format!(
            "{} written to {inc_rel}{} (backup in {backup_dir}); {}",
            wanted
                .iter()
                .map(|c| format!(
                    "carriage {}: X {} Y {} Z {} mm",
                    c.carriage,
                    c.values.x_mm.unwrap_or(0.0),
                    c.values.y_mm.unwrap_or(0.0),
                    c.values.z_mm.unwrap_or(0.0)
                ))
                .collect::<Vec<_>>()
                .join(", "),
            if included {
                String::new()
            } else {
                format!(", included from {main_rel}")
            },
            format_args!("smooth_time {smooth_s} s")
        ))
    }
}
