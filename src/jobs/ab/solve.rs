//! `klipcal_ab_solve`: the rotation distances (and skew) from the readings, in words.

use super::*;

impl Ab {
    /// `klipcal_solve`: computes new rotation distances from the readings.
    ///
    /// # Errors
    /// Readings missing or inconsistent (the solver's message names the pair).
    pub(crate) async fn solve(&self) -> anyhow::Result<Solved> {
        let s = self.measuring()?;
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?.clone();
        let raw = self.readings(&s)?;
        let stepper = |d: &StepperDoc| StepperFacts {
            rotation_distance_mm: d.rotation_distance_mm,
            microsteps: d.microsteps,
            full_steps_per_rotation: d.full_steps_per_rotation,
            gear_ratio: d.gear_ratio,
        };
        let facts = MotionFacts {
            kinematics: if round.kinematics == "corexy" {
                CalibKinematics::CoreXy
            } else {
                CalibKinematics::Cartesian
            },
            stepper_x: stepper(&round.stepper_x),
            stepper_y: stepper(&round.stepper_y),
        };
        let mut opts = SolveOptions {
            shear_to: if s.options.shear_to == "klipper_skew" {
                ShearTo::KlipperSkew
            } else {
                ShearTo::Motors
            },
            ..SolveOptions::default()
        };
        // The caliper's last digit is part of every reading's uncertainty.
        opts.rules.resolution_mm = s.options.caliper_resolution_mm;
        if s.rounds.len() > 1 {
            let prev = &s.rounds[s.rounds.len() - 2];
            opts.previous = prev.solution.as_ref().map(|sol| {
                sol.groups
                    .iter()
                    .map(|g| (g.group.clone(), g.scale))
                    .collect()
            });
        }
        let solution =
            solve(&round.layout, &raw, &facts, &opts).map_err(|e| user(e.to_string()))?;
        let decision = solution_text(&solution);
        let mut message = decision.clone();
        let sol = solution.clone();
        self.update(s.id, |s| {
            if let Some(r) = s.rounds.last_mut() {
                r.solution = Some(solution);
            }
            s.state = State::Solved;
            s.progress = "solved; apply with KLIPCAL_AB_APPLY".into();
            Ok(())
        })
        .await?;
        // The rounds so far as a picture where Mainsail/Fluidd's file browser shows it.
        let doc = serde_json::to_value(self.session_status(&self.load(s.id)?)?)?;
        if let Ok(svg) = crate::plots::convergence_of_status(&doc) {
            let path = format!("klipcal/ab-s{}-convergence.svg", s.id);
            if let Some(shown) = self.core.save_picture(&path, svg).await {
                message.push_str(&format!("\nplot of the rounds: {shown}"));
            }
        }
        self.core
            .prompt(&Prompt {
                title: format!("Round {} · new values", s.rounds.len()),
                // One text row (each prompt line is a console row; issue 40 item 6): the
                // answer above lists the same lines one by one.
                lines: vec![decision.lines().collect::<Vec<_>>().join(" · ")],
                buttons: vec![Button::new("Apply", "KLIPCAL_AB_APPLY", "primary")],
                footer: vec![Button::new("Close", "_KLIPCAL_PROMPT_CLOSE", "info")],
            })
            .await;
        Ok(Solved {
            solution: sol,
            message,
        })
    }
}

/// The solver's result in a few console lines.
pub(super) fn solution_text(sol: &Solution) -> String {
    let mut t = String::new();
    for (name, s) in [("stepper_x", &sol.stepper_x), ("stepper_y", &sol.stepper_y)] {
        t.push_str(&format!(
            "{name}: rotation_distance {} → {} (scale {:.5} ± {:.5})\n",
            entry::fmt_rd(s.rotation_distance_old),
            entry::fmt_rd(s.rotation_distance_new),
            s.scale,
            s.uncertainty,
        ));
    }
    t.push_str(if sol.converged {
        "converged: the values are within the error budget"
    } else {
        "not converged: apply, then print another round"
    });
    for w in &sol.warnings {
        t.push_str("\nwarning: ");
        t.push_str(w);
    }
    t
}
