//! PURE: the plots a user looks at instead of reading numbers — the bed soak (temperature and
//! power over time with the detector's fitted decay) and a calibration's convergence over its
//! rounds — drawn with plotters' SVG backend into a string. Data in, SVG text out; no I/O.

use plotters::prelude::*;
use serde_json::Value;

use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};

/// One heater sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BedSample {
    /// Seconds, any origin (the plot shows minutes from the first sample).
    pub t_s: f64,
    /// °C.
    pub temp_c: f64,
    /// °C.
    pub target_c: f64,
    /// 0..1.
    pub power: f64,
}

/// The detector's fitted decay of the bed power: P(t) = final + remaining · e^(−(t − now)/τ).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DecayCurve {
    /// The time the fit describes as "now" (same origin as the samples).
    pub now_s: f64,
    /// Time constant, s.
    pub tau_s: f64,
    /// Power the decay tends to, 0..1.
    pub final_power: f64,
    /// Power still to fall from now, 0..1.
    pub remaining: f64,
}

/// One round of a calibration: its residual scale error per axis and the uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoundPoint {
    /// 1-based round.
    pub n: u32,
    /// |scale − 1| per axis in µm per 100 mm.
    pub error_um_per_100mm: [f64; 2],
    /// Uncertainty per axis, µm per 100 mm.
    pub uncertainty_um_per_100mm: [f64; 2],
}

const BLUE_: RGBColor = RGBColor(0x1c, 0x7e, 0xd6);
const RED_: RGBColor = RGBColor(0xd9, 0x48, 0x0f);
const GREY: RGBColor = RGBColor(0x86, 0x8e, 0x96);

fn err<E: std::fmt::Display>(e: E) -> String {
    format!("plot: {e}")
}

/// Size of the plots' text (plotters' points): at the plots' 600 px width it stays 10 px or more
/// when a phone shows the picture 360 px wide.
const TEXT_PT: u32 = 22;
/// The soak plot's width and height, px.
pub const SOAK_SIZE: (u32, u32) = (600, 460);

/// The fitted decay as points (minutes from `t0`, power %) from one time constant before the
/// fit's "now" (not before the first sample) to `to_s`; `None` when the fit is not one a bed can
/// have (a power beyond 0..`max_power`, as the detector says early in a soak): nothing is drawn
/// then rather than a line clamped at 100 % or 0 %.
pub fn decay_points(
    fit: &DecayCurve,
    t0: f64,
    to_s: f64,
    max_power: f64,
) -> Option<Vec<(f64, f64)>> {
    let plausible = fit.tau_s > 0.0
        && fit.tau_s.is_finite()
        && (-0.05..=max_power + 0.05).contains(&fit.final_power)
        && (0.0..=max_power).contains(&fit.remaining);
    if !plausible {
        return None;
    }
    let from = (fit.now_s - fit.tau_s).max(t0);
    let n = 120;
    Some(
        (0..=n)
            .map(|i| {
                let t = from + (to_s - from) * f64::from(i) / f64::from(n);
                let p = fit.final_power + fit.remaining * (-(t - fit.now_s) / fit.tau_s).exp();
                ((t - t0) / 60.0, (p * 100.0).clamp(0.0, 100.0))
            })
            .collect(),
    )
}

/// Whether the fitted decay passes through the power it was fitted to: its value now within 5 %
/// of full power of the mean over the last two minutes. A fit whose summary leaves out a decay
/// (the controller's, of the other sign) was once drawn flat at 45 % over a power at 18 %: such a
/// curve is not drawn.
fn fit_meets_data(fit: &DecayCurve, samples: &[BedSample]) -> bool {
    let Some(last) = samples.last() else {
        return false;
    };
    let recent: Vec<f64> = samples
        .iter()
        .filter(|s| s.t_s >= last.t_s - 120.0 && s.power.is_finite())
        .map(|s| s.power)
        .collect();
    if recent.is_empty() {
        return false;
    }
    let mean = recent.iter().sum::<f64>() / recent.len() as f64;
    let at_last = fit.final_power + fit.remaining * (-(last.t_s - fit.now_s) / fit.tau_s).exp();
    (at_last - mean).abs() <= 0.05
}

/// The soak plot: bed temperature and target (left axis, °C) and power (right axis, %) over
/// minutes, with the fitted decay dashed up to `eta_s` past the last sample; the legend in a
/// row under the plot, where it covers no data.
///
/// # Errors
/// No samples, or plotters failed (the message says which).
pub fn soak_svg(
    samples: &[BedSample],
    fit: Option<DecayCurve>,
    eta_s: Option<f64>,
    title: &str,
) -> Result<String, String> {
    let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
        return Err("plot: no bed samples yet".into());
    };
    let t0 = first.t_s;
    // The fitted decay is drawn ahead by the ETA, but never further than the data go back:
    // 6 min of data on a 50 min axis showed nothing (issue 38 item 7).
    let span_s = last.t_s - t0;
    let ahead_s = eta_s.unwrap_or(0.0).clamp(0.0, span_s.max(120.0));
    let x1 = ((last.t_s - t0 + ahead_s) / 60.0).max(1.0);
    let (lo, hi) = temperature_axis(samples)?;
    let max_power = samples
        .iter()
        .map(|s| s.power)
        .filter(|p| p.is_finite())
        .fold(0.0_f64, f64::max)
        .max(0.05);
    let curve = fit
        .filter(|f| fit_meets_data(f, samples))
        .and_then(|f| decay_points(&f, t0, last.t_s + ahead_s, max_power));
    let text = ("sans-serif", TEXT_PT);
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, SOAK_SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        let legend_h = 2 * TEXT_PT + 16;
        let (plot, legend) = root.split_vertically(SOAK_SIZE.1 - legend_h);
        let mut chart = ChartBuilder::on(&plot)
            .caption(title, ("sans-serif", TEXT_PT + 2))
            .margin(8)
            .margin_right(4)
            .x_label_area_size(2 * TEXT_PT + 8)
            .y_label_area_size(2 * TEXT_PT + 14)
            .right_y_label_area_size(2 * TEXT_PT + 10)
            .build_cartesian_2d(0.0..x1, lo..hi)
            .map_err(err)?
            .set_secondary_coord(0.0..x1, 0.0..100.0);
        chart
            .configure_mesh()
            .x_desc("minutes")
            .y_desc("bed °C")
            .x_labels(5)
            .y_labels(5)
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_label_formatter(&|y| format!("{y:.0}"))
            .label_style(text)
            .axis_desc_style(text)
            .light_line_style(WHITE.mix(0.0))
            .draw()
            .map_err(err)?;
        chart
            .configure_secondary_axes()
            .y_desc("power %")
            .y_labels(5)
            .y_label_formatter(&|y| format!("{y:.0}"))
            .label_style(text)
            .axis_desc_style(text)
            .draw()
            .map_err(err)?;
        let minutes = |t: f64| (t - t0) / 60.0;
        chart
            .draw_series(LineSeries::new(
                samples.iter().map(|s| (minutes(s.t_s), s.target_c)),
                GREY.stroke_width(1),
            ))
            .map_err(err)?;
        chart
            .draw_series(LineSeries::new(
                samples.iter().map(|s| (minutes(s.t_s), s.temp_c)),
                RED_.stroke_width(2),
            ))
            .map_err(err)?;
        chart
            .draw_secondary_series(LineSeries::new(
                samples
                    .iter()
                    .map(|s| (minutes(s.t_s), (s.power * 100.0).clamp(0.0, 100.0))),
                BLUE_.stroke_width(1),
            ))
            .map_err(err)?;
        let mut keys: Vec<(String, RGBColor, bool)> = vec![
            ("target °C".into(), GREY, false),
            ("bed °C".into(), RED_, false),
            ("power %".into(), BLUE_, false),
        ];
        if let (Some(points), Some(f)) = (curve, fit) {
            chart
                .draw_secondary_series(DashedLineSeries::new(points, 6, 4, BLACK.stroke_width(2)))
                .map_err(err)?;
            keys.push((
                format!("fitted decay, τ {:.0} min", f.tau_s / 60.0),
                BLACK,
                true,
            ));
        }
        draw_legend(&legend, &keys)?;
        root.present().map_err(err)?;
    }
    Ok(out)
}

/// The bed axis: the temperatures and targets, 2 °C of room each side, whole degrees.
fn temperature_axis(samples: &[BedSample]) -> Result<(f64, f64), String> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for s in samples {
        for v in [s.temp_c, s.target_c] {
            if v.is_finite() {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return Err("plot: no finite temperatures".into());
    }
    Ok(((lo - 2.0).floor(), (hi + 2.0).ceil()))
}

/// The legend: two rows under the plot, a short line (dashed for the fit) and the words for
/// each series.
fn draw_legend(
    area: &DrawingArea<SVGBackend<'_>, plotters::coord::Shift>,
    keys: &[(String, RGBColor, bool)],
) -> Result<(), String> {
    let text = ("sans-serif", TEXT_PT);
    let (w, _) = area.dim_in_pixel();
    let col = i32::try_from(w / 2).unwrap_or(300);
    let row = i32::try_from(TEXT_PT + 6).unwrap_or(28);
    for (k, (words, colour, dashed)) in keys.iter().enumerate() {
        let k = i32::try_from(k).unwrap_or(0);
        let (x, y) = (12 + (k % 2) * col, 6 + (k / 2) * row + row / 2);
        let style = colour.stroke_width(if *dashed { 2 } else { 3 });
        if *dashed {
            for seg in 0..3 {
                area.draw(&PathElement::new(
                    vec![(x + seg * 10, y), (x + seg * 10 + 6, y)],
                    style,
                ))
                .map_err(err)?;
            }
        } else {
            area.draw(&PathElement::new(vec![(x, y), (x + 26, y)], style))
                .map_err(err)?;
        }
        area.draw(&Text::new(
            words.clone(),
            (x + 34, y - i32::try_from(TEXT_PT).unwrap_or(22) * 2 / 5),
            text,
        ))
        .map_err(err)?;
    }
    Ok(())
}

/// The convergence plot: each round's residual scale error per axis with its uncertainty.
///
/// # Errors
/// No solved round, or plotters failed.
pub fn convergence_svg(
    rounds: &[RoundPoint],
    labels: [&str; 2],
    title: &str,
) -> Result<String, String> {
    if rounds.is_empty() {
        return Err("plot: no solved round yet".into());
    }
    let top = rounds
        .iter()
        .flat_map(|r| (0..2).map(move |k| r.error_um_per_100mm[k] + r.uncertainty_um_per_100mm[k]))
        .filter(|v| v.is_finite())
        .fold(1.0_f64, f64::max)
        * 1.15;
    let last = rounds.iter().map(|r| r.n).max().unwrap_or(1);
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (720, 300)).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(32)
            .y_label_area_size(52)
            .build_cartesian_2d(0.5..(f64::from(last) + 0.5), 0.0..top)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("round")
            .y_desc("µm per 100 mm")
            .x_labels(last as usize + 1)
            .x_label_formatter(&|x| format!("{x:.0}"))
            .light_line_style(WHITE.mix(0.0))
            .draw()
            .map_err(err)?;
        for (k, colour) in [(0usize, RED_), (1usize, BLUE_)] {
            let shift = if k == 0 { -0.06 } else { 0.06 };
            let pts: Vec<(f64, f64)> = rounds
                .iter()
                .map(|r| (f64::from(r.n) + shift, r.error_um_per_100mm[k]))
                .collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
                .map_err(err)?
                .label(labels[k])
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], colour));
            chart
                .draw_series(pts.iter().map(|p| Circle::new(*p, 4, colour.filled())))
                .map_err(err)?;
            chart
                .draw_series(rounds.iter().map(|r| {
                    let x = f64::from(r.n) + shift;
                    let (v, u) = (r.error_um_per_100mm[k], r.uncertainty_um_per_100mm[k]);
                    PathElement::new(vec![(x, (v - u).max(0.0)), (x, v + u)], colour)
                }))
                .map_err(err)?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(GREY)
            .draw()
            .map_err(err)?;
        root.present().map_err(err)?;
    }
    Ok(out)
}

/// The convergence plot of an A/B session's status document.
///
/// # Errors
/// No solved round.
pub fn convergence_of_status(doc: &Value) -> Result<String, String> {
    let points: Vec<RoundPoint> = doc["rounds"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|r| {
            let scale = r["scale"].as_array()?;
            let unc = r["uncertainty"].as_array()?;
            let s = |k: usize| scale.get(k).and_then(Value::as_f64);
            let u = |k: usize| unc.get(k).and_then(Value::as_f64);
            Some(RoundPoint {
                n: u32::try_from(r["n"].as_u64()?).ok()?,
                error_um_per_100mm: [(s(0)? - 1.0).abs() * 1e5, (s(1)? - 1.0).abs() * 1e5],
                uncertainty_um_per_100mm: [u(0)? * 1e5, u(1)? * 1e5],
            })
        })
        .collect();
    convergence_svg(
        &points,
        ["stepper_x", "stepper_y"],
        &format!("session {}: scale error per round", doc["id"]),
    )
}

/// Where the current heat-up begins in a series of targets (1 s apart): a minute before the
/// target last changed to the one it has now, so an earlier session's heat-up and cool-down
/// are not drawn (nor fed to the detector); 0 when it never changed.
pub fn current_heat_start(targets: &[f64]) -> usize {
    let Some(now) = targets.iter().rev().find(|t| t.is_finite()).copied() else {
        return 0;
    };
    let changed = targets
        .iter()
        .rposition(|t| t.is_finite() && (t - now).abs() > 0.05)
        .map_or(0, |i| i + 1);
    changed.saturating_sub(60)
}

/// The soak plot's title: the target and the minutes `samples` really span.
#[must_use]
pub fn soak_title(samples: &[BedSample]) -> String {
    let (target, minutes) = match (samples.first(), samples.last()) {
        (Some(a), Some(b)) => (b.target_c, ((b.t_s - a.t_s) / 60.0).max(0.0)),
        _ => (f64::NAN, 0.0),
    };
    format!("bed soak at {target:.0} °C: the last {minutes:.0} min")
}

/// The bed samples of a `server.temperature_store` entry (1 s apart, the last one now) since
/// the current heat-up began ([`current_heat_start`]) and what a soak detector fed with them
/// says: its fitted decay and ETA while soaking.
#[must_use]
pub fn replay_soak(
    bed: &Value,
    params: &SoakParams,
) -> Option<(Vec<BedSample>, Option<DecayCurve>, Option<f64>)> {
    let series = |k: &str| -> Option<Vec<f64>> {
        Some(
            bed[k]
                .as_array()?
                .iter()
                .map(|v| v.as_f64().unwrap_or(f64::NAN))
                .collect(),
        )
    };
    let temps = series("temperatures")?;
    let targets = series("targets").unwrap_or_else(|| vec![f64::NAN; temps.len()]);
    let powers = series("powers").unwrap_or_else(|| vec![0.0; temps.len()]);
    let n = temps.len().min(targets.len()).min(powers.len());
    let start = current_heat_start(&targets[..n]);
    let mut det = SoakDetector::new(params.clone());
    let mut samples = Vec::with_capacity(n - start);
    let mut eta = None;
    for i in start..n {
        let s = BedSample {
            t_s: i as f64,
            temp_c: temps[i],
            target_c: targets[i],
            power: powers[i],
        };
        if [s.temp_c, s.target_c, s.power]
            .iter()
            .all(|v| v.is_finite())
        {
            eta = match det.push(s.t_s, s.power, s.temp_c, s.target_c) {
                SoakStatus::Soaking { eta_s, .. } => eta_s,
                _ => None,
            };
        }
        samples.push(s);
    }
    let fit = det.fit().map(|f| DecayCurve {
        now_s: n.saturating_sub(1) as f64,
        tau_s: f.tau_s,
        final_power: f.final_power,
        remaining: f.remaining,
    });
    Some((samples, fit, eta))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bed(n: usize) -> Vec<BedSample> {
        (0..n)
            .map(|i| {
                let t = i as f64 * 10.0;
                BedSample {
                    t_s: 1000.0 + t,
                    temp_c: 60.0 - 20.0 * (-t / 120.0).exp(),
                    target_c: 60.0,
                    power: 0.3 + 0.4 * (-t / 600.0).exp(),
                }
            })
            .collect()
    }

    #[test]
    fn the_soak_plot_draws_temperature_power_and_the_fitted_decay() {
        let samples = bed(120);
        let fit = DecayCurve {
            now_s: samples.last().unwrap().t_s,
            tau_s: 600.0,
            final_power: 0.3,
            remaining: 0.05,
        };
        let svg = soak_svg(&samples, Some(fit), Some(300.0), "bed soak").unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        for text in [
            "bed soak",
            "bed °C",
            "power %",
            "fitted decay, τ 10 min",
            "minutes",
        ] {
            assert!(svg.contains(text), "missing {text}");
        }
        // Three solid series and the dashed fit are paths or polylines.
        assert!(svg.matches("<polyline").count() + svg.matches("<path").count() >= 4);
        let without = soak_svg(&samples, None, None, "bed soak").unwrap();
        assert!(!without.contains("fitted decay"));
    }

    /// Issue 38 item 7: a fit that does not pass through the power it was fitted to is not
    /// drawn (it showed flat at 45 % over a power at 18 %), and 6 min of data are not drawn on
    /// a 50 min axis.
    #[test]
    fn a_fit_away_from_the_data_is_not_drawn_and_the_axis_fits_the_data() {
        let samples: Vec<BedSample> = (0..36)
            .map(|i| BedSample {
                t_s: f64::from(i) * 10.0,
                temp_c: 60.0,
                target_c: 60.0,
                power: 0.18,
            })
            .collect();
        let flat = DecayCurve {
            now_s: 350.0,
            tau_s: 3600.0,
            final_power: 0.45,
            remaining: 0.0,
        };
        assert!(!fit_meets_data(&flat, &samples));
        let svg = soak_svg(&samples, Some(flat), Some(2640.0), "bed soak").unwrap();
        assert!(!svg.contains("fitted decay"), "drawn");
        // The minute labels stop near twice the data's span, not at 50.
        assert!(
            !svg.contains(">50<") && !svg.contains(">40<"),
            "axis beyond the data"
        );
        let near = DecayCurve {
            final_power: 0.17,
            remaining: 0.01,
            ..flat
        };
        assert!(fit_meets_data(&near, &samples));
    }

    /// A temperature store as Moonraker keeps it (1 Hz): an earlier session's heat-up to 60 °C
    /// and cool-down (20 min), then the current one to 70 °C (38 min).
    fn store_with_an_earlier_session() -> Value {
        let (mut temps, mut targets, mut powers) = (vec![], vec![], vec![]);
        for i in 0..1200 {
            let t = f64::from(i);
            let on = i < 600;
            temps.push(if on {
                60.0
            } else {
                25.0 + 35.0 * (-(t - 600.0) / 300.0).exp()
            });
            targets.push(if on { 60.0 } else { 0.0 });
            powers.push(if on { 0.3 } else { 0.0 });
        }
        for i in 0..(38 * 60) {
            let t = f64::from(i);
            temps.push(70.0 - 45.0 * (-t / 200.0).exp());
            targets.push(70.0);
            powers.push(if t < 400.0 {
                1.0
            } else {
                0.3 + 0.3 * (-(t - 400.0) / 600.0).exp()
            });
        }
        serde_json::json!({"temperatures": temps, "targets": targets, "powers": powers})
    }

    #[test]
    fn the_soak_plot_shows_the_current_heat_up_only_and_says_the_span_it_shows() {
        let (samples, _, _) =
            replay_soak(&store_with_an_earlier_session(), &SoakParams::default()).unwrap();
        assert!(
            samples.iter().all(|s| s.target_c != 60.0),
            "the earlier session's heat-up is drawn"
        );
        assert_eq!(samples.iter().filter(|s| s.target_c == 0.0).count(), 60);
        // 38 min of the current heat-up and the minute before it.
        assert_eq!(soak_title(&samples), "bed soak at 70 °C: the last 39 min");
        let svg = soak_svg(&samples, None, None, &soak_title(&samples)).unwrap();
        assert!(svg.contains("the last 39 min"));
        // A store that never changed target: all of it.
        let flat = serde_json::json!({"temperatures": vec![60.0; 300], "targets": vec![60.0; 300], "powers": vec![0.3; 300]});
        let (all, _, _) = replay_soak(&flat, &SoakParams::default()).unwrap();
        assert_eq!(all.len(), 300);
    }

    #[test]
    fn the_fitted_decay_is_drawn_as_a_curve_or_not_at_all() {
        // What the detector fits early on a real bed (burneypromod-voron2-4-1, max_power 0.6):
        // a power the heater cannot give. The old plot clamped it into a line at 100 %.
        let wild = DecayCurve {
            now_s: 2541.0,
            tau_s: 317.7,
            final_power: 8.22,
            remaining: 0.0,
        };
        assert_eq!(decay_points(&wild, 0.0, 4000.0, 0.6), None);
        let fit = DecayCurve {
            now_s: 2000.0,
            tau_s: 600.0,
            final_power: 0.3,
            remaining: 0.05,
        };
        let pts = decay_points(&fit, 0.0, 3000.0, 0.6).unwrap();
        assert!(pts.windows(2).all(|w| w[1].1 < w[0].1), "falls throughout");
        // From 0.3 + 0.05·e at now − τ to near 0.3: within what the bed's power does.
        assert!(pts.iter().all(|p| (30.0..=43.6).contains(&p.1)), "{pts:?}");
        assert!(
            (pts[0].0 - 1400.0 / 60.0).abs() < 1e-9,
            "starts one τ before now"
        );
    }

    /// The font sizes of an SVG's texts, px, and each text's y and words.
    fn texts(svg: &str) -> Vec<(f64, f64, String)> {
        svg.split("<text ")
            .skip(1)
            .map(|t| {
                let num = |k: &str| -> f64 {
                    let key = format!(" {k}=\"");
                    let at = format!(" {t}").find(&key).unwrap() + key.len() - 1;
                    let rest = &t[at..];
                    rest[..rest.find('"').unwrap()].parse().unwrap()
                };
                let words = t[t.find('>').unwrap() + 1..t.find('<').unwrap()]
                    .trim()
                    .to_string();
                (num("font-size"), num("y"), words)
            })
            .collect()
    }

    #[test]
    fn the_soak_plot_reads_on_a_phone_and_its_legend_covers_no_data() {
        let samples = bed(240);
        let fit = DecayCurve {
            now_s: samples.last().unwrap().t_s,
            tau_s: 600.0,
            final_power: 0.3,
            remaining: 0.05,
        };
        let svg = soak_svg(&samples, Some(fit), Some(300.0), "bed soak").unwrap();
        let width: f64 = svg
            .split("width=\"")
            .nth(1)
            .and_then(|r| r.split('"').next())
            .unwrap()
            .parse()
            .unwrap();
        let all = texts(&svg);
        assert!(all.len() > 10);
        for (size, _, words) in &all {
            let phone = size * 360.0 / width;
            assert!(
                phone >= 10.0,
                "'{words}' is {phone:.1} px on a 360 px wide phone"
            );
        }
        // The legend stands under the x axis's "minutes", outside the plotted area.
        let axis_y = all.iter().find(|t| t.2 == "minutes").unwrap().1;
        for key in ["target °C", "bed °C", "power %", "fitted decay, τ 10 min"] {
            // (the last text of those words: "bed °C" also names the left axis)
            let (_, y, _) = all
                .iter()
                .rfind(|t| t.2 == key)
                .unwrap_or_else(|| panic!("no legend entry {key}"));
            assert!(
                *y > axis_y,
                "the legend entry {key} at y {y}, inside the plot"
            );
        }
    }

    #[test]
    fn a_plot_without_data_says_so_instead_of_drawing_nothing() {
        assert!(soak_svg(&[], None, None, "x")
            .unwrap_err()
            .contains("no bed samples"));
        assert!(convergence_svg(&[], ["A", "B"], "x")
            .unwrap_err()
            .contains("no solved round"));
    }

    #[test]
    fn the_convergence_plot_has_a_point_per_round_and_axis() {
        let rounds = [
            RoundPoint {
                n: 1,
                error_um_per_100mm: [210.0, 150.0],
                uncertainty_um_per_100mm: [12.0, 12.0],
            },
            RoundPoint {
                n: 2,
                error_um_per_100mm: [8.0, 5.0],
                uncertainty_um_per_100mm: [11.0, 11.0],
            },
        ];
        let svg = convergence_svg(&rounds, ["stepper_x", "stepper_y"], "rounds").unwrap();
        assert_eq!(svg.matches("<circle").count(), 4, "{svg}");
        assert!(svg.contains("stepper_x") && svg.contains("µm per 100 mm"));
    }
}

/// The font PNG text is drawn with: a subset of DejaVu Sans (assets/fonts/LICENSE), embedded so
/// a picture looks the same on a printer host without fonts.
const PNG_FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans-klipcal-subset.ttf");
const PNG_FONT_FAMILY: &str = "DejaVu Sans";

/// Width of the PNG twins of klipcal's pictures, px: readable on a phone, a few MB while drawn.
pub const PNG_WIDTH_PX: u32 = 900;

/// An SVG picture (one of klipcal's) drawn as PNG, `width_px` wide, the height from the
/// picture's aspect ratio, on white; text in the embedded font whatever family it names.
///
/// # Errors
/// SVG text resvg cannot read, a width of 0 or above 8000 px, or a picture that would be taller
/// than 8000 px.
pub fn svg_to_png(svg: &str, width_px: u32) -> anyhow::Result<Vec<u8>> {
    use resvg::{tiny_skia, usvg};
    if !(1..=8000).contains(&width_px) {
        anyhow::bail!("PNG width {width_px} px; expected 1..8000");
    }
    let mut opt = usvg::Options::default();
    {
        let db = opt.fontdb_mut();
        db.load_font_data(PNG_FONT.to_vec());
        db.set_sans_serif_family(PNG_FONT_FAMILY);
        db.set_serif_family(PNG_FONT_FAMILY);
        db.set_monospace_family(PNG_FONT_FAMILY);
    }
    opt.font_family = PNG_FONT_FAMILY.to_string();
    let tree = usvg::Tree::from_str(svg, &opt)
        .map_err(|e| anyhow::anyhow!("the picture's SVG does not read: {e}"))?;
    let size = tree.size();
    let scale = width_px as f32 / size.width();
    let height = (size.height() * scale).ceil();
    if !(height.is_finite() && (1.0..=8000.0).contains(&height)) {
        anyhow::bail!("the picture would be {height} px tall at {width_px} px wide");
    }
    let mut pixmap = tiny_skia::Pixmap::new(width_px, height as u32)
        .ok_or_else(|| anyhow::anyhow!("no {width_px}×{height} px image"))?;
    pixmap.fill(tiny_skia::Color::WHITE);
    resvg::render(
        &tree,
        tiny_skia::Transform::from_scale(scale, scale),
        &mut pixmap.as_mut(),
    );
    pixmap
        .encode_png()
        .map_err(|e| anyhow::anyhow!("encoding the PNG: {e}"))
}

#[cfg(test)]
mod png_tests {
    use super::*;
    use resvg::tiny_skia::Pixmap;

    fn dark_pixels(png: &[u8]) -> (u32, u32, usize) {
        let p = Pixmap::decode_png(png).expect("a PNG");
        let dark = p
            .pixels()
            .iter()
            .filter(|c| u32::from(c.red()) + u32::from(c.green()) + u32::from(c.blue()) < 300)
            .count();
        (p.width(), p.height(), dark)
    }

    #[test]
    fn text_is_drawn_with_the_embedded_font_whatever_family_the_svg_names() {
        let blank = r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 100 50"></svg>"#;
        let (w, h, dark) = dark_pixels(&svg_to_png(blank, 400).unwrap());
        assert_eq!((w, h, dark), (400, 200, 0));
        for family in ["sans-serif", "Helvetica, Arial", "monospace", "NoSuchFont"] {
            let svg = format!(
                r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 100 50"><text x="5" y="30" font-size="20" font-family="{family}" fill="black">A1 ✓ τ</text></svg>"#
            );
            let (_, _, dark) = dark_pixels(&svg_to_png(&svg, 400).unwrap());
            assert!(
                dark > 500,
                "{family}: {dark} dark pixels, the text is missing"
            );
        }
    }

    #[test]
    fn the_pylon_layout_renders_at_the_picture_width_and_its_aspect_ratio() {
        use crate::gcode::{generate, Kinematics, Machine, Options};
        let m = Machine {
            z_max_mm: Some(250.0),
            ..Machine::square_bed(Kinematics::CoreXy, 300.0)
        };
        let job = generate(&m, &Options::default()).unwrap();
        let png = svg_to_png(&job.svg, PNG_WIDTH_PX).unwrap();
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
        let (w, h, dark) = dark_pixels(&png);
        assert_eq!(w, PNG_WIDTH_PX);
        let vb: Vec<f32> = job
            .svg
            .split("viewBox=\"")
            .nth(1)
            .and_then(|r| r.split('"').next())
            .unwrap()
            .split_whitespace()
            .map(|v| v.parse().unwrap())
            .collect();
        let want_h = (vb[3] / vb[2] * PNG_WIDTH_PX as f32).ceil() as u32;
        assert_eq!(h, want_h);
        assert!(dark > 2000, "labels and outlines drawn: {dark}");
    }

    #[test]
    fn bad_svg_and_sizes_are_refused_not_panicked_on() {
        assert!(svg_to_png("<svg", 400).is_err());
        assert!(svg_to_png("not xml at all", 400).is_err());
        let ok = r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 10 10"></svg>"#;
        assert!(svg_to_png(ok, 0).is_err());
        assert!(svg_to_png(ok, 9000).is_err());
        let tall = r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 1 100"></svg>"#;
        assert!(svg_to_png(tall, 400).is_err());
    }
}
