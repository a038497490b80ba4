//! PURE: slices the placed pylons into per-layer toolpaths — layer heights, the top chamfer,
//! perimeter loops (external first, seam on a rounded end) and solid infill between them.
//! Geometry only: no G-code text, no extrusion amounts (see `emit`).

use super::plan::{Placed, PlacedPylon};
use super::Options;

/// What a path is, for the `;TYPE:` comments and speeds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The outermost loop: its outer edge is the measured face.
    ExternalPerimeter,
    /// Inner loops.
    Perimeter,
    /// Lines between the innermost loops.
    SolidInfill,
}

/// One continuous extrusion: a polyline printed with one line width.
#[derive(Debug, Clone, PartialEq)]
pub struct Path {
    /// Points in printer XY mm; a loop ends where it started.
    pub points: Vec<[f64; 2]>,
    /// Line width, mm.
    pub width_mm: f64,
    /// Kind of path.
    pub role: Role,
}

/// Everything printed on one pylon in one layer.
#[derive(Debug, Clone, PartialEq)]
pub struct Island {
    /// Index into [`Placed::pylons`].
    pub pylon: usize,
    /// Paths in print order.
    pub paths: Vec<Path>,
}

/// One layer of the job.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    /// Nozzle height while printing this layer (its top), mm.
    pub z_mm: f64,
    /// Layer thickness, mm.
    pub height_mm: f64,
    /// Islands in print order.
    pub islands: Vec<Island>,
}

/// Layer tops from the first layer to the pylon height; the layers above the first share the
/// rest evenly so the top lands exactly on the pylon height.
pub fn layer_tops(o: &Options) -> Vec<(f64, f64)> {
    let first = o.first_layer_height_mm;
    let rest = o.pylon_height_mm - first;
    let n = ((rest / o.layer_height_mm).round() as usize).max(1);
    let h = rest / n as f64;
    let mut out = vec![(first, first)];
    out.extend((1..=n).map(|i| (first + h * i as f64, h)));
    out
}

/// How far the outline is inset at height `z_mid_mm` by the top chamfer.
pub fn chamfer_inset(o: &Options, z_mid_mm: f64) -> f64 {
    let total = (o.pylon_thickness_mm - o.chamfer_top_thickness_mm) / 2.0;
    let start = o.pylon_height_mm - o.chamfer_height_mm;
    if o.chamfer_height_mm <= 0.0 || z_mid_mm <= start {
        0.0
    } else {
        total * ((z_mid_mm - start) / o.chamfer_height_mm).min(1.0)
    }
}

/// A point `s` along the normal and `t` along the long axis from the pylon centre.
fn at(p: &PlacedPylon, s: f64, t: f64) -> [f64; 2] {
    [
        p.center[0] + s * p.normal[0] + t * p.axis[0],
        p.center[1] + s * p.normal[1] + t * p.axis[1],
    ]
}

/// Angle steps for a quarter circle of radius `r_mm` (chord error under ~10 µm).
fn quarter_steps(r_mm: f64) -> usize {
    if r_mm < 0.3 {
        2
    } else if r_mm < 0.8 {
        4
    } else {
        6
    }
}

/// A closed stadium loop of half-width `r` with straight half-length `a`, starting and ending
/// at the tip of the +axis rounded end (the seam), counter-clockwise in (normal, axis).
fn stadium_loop(p: &PlacedPylon, r: f64, a: f64) -> Vec<[f64; 2]> {
    let q = quarter_steps(r);
    let step = std::f64::consts::FRAC_PI_2 / q as f64;
    let arc = |centre_t: f64, from: f64, steps: usize, out: &mut Vec<[f64; 2]>| {
        for i in 0..=steps {
            let phi = from + step * i as f64;
            out.push(at(p, r * phi.cos(), centre_t + r * phi.sin()));
        }
    };
    let mut pts = Vec::with_capacity(4 * q + 6);
    // tip (φ = 90°) → side s = −r at the +end, then down the −r side
    arc(a, std::f64::consts::FRAC_PI_2, q, &mut pts);
    // the −end: φ from 180° through 270° (the other tip) to 360°
    arc(-a, std::f64::consts::PI, 2 * q, &mut pts);
    // the +r side back up, then φ 0° → 90° to the tip
    arc(a, 0.0, q, &mut pts);
    pts.dedup_by(|b, a| (a[0] - b[0]).hypot(a[1] - b[1]) < 1e-9);
    pts
}

/// Toolpaths of one pylon at one layer, with the outline inset by `inset_mm`.
pub fn island(p: &PlacedPylon, o: &Options, w: f64, inset_mm: f64) -> Vec<Path> {
    let half = o.pylon_thickness_mm / 2.0 - inset_mm;
    let a = (o.pylon_length_mm - o.pylon_thickness_mm) / 2.0;
    let mut paths = Vec::new();
    let mut loops = 0usize;
    for k in 0..o.perimeters as usize {
        let r = half - w / 2.0 - k as f64 * w;
        if r < w / 2.0 - 1e-9 {
            break;
        }
        paths.push(Path {
            points: stadium_loop(p, r, a),
            width_mm: w,
            role: if k == 0 {
                Role::ExternalPerimeter
            } else {
                Role::Perimeter
            },
        });
        loops += 1;
    }
    let r_in = half - loops as f64 * w;
    if 2.0 * r_in >= 0.25 * w {
        let count = ((2.0 * r_in / w).round() as usize).max(1);
        let wf = 2.0 * r_in / count as f64;
        for j in 0..count {
            let s = -r_in + wf * (j as f64 + 0.5);
            let ext = ((r_in * r_in - s * s).max(0.0).sqrt() - wf / 2.0).max(0.0);
            let (t0, t1) = if j % 2 == 0 {
                (a + ext, -(a + ext))
            } else {
                (-(a + ext), a + ext)
            };
            paths.push(Path {
                points: vec![at(p, s, t0), at(p, s, t1)],
                width_mm: wf,
                role: Role::SolidInfill,
            });
        }
    }
    paths
}

/// Print order of the pylons: nearest neighbour between seams, from the first pylon.
fn order(placed: &Placed, o: &Options) -> Vec<usize> {
    let a = (o.pylon_length_mm - o.pylon_thickness_mm) / 2.0;
    let seam = |i: usize| at(&placed.pylons[i], 0.0, a + o.pylon_thickness_mm / 2.0);
    let mut left: Vec<usize> = (0..placed.pylons.len()).collect();
    let mut out = Vec::with_capacity(left.len());
    let mut cur = 0usize;
    while !left.is_empty() {
        let here = seam(cur);
        let (pos, _) = left
            .iter()
            .enumerate()
            .fold((0, f64::INFINITY), |best, (k, &i)| {
                let s = seam(i);
                let d = (s[0] - here[0]).hypot(s[1] - here[1]);
                if d < best.1 {
                    (k, d)
                } else {
                    best
                }
            });
        cur = left.remove(pos);
        out.push(cur);
    }
    out
}

/// Slices every pylon at every layer.
pub fn slice_all(placed: &Placed, o: &Options, w: f64) -> Vec<Layer> {
    let order = order(placed, o);
    layer_tops(o)
        .into_iter()
        .map(|(z_mm, height_mm)| {
            let inset = chamfer_inset(o, z_mm - height_mm / 2.0);
            Layer {
                z_mm,
                height_mm,
                islands: order
                    .iter()
                    .map(|&i| Island {
                        pylon: i,
                        paths: island(&placed.pylons[i], o, w, inset),
                    })
                    .collect(),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pylon() -> PlacedPylon {
        PlacedPylon {
            id: "A1".into(),
            group: 0,
            center: [100.0, 100.0],
            normal: [1.0, 0.0],
            axis: [0.0, 1.0],
        }
    }

    #[test]
    fn default_layers_end_exactly_at_the_pylon_height() {
        let o = Options::default();
        let tops = layer_tops(&o);
        assert_eq!(tops.len(), 40);
        assert!((tops.last().map(|t| t.0).unwrap_or(0.0) - 8.0).abs() < 1e-9);
        let sum: f64 = tops.iter().map(|t| t.1).sum();
        assert!((sum - 8.0).abs() < 1e-9);
    }

    #[test]
    fn the_chamfer_narrows_the_top_to_three_millimetres() {
        // seed README: top 0.3 mm chamfered from 3.6 to 3.0 mm.
        let o = Options::default();
        assert_eq!(chamfer_inset(&o, 7.5), 0.0);
        assert!((chamfer_inset(&o, 8.0) - 0.3).abs() < 1e-12);
        assert!((chamfer_inset(&o, 7.85) - 0.15).abs() < 1e-12);
    }

    #[test]
    fn a_3_6_mm_slab_gets_three_loops_and_a_centre_line() {
        let o = Options::default();
        let paths = island(&pylon(), &o, 0.5, 0.0);
        let roles: Vec<_> = paths.iter().map(|p| p.role).collect();
        assert_eq!(
            roles,
            [
                Role::ExternalPerimeter,
                Role::Perimeter,
                Role::Perimeter,
                Role::SolidInfill
            ]
        );
        assert!((paths[3].width_mm - 0.6).abs() < 1e-9);
        // the outer loop's straight sides are at ±(1.8 − 0.25) from the centre
        let xs: Vec<f64> = paths[0].points.iter().map(|p| p[0] - 100.0).collect();
        let max = xs.iter().cloned().fold(f64::MIN, f64::max);
        let min = xs.iter().cloned().fold(f64::MAX, f64::min);
        assert!((max - 1.55).abs() < 1e-9 && (min + 1.55).abs() < 1e-9);
    }

    #[test]
    fn loops_start_and_end_on_the_rounded_end() {
        let o = Options::default();
        for path in island(&pylon(), &o, 0.5, 0.0)
            .iter()
            .filter(|p| p.role != Role::SolidInfill)
        {
            let first = path.points[0];
            let last = path.points[path.points.len() - 1];
            assert!((first[0] - last[0]).abs() < 1e-9 && (first[1] - last[1]).abs() < 1e-9);
            // the seam is on the axis, beyond the straight part (on the rounded end)
            assert!((first[0] - 100.0).abs() < 1e-9);
            assert!(first[1] - 100.0 > (53.6 - 3.6) / 2.0);
        }
    }
}
