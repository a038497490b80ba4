//! `klipcal_mesh_check`: seed 001's 0.5 mm reference rule before a print, on the mesh's
//! corners and centre.

use super::*;

impl Mesh {
    /// `klipcal_mesh_check`: probes the mesh's corners and centre and compares each with the
    /// model at the current frame temperature (seed 001: a difference over the reference
    /// limit halts the print start).
    pub(super) async fn check(&self) -> anyhow::Result<Checked> {
        // From PRINT_START the macro pauses the print right after asking (a remote call does
        // not wait): wait for the pause, probe, then RESUME on a pass or CANCEL_PRINT on a fail.
        let in_print = self.paused_print().await?;
        let outcome = self.check_points().await;
        if in_print {
            let next = if outcome.is_ok() {
                "RESUME"
            } else {
                "CANCEL_PRINT"
            };
            if let Err(e) = self.core.m().gcode(next).await {
                warn!(error = %e, "{next} after the mesh check failed");
            }
        }
        outcome
    }

    /// Whether a print is paused for the check (waiting up to 20 s for the macro's PAUSE).
    pub(super) async fn paused_print(&self) -> anyhow::Result<bool> {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let st = self
                .core
                .m()
                .objects_query(json!({"print_stats": ["state"]}))
                .await?;
            match st["print_stats"]["state"].as_str().unwrap_or("") {
                "paused" => return Ok(true),
                "printing" if Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(250)).await;
                }
                "printing" => {
                    return Err(user(
                        "a print is running and was not paused for the check: KLIPCAL_MESH_CHECK pauses \
                         the print itself when called from PRINT_START (use klipcal.cfg's macro)",
                    ))
                }
                _ => return Ok(false),
            }
        }
    }

    pub(super) async fn check_points(&self) -> anyhow::Result<Checked> {
        let (s, sel) = self.model()?;
        let params = s
            .params
            .clone()
            .ok_or_else(|| anyhow!("no mesh parameters"))?;
        let temp = self.frame_temp(&s.options.frame_sensor).await?;
        // A print start warms the frame: the heating model.
        let (lo, hi) = sel.heating.fit.range_c;
        let t_model = temp.clamp(lo, hi);
        let predicted = sel.heating.fit.predict(t_model).points_mm;
        self.homed().await?;
        let (xc, yc) = (params.x_count, params.y_count);
        let nodes = [
            (0, 0),
            (xc - 1, 0),
            (0, yc - 1),
            (xc - 1, yc - 1),
            (xc / 2, yc / 2),
        ];
        let at = |i: usize, n: usize, a: f64, b: f64| {
            if n > 1 {
                a + (b - a) * i as f64 / (n - 1) as f64
            } else {
                a
            }
        };
        let cf = self.core.m().configfile().await?;
        let probe = cf.settings.probe.unwrap_or_default();
        let (ox, oy) = (probe.x_offset, probe.y_offset);
        // bed_mesh stores each point as the probe's result less its z_offset: the same here.
        let z_offset = probe.z_offset;
        let mut worst: (f64, String) = (0.0, String::new());
        let mut rows = Vec::new();
        for (ix, iy) in nodes {
            let (x, y) = (
                at(ix, xc, params.min_x, params.max_x),
                at(iy, yc, params.min_y, params.max_y),
            );
            let up = crate::klipper::GcodeCmd::new("G1")
                .axis('Z', 5.0)
                .axis('F', 600.0)
                .build()
                .map_err(|e| anyhow!("{e}"))?;
            let over = crate::klipper::GcodeCmd::new("G1")
                .axis('X', x - ox)
                .axis('Y', y - oy)
                .axis('F', 6000.0)
                .build()
                .map_err(|e| anyhow!("{e}"))?;
            self.core.m().gcode(&format!("G90\n{up}\n{over}")).await?;
            self.core
                .m()
                .gcode_within("PROBE", Duration::from_secs(120))
                .await?;
            let st = self
                .core
                .m()
                .objects_query(json!({"probe": ["last_z_result"]}))
                .await?;
            let z = st["probe"]["last_z_result"]
                .as_f64()
                .ok_or_else(|| anyhow!("probe gave no result"))?
                - z_offset;
            let want = predicted[iy * xc + ix];
            let diff = z - want;
            let label = format!("X{x:.1} Y{y:.1}");
            if diff.abs() > worst.0.abs() {
                worst = (diff, label.clone());
            }
            rows.push(CheckPoint {
                x,
                y,
                probed_mm: z,
                model_mm: want,
                diff_mm: diff,
            });
        }
        let limit = self.settings.reference_limit_mm;
        let clamp_note = if (temp - t_model).abs() > 1e-9 {
            format!(" (frame {temp:.2} °C is outside the captured {lo:.2}–{hi:.2} °C: the model at {t_model:.2} °C was used)")
        } else {
            String::new()
        };
        if worst.0.abs() > limit {
            self.stop_following("the reference check failed").await;
            let msg = format!(
                "{TITLE} check: at {} the bed is {:+.3} mm from the model (limit {limit} mm, \
                 mesh.reference_limit_mm){clamp_note}: a swapped build plate or a loose probe? \
                 The print start is cancelled and following is off until a new KLIPCAL_MESH_CAPTURE",
                worst.1, worst.0
            );
            return Err(user(msg));
        }
        let msg = format!(
            "{TITLE} check passed: largest difference {:+.3} mm at {} (limit {limit} mm){clamp_note}",
            worst.0, worst.1
        );
        Ok(Checked {
            ok_check: true,
            points: rows,
            frame_c: temp,
            message: msg,
        })
    }
}
