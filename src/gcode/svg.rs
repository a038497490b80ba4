//! PURE: the SVG preview of a pylon job — bed outline, pylons, and every measured pair as a
//! dimension line with its label and nominal distance, so a user sees where the calipers go.
//! Text only; ids written into the drawing come from the generator, never from user text.

use std::fmt::Write as _;

use super::plan::Placed;
use super::{Machine, Options};
use crate::layout::Layout;

const COLOURS: [&str; 4] = ["#d9480f", "#1c7ed6", "#2b8a3e", "#862e9c"];

/// Draws the preview; 1 SVG unit = 1 mm, +Y up as on the printer.
pub(crate) fn render(m: &Machine, o: &Options, placed: &Placed, layout: &Layout) -> String {
    let pad = 20.0;
    let (w, h) = (m.x_max_mm - m.x_min_mm, m.y_max_mm - m.y_min_mm);
    let sx = |x: f64| x - m.x_min_mm + pad;
    let sy = |y: f64| m.y_max_mm - y + pad;
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {:.1} {:.1}" width="{:.0}mm" height="{:.0}mm" font-family="sans-serif">"#,
        w + 2.0 * pad,
        h + 2.0 * pad,
        w + 2.0 * pad,
        h + 2.0 * pad
    );
    let _ = writeln!(
        s,
        r##"<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="6" markerHeight="6" orient="auto-start-reverse"><path d="M0,0 L10,5 L0,10 z" fill="#333"/></marker></defs>"##
    );
    let _ = writeln!(
        s,
        r##"<title>klipcal pylons: {} layout, {}, D1 = {} mm, D2 = {} mm</title>"##,
        o.layout.as_str(),
        m.kinematics.as_str(),
        o.d1_mm,
        o.d2_mm
    );
    let _ = writeln!(
        s,
        r##"<rect x="{:.2}" y="{:.2}" width="{w:.2}" height="{h:.2}" fill="#f8f9fa" stroke="#495057" stroke-width="0.8"/>"##,
        sx(m.x_min_mm),
        sy(m.y_max_mm)
    );
    let e = o.edge_margin_mm;
    let _ = writeln!(
        s,
        r##"<rect x="{:.2}" y="{:.2}" width="{:.2}" height="{:.2}" fill="none" stroke="#adb5bd" stroke-width="0.4" stroke-dasharray="3 3"/>"##,
        sx(m.x_min_mm + e),
        sy(m.y_max_mm - e),
        (w - 2.0 * e).max(0.0),
        (h - 2.0 * e).max(0.0)
    );
    let _ = writeln!(
        s,
        r##"<text x="{:.2}" y="{:.2}" font-size="5" fill="#495057">X {}..{}  Y {}..{} mm (printable area)</text>"##,
        sx(m.x_min_mm),
        sy(m.y_min_mm) + 8.0,
        m.x_min_mm,
        m.x_max_mm,
        m.y_min_mm,
        m.y_max_mm
    );
    let t = o.pylon_thickness_mm;
    let l = o.pylon_length_mm;
    for p in &placed.pylons {
        let deg = placed.groups[p.group].direction_deg;
        let colour = COLOURS[p.group % COLOURS.len()];
        let _ = writeln!(
            s,
            r##"<rect x="{:.3}" y="{:.3}" width="{t:.3}" height="{l:.3}" rx="{:.3}" fill="{colour}" fill-opacity="0.75" transform="translate({:.3} {:.3}) rotate({:.3})"><title>{}</title></rect>"##,
            -t / 2.0,
            -l / 2.0,
            t / 2.0,
            sx(p.center[0]),
            sy(p.center[1]),
            -deg,
            p.id
        );
        // the id along the slab, upright, with a halo so it reads on the slab
        let mut text_deg = -(deg + 90.0);
        while text_deg <= -90.0 {
            text_deg += 180.0;
        }
        while text_deg > 90.0 {
            text_deg -= 180.0;
        }
        let _ = writeln!(
            s,
            r##"<text x="0" y="0" font-size="3" text-anchor="middle" dominant-baseline="middle" fill="#212529" stroke="#ffffff" stroke-width="0.6" paint-order="stroke" transform="translate({:.3} {:.3}) rotate({:.3})">{}</text>"##,
            sx(p.center[0]),
            sy(p.center[1]),
            text_deg,
            p.id
        );
    }
    for (k, pair) in layout.pairs.iter().enumerate() {
        let (Some(from), Some(to)) = (
            placed.pylons.iter().find(|p| p.id == pair.from),
            placed.pylons.iter().find(|p| p.id == pair.to),
        ) else {
            continue;
        };
        let u = from.normal;
        let dir = (to.center[0] - from.center[0]) * u[0] + (to.center[1] - from.center[1]) * u[1];
        let sign = if dir >= 0.0 { 1.0 } else { -1.0 };
        let off = l / 2.0 + if k % 2 == 0 { 5.0 } else { 11.0 };
        let a = [
            from.center[0] - sign * t / 2.0 * u[0] + from.axis[0] * off,
            from.center[1] - sign * t / 2.0 * u[1] + from.axis[1] * off,
        ];
        let b = [
            to.center[0] + sign * t / 2.0 * u[0] + to.axis[0] * off,
            to.center[1] + sign * t / 2.0 * u[1] + to.axis[1] * off,
        ];
        let colour = COLOURS[from.group % COLOURS.len()];
        // One group per pair, so a page can highlight the pair being entered.
        let _ = writeln!(s, r##"<g class="pair" data-pair="{}">"##, pair.id);
        for (face, p) in [(a, from), (b, to)] {
            let near = [
                face[0] - p.axis[0] * (off - l / 2.0),
                face[1] - p.axis[1] * (off - l / 2.0),
            ];
            let _ = writeln!(
                s,
                r##"<line x1="{:.3}" y1="{:.3}" x2="{:.3}" y2="{:.3}" stroke="{colour}" stroke-width="0.25"/>"##,
                sx(near[0]),
                sy(near[1]),
                sx(face[0]),
                sy(face[1])
            );
        }
        let _ = writeln!(
            s,
            r##"<line x1="{:.3}" y1="{:.3}" x2="{:.3}" y2="{:.3}" stroke="#333" stroke-width="0.35" marker-start="url(#arrow)" marker-end="url(#arrow)"/>"##,
            sx(a[0]),
            sy(a[1]),
            sx(b[0]),
            sy(b[1])
        );
        let mid = [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
        let _ = writeln!(
            s,
            r##"<text x="{:.2}" y="{:.2}" font-size="4" text-anchor="middle" fill="#212529" stroke="#f8f9fa" stroke-width="0.8" paint-order="stroke">{} {:.2} mm</text>"##,
            sx(mid[0]),
            sy(mid[1]) - 1.5,
            pair.id,
            pair.nominal_mm
        );
        s.push_str("</g>\n");
    }
    s.push_str("</svg>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::super::{generate, Kinematics, LayoutKind, Machine, Options};

    #[test]
    fn the_preview_labels_every_pair_with_its_nominal_distance() {
        let m = Machine {
            z_max_mm: Some(250.0),
            ..Machine::square_bed(Kinematics::CoreXy, 300.0)
        };
        let o = Options {
            layout: LayoutKind::Full,
            ..Options::default()
        };
        let job = generate(&m, &o).expect("fits");
        assert!(job.svg.starts_with("<svg"));
        assert!(job.svg.trim_end().ends_with("</svg>"));
        for pair in &job.layout.pairs {
            let label = format!("{} {:.2} mm", pair.id, pair.nominal_mm);
            assert!(job.svg.contains(&label), "missing {label}");
            let group = format!("<g class=\"pair\" data-pair=\"{}\">", pair.id);
            assert_eq!(job.svg.matches(&group).count(), 1, "{group}");
        }
        assert_eq!(
            job.svg.matches("<g ").count(),
            job.svg.matches("</g>").count()
        );
        assert_eq!(job.svg.matches("<rect x=\"-1.800\"").count(), 12);
    }
}
