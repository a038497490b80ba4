//! The metrology benchmark's targets and its report, each figure beside its target.

use super::{layout_groups, ScenarioReport, COVERAGE_TARGET, UM_PER_100MM};
use crate::calib::metric::Kinematics;

/// The residual target (95th percentile, µm/100 mm) for a direction in a scenario, if any:
/// paper 25 along its measured (motor) directions; full 15 along X, Y and both diagonals.
#[must_use]
pub(super) fn target_um_per_100mm(kin: Kinematics, full: bool, direction: &str) -> Option<f64> {
    let motor = match kin {
        Kinematics::CoreXy => direction.contains("45"),
        Kinematics::Cartesian => direction == "X" || direction == "Y",
    };
    match (full, direction) {
        (_, "shear") => None,
        (true, _) => Some(15.0),
        (false, _) if motor => Some(25.0),
        _ => None,
    }
}

/// Whether every figure with a target meets it.
#[must_use]
pub(crate) fn all_targets_met(reports: &[ScenarioReport]) -> bool {
    reports.iter().all(|r| {
        r.failures == 0
            && r.residual.iter().all(|(name, s)| {
                target_um_per_100mm(r.kinematics, r.full, name).map_or(true, |t| s.p95 <= t)
            })
            && r.crb.iter().all(|c| c.spread <= 1.5 * c.crb)
            && r.coverage.iter().all(|(_, _, h)| coverage_met(*h))
    })
}

/// Whether a coverage lies in [`COVERAGE_TARGET`].
#[must_use]
pub(super) fn coverage_met(c: f64) -> bool {
    (COVERAGE_TARGET.0..=COVERAGE_TARGET.1).contains(&c)
}

/// Human-readable report, each figure beside its target.
#[must_use]
pub(crate) fn format_report(reports: &[ScenarioReport]) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let mark = |ok: bool| if ok { "ok" } else { "MISSED" };
    for r in reports {
        let kin = match r.kinematics {
            Kinematics::CoreXy => "CoreXY",
            Kinematics::Cartesian => "Cartesian",
        };
        let lay = if r.full { "full" } else { "paper" };
        let _ = writeln!(
            s,
            "\n== {kin}, {lay} layout: {} machines, {} solver failure(s)",
            r.machines, r.failures
        );
        let groups: Vec<String> = layout_groups(r.kinematics, r.full)
            .iter()
            .map(|(g, deg)| format!("{g} ({deg:+.0}°)"))
            .collect();
        let _ = writeln!(
            s,
            "  layout: groups {}, D1 {} mm, D2 {} mm; per print: new bed drift, pylon widths, caliper noise",
            groups.join(", "),
            r.d_mm.0,
            r.d_mm.1
        );
        let _ = writeln!(
            s,
            "  residual motion error after one print, µm/100 mm   median     p95   target (p95)"
        );
        for (name, st) in &r.residual {
            let target = target_um_per_100mm(r.kinematics, r.full, name);
            let t = target.map_or_else(
                || "—".to_string(),
                |t| format!("≤ {t:.0}  {}", mark(st.p95 <= t)),
            );
            let _ = writeln!(s, "    {name:<46} {:>7.1} {:>7.1}   {t}", st.median, st.p95);
        }
        let _ = writeln!(
            s,
            "  prints to converge (|α−1| < precision bound): median {:.0}, p95 {:.0}, not converged within the limit: {}",
            r.prints.median, r.prints.p95, r.not_converged
        );
        let _ = writeln!(
            s,
            "  estimate spread vs Cramér–Rao bound (caliper + width scatter + bed drift), µm/100 mm\n    {:<46}  spread     CRB   ratio   target",
            ""
        );
        for c in &r.crb {
            let ratio = c.spread / c.crb;
            let _ = writeln!(
                s,
                "    {:<46} {:>7.2} {:>7.2}   {:>5.2}   ≤ 1.5  {}",
                c.name,
                c.spread * UM_PER_100MM,
                c.crb * UM_PER_100MM,
                ratio,
                mark(ratio <= 1.5)
            );
        }
        let _ = writeln!(
            s,
            "  stated 95 % interval (scale ± 1.96 u) holds the exact correction, first print:\n    {:<46}   ideal   human   target (human)",
            ""
        );
        for (name, ideal, human) in &r.coverage {
            let _ = writeln!(
                s,
                "    {name:<46} {:>6.1} % {:>6.1} %   {:.0}–{:.0} %  {}",
                ideal * 100.0,
                human * 100.0,
                COVERAGE_TARGET.0 * 100.0,
                COVERAGE_TARGET.1 * 100.0,
                mark(coverage_met(*human))
            );
        }
        let _ = writeln!(
            s,
            "  common method (scale from a 100 mm part's outer size), residual µm/100 mm:"
        );
        for (name, st) in &r.common_method {
            let _ = writeln!(
                s,
                "    along {name:<40} median {:>7.1}   p95 {:>7.1}",
                st.median, st.p95
            );
        }
    }
    let _ = writeln!(
        s,
        "\nall targets: {}",
        if all_targets_met(reports) {
            "met"
        } else {
            "NOT met"
        }
    );
    s
}
