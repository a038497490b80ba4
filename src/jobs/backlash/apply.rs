//! `KLIPCAL_BACKLASH_APPLY`: the measured values set in Klipper (reply checked) and persisted
//! through the shared config transaction.

use super::*;

impl Backlash {
    /// `klipcal_backlash_apply`: sets and persists the measured values.
    ///
    /// # Errors
    /// Nothing measured, a printer printing, neither branch (with the reason), a reply that
    /// disagrees, or a config Klipper rejects (rolled back).
    pub(crate) async fn apply(&self) -> anyhow::Result<Applied> {
        let s = match self.active()? {
            Some(s) if s.state == State::Measured => s,
            _ => {
                return Err(user(
                    "nothing measured to apply; measure an axis first (KLIPCAL_BACKLASH_START)",
                ))
            }
        };
        self.core.printer_idle().await?;
        let (detection, _) = self.detect().await?;
        if !detection.can_apply() {
            return Err(user(format!("cannot apply: {}", detection.why)));
        }
        let results = self.results(&s)?;
        let mut values: BTreeMap<String, f64> = BTreeMap::new();
        for (axis, r) in &results {
            let active = s.active_mm.get(axis).copied().unwrap_or(0.0);
            if r.compensate || active > 0.0 {
                values.insert(axis.clone(), round_um(active + r.backlash_mm));
            }
        }
        if values.is_empty() {
            self.finish(
                s.id,
                State::Done,
                "nothing to apply: no axis needs compensation",
            )
            .await?;
            return Ok(Applied {
                session: s.id,
                state: State::Done.name(),
                values: None,
                smooth_time_s: None,
                message: "no axis needs compensation; nothing written".into(),
            });
        }
        let smooth =
            (detection.branch == Branch::Seed).then(|| common_smooth_time_s(results.values()));
        if detection.dual_carriage && detection.branch == Branch::Seed {
            return self
                .apply_dual(&s, &values, smooth.unwrap_or(SEED_SMOOTH_TIME_S))
                .await;
        }
        if let Some(k) = values.keys().find(|k| k.contains('@')) {
            return Err(user(format!(
                "{} was measured for a dual carriage, but this printer's config has no \
                 [dual_carriage] now; measure again",
                key_words(k)
            )));
        }
        let triples = kb::config_values(detection.branch, &values, smooth)
            .map_err(|e| user(e.to_string()))?;
        self.set_state(s.id, State::Applying, "applying").await?;
        let outcome = self
            .apply_values(&detection, &values, smooth, &triples)
            .await;
        self.settle(s.id, &values, smooth, outcome).await
    }

    /// Ends an apply: done with the message, or back to measured with the reason. The answer
    /// carries the message (a macro's caller reads it on the console, the page shows it): said
    /// here too it showed twice (issue 26 A.7).
    pub(super) async fn settle(
        &self,
        id: i64,
        values: &BTreeMap<String, f64>,
        smooth: Option<f64>,
        outcome: anyhow::Result<String>,
    ) -> anyhow::Result<Applied> {
        match outcome {
            Ok(msg) => {
                self.finish(id, State::Done, &msg).await?;
                let msg = format!("{TITLE}: {msg}");
                Ok(Applied {
                    session: id,
                    state: State::Done.name(),
                    values: Some(values.clone()),
                    smooth_time_s: Some(smooth),
                    message: msg,
                })
            }
            Err(e) => {
                let why = format!("{e:#}");
                self.set_state(id, State::Measured, &format!("apply failed: {why}"))
                    .await?;
                Err(e)
            }
        }
    }

    pub(super) async fn apply_values(
        &self,
        detection: &Detection,
        values: &BTreeMap<String, f64>,
        smooth: Option<f64>,
        triples: &[(String, String, String)],
    ) -> anyhow::Result<String> {
        let get = |k: &str| values.get(k).copied();
        let want = SetBacklash {
            x_mm: get("x"),
            y_mm: get("y"),
            z_mm: get("z"),
            smooth_time_s: smooth,
        };
        if detection.branch == Branch::Seed {
            self.set_checked(&want).await?;
        }
        let pc = printer_config::fetch(self.core.m(), self.core.files()).await?;
        let sets: Vec<ValueSet> = triples
            .iter()
            .map(|(section, key, value)| ValueSet {
                section: section.clone(),
                key: key.clone(),
                value: value.clone(),
            })
            .collect();
        let stamp = printer_config::stamp(now_unix() as u64);
        let report =
            printer_config::apply(self.core.m(), self.core.files(), &pc, &sets, &stamp).await?;
        if detection.branch == Branch::Seed {
            let after = self.seed_values().await?;
            if !after.agrees_with(&want) {
                return Err(anyhow!(
                    "after the restart SET_BACKLASH_COMPENSATION reports {after:?}, not the values written"
                ));
            }
        }
        Ok(format!(
            "written {} (backup in {})",
            report
                .changes
                .iter()
                .map(|(s, k, o, n)| format!("[{s}] {k}: {o} → {n}"))
                .collect::<Vec<_>>()
                .join(", "),
            report.backup_dir
        ))
    }
}
