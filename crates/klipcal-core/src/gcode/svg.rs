//! PURE: the SVG preview of a pylon job — the pylons and every measured pair as a dimension
//! line — drawn to be read on a phone: the drawing shows the pylons' part of the bed, every
//! text is the same size (1/30 of the drawing's width), horizontal, and stands where it
//! touches no line, pylon or other text; each pylon's name stands beside its own pylon; under
//! the drawing stand the printer's front, the nominal distances, and a map of the bed with the
//! origin and the part drawn. Text only; ids written into the drawing come from the generator,
//! never from user text.

use std::fmt::Write as _;

use super::plan::Placed;
use super::{Machine, Options};
use crate::layout::Layout;

const COLOURS: [&str; 4] = ["#d9480f", "#1c7ed6", "#2b8a3e", "#862e9c"];

/// The drawing's width in text sizes: 30 draws the texts 30 px tall in the 900 px PNG, 12 px
/// when a phone shows the picture 360 px wide.
const WIDTH_IN_TEXTS: f64 = 30.0;

type P = [f64; 2];

/// An axis-aligned box in SVG coordinates (y down).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TextBox {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

impl TextBox {
    fn around(c: P, w: f64, h: f64) -> Self {
        TextBox {
            x0: c[0] - w / 2.0,
            y0: c[1] - h / 2.0,
            x1: c[0] + w / 2.0,
            y1: c[1] + h / 2.0,
        }
    }
    pub fn overlaps(&self, o: &TextBox) -> bool {
        self.x0 < o.x1 && o.x0 < self.x1 && self.y0 < o.y1 && o.y0 < self.y1
    }
    fn inside(&self, o: &TextBox) -> bool {
        self.x0 >= o.x0 && self.x1 <= o.x1 && self.y0 >= o.y0 && self.y1 <= o.y1
    }
    fn corners(&self) -> [P; 4] {
        [
            [self.x0, self.y0],
            [self.x1, self.y0],
            [self.x1, self.y1],
            [self.x0, self.y1],
        ]
    }
    /// Whether the segment a–b touches the box.
    pub fn hits_segment(&self, a: P, b: P) -> bool {
        // Liang–Barsky clipping of the segment against the box.
        let d = [b[0] - a[0], b[1] - a[1]];
        let (mut t0, mut t1) = (0.0_f64, 1.0_f64);
        for (p, q) in [
            (-d[0], a[0] - self.x0),
            (d[0], self.x1 - a[0]),
            (-d[1], a[1] - self.y0),
            (d[1], self.y1 - a[1]),
        ] {
            if p == 0.0 {
                if q < 0.0 {
                    return false;
                }
            } else {
                let r = q / p;
                if p < 0.0 {
                    t0 = t0.max(r);
                } else {
                    t1 = t1.min(r);
                }
                if t0 > t1 {
                    return false;
                }
            }
        }
        true
    }
    /// Distance from the segment a–b to the box, 0 when they touch.
    pub fn distance_to_segment(&self, a: P, b: P) -> f64 {
        if self.hits_segment(a, b) {
            return 0.0;
        }
        let to_box = |p: P| {
            let dx = (self.x0 - p[0]).max(p[0] - self.x1).max(0.0);
            let dy = (self.y0 - p[1]).max(p[1] - self.y1).max(0.0);
            dx.hypot(dy)
        };
        self.corners()
            .into_iter()
            .map(|c| point_to_segment(c, a, b))
            .chain([to_box(a), to_box(b)])
            .fold(f64::INFINITY, f64::min)
    }
}

fn point_to_segment(p: P, a: P, b: P) -> f64 {
    let d = [b[0] - a[0], b[1] - a[1]];
    let len2 = d[0] * d[0] + d[1] * d[1];
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * d[0] + (p[1] - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p[0] - a[0] - t * d[0]).hypot(p[1] - a[1] - t * d[1])
}

/// Width of `text` in em of DejaVu Sans (the PNG's font), rounded up: an upper bound also for
/// the narrower sans-serif fonts a browser draws the inline SVG with.
pub fn text_em(text: &str) -> f64 {
    text.chars()
        .map(|c| match c {
            'I' | 'i' | 'j' | 'l' | '|' => 0.32,
            ' ' | '.' | ',' | ':' | ';' | '\'' => 0.34,
            '-' | '(' | ')' | 'f' | 'r' | 't' => 0.42,
            'M' | 'W' | 'm' | 'w' | '—' => 1.0,
            '0'..='9' => 0.66,
            'a'..='z' => 0.64,
            _ => 0.8,
        })
        .sum()
}

/// What labels must keep clear of, in SVG coordinates.
#[derive(Default)]
struct Obstacles {
    segments: Vec<(P, P)>,
    /// Pylon footprints: the core segment and the half thickness.
    slabs: Vec<(P, P, f64)>,
    boxes: Vec<TextBox>,
}

impl Obstacles {
    fn collisions(&self, b: &TextBox) -> usize {
        self.segments
            .iter()
            .filter(|(p, q)| b.hits_segment(*p, *q))
            .count()
            + self
                .slabs
                .iter()
                .filter(|(p, q, r)| b.distance_to_segment(*p, *q) < *r)
                .count()
            + self.boxes.iter().filter(|o| b.overlaps(o)).count()
    }
}

/// The box of size `w`×`h`, centred on a grid point of `region` (step `step`), that lies in
/// `bounds`, touches nothing and costs least (`cost` refuses a box with `None`); else, when no
/// box is free, the one touching the fewest things (the picture's tests then fail), and
/// whether it is free.
fn place(
    obstacles: &Obstacles,
    bounds: &TextBox,
    (w, h): (f64, f64),
    region: &TextBox,
    step: f64,
    cost: &dyn Fn(&TextBox) -> Option<f64>,
) -> (TextBox, bool) {
    let mut best: Option<(usize, f64, TextBox)> = None;
    let nx = ((region.x1 - region.x0) / step).ceil().max(0.0) as usize;
    let ny = ((region.y1 - region.y0) / step).ceil().max(0.0) as usize;
    for i in 0..=nx {
        for j in 0..=ny {
            let c = [region.x0 + i as f64 * step, region.y0 + j as f64 * step];
            let b = TextBox::around(c, w, h);
            if !b.inside(bounds) {
                continue;
            }
            let k = cost(&b);
            if let (Some((0, bk, _)), Some(k)) = (best, k) {
                if k >= bk {
                    continue;
                }
            }
            let (n, k) = match k {
                Some(k) => (obstacles.collisions(&b), k),
                None if best.map_or(true, |(m, _, _)| m > 0) => {
                    (obstacles.collisions(&b) + 1, f64::INFINITY)
                }
                None => continue,
            };
            if best.map_or(true, |(m, bk, _)| n < m || (n == m && k < bk)) {
                best = Some((n, k, b));
            }
        }
    }
    best.map_or_else(
        || {
            let c = [(region.x0 + region.x1) / 2.0, (region.y0 + region.y1) / 2.0];
            (TextBox::around(c, w, h), false)
        },
        |(n, _, b)| (b, n == 0),
    )
}

fn unit(v: P) -> P {
    let n = v[0].hypot(v[1]);
    if n > 0.0 {
        [v[0] / n, v[1] / n]
    } else {
        [1.0, 0.0]
    }
}

/// Draws the preview; 1 SVG unit = 1 mm, +Y up as on the printer, the front (Y min) at the
/// bottom. The drawing shows the pylons' part of the bed (so they and their texts are large);
/// under it stand the front, the nominal distances, and a map of the whole bed with the origin
/// and the part drawn.
pub fn render(m: &Machine, o: &Options, placed: &Placed, layout: &Layout) -> String {
    let pairings = pairings(o, placed, layout);
    let fr = Frame::new(m, o, placed, &pairings);
    let mut obstacles = fr.obstacles(m, o, placed, &pairings);
    let names = fr.place_names(placed, o.pylon_length_mm, &mut obstacles);
    let pair_ids = fr.place_pair_ids(&pairings, &mut obstacles);
    let entries: Vec<String> = pairings.iter().map(|q| entry(layout, q)).collect();
    let (front, legend, y) = fr.legend(&pairings, &entries);
    let map = BedMap::new(m, &fr, y);
    let width = fr.width.max(map.area_box.x1 + 0.5 * fr.f);
    let height = map.origin_box.y1.max(map.map.y1).max(map.area_box.y1) + 0.5 * fr.f;

    let mut s = String::new();
    fr.write_head(&mut s, m, o, width, height);
    fr.write_pylons(&mut s, o, placed, &names);
    for (i, q) in pairings.iter().enumerate() {
        fr.write_pair(&mut s, q, &pair_ids[i], &entries[i], &legend[i]);
    }
    let _ = writeln!(
        s,
        "{}",
        text_element("FRONT", &front, fr.f, "#212529", "front")
    );
    map.write(&mut s, m, &fr, width);
    s.push_str("</svg>\n");
    s
}

/// One measured pair as drawn, in printer millimetres.
struct Pairing {
    id: String,
    group: usize,
    a: P,
    b: P,
    /// The two extension lines, pylon end → arrow end.
    ext: [(P, P); 2],
}

/// Each pair's dimension line, from the outer face of one pylon to the outer face of the
/// other, past the pylons' ends (the short pair's outside the long one's).
fn pairings(o: &Options, placed: &Placed, layout: &Layout) -> Vec<Pairing> {
    let t = o.pylon_thickness_mm;
    let l = o.pylon_length_mm;
    let mut pairings: Vec<Pairing> = Vec::new();
    for pair in &layout.pairs {
        let (Some(from), Some(to)) = (
            placed.pylons.iter().find(|p| p.id == pair.from),
            placed.pylons.iter().find(|p| p.id == pair.to),
        ) else {
            continue;
        };
        let u = from.normal;
        let along = (to.center[0] - from.center[0]) * u[0] + (to.center[1] - from.center[1]) * u[1];
        let sign = if along >= 0.0 { 1.0 } else { -1.0 };
        // the short (D1) pair's line outside the long one's, so its id has room past the end
        let short = (pair.nominal_mm - o.d1_mm).abs() < (pair.nominal_mm - o.d2_mm).abs();
        let off = l / 2.0 + if short { 11.0 } else { 5.0 };
        let a = [
            from.center[0] - sign * t / 2.0 * u[0] + from.axis[0] * off,
            from.center[1] - sign * t / 2.0 * u[1] + from.axis[1] * off,
        ];
        let b = [
            to.center[0] + sign * t / 2.0 * u[0] + to.axis[0] * off,
            to.center[1] + sign * t / 2.0 * u[1] + to.axis[1] * off,
        ];
        let near = |face: P, p: &super::plan::PlacedPylon| {
            [
                face[0] - p.axis[0] * (off - l / 2.0),
                face[1] - p.axis[1] * (off - l / 2.0),
            ]
        };
        pairings.push(Pairing {
            id: pair.id.clone(),
            group: from.group,
            a,
            b,
            ext: [(near(a, from), a), (near(b, to), b)],
        });
    }
    pairings
}

/// A pair's entry in the legend: its id and nominal distance.
fn entry(layout: &Layout, q: &Pairing) -> String {
    let nominal = layout
        .pairs
        .iter()
        .find(|p| p.id == q.id)
        .map_or(f64::NAN, |p| p.nominal_mm);
    format!("{} {nominal:.2} mm", q.id)
}

/// The drawing's frame: the part of the bed drawn (printer millimetres) and the text size.
struct Frame {
    /// The drawn part's lower left and upper right corners, printer mm.
    lo: P,
    hi: P,
    /// The text size, SVG units.
    f: f64,
    /// The drawing's width and height, SVG units.
    width: f64,
    draw_h: f64,
}

impl Frame {
    /// The pylons and the pairs' lines, with 2.5 texts of room on each side; the text
    /// 1/WIDTH_IN_TEXTS of the drawing's width.
    fn new(m: &Machine, o: &Options, placed: &Placed, pairings: &[Pairing]) -> Frame {
        let t = o.pylon_thickness_mm;
        let l = o.pylon_length_mm;
        let mut pts: Vec<P> = Vec::new();
        for p in &placed.pylons {
            for (sa, sn) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                pts.push([
                    p.center[0] + p.axis[0] * sa * l / 2.0 + p.normal[0] * sn * t / 2.0,
                    p.center[1] + p.axis[1] * sa * l / 2.0 + p.normal[1] * sn * t / 2.0,
                ]);
            }
        }
        for q in pairings {
            pts.extend([q.a, q.b, q.ext[0].0, q.ext[1].0]);
        }
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in &pts {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        if pts.is_empty() {
            (lo, hi) = ([m.x_min_mm, m.y_min_mm], [m.x_max_mm, m.y_max_mm]);
        }
        // the text size: 1/WIDTH_IN_TEXTS of the drawing's width, the drawing the content plus
        // 2.5 texts of room on each side
        let f = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(20.0) / (WIDTH_IN_TEXTS - 5.0);
        let margin = 2.5 * f;
        let (lo, hi) = (
            [lo[0] - margin, lo[1] - margin],
            [hi[0] + margin, hi[1] + margin],
        );
        let width = (hi[0] - lo[0]).max(WIDTH_IN_TEXTS * f);
        let lo = [(lo[0] + hi[0] - width) / 2.0, lo[1]];
        let draw_h = hi[1] - lo[1];
        Frame {
            lo,
            hi,
            f,
            width,
            draw_h,
        }
    }
    fn sx(&self, x: f64) -> f64 {
        x - self.lo[0]
    }
    fn sy(&self, y: f64) -> f64 {
        self.hi[1] - y
    }
    fn at(&self, p: P) -> P {
        [self.sx(p[0]), self.sy(p[1])]
    }
    fn box_h(&self) -> f64 {
        1.02 * self.f
    }
    fn text_box(&self, text: &str) -> (f64, f64) {
        (text_em(text) * self.f + 0.3 * self.f, self.box_h())
    }
    fn stroke(&self) -> f64 {
        0.06 * self.f
    }
    fn bed(&self, m: &Machine) -> TextBox {
        TextBox {
            x0: self.sx(m.x_min_mm),
            y0: self.sy(m.y_max_mm),
            x1: self.sx(m.x_max_mm),
            y1: self.sy(m.y_min_mm),
        }
    }
    fn view(&self) -> TextBox {
        TextBox {
            x0: 0.0,
            y0: 0.0,
            x1: self.width,
            y1: self.draw_h,
        }
    }

    /// What the texts keep clear of: the bed's edges, the pylons, the pairs' lines.
    fn obstacles(
        &self,
        m: &Machine,
        o: &Options,
        placed: &Placed,
        pairings: &[Pairing],
    ) -> Obstacles {
        let mut obstacles = Obstacles::default();
        let bed = self.bed(m);
        obstacles.segments.extend([
            ([bed.x0, bed.y0], [bed.x1, bed.y0]),
            ([bed.x1, bed.y0], [bed.x1, bed.y1]),
            ([bed.x1, bed.y1], [bed.x0, bed.y1]),
            ([bed.x0, bed.y1], [bed.x0, bed.y0]),
        ]);
        let t = o.pylon_thickness_mm;
        for p in &placed.pylons {
            let (a, b) = p.core(o.pylon_length_mm, t);
            obstacles
                .slabs
                .push((self.at(a), self.at(b), t / 2.0 + 0.1 * self.f));
        }
        for q in pairings {
            obstacles.segments.push((self.at(q.a), self.at(q.b)));
            obstacles
                .segments
                .extend(q.ext.iter().map(|(x, y)| (self.at(*x), self.at(*y))));
        }
        obstacles
    }

    /// Each pylon's name beside it: the free spot nearest to it, nearer to it than to any
    /// other pylon, preferring its middle to its ends.
    fn place_names(&self, placed: &Placed, l: f64, obstacles: &mut Obstacles) -> Vec<TextBox> {
        let f = self.f;
        let step = 0.25 * f;
        let view = self.view();
        let slabs_at = obstacles.slabs.clone();
        let mut names: Vec<TextBox> = Vec::new();
        for (i, p) in placed.pylons.iter().enumerate() {
            let size = self.text_box(&p.id);
            let c = self.at(p.center);
            let ax = unit([p.axis[0], -p.axis[1]]);
            // nearest first; farther only when nothing near is free
            let mut bx = None;
            for limit in [1.5 * f, 3.0 * f] {
                let reach = l / 2.0 + limit + size.0;
                let region = TextBox::around(c, 2.0 * reach, 2.0 * reach);
                let cost = |b: &TextBox| {
                    let d = |k: usize| {
                        b.distance_to_segment(slabs_at[k].0, slabs_at[k].1) - slabs_at[k].2
                    };
                    let mine = d(i);
                    let clear = (0..slabs_at.len()).all(|k| k == i || d(k) > mine + 0.2 * f);
                    let centre = [(b.x0 + b.x1) / 2.0 - c[0], (b.y0 + b.y1) / 2.0 - c[1]];
                    let along = (centre[0] * ax[0] + centre[1] * ax[1]).abs();
                    (clear && mine <= limit).then_some(mine + 0.1 * along)
                };
                let (b, free) = place(obstacles, &view, size, &region, step, &cost);
                bx = Some(b);
                if free {
                    break;
                }
            }
            let bx = bx.unwrap_or_else(|| TextBox::around(c, size.0, size.1));
            obstacles.boxes.push(bx);
            names.push(bx);
        }
        names
    }

    /// Each pair's id beside its arrow: the free spot nearest to it, nearer to it than to any
    /// other arrow, preferring its middle.
    fn place_pair_ids(&self, pairings: &[Pairing], obstacles: &mut Obstacles) -> Vec<TextBox> {
        let f = self.f;
        let step = 0.25 * f;
        let view = self.view();
        let arrows: Vec<(P, P)> = pairings
            .iter()
            .map(|q| (self.at(q.a), self.at(q.b)))
            .collect();
        let mut pair_ids: Vec<TextBox> = Vec::new();
        for (i, q) in pairings.iter().enumerate() {
            let size = self.text_box(&q.id);
            let (a, b) = arrows[i];
            let mid = [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
            let along = unit([b[0] - a[0], b[1] - a[1]]);
            let mut bx = None;
            // near and unambiguous first; then farther; last, nearer to it than to any other
            // group's arrow (the same group's other arrow starts at the same face: the
            // legend's distances and the pylon names tell the two apart)
            for (limit, all) in [(2.0 * f, true), (3.5 * f, true), (3.5 * f, false)] {
                let region = TextBox {
                    x0: a[0].min(b[0]) - limit - size.0,
                    y0: a[1].min(b[1]) - limit - size.1,
                    x1: a[0].max(b[0]) + limit + size.0,
                    y1: a[1].max(b[1]) + limit + size.1,
                };
                let cost = |bx: &TextBox| {
                    let mine = bx.distance_to_segment(a, b);
                    let clear = (0..arrows.len()).all(|k| {
                        k == i
                            || (!all && pairings[k].group == q.group)
                            || bx.distance_to_segment(arrows[k].0, arrows[k].1) > mine + 0.05 * f
                    });
                    let centre = [
                        (bx.x0 + bx.x1) / 2.0 - mid[0],
                        (bx.y0 + bx.y1) / 2.0 - mid[1],
                    ];
                    let off = (centre[0] * along[0] + centre[1] * along[1]).abs();
                    (clear && mine <= limit).then_some(mine + 0.1 * off)
                };
                let (found, free) = place(obstacles, &view, size, &region, step, &cost);
                bx = Some(found);
                if free {
                    break;
                }
            }
            let bx = bx.unwrap_or_else(|| TextBox::around(mid, size.0, size.1));
            obstacles.boxes.push(bx);
            pair_ids.push(bx);
        }
        pair_ids
    }

    /// Under the drawing: the front, then the nominal distances (a row per group). Returns
    /// their boxes and the last row's middle.
    fn legend(&self, pairings: &[Pairing], entries: &[String]) -> (TextBox, Vec<TextBox>, f64) {
        let f = self.f;
        let row = 1.4 * f;
        let front = TextBox::around(
            [self.width / 2.0, self.draw_h + 0.8 * f],
            self.text_box("FRONT").0,
            self.box_h(),
        );
        let left = f;
        let mut legend: Vec<TextBox> = Vec::new();
        let mut y = front.y1 + 0.6 * f + row / 2.0;
        let mut x = left;
        for i in 0..pairings.len() {
            let (bw, bh) = self.text_box(&entries[i]);
            let new_group = i > 0 && pairings[i - 1].group != pairings[i].group;
            if i > 0 && (new_group || x + bw > self.width - left) {
                x = left;
                y += row;
            }
            legend.push(TextBox::around([x + bw / 2.0, y], bw, bh));
            x += bw + f;
        }
        (front, legend, y)
    }

    fn write_head(&self, s: &mut String, m: &Machine, o: &Options, width: f64, height: f64) {
        let (f, draw_h, stroke) = (self.f, self.draw_h, self.stroke());
        let _ = writeln!(
            s,
            r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width:.1} {height:.1}" width="{width:.1}mm" height="{height:.1}mm" font-family="sans-serif">"#,
        );
        let _ = writeln!(
            s,
            r##"<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="6" markerHeight="6" orient="auto-start-reverse"><path d="M0,0 L10,5 L0,10 z" fill="#333"/></marker><clipPath id="drawing"><rect x="0" y="0" width="{width:.2}" height="{draw_h:.2}"/></clipPath></defs>"##
        );
        let _ = writeln!(
            s,
            r##"<title>klipcal pylons: {} layout, {}, D1 = {} mm, D2 = {} mm</title>"##,
            o.layout.as_str(),
            m.kinematics.as_str(),
            o.d1_mm,
            o.d2_mm
        );
        let bed = self.bed(m);
        let _ = writeln!(
            s,
            r##"<rect class="bed" x="{:.2}" y="{:.2}" width="{:.2}" height="{:.2}" fill="#f8f9fa" stroke="#495057" stroke-width="{:.2}" clip-path="url(#drawing)"/>"##,
            bed.x0,
            bed.y0,
            bed.x1 - bed.x0,
            bed.y1 - bed.y0,
            1.5 * stroke
        );
        let _ = writeln!(
            s,
            r##"<rect class="drawn" x="0" y="0" width="{width:.2}" height="{draw_h:.2}" fill="none" stroke="#adb5bd" stroke-width="{:.2}" stroke-dasharray="{:.2} {:.2}"/>"##,
            stroke,
            0.4 * f,
            0.3 * f
        );
    }

    fn write_pylons(&self, s: &mut String, o: &Options, placed: &Placed, names: &[TextBox]) {
        let t = o.pylon_thickness_mm;
        let l = o.pylon_length_mm;
        for p in &placed.pylons {
            let deg = placed.groups[p.group].direction_deg;
            let colour = COLOURS[p.group % COLOURS.len()];
            let _ = writeln!(
                s,
                r##"<rect x="{:.3}" y="{:.3}" width="{t:.3}" height="{l:.3}" rx="{:.3}" fill="{colour}" fill-opacity="0.85" transform="translate({:.3} {:.3}) rotate({:.3})"><title>{}</title></rect>"##,
                -t / 2.0,
                -l / 2.0,
                t / 2.0,
                self.sx(p.center[0]),
                self.sy(p.center[1]),
                -deg,
                p.id
            );
        }
        for (p, b) in placed.pylons.iter().zip(names) {
            let colour = COLOURS[p.group % COLOURS.len()];
            let _ = writeln!(
                s,
                "{}",
                text_element(&p.id, b, self.f, colour, "pylon-name")
            );
        }
    }

    /// One group per pair, so a page can highlight the pair being entered.
    fn write_pair(&self, s: &mut String, q: &Pairing, id: &TextBox, entry: &str, at: &TextBox) {
        let (f, stroke) = (self.f, self.stroke());
        let colour = COLOURS[q.group % COLOURS.len()];
        let _ = writeln!(s, r##"<g class="pair" data-pair="{}">"##, q.id);
        for (x, y) in &q.ext {
            let _ = writeln!(
                s,
                r##"<line x1="{:.3}" y1="{:.3}" x2="{:.3}" y2="{:.3}" stroke="{colour}" stroke-width="{:.3}"/>"##,
                self.sx(x[0]),
                self.sy(x[1]),
                self.sx(y[0]),
                self.sy(y[1]),
                stroke
            );
        }
        let _ = writeln!(
            s,
            r##"<line x1="{:.3}" y1="{:.3}" x2="{:.3}" y2="{:.3}" stroke="#333" stroke-width="{:.3}" marker-start="url(#arrow)" marker-end="url(#arrow)"/>"##,
            self.sx(q.a[0]),
            self.sy(q.a[1]),
            self.sx(q.b[0]),
            self.sy(q.b[1]),
            stroke
        );
        let _ = writeln!(s, "{}", text_element(&q.id, id, f, "#212529", "pair-id"));
        let _ = writeln!(s, "{}", text_element(entry, at, f, colour, "nominal"));
        s.push_str("</g>\n");
    }
}

/// The map of the whole bed under the legend: the part drawn, the origin, the axes and the
/// bed's size.
struct BedMap {
    map: TextBox,
    scale: f64,
    origin: P,
    origin_text: String,
    origin_box: TextBox,
    x_arrow: (P, P),
    y_arrow: (P, P),
    x_box: TextBox,
    y_box: TextBox,
    area: String,
    area_box: TextBox,
}

impl BedMap {
    /// The map under the legend's last row at `y`.
    fn new(m: &Machine, fr: &Frame, y: f64) -> BedMap {
        let f = fr.f;
        let (row, left, box_h) = (1.4 * f, f, fr.box_h());
        let scale = 4.5 * f / (m.x_max_mm - m.x_min_mm).max(m.y_max_mm - m.y_min_mm);
        let map = TextBox {
            x0: left + 1.8 * f,
            y0: y + row / 2.0 + 0.8 * f,
            x1: left + 1.8 * f + (m.x_max_mm - m.x_min_mm) * scale,
            y1: y + row / 2.0 + 0.8 * f + (m.y_max_mm - m.y_min_mm) * scale,
        };
        let origin = [
            map.x0 + (0.0_f64.clamp(m.x_min_mm, m.x_max_mm) - m.x_min_mm) * scale,
            map.y1 - (0.0_f64.clamp(m.y_min_mm, m.y_max_mm) - m.y_min_mm) * scale,
        ];
        let origin_text = if (m.x_min_mm..=m.x_max_mm).contains(&0.0)
            && (m.y_min_mm..=m.y_max_mm).contains(&0.0)
        {
            "0,0".to_string()
        } else {
            format!(
                "{},{}",
                m.x_min_mm.max(0.0).min(m.x_max_mm),
                m.y_min_mm.max(0.0).min(m.y_max_mm)
            )
        };
        let origin_box = TextBox::around(
            [
                origin[0].max(fr.text_box(&origin_text).0 / 2.0 + 0.2 * f),
                origin[1] + 0.9 * f,
            ],
            fr.text_box(&origin_text).0,
            box_h,
        );
        let x_arrow = ([map.x1 + 0.6 * f, map.y1], [map.x1 + 2.6 * f, map.y1]);
        let y_arrow = (
            [map.x0 - 0.9 * f, map.y1 - 0.4 * f],
            [map.x0 - 0.9 * f, map.y0],
        );
        let x_box = TextBox::around(
            [x_arrow.1[0] + 0.7 * f, map.y1 - 0.35 * f],
            fr.text_box("X").0,
            box_h,
        );
        let y_box = TextBox::around(
            [y_arrow.0[0] - 0.75 * f, map.y0 + 0.5 * f],
            fr.text_box("Y").0,
            box_h,
        );
        let area = format!(
            "bed X {}..{}, Y {}..{} mm",
            m.x_min_mm, m.x_max_mm, m.y_min_mm, m.y_max_mm
        );
        let area_box = TextBox::around(
            [
                x_box.x1 + 0.8 * f + fr.text_box(&area).0 / 2.0,
                (map.y0 + map.y1) / 2.0,
            ],
            fr.text_box(&area).0,
            box_h,
        );
        BedMap {
            map,
            scale,
            origin,
            origin_text,
            origin_box,
            x_arrow,
            y_arrow,
            x_box,
            y_box,
            area,
            area_box,
        }
    }

    /// The map, with the part drawn (`width` the picture's width) shaded.
    fn write(&self, s: &mut String, m: &Machine, fr: &Frame, width: f64) {
        let (f, stroke, map) = (fr.f, fr.stroke(), &self.map);
        let mx = |x: f64| map.x0 + (x - m.x_min_mm) * self.scale;
        let my = |y: f64| map.y1 - (y - m.y_min_mm) * self.scale;
        let _ = writeln!(
            s,
            r##"<rect class="bed-map" x="{:.2}" y="{:.2}" width="{:.2}" height="{:.2}" fill="#f8f9fa" stroke="#495057" stroke-width="{:.2}"/>"##,
            map.x0,
            map.y0,
            map.x1 - map.x0,
            map.y1 - map.y0,
            stroke
        );
        let drawn_lo = [fr.lo[0].max(m.x_min_mm), fr.lo[1].max(m.y_min_mm)];
        let drawn_hi = [(fr.lo[0] + width).min(m.x_max_mm), fr.hi[1].min(m.y_max_mm)];
        let _ = writeln!(
            s,
            r##"<rect class="map-drawn" x="{:.2}" y="{:.2}" width="{:.2}" height="{:.2}" fill="#adb5bd" fill-opacity="0.5" stroke="#495057" stroke-width="{:.2}" stroke-dasharray="{:.2} {:.2}"/>"##,
            mx(drawn_lo[0]),
            my(drawn_hi[1]),
            ((drawn_hi[0] - drawn_lo[0]) * self.scale).max(0.0),
            ((drawn_hi[1] - drawn_lo[1]) * self.scale).max(0.0),
            stroke,
            0.2 * f,
            0.15 * f
        );
        let _ = writeln!(
            s,
            r##"<circle class="origin" cx="{:.2}" cy="{:.2}" r="{:.2}" fill="#212529"/>"##,
            self.origin[0],
            self.origin[1],
            0.25 * f
        );
        for (a, b) in [self.x_arrow, self.y_arrow] {
            let _ = writeln!(
                s,
                r##"<line x1="{:.2}" y1="{:.2}" x2="{:.2}" y2="{:.2}" stroke="#333" stroke-width="{:.2}" marker-end="url(#arrow)"/>"##,
                a[0],
                a[1],
                b[0],
                b[1],
                1.5 * stroke
            );
        }
        for (text, b, class) in [
            (self.origin_text.as_str(), &self.origin_box, "origin"),
            ("X", &self.x_box, "axis"),
            ("Y", &self.y_box, "axis"),
            (self.area.as_str(), &self.area_box, "bed-size"),
        ] {
            let _ = writeln!(s, "{}", text_element(text, b, f, "#212529", class));
        }
    }
}

/// A horizontal text centred in `b`, with a halo so it reads over anything behind it.
fn text_element(text: &str, b: &TextBox, f: f64, fill: &str, class: &str) -> String {
    format!(
        r##"<text class="{class}" x="{:.2}" y="{:.2}" font-size="{f:.2}" text-anchor="middle" fill="{fill}" stroke="#f8f9fa" stroke-width="{:.2}" paint-order="stroke">{text}</text>"##,
        (b.x0 + b.x1) / 2.0,
        // the baseline: the font's ascent (0.76 em) above it, its descent (0.24 em) below
        b.y1 - 0.26 * f,
        0.15 * f
    )
}

#[cfg(test)]
mod tests {
    use super::super::{generate, Kinematics, LayoutKind, Machine, Options};
    use super::{text_em, TextBox, P};

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

    fn attr<'a>(tag: &'a str, name: &str) -> Option<&'a str> {
        let key = format!(" {name}=\"");
        let rest = &tag[tag.find(&key)? + key.len()..];
        Some(&rest[..rest.find('"')?])
    }

    fn num(tag: &str, name: &str) -> f64 {
        attr(tag, name)
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{name} in {tag}"))
    }

    /// Every element named `name`: its opening tag and, for texts, its words.
    fn elements<'a>(svg: &'a str, name: &str) -> Vec<(&'a str, &'a str)> {
        let open = format!("<{name} ");
        svg.match_indices(&open)
            .map(|(i, _)| {
                let tag = &svg[i..i + svg[i..].find('>').unwrap() + 1];
                let after = &svg[i + tag.len()..];
                (tag, &after[..after.find('<').unwrap_or(0)])
            })
            .collect()
    }

    struct Drawing {
        width: f64,
        bed: TextBox,
        texts: Vec<(String, String, f64, TextBox)>,
        lines: Vec<(P, P)>,
        /// Each pylon: its id and the core segment of its footprint with the half thickness.
        slabs: Vec<(String, P, P, f64)>,
    }

    /// What the picture shows, read back from its SVG text as a viewer would draw it: each
    /// text's box from its font size, anchor and DejaVu width (checked against the rendered
    /// font in `the_text_width_bound_holds_for_the_rendered_font`).
    fn read(svg: &str) -> Drawing {
        let vb: Vec<f64> = attr(svg, "viewBox")
            .unwrap()
            .split_whitespace()
            .map(|v| v.parse().unwrap())
            .collect();
        let bed_tag = elements(svg, "rect")
            .into_iter()
            .find(|(tag, _)| attr(tag, "class") == Some("drawn"))
            .unwrap()
            .0;
        let bed = TextBox {
            x0: num(bed_tag, "x"),
            y0: num(bed_tag, "y"),
            x1: num(bed_tag, "x") + num(bed_tag, "width"),
            y1: num(bed_tag, "y") + num(bed_tag, "height"),
        };
        let texts = elements(svg, "text")
            .into_iter()
            .map(|(tag, words)| {
                assert!(!tag.contains("rotate"), "a turned text: {tag}");
                assert_eq!(attr(tag, "text-anchor"), Some("middle"), "{tag}");
                let f = num(tag, "font-size");
                let (x, y) = (num(tag, "x"), num(tag, "y"));
                let w = text_em(words) * f;
                let b = TextBox {
                    x0: x - w / 2.0,
                    y0: y - 0.76 * f,
                    x1: x + w / 2.0,
                    y1: y + 0.24 * f,
                };
                (
                    attr(tag, "class").unwrap_or("").to_string(),
                    words.to_string(),
                    f,
                    b,
                )
            })
            .collect();
        let lines = elements(svg, "line")
            .into_iter()
            .map(|(tag, _)| {
                (
                    [num(tag, "x1"), num(tag, "y1")],
                    [num(tag, "x2"), num(tag, "y2")],
                )
            })
            .collect();
        let slabs = elements(svg, "rect")
            .into_iter()
            .filter_map(|(tag, _)| {
                let tr = attr(tag, "transform")?;
                let nums: Vec<f64> = tr
                    .split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
                    .filter(|s| !s.is_empty())
                    .map(|s| s.parse().unwrap())
                    .collect();
                let (cx, cy, deg) = (nums[0], nums[1], nums[2].to_radians());
                let (t, l) = (num(tag, "width"), num(tag, "height"));
                // the slab's local +y axis, turned
                let ax = [-deg.sin(), deg.cos()];
                let half = (l - t) / 2.0;
                let id = tag.split("<title>").nth(1).unwrap_or("");
                let id = svg[svg.find(tag).unwrap() + tag.len()..]
                    .split("<title>")
                    .nth(1)
                    .and_then(|r| r.split('<').next())
                    .unwrap_or(id)
                    .to_string();
                Some((
                    id,
                    [cx - ax[0] * half, cy - ax[1] * half],
                    [cx + ax[0] * half, cy + ax[1] * half],
                    t / 2.0,
                ))
            })
            .collect();
        Drawing {
            width: vb[2],
            bed,
            texts,
            lines,
            slabs,
        }
    }

    fn machines() -> Vec<(String, Machine, LayoutKind)> {
        let mut out = Vec::new();
        for kin in [Kinematics::CoreXy, Kinematics::Cartesian] {
            for kind in [LayoutKind::Paper, LayoutKind::Full] {
                for (x0, y0, x1, y1) in [
                    (0.0, 0.0, 220.0, 220.0),
                    (0.0, 0.0, 300.0, 300.0),
                    (0.0, 0.0, 350.0, 350.0),
                    (-5.0, -3.0, 250.0, 210.0),
                ] {
                    let m = Machine {
                        x_min_mm: x0,
                        y_min_mm: y0,
                        x_max_mm: x1,
                        y_max_mm: y1,
                        z_max_mm: Some(250.0),
                        ..Machine::square_bed(kin, 300.0)
                    };
                    let name =
                        format!("{} {} X{x0}..{x1} Y{y0}..{y1}", kin.as_str(), kind.as_str());
                    out.push((name, m, kind));
                }
            }
        }
        out
    }

    /// The PNG twin is 900 px wide (plots::PNG_WIDTH_PX) and a phone shows it about 360 px
    /// wide: a text of 25 px in the PNG is 10 px on the phone.
    const MIN_TEXT_PX_IN_PNG: f64 = 25.0;

    #[test]
    fn every_text_is_phone_sized_horizontal_and_touches_no_line_pylon_or_other_text() {
        let png_w = f64::from(crate::plots::PNG_WIDTH_PX);
        for (name, m, kind) in machines() {
            let o = Options {
                layout: kind,
                ..Options::default()
            };
            let job = generate(&m, &o).unwrap_or_else(|e| panic!("{name}: {e}"));
            let d = read(&job.svg);
            assert!(!d.texts.is_empty());
            for (i, (class, words, f, b)) in d.texts.iter().enumerate() {
                let px = f * png_w / d.width;
                assert!(
                    px >= MIN_TEXT_PX_IN_PNG,
                    "{name}: '{words}' is {px:.1} px in the {png_w} px PNG, want ≥ {MIN_TEXT_PX_IN_PNG}"
                );
                assert!(
                    b.x0 >= 0.0 && b.x1 <= d.width,
                    "{name}: '{words}' leaves the picture"
                );
                for (c2, w2, _, b2) in &d.texts[i + 1..] {
                    assert!(
                        !b.overlaps(b2),
                        "{name}: '{words}' ({class}) runs into '{w2}' ({c2})"
                    );
                }
                for (a, z) in &d.lines {
                    assert!(
                        !b.hits_segment(*a, *z),
                        "{name}: '{words}' ({class}) runs into the line {a:?}–{z:?}"
                    );
                }
                for (id, a, z, r) in &d.slabs {
                    assert!(
                        b.distance_to_segment(*a, *z) > *r,
                        "{name}: '{words}' ({class}) lies on pylon {id}"
                    );
                }
            }
        }
    }

    #[test]
    fn each_pylon_name_stands_beside_its_own_pylon_and_front_and_origin_are_marked() {
        for (name, m, kind) in machines() {
            let o = Options {
                layout: kind,
                ..Options::default()
            };
            let job = generate(&m, &o).unwrap();
            let d = read(&job.svg);
            for p in &job.layout.pylons {
                let (_, _, f, b) = d
                    .texts
                    .iter()
                    .find(|(class, words, _, _)| class == "pylon-name" && *words == p.id)
                    .unwrap_or_else(|| panic!("{name}: no name for pylon {}", p.id));
                let dist = |id: &str| {
                    let (_, a, z, r) = d.slabs.iter().find(|s| s.0 == id).unwrap();
                    b.distance_to_segment(*a, *z) - r
                };
                let own = dist(&p.id);
                assert!(
                    own <= 3.0 * f,
                    "{name}: {} stands {own:.1} mm from its pylon",
                    p.id
                );
                for q in &job.layout.pylons {
                    assert!(
                        q.id == p.id || dist(&q.id) > own,
                        "{name}: the name {} is nearer to pylon {}",
                        p.id,
                        q.id
                    );
                }
            }
            let find = |words: &str| {
                d.texts
                    .iter()
                    .find(|t| t.1 == words)
                    .unwrap_or_else(|| panic!("{name}: no '{words}' in {}", job.svg))
                    .3
            };
            // each pair's id beside its own arrow, nearer to it than to any other group's arrow
            let arrows: Vec<(String, P, P)> = elements(&job.svg, "line")
                .into_iter()
                .filter(|(tag, _)| tag.contains("marker-start"))
                .map(|(tag, _)| {
                    let at = job.svg.find(tag).unwrap();
                    let group = job.svg[..at].rsplit("data-pair=\"").next().unwrap();
                    (
                        group[..group.find('"').unwrap()].to_string(),
                        [num(tag, "x1"), num(tag, "y1")],
                        [num(tag, "x2"), num(tag, "y2")],
                    )
                })
                .collect();
            assert_eq!(arrows.len(), job.layout.pairs.len());
            for (id, a, z) in &arrows {
                let (_, _, f, b) = d
                    .texts
                    .iter()
                    .find(|(class, words, _, _)| class == "pair-id" && words == id)
                    .unwrap_or_else(|| panic!("{name}: no id at the arrow of {id}"));
                let own = b.distance_to_segment(*a, *z);
                assert!(
                    own <= 3.5 * f,
                    "{name}: {id} stands {own:.1} mm from its arrow"
                );
                let group = |pair: &str| pair.split('-').next().unwrap().to_string();
                for (other, a2, z2) in &arrows {
                    assert!(
                        group(other) == group(id) || b.distance_to_segment(*a2, *z2) > own,
                        "{name}: the id {id} is nearer to the arrow of {other}"
                    );
                }
            }
            let front = find("FRONT");
            assert!(front.y0 >= d.bed.y1, "{name}: FRONT under the drawing");
            // the bed map: the whole bed, the origin where it is on the bed, labelled
            let tag = |class: &str, el: &str| {
                elements(&job.svg, el)
                    .into_iter()
                    .find(|(t, _)| attr(t, "class") == Some(class))
                    .unwrap_or_else(|| panic!("{name}: no {el} {class}"))
                    .0
            };
            let map = tag("bed-map", "rect");
            let (mx, my, mw, mh) = (
                num(map, "x"),
                num(map, "y"),
                num(map, "width"),
                num(map, "height"),
            );
            let (bw, bh) = (m.x_max_mm - m.x_min_mm, m.y_max_mm - m.y_min_mm);
            assert!(
                (mw / mh - bw / bh).abs() < 0.01,
                "{name}: the map has the bed's shape"
            );
            let dot = tag("origin", "circle");
            let want = [mx - m.x_min_mm / bw * mw, my + mh + m.y_min_mm / bh * mh];
            let got = [num(dot, "cx"), num(dot, "cy")];
            assert!(
                (got[0] - want[0]).abs() < 0.1 && (got[1] - want[1]).abs() < 0.1,
                "{name}: the origin dot at {got:?}, want {want:?}"
            );
            let label = find("0,0");
            assert!(
                label.distance_to_segment(got, got) < 1.5 * f_of(&d),
                "{name}: '0,0' beside the origin"
            );
            let x = find("X");
            let y = find("Y");
            assert!(
                x.x0 > mx + mw && y.x1 < mx,
                "{name}: axis arrows beside the map"
            );
            let drawn = tag("map-drawn", "rect");
            assert!(num(drawn, "x") >= mx - 0.01 && num(drawn, "width") > 0.0);
        }
    }

    fn f_of(d: &Drawing) -> f64 {
        d.texts[0].2
    }

    /// `text_em` bounds the width the PNG's font really draws: each text of the pictures
    /// rendered alone is no wider than the box the placement and the tests above assume.
    #[test]
    fn the_text_width_bound_holds_for_the_rendered_font() {
        use resvg::tiny_skia::Pixmap;
        for words in [
            "A1",
            "B3",
            "X2",
            "Y1",
            "U3",
            "V2",
            "A-D1",
            "B-D2",
            "Y-D2",
            "V-D1",
            "A-D1 10.00 mm",
            "X-D2 150.00 mm",
            "FRONT",
            "0,0",
            "-5,-3",
            "X",
            "Y",
            "printable X -5..250, Y -3..210 mm",
            "W",
            "M",
        ] {
            let f = 40.0;
            let svg = format!(
                r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 1000 100"><text x="500" y="70" font-size="{f}" text-anchor="middle" font-family="sans-serif">{words}</text></svg>"#
            );
            let png = crate::plots::svg_to_png(&svg, 1000).unwrap();
            let p = Pixmap::decode_png(&png).unwrap();
            let xs: Vec<u32> = p
                .pixels()
                .iter()
                .enumerate()
                .filter(|(_, c)| c.red() < 128)
                .map(|(i, _)| i as u32 % p.width())
                .collect();
            let drawn = f64::from(xs.iter().max().unwrap() - xs.iter().min().unwrap() + 1);
            let bound = text_em(words) * f;
            assert!(
                drawn <= bound,
                "'{words}': drawn {drawn} px wide, bound {bound:.0} px"
            );
            assert!(
                drawn > 0.6 * bound,
                "'{words}': the bound is loose: {drawn} of {bound:.0} px"
            );
        }
    }
}
