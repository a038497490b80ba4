//! `klipcal bench soak`'s part on the real printers' traces (`tests/fixtures/soak/real`).

use std::path::Path;

use crate::calib::soak::SoakParams;

use super::pass;

/// `klipcal bench soak`'s part on the real printers' traces (`tests/fixtures/soak/real`): per
/// trace what the detector did, and whether anything that must hold on any bed failed (a
/// declaration before the band was reached and settled, or out of it). True when nothing did.
pub(super) fn report_real(params: &SoakParams, show_failures: bool) -> bool {
    use crate::cmd::soak_real::{load_dir, run_real, REAL_DIR};
    let traces = match load_dir(Path::new(REAL_DIR)) {
        Ok(t) => t,
        Err(e) => {
            // A missing fixture is a failure, never a pass (issue 24 step 5).
            println!(
                "  real printers: FAIL: the traces are missing ({e}); klipcal bench runs from a \
                 source checkout (cargo run --release -- bench soak)"
            );
            return false;
        }
    };
    println!(
        "  real printers (klippy.log Stats lines at 1 Hz, tests/fixtures/soak/real; a print runs \
         in each hold, so no true moment is known and the power wanders with the print):"
    );
    let mut violations = 0;
    let mut declared = 0;
    for t in &traces {
        let out = run_real(t, params);
        let end = t.samples.last().map_or(0.0, |s| s.t_s);
        let min = |s: Option<f64>| s.map_or("—".to_string(), |v| format!("{:.1} min", v / 60.0));
        let said = match out.declared_s {
            Some(d) => {
                declared += 1;
                format!("declared {:.1} min", d / 60.0)
            }
            None => format!(
                "not declared in {:.1} min (at most {} still to go, bin noise {})",
                end / 60.0,
                out.remaining_upper
                    .filter(|r| r.is_finite())
                    .map_or("—".to_string(), |r| format!("{:.2} %", r * 100.0)),
                out.test_sd
                    .map_or("—".to_string(), |r| format!("{:.2} %", r * 100.0)),
            ),
        };
        println!(
            "    {}: {} °C, {} max_power {:.2}{}; reached the band {}; {said}",
            t.name,
            t.step,
            t.control,
            t.max_power,
            if t.printing { ", printing" } else { "" },
            min(out.reach_s),
        );
        println!("      {}", out.coupling);
        for v in &out.violations {
            violations += 1;
            println!("      {v}");
        }
        if show_failures {
            println!("      {}", out.why);
        }
    }
    println!(
        "    declared on {declared} of {}; declared before settling or out of the band: {violations}   target 0          {}",
        traces.len(),
        pass(violations == 0)
    );
    violations == 0
}
