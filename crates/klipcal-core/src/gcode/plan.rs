//! PURE: where the pylon groups stand on the bed — group directions per kinematics, pylon
//! centres from D1/D2, the fit check against the printable area and between groups, and the
//! `--d2` suggestion when they do not fit. No toolpaths and no text output here.

use super::{Error, Kinematics, LayoutKind, Machine, Options};
use crate::layout::{Layout, Pair, Pylon, LAYOUT_VERSION};

/// ε_max of the paper's error budget, mm (seed 000, §3.7: 2.4 + 2.9 + 10 + 0.78 µm ≈ 0.017 mm).
const EPSILON_MAX_MM: f64 = 0.017;

/// The paper's scale precision bound 2·ε_max / (D2 − D1) as a fraction (seed 000, §3.7).
pub fn precision_bound(d1_mm: f64, d2_mm: f64) -> f64 {
    2.0 * EPSILON_MAX_MM / (d2_mm - d1_mm)
}

/// The smallest D2 the generator accepts for `options`' D1.
pub fn min_d2(options: &Options) -> f64 {
    options.d1_mm + 20.0
}

/// One group of three pylons along a measuring direction.
#[derive(Debug, Clone, PartialEq)]
pub struct Group {
    /// `A`, `B`, `X`, `Y`, `U` (+45° on a Cartesian) or `V` (−45° on a Cartesian).
    pub id: &'static str,
    /// Measuring direction, degrees from +X.
    pub direction_deg: f64,
}

/// One pylon placed on the bed.
#[derive(Debug, Clone, PartialEq)]
pub struct PlacedPylon {
    /// e.g. `A1`.
    pub id: String,
    /// Index into [`Placed::groups`].
    pub group: usize,
    /// Centre, printer XY mm.
    pub center: [f64; 2],
    /// Unit normal of the measured faces (the group's measuring direction).
    pub normal: [f64; 2],
    /// Unit vector along the slab's long axis.
    pub axis: [f64; 2],
}

impl PlacedPylon {
    /// The core segment of the stadium footprint: the long axis between the centres of the
    /// rounded ends of a slab `length_mm` long and `thickness_mm` thick.
    pub fn core(&self, length_mm: f64, thickness_mm: f64) -> ([f64; 2], [f64; 2]) {
        let half = (length_mm - thickness_mm) / 2.0;
        (
            add(self.center, scale(self.axis, -half)),
            add(self.center, scale(self.axis, half)),
        )
    }
}

/// The placed groups.
#[derive(Debug, Clone, PartialEq)]
pub struct Placed {
    /// Groups in print order of their ids.
    pub groups: Vec<Group>,
    /// Pylons, three per group (pylon 1, 2, 3 of each group in turn).
    pub pylons: Vec<PlacedPylon>,
}

pub fn groups(kinematics: Kinematics, kind: LayoutKind) -> Vec<Group> {
    let g = |id, direction_deg| Group { id, direction_deg };
    match (kinematics, kind) {
        (Kinematics::CoreXy, LayoutKind::Paper) => vec![g("A", 45.0), g("B", -45.0)],
        (Kinematics::CoreXy, LayoutKind::Full) => {
            vec![g("A", 45.0), g("B", -45.0), g("X", 0.0), g("Y", 90.0)]
        }
        (Kinematics::Cartesian, LayoutKind::Paper) => vec![g("X", 0.0), g("Y", 90.0)],
        (Kinematics::Cartesian, LayoutKind::Full) => {
            vec![g("X", 0.0), g("Y", 90.0), g("U", 45.0), g("V", -45.0)]
        }
    }
}

fn add(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] + b[0], a[1] + b[1]]
}

fn sub(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

fn scale(a: [f64; 2], k: f64) -> [f64; 2] {
    [a[0] * k, a[1] * k]
}

fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

fn cross(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

fn point_segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let ab = sub(b, a);
    let len2 = dot(ab, ab);
    let t = if len2 > 0.0 {
        (dot(sub(p, a), ab) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let d = sub(p, add(a, scale(ab, t)));
    dot(d, d).sqrt()
}

/// Distance between two segments in the plane (0 when they cross).
pub fn segment_distance(a: ([f64; 2], [f64; 2]), b: ([f64; 2], [f64; 2])) -> f64 {
    let d1 = cross(sub(a.1, a.0), sub(b.0, a.0));
    let d2 = cross(sub(a.1, a.0), sub(b.1, a.0));
    let d3 = cross(sub(b.1, b.0), sub(a.0, b.0));
    let d4 = cross(sub(b.1, b.0), sub(a.1, b.0));
    if d1 * d2 < 0.0 && d3 * d4 < 0.0 {
        return 0.0;
    }
    point_segment_distance(a.0, b.0, b.1)
        .min(point_segment_distance(a.1, b.0, b.1))
        .min(point_segment_distance(b.0, a.0, a.1))
        .min(point_segment_distance(b.1, a.0, a.1))
}

/// Centre of the printable area, or the user's `--center`.
pub fn center(machine: &Machine, options: &Options) -> [f64; 2] {
    options.center_mm.unwrap_or([
        (machine.x_min_mm + machine.x_max_mm) / 2.0,
        (machine.y_min_mm + machine.y_max_mm) / 2.0,
    ])
}

/// Places every group crossing at `centre`, each group's span of D2 centred on it and moved by
/// its `shifts` entry (along its direction, along its slabs); `flips` bit g puts group g's
/// pylon 1 at the far (+direction) end.
fn arrange(
    groups: &[Group],
    flips: u32,
    shifts: &[[f64; 2]],
    centre: [f64; 2],
    d2_mm: f64,
    o: &Options,
) -> Vec<PlacedPylon> {
    let t = o.pylon_thickness_mm;
    let mut out = Vec::with_capacity(groups.len() * 3);
    for (gi, g) in groups.iter().enumerate() {
        let rad = g.direction_deg.to_radians();
        let normal = [rad.cos(), rad.sin()];
        let axis = [-rad.sin(), rad.cos()];
        let sign = if flips & (1 << gi) != 0 { -1.0 } else { 1.0 };
        let shift = shifts.get(gi).copied().unwrap_or([0.0, 0.0]);
        let origin = add(centre, add(scale(normal, shift[0]), scale(axis, shift[1])));
        let s1 = -d2_mm / 2.0 + t / 2.0;
        let offsets = [s1, s1 + (o.d1_mm - t), s1 + (d2_mm - t)];
        for (k, s) in offsets.iter().enumerate() {
            out.push(PlacedPylon {
                id: format!("{}{}", g.id, k + 1),
                group: gi,
                center: add(origin, scale(normal, sign * s)),
                normal,
                axis,
            });
        }
    }
    out
}

/// How well one arrangement fits.
#[derive(Debug, Clone)]
struct Fit {
    /// How far the worst pylon passes the printable area (minus margin), mm; 0 when inside.
    overflow_mm: f64,
    overflow_pylon: String,
    /// Smallest gap between pylons of different groups, mm.
    min_gap_mm: f64,
    gap_pylons: (String, String),
}

impl Fit {
    fn fits(&self, o: &Options) -> bool {
        self.overflow_mm <= 1e-9 && self.min_gap_mm >= o.group_gap_mm
    }

    fn badness(&self, o: &Options) -> f64 {
        self.overflow_mm + (o.group_gap_mm - self.min_gap_mm).max(0.0)
    }

    /// What the search maximises: no overflow first, then a wider gap (up to 10 mm spare).
    fn score(&self, o: &Options) -> f64 {
        -10.0 * self.overflow_mm + self.min_gap_mm.min(o.group_gap_mm + 10.0)
    }

    fn better_than(&self, other: &Fit, o: &Options) -> bool {
        match (self.fits(o), other.fits(o)) {
            (true, false) => true,
            (false, true) => false,
            (true, true) => self.min_gap_mm > other.min_gap_mm + 1e-9,
            (false, false) => self.badness(o) < other.badness(o) - 1e-9,
        }
    }
}

fn evaluate(m: &Machine, o: &Options, pylons: &[PlacedPylon]) -> Fit {
    let r = o.pylon_thickness_mm / 2.0;
    let (x0, x1) = (m.x_min_mm + o.edge_margin_mm, m.x_max_mm - o.edge_margin_mm);
    let (y0, y1) = (m.y_min_mm + o.edge_margin_mm, m.y_max_mm - o.edge_margin_mm);
    let mut fit = Fit {
        overflow_mm: 0.0,
        overflow_pylon: String::new(),
        min_gap_mm: f64::INFINITY,
        gap_pylons: (String::new(), String::new()),
    };
    let cores: Vec<_> = pylons
        .iter()
        .map(|p| p.core(o.pylon_length_mm, o.pylon_thickness_mm))
        .collect();
    for (p, core) in pylons.iter().zip(&cores) {
        for e in [core.0, core.1] {
            let over = (x0 - (e[0] - r))
                .max((e[0] + r) - x1)
                .max(y0 - (e[1] - r))
                .max((e[1] + r) - y1);
            if over > fit.overflow_mm {
                fit.overflow_mm = over;
                fit.overflow_pylon.clone_from(&p.id);
            }
        }
    }
    for i in 0..pylons.len() {
        for j in (i + 1)..pylons.len() {
            if pylons[i].group == pylons[j].group {
                continue;
            }
            let gap = segment_distance(cores[i], cores[j]) - 2.0 * r;
            if gap < fit.min_gap_mm {
                fit.min_gap_mm = gap;
                fit.gap_pylons = (pylons[i].id.clone(), pylons[j].id.clone());
            }
        }
    }
    fit
}

/// The best arrangement for a D2: over which end of each group holds pylon 1, then, when that
/// alone does not fit, moving groups off the common centre (coordinate descent, 8 → 1 mm).
fn best(m: &Machine, o: &Options, groups: &[Group], d2_mm: f64) -> (Fit, Vec<PlacedPylon>) {
    let centre = center(m, o);
    let zero = vec![[0.0, 0.0]; groups.len()];
    let mut tried: Vec<(Fit, u32)> = (0..(1u32 << groups.len()))
        .map(|flips| {
            (
                evaluate(m, o, &arrange(groups, flips, &zero, centre, d2_mm, o)),
                flips,
            )
        })
        .collect();
    tried.sort_by(|a, b| b.0.score(o).total_cmp(&a.0.score(o)));
    let mut best: Option<(Fit, Vec<PlacedPylon>)> = None;
    for (fit, flips) in tried.into_iter().take(2) {
        let (fit, pylons) = if fit.fits(o) {
            (fit, arrange(groups, flips, &zero, centre, d2_mm, o))
        } else {
            descend(m, o, groups, flips, centre, d2_mm, fit)
        };
        if best.as_ref().map_or(true, |b| fit.better_than(&b.0, o)) {
            best = Some((fit, pylons));
        }
    }
    // `groups` is never empty, so at least one arrangement was tried.
    best.unwrap_or_else(|| (evaluate(m, o, &[]), Vec::new()))
}

fn descend(
    m: &Machine,
    o: &Options,
    groups: &[Group],
    flips: u32,
    centre: [f64; 2],
    d2_mm: f64,
    start: Fit,
) -> (Fit, Vec<PlacedPylon>) {
    let mut shifts = vec![[0.0, 0.0]; groups.len()];
    let mut fit = start;
    for step in [8.0, 4.0, 2.0, 1.0] {
        for _ in 0..6 {
            let mut improved = false;
            for g in 0..groups.len() {
                for dir in [[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]] {
                    let mut trial = shifts.clone();
                    trial[g] = add(trial[g], scale(dir, step));
                    let f = evaluate(m, o, &arrange(groups, flips, &trial, centre, d2_mm, o));
                    if f.score(o) > fit.score(o) + 1e-6 {
                        shifts = trial;
                        fit = f;
                        improved = true;
                    }
                }
            }
            if !improved || fit.fits(o) && fit.min_gap_mm >= o.group_gap_mm + 10.0 {
                break;
            }
        }
    }
    let pylons = arrange(groups, flips, &shifts, centre, d2_mm, o);
    (fit, pylons)
}

/// Places the groups, or explains why they do not fit and which `--d2` would.
pub fn place(m: &Machine, o: &Options) -> Result<Placed, Error> {
    let groups = groups(m.kinematics, o.layout);
    let (fit, pylons) = best(m, o, &groups, o.d2_mm);
    if fit.fits(o) {
        return Ok(Placed { groups, pylons });
    }
    let mut why = Vec::new();
    if fit.overflow_mm > 1e-9 {
        why.push(format!(
            "pylon {} passes the printable area (X {}..{}, Y {}..{} less a {} mm margin) by {:.1} mm",
            fit.overflow_pylon,
            m.x_min_mm,
            m.x_max_mm,
            m.y_min_mm,
            m.y_max_mm,
            o.edge_margin_mm,
            fit.overflow_mm
        ));
    }
    if fit.min_gap_mm < o.group_gap_mm {
        why.push(if fit.min_gap_mm <= 0.0 {
            format!(
                "pylons {} and {} of different groups overlap by {:.1} mm (at least {} mm gap needed)",
                fit.gap_pylons.0, fit.gap_pylons.1, -fit.min_gap_mm, o.group_gap_mm
            )
        } else {
            format!(
                "pylons {} and {} of different groups are {:.1} mm apart (at least {} mm needed)",
                fit.gap_pylons.0, fit.gap_pylons.1, fit.min_gap_mm, o.group_gap_mm
            )
        });
    }
    let head = format!(
        "layout `{}` ({} groups of 3, D1 = {} mm, D2 = {} mm) does not fit this printer: {}",
        o.layout.as_str(),
        groups.len(),
        o.d1_mm,
        o.d2_mm,
        why.join("; ")
    );
    match suggest_d2(m, o, &groups) {
        Some(d2) => Err(Error::DoesNotFit {
            message: format!(
            "{head}. Try --d2 {d2:.0}: it fits, with a scale precision bound of {:.3} % instead of {:.3} % (paper §3.7)",
            100.0 * precision_bound(o.d1_mm, d2),
            100.0 * precision_bound(o.d1_mm, o.d2_mm)
            ),
            suggested_d2_mm: Some(d2.round()),
        }),
        None => Err(Error::DoesNotFit { suggested_d2_mm: None, message: format!(
            "{head}. No --d2 makes this layout fit{}",
            match o.layout {
                LayoutKind::Full => "; try --layout paper or a shorter --pylon-length",
                LayoutKind::Paper => "; the printable area is too small for these pylons",
            }
        )}),
    }
}

/// The whole-millimetre D2 nearest below the requested one that fits (else the nearest above).
pub fn suggest_d2(m: &Machine, o: &Options, groups: &[Group]) -> Option<f64> {
    let fits = |d2: f64| best(m, o, groups, d2).0.fits(o);
    let lo = min_d2(o).ceil();
    let mut d2 = o.d2_mm.floor();
    if d2 >= o.d2_mm {
        d2 -= 1.0;
    }
    while d2 >= lo {
        if fits(d2) {
            return Some(d2);
        }
        d2 -= 1.0;
    }
    let span = (m.x_max_mm - m.x_min_mm).hypot(m.y_max_mm - m.y_min_mm);
    let mut d2 = o.d2_mm.floor() + 1.0;
    while d2 <= span {
        if fits(d2) {
            return Some(d2);
        }
        d2 += 1.0;
    }
    None
}

/// The `layout.json` contents for the placed pylons.
pub fn to_layout(m: &Machine, o: &Options, placed: &Placed) -> Layout {
    let pylons = placed
        .pylons
        .iter()
        .map(|p| Pylon {
            id: p.id.clone(),
            center: p.center,
            normal_deg: placed.groups[p.group].direction_deg,
            thickness: o.pylon_thickness_mm,
            length: o.pylon_length_mm,
            height: o.pylon_height_mm,
        })
        .collect();
    let mut pairs = Vec::new();
    for g in &placed.groups {
        for (name, to, nominal_mm) in [("D1", 2, o.d1_mm), ("D2", 3, o.d2_mm)] {
            pairs.push(Pair {
                id: format!("{}-{}", g.id, name),
                group: g.id.to_string(),
                from: format!("{}1", g.id),
                to: format!("{}{}", g.id, to),
                direction_deg: g.direction_deg,
                nominal_mm,
            });
        }
    }
    Layout {
        version: LAYOUT_VERSION,
        kinematics: m.kinematics.as_str().to_string(),
        pylons,
        pairs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn machine(kinematics: Kinematics, size_mm: f64) -> Machine {
        Machine {
            z_max_mm: Some(200.0),
            max_velocity_mm_s: None,
            max_accel_mm_s2: None,
            ..Machine::square_bed(kinematics, size_mm)
        }
    }

    #[test]
    fn paper_precision_bound_matches_section_3_7() {
        // seed 000, §3.7: with D2 = 150 and D1 = 10, (ε1 − ε2)/(D2 − D1) < 2.5e-4.
        let p = precision_bound(10.0, 150.0);
        assert!(p < 2.5e-4 && p > 2.4e-4, "{p}");
    }

    #[test]
    fn corexy_paper_groups_run_along_the_motor_diagonals() {
        let g = groups(Kinematics::CoreXy, LayoutKind::Paper);
        assert_eq!(
            g.iter()
                .map(|g| (g.id, g.direction_deg))
                .collect::<Vec<_>>(),
            vec![("A", 45.0), ("B", -45.0)]
        );
        let g = groups(Kinematics::Cartesian, LayoutKind::Full);
        assert_eq!(g.len(), 4);
        assert!(g.iter().any(|g| g.direction_deg == 45.0));
    }

    #[test]
    fn pylon_centres_are_d_minus_thickness_apart_along_the_direction() {
        // seed README: pylons 1–2 are 6.4 mm apart centre to centre, pylon 3 is 146.4 mm away.
        let m = machine(Kinematics::CoreXy, 300.0);
        let placed = place(&m, &Options::default()).expect("fits");
        for g in 0..2 {
            let p: Vec<_> = placed.pylons.iter().filter(|p| p.group == g).collect();
            let along =
                |a: &PlacedPylon, b: &PlacedPylon| dot(sub(b.center, a.center), a.normal).abs();
            assert!((along(p[0], p[1]) - 6.4).abs() < 1e-9);
            assert!((along(p[0], p[2]) - 146.4).abs() < 1e-9);
            let lateral = dot(sub(p[2].center, p[0].center), p[0].axis);
            assert!(lateral.abs() < 1e-9);
        }
    }

    #[test]
    fn a_120_mm_bed_gets_a_clear_error_with_a_d2_that_fits() {
        let m = machine(Kinematics::CoreXy, 120.0);
        let err = place(&m, &Options::default()).expect_err("150 mm cannot fit");
        let Error::DoesNotFit { message: text, .. } = err else {
            panic!("wrong error {err:?}")
        };
        assert!(text.contains("passes the printable area"), "{text}");
        let d2: f64 = text
            .split("Try --d2 ")
            .nth(1)
            .and_then(|s| s.split(':').next())
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no suggestion in {text}"));
        let o = Options {
            d2_mm: d2,
            ..Options::default()
        };
        assert!(place(&m, &o).is_ok(), "suggested --d2 {d2} does not fit");
        let o1 = Options {
            d2_mm: d2 + 1.0,
            ..Options::default()
        };
        assert!(place(&m, &o1).is_err(), "a larger --d2 than {d2} also fits");
        assert!(
            d2 > 60.0,
            "a 120 mm bed must still get a usable D2, got {d2}"
        );
    }

    #[test]
    fn groups_of_a_full_layout_keep_their_gap() {
        let m = machine(Kinematics::CoreXy, 250.0);
        let o = Options {
            layout: LayoutKind::Full,
            ..Options::default()
        };
        let placed = place(&m, &o).expect("full fits 250");
        assert_eq!(placed.pylons.len(), 12);
        let fit = evaluate(&m, &o, &placed.pylons);
        assert!(fit.min_gap_mm >= o.group_gap_mm, "{fit:?}");
        assert_eq!(fit.overflow_mm, 0.0);
    }

    #[test]
    fn layout_pairs_name_the_outer_distances() {
        let m = machine(Kinematics::Cartesian, 235.0);
        let o = Options::default();
        let placed = place(&m, &o).expect("fits");
        let layout = to_layout(&m, &o, &placed);
        assert_eq!(layout.kinematics, "cartesian");
        assert_eq!(layout.pylons.len(), 6);
        let ids: Vec<_> = layout.pairs.iter().map(|p| p.id.as_str()).collect();
        assert_eq!(ids, ["X-D1", "X-D2", "Y-D1", "Y-D2"]);
        assert_eq!(layout.pairs[1].from, "X1");
        assert_eq!(layout.pairs[1].to, "X3");
        assert_eq!(layout.pairs[1].nominal_mm, 150.0);
    }

    #[test]
    fn crossing_segments_have_zero_distance() {
        let a = ([0.0, 0.0], [2.0, 2.0]);
        let b = ([0.0, 2.0], [2.0, 0.0]);
        assert_eq!(segment_distance(a, b), 0.0);
        let c = ([3.0, 0.0], [3.0, 5.0]);
        assert!((segment_distance(a, c) - 1.0).abs() < 1e-12);
    }
}
