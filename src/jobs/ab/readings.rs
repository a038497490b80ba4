//! The readings: `klipcal_ab_measure` and `klipcal_ab_check`, what is still missing, and the
//! measuring guide.

use super::*;

impl Ab {
    pub(super) fn readings(&self, s: &Session) -> anyhow::Result<BTreeMap<String, Vec<f64>>> {
        let n = s.rounds.len() as i64;
        let mut out: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        for r in self.core.store().readings(s.id, n)? {
            out.entry(r.pair).or_default().push(r.value_mm);
        }
        Ok(out)
    }

    pub(super) fn missing_lines(&self, s: &Session) -> anyhow::Result<Vec<String>> {
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?;
        let have = self.readings(s)?;
        let mut lines = Vec::new();
        for p in &round.layout.pairs {
            let got = have.get(&p.id).map_or(0, Vec::len);
            if got < s.options.readings_per_pair {
                lines.push(format!(
                    "{} ({}→{}, nominal {} mm): {} of {} readings; KLIPCAL_MEASURE PAIR={} VALUES={},…",
                    p.id,
                    p.from,
                    p.to,
                    entry::fmt_mm(p.nominal_mm),
                    got,
                    s.options.readings_per_pair,
                    p.id,
                    entry::example(p.nominal_mm)
                ));
            }
        }
        Ok(lines)
    }

    pub(super) fn measuring(&self) -> anyhow::Result<Session> {
        match self.active()? {
            Some(s) if matches!(s.state, State::Measuring | State::Solved) => Ok(s),
            Some(s) => Err(user(format!(
                "session {} is {} ({}); readings are taken once the print is done and the part has cooled",
                s.id,
                s.state.name(),
                s.progress
            ))),
            None => Err(user("no calibration session; start one with KLIPCAL_AB_START")),
        }
    }

    /// `klipcal_measure`: saves one entry of readings for a pair, whole or not at all; with
    /// CLEAR=1 first removes the pair's readings (logged in the session's notes). Any change
    /// of the readings after solving drops the solution: apply waits for a new solve.
    ///
    /// # Errors
    /// No session waiting for readings, an unknown pair, or an entry refused (nothing saved).
    pub(crate) async fn measure(&self, req: &MeasureRequest) -> anyhow::Result<Saved> {
        let s = self.measuring()?;
        let (pair, window) = pair_window(&s, &req.pair)?;
        let values = if req.values.is_empty() && req.clear {
            Vec::new()
        } else {
            entry::parse(&req.values, &pair.id, &window)
                .map_err(|e| user(format!("{}: nothing saved; {}", pair.id, e.0)))?
        };
        let per_pair = s.options.readings_per_pair;
        if !req.clear && !values.is_empty() {
            self.refuse_sent_again(&s, &pair.id, &values)?;
        }
        let notes = self.save_entry(&s, req, &pair.id, &values).await?;
        let s = self.load(s.id)?;
        let have = self.readings(&s)?;
        let count = have.get(&pair.id).map_or(0, Vec::len);
        let missing = self.missing_lines(&s)?;
        let mut message = String::new();
        for n in &notes {
            message.push_str(n);
            message.push('\n');
        }
        message.push_str(&format!(
            "{}: {} reading(s) saved, {count} of {} in all",
            pair.id,
            values.len(),
            s.options.readings_per_pair
        ));
        if req.typed_line && !values.is_empty() && values.len() < per_pair && count < per_pair {
            // Klipper cut the line before klipcal saw it (issue 40: `;` saved 1 of 5 without
            // a word). Said in words: RESPOND cannot carry the three characters themselves.
            message.push_str(&format!(
                " — fewer than the {per_pair} a pair takes: if you typed more, a semicolon, a \
                 hash sign or an asterisk ends a Klipper command line (what follows never \
                 reaches klipcal): separate readings with commas, VALUES={}",
                entry::example(pair.nominal_mm)
            ));
        }
        if count > s.options.readings_per_pair && !values.is_empty() {
            message.push_str(&format!(
                " — more than the {} asked for (all are used); if some were wrong, replace \
                 them: KLIPCAL_MEASURE PAIR={} CLEAR=1 VALUES=…",
                s.options.readings_per_pair, pair.id
            ));
        }
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?;
        let progress = pairs_progress(&round.layout.pairs, &have, s.options.readings_per_pair);
        // One console row per entry: what was saved, then where every pair stands (issue 26
        // A.4: two rows each).
        message.push_str(" · ");
        message.push_str(&progress);
        if missing.is_empty() && s.state == State::Measuring {
            message.push_str("\nall pairs measured: KLIPCAL_AB_SOLVE computes the new values");
            // A decision its buttons can answer: solve now, or close and look again.
            self.core
                .prompt(&Prompt {
                    title: format!("Round {} · all pairs measured", s.rounds.len()),
                    // No text row: the title says it, the row just said where each pair
                    // stands (issue 40 item 6).
                    lines: Vec::new(),
                    buttons: vec![Button::new("Solve", "KLIPCAL_AB_SOLVE", "primary")],
                    footer: vec![Button::new("Close", "_KLIPCAL_PROMPT_CLOSE", "info")],
                })
                .await;
        }
        Ok(Saved {
            readings: have.get(&pair.id).cloned().unwrap_or_default(),
            pair: pair.id,
            saved: values,
            count,
            missing,
            message,
        })
    }

    /// The last entry sent again (a re-sent console line, a double tap) would double the
    /// pair's readings: refused, with the way to replace them.
    fn refuse_sent_again(&self, s: &Session, pair: &str, values: &[f64]) -> anyhow::Result<()> {
        let per_pair = s.options.readings_per_pair;
        // The last entry sent again (a re-sent console line, a double tap) would double the
        // pair's readings: refused, with the way to replace them. A new reading that
        // happens to equal an earlier one is not an entry sent again.
        let have = self.readings(s)?.remove(pair).unwrap_or_default();
        let again = s.last_entry.as_ref().is_some_and(|(p, last)| {
            *p == pair
                && last.len() == values.len()
                && last.iter().zip(values).all(|(a, b)| (a - b).abs() < 1e-9)
        });
        if again && have.len() + values.len() > per_pair {
            return Err(user(format!(
                "{}: nothing saved: these {} reading(s) are already saved (the same entry \
                 sent again?), {} of {per_pair} in all. To enter the pair again, replace its \
                 readings: KLIPCAL_MEASURE PAIR={} CLEAR=1 VALUES=…",
                pair,
                values.len(),
                have.len(),
                pair
            )));
        }
        Ok(())
    }

    /// Saves the entry (after removing the pair's readings with CLEAR=1) and drops a solution
    /// the readings no longer match. Returns the notes logged in the session.
    async fn save_entry(
        &self,
        s: &Session,
        req: &MeasureRequest,
        pair: &str,
        values: &[f64],
    ) -> anyhow::Result<Vec<String>> {
        let n = s.rounds.len() as i64;
        let mut notes = Vec::new();
        if req.clear {
            let old: Vec<String> = self
                .readings(s)?
                .remove(pair)
                .unwrap_or_default()
                .iter()
                .map(|v| entry::fmt_mm(*v))
                .collect();
            self.core.store().clear_readings(s.id, n, pair)?;
            notes.push(format!(
                "{}: readings removed by CLEAR=1: {}",
                pair,
                if old.is_empty() {
                    "none".to_string()
                } else {
                    old.join(", ")
                }
            ));
        }
        if !values.is_empty() {
            self.core.store().add_readings(s.id, n, pair, values)?;
        }
        let was_solved = s.state == State::Solved;
        if was_solved {
            notes.push(
                "the readings changed after solving: the solution was dropped; solve again".into(),
            );
        }
        let logged = notes.clone();
        let entry = (!values.is_empty()).then(|| (pair.to_string(), values.to_vec()));
        self.update(s.id, |s| {
            s.notes.extend(logged);
            if entry.is_some() || req.clear {
                s.last_entry.clone_from(&entry);
            }
            if s.state == State::Solved {
                s.state = State::Measuring;
                s.progress = "waiting for caliper readings".into();
                if let Some(r) = s.rounds.last_mut() {
                    r.solution = None;
                }
            }
            Ok(())
        })
        .await?;
        if was_solved {
            // The Apply prompt is no longer true.
            self.core.prompt_end().await;
        }
        Ok(notes)
    }

    /// `klipcal_ab_check`: judges an entry by the rules [`Ab::measure`] applies, field by field
    /// (a JSON list: one form field each; text: one item each) and as a whole; saves nothing
    /// (the page's live validation).
    ///
    /// # Errors
    /// No session waiting for readings, an unknown pair, or a bad argument.
    pub(crate) fn check(&self, req: &CheckRequest) -> anyhow::Result<Checked> {
        let typed_items = &req.items;
        let s = self.measuring()?;
        let (pair, window) = pair_window(&s, &req.pair)?;
        // One answer per field as sent (blank fields too), so the page marks the field the
        // user typed in; a console list: one per item.
        let per_field: Vec<ItemAnswer> = match &req.fields {
            Some(texts) => texts
                .iter()
                .enumerate()
                .map(|(i, t)| {
                    let item = typed_items
                        .iter()
                        .find(|it| it.label == format!("field {}", i + 1));
                    item_answer(t, item, &pair.id, &window)
                })
                .collect(),
            None => typed_items
                .iter()
                .map(|it| item_answer(&it.text, Some(it), &pair.id, &window))
                .collect(),
        };
        let whole = entry::parse(typed_items, &pair.id, &window);
        let message = match &whole {
            Ok(v) => format!(
                "{}: {} reading(s) would be accepted (plausible {:.2}–{:.2} mm); nothing saved",
                pair.id,
                v.len(),
                window.nominal_mm - window.half_width_mm(),
                window.nominal_mm + window.half_width_mm()
            ),
            Err(e) => format!("{}: would be refused; {}", pair.id, e.0),
        };
        let items = per_field;
        Ok(Checked {
            nominal_mm: pair.nominal_mm,
            pair: pair.id,
            window_mm: [
                window.nominal_mm - window.half_width_mm(),
                window.nominal_mm + window.half_width_mm(),
            ],
            valid: whole.is_ok(),
            message,
            items,
        })
    }
}

/// Every pair's count of readings in one line: `A-D1 5/5 ✓ · A-D2 2/5 · …`.
pub(super) fn pairs_progress(
    pairs: &[crate::layout::Pair],
    have: &BTreeMap<String, Vec<f64>>,
    per_pair: usize,
) -> String {
    pairs
        .iter()
        .map(|p| {
            let n = have.get(&p.id).map_or(0, Vec::len);
            format!(
                "{} {n}/{per_pair}{}",
                p.id,
                if n >= per_pair { " ✓" } else { "" }
            )
        })
        .collect::<Vec<_>>()
        .join(" · ")
}

/// The check's answer for one field or item: its value, or the problem alone (the page
/// shows it beside the field).
pub(super) fn item_answer(
    text: &str,
    item: Option<&entry::Item>,
    pair: &str,
    window: &entry::Window,
) -> ItemAnswer {
    let one = item.map(|it| entry::one(it, pair, window));
    ItemAnswer {
        text: text.to_string(),
        values: one.as_ref().and_then(|r| r.as_ref().ok()).map(|v| vec![*v]),
        error: one.and_then(Result::err),
    }
}

/// The round's pair named `typed` (any case) and its plausibility window.
pub(super) fn pair_window(
    s: &Session,
    typed: &str,
) -> anyhow::Result<(crate::layout::Pair, entry::Window)> {
    let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?;
    let Some(pair) = round
        .layout
        .pairs
        .iter()
        .find(|p| p.id.eq_ignore_ascii_case(typed))
        .cloned()
    else {
        let ids: Vec<&str> = round.layout.pairs.iter().map(|p| p.id.as_str()).collect();
        return Err(user(format!(
            "unknown pair {typed:?}; this print's pairs are {}",
            ids.join(", ")
        )));
    };
    let window = entry::Window {
        nominal_mm: pair.nominal_mm,
        tolerance_mm: s.options.reading_tolerance_mm,
        max_change_pct: s.options.max_change_pct,
        resolution_mm: s.options.caliper_resolution_mm,
    };
    Ok((pair, window))
}

/// What to measure and how, for the console (and where else to type: klipcal's page).
pub(super) fn measuring_guide(s: &Session, page: Option<&str>) -> Vec<String> {
    let Some(round) = s.rounds.last() else {
        return Vec::new();
    };
    let on = if s.options.bed_temp_c > 0.0 {
        "with the part still on the hot bed"
    } else {
        "with the part still on the bed"
    };
    let mut lines = vec![format!(
        "{TITLE} round {}: measure the pylons now, {on}. For each pair, {} readings with \
         calipers from outer face to outer face, just below the top chamfer:",
        round.n, s.options.readings_per_pair
    )];
    for p in &round.layout.pairs {
        lines.push(format!(
            "{}: pylon {} to pylon {}, nominal {} mm: KLIPCAL_MEASURE PAIR={} VALUES={},…",
            p.id,
            p.from,
            p.to,
            entry::fmt_mm(p.nominal_mm),
            p.id,
            entry::example(p.nominal_mm)
        ));
    }
    let shown = round
        .picture
        .clone()
        .or_else(|| round.diagram.as_ref().map(|d| format!("config/{d}")));
    if let Some(p) = shown {
        lines.push(format!(
            "picture of the pylons and pairs: {p} (Mainsail/Fluidd: Machine → config files → klipcal)"
        ));
    }
    lines.push(format!(
        "type readings on the console (or on klipcal's page{}); a wrong one: KLIPCAL_MEASURE \
         PAIR=… CLEAR=1, then enter the pair again",
        page.map(|p| format!(", {p}, on a phone also its webcam tile 'klipcal'"))
            .unwrap_or_default()
    ));
    lines
}
