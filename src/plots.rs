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

/// The soak plot: bed temperature and target (left axis, °C) and power (right axis, %) over
/// minutes, with the fitted decay dashed up to `eta_s` past the last sample.
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
    let ahead_s = eta_s.unwrap_or(0.0).clamp(0.0, 3600.0);
    let x1 = ((last.t_s - t0 + ahead_s) / 60.0).max(1.0);
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
    let (lo, hi) = ((lo - 2.0).floor(), (hi + 2.0).ceil());
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (720, 340)).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(32)
            .y_label_area_size(44)
            .right_y_label_area_size(44)
            .build_cartesian_2d(0.0..x1, lo..hi)
            .map_err(err)?
            .set_secondary_coord(0.0..x1, 0.0..100.0);
        chart
            .configure_mesh()
            .x_desc("minutes")
            .y_desc("bed °C")
            .light_line_style(WHITE.mix(0.0))
            .draw()
            .map_err(err)?;
        chart
            .configure_secondary_axes()
            .y_desc("bed power %")
            .draw()
            .map_err(err)?;
        let minutes = |t: f64| (t - t0) / 60.0;
        chart
            .draw_series(LineSeries::new(
                samples.iter().map(|s| (minutes(s.t_s), s.target_c)),
                GREY.stroke_width(1),
            ))
            .map_err(err)?
            .label("target °C")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], GREY));
        chart
            .draw_series(LineSeries::new(
                samples.iter().map(|s| (minutes(s.t_s), s.temp_c)),
                RED_.stroke_width(2),
            ))
            .map_err(err)?
            .label("bed °C")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], RED_));
        chart
            .draw_secondary_series(LineSeries::new(
                samples
                    .iter()
                    .map(|s| (minutes(s.t_s), (s.power * 100.0).clamp(0.0, 100.0))),
                BLUE_.stroke_width(1),
            ))
            .map_err(err)?
            .label("power %")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLUE_));
        if let Some(f) = fit.filter(|f| f.tau_s > 0.0 && f.tau_s.is_finite()) {
            let from = (f.now_s - 3.0 * f.tau_s).max(t0);
            let to = last.t_s + ahead_s;
            let n = 120;
            let curve: Vec<(f64, f64)> = (0..=n)
                .map(|i| {
                    let t = from + (to - from) * f64::from(i) / f64::from(n);
                    let p = f.final_power + f.remaining * (-(t - f.now_s) / f.tau_s).exp();
                    (minutes(t), (p * 100.0).clamp(0.0, 100.0))
                })
                .collect();
            chart
                .draw_secondary_series(DashedLineSeries::new(curve, 6, 4, BLACK.stroke_width(1)))
                .map_err(err)?
                .label(format!("fitted decay, τ {:.0} min", f.tau_s / 60.0))
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(GREY)
            .position(SeriesLabelPosition::LowerRight)
            .draw()
            .map_err(err)?;
        root.present().map_err(err)?;
    }
    Ok(out)
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

/// The bed samples of a `server.temperature_store` entry (1 s apart, the last one now) and
/// what a soak detector fed with them says: its fitted decay and ETA while soaking.
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
    let mut det = SoakDetector::new(params.clone());
    let mut samples = Vec::with_capacity(n);
    let mut eta = None;
    for i in 0..n {
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
