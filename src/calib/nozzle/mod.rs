//! PURE: the nozzle seen from below by a camera (issue 27), found to sub-pixel precision in a
//! grey image — or refused, with the reason, when the picture does not allow a sure answer.
//!
//! Coordinates are pixels with the centre of pixel (i, j) at (i, j): x to the right, y down.
//!
//! The method, and why:
//! 1. **Refusals first.** Clipped pixels (saturation) and a flat picture are told apart before
//!    any search, so a bad exposure is never read as a nozzle.
//! 2. **Lighting taken out.** A quadratic background (vignetting, a light from one side) is fitted
//!    robustly — iteratively, leaving out what stands out — and subtracted, so thresholds are
//!    in grey levels above or below the local background whatever the exposure.
//! 3. **Candidates.** What stands out from that background by a margin over the measured noise
//!    is grouped into connected regions; parts nested in a larger one (a ring's orifice) join it.
//!    None → "no nozzle"; two of similar weight → "two candidates"; touching the frame → refused.
//! 4. **Sub-pixel centre by radial symmetry** (Parthasarathy, Nature Methods 2012): every edge
//!    pixel's gradient lies on a line through the centre of a round object, whichever its
//!    polarity — a bright ring's two edges and a dark tip's one edge all agree. The centre is the
//!    point nearest to those lines in least squares, weighted by gradient strength. Unlike a
//!    centroid it is not pulled by uneven lighting across the object, and unlike a Hough circle
//!    (kTAMV's OpenCV detector) it needs no radius guess or accumulator threshold and gives
//!    its own uncertainty: the lines' scatter about the centre, propagated (sandwich estimator),
//!    widened for the correlation of neighbouring pixels' gradients.
//! 5. **Checks on the answer.** Lines that do not meet (not a round object) or an uncertainty
//!    over the limit are refused rather than returned.

use serde::Serialize;

/// A grey image borrowed from its decoder: row-major, one byte per pixel.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Gray<'a> {
    pub width: usize,
    pub height: usize,
    pub data: &'a [u8],
}

/// Limits of the detection. The defaults suit 320×240 to 1920×1080 snapshots of a nozzle that
/// spans a few percent of the frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct DetectParams {
    /// Refuse when more than this fraction of pixels is clipped white (≥ 250) or black (≤ 5).
    pub max_clipped_fraction: f64,
    /// The nozzle must stand out from the background by at least this many grey levels.
    pub min_contrast: f64,
    /// … and by this many times the picture's noise sd.
    pub min_snr: f64,
    /// A candidate smaller than this (pixels) is a speck, not a nozzle.
    pub min_area_px: usize,
    /// A second candidate with at least this share of the first one's weight makes the picture
    /// ambiguous: refused as "two candidates".
    pub second_candidate_ratio: f64,
    /// Refuse an answer whose uncertainty (1 sd per axis) exceeds this, px.
    pub max_uncertainty_px: f64,
    /// Refuse when the gradient lines scatter about the centre by more than this share of the
    /// radius (weighted rms): not a round object.
    pub max_scatter_share: f64,
}

impl Default for DetectParams {
    fn default() -> Self {
        DetectParams {
            max_clipped_fraction: 0.2,
            min_contrast: 12.0,
            min_snr: 8.0,
            min_area_px: 20,
            second_candidate_ratio: 0.25,
            max_uncertainty_px: 0.5,
            max_scatter_share: 0.2,
        }
    }
}

/// Why no centre is given.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub(crate) enum Refusal {
    /// The buffer does not hold width × height pixels, or the picture is too small.
    BadImage { detail: String },
    /// Too many pixels clipped white or black.
    Saturated { white_pct: f64, black_pct: f64 },
    /// The whole picture, or the only thing in it, barely differs from its background.
    TooLittleContrast { contrast: f64, needed: f64 },
    /// Nothing stands out from the background.
    NoNozzle { strongest: f64, needed: f64 },
    /// More than one object that could be the nozzle.
    TwoCandidates {
        count: usize,
        centres_px: Vec<[f64; 2]>,
    },
    /// The object touches the frame, so its centre cannot be measured.
    AtEdge { centre_px: [f64; 2] },
    /// The object is not round: its edges do not point at one centre.
    NotRound { scatter_px: f64, radius_px: f64 },
    /// A centre was found but its uncertainty is over the limit.
    Uncertain { uncertainty_px: f64, limit_px: f64 },
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::BadImage { detail } => write!(f, "not a usable image: {detail}"),
            Refusal::Saturated {
                white_pct,
                black_pct,
            } => write!(
                f,
                "saturated: {white_pct:.0} % of the pixels are clipped white and {black_pct:.0} % \
                 black; expected a lit background below full white — lower the exposure or the \
                 light (or raise it, if the picture is black)"
            ),
            Refusal::TooLittleContrast { contrast, needed } => write!(
                f,
                "too little contrast: the picture varies by only {contrast:.1} grey levels, \
                 {needed:.1} needed; light the nozzle from the side or below and check the focus"
            ),
            Refusal::NoNozzle { strongest, needed } => write!(
                f,
                "no nozzle: nothing stands out from the background by more than {strongest:.1} \
                 grey levels ({needed:.1} needed); bring the nozzle over the camera"
            ),
            Refusal::TwoCandidates { count, centres_px } => write!(
                f,
                "{count} candidates that could be the nozzle, at {}; expected one — clear the view \
                 (a second toolhead, a reflection, debris on the lens)",
                centres_px
                    .iter()
                    .map(|c| format!("({:.0}, {:.0}) px", c[0], c[1]))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
            Refusal::AtEdge { centre_px } => write!(
                f,
                "the nozzle touches the edge of the picture (near ({:.0}, {:.0}) px); move it \
                 towards the middle of the camera's view",
                centre_px[0], centre_px[1]
            ),
            Refusal::NotRound {
                scatter_px,
                radius_px,
            } => write!(
                f,
                "not sure: the object's edges do not point at one centre (scatter {scatter_px:.1} \
                 px for a radius of {radius_px:.1} px); expected a round nozzle seen from below"
            ),
            Refusal::Uncertain {
                uncertainty_px,
                limit_px,
            } => write!(
                f,
                "not sure: the centre is uncertain by ±{uncertainty_px:.2} px, over the \
                 {limit_px:.2} px limit; check the focus and the lighting"
            ),
        }
    }
}

/// The nozzle looks brighter or darker than its background (by the mean over its region).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum Polarity {
    Bright,
    Dark,
}

/// What the detection saw, for a person checking their camera.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Diagnostics {
    /// Background level at the centre, grey levels.
    pub background: f64,
    /// Noise sd of the picture after the background is taken out, grey levels.
    pub noise_sd: f64,
    /// How far the nozzle stands out from the background at its strongest, grey levels.
    pub contrast: f64,
    pub polarity: Polarity,
    /// Gradient-weighted mean distance of the edges from the centre, px.
    pub radius_px: f64,
    /// Weighted rms distance of the gradient lines from the centre, px.
    pub scatter_px: f64,
    /// Candidate regions found (after nested parts were joined), including the nozzle.
    pub candidates: usize,
    /// Share of clipped pixels (white + black).
    pub clipped_fraction: f64,
    /// Edge pixels used by the fit.
    pub edge_pixels: usize,
    /// The nozzle region's contrast-weighted centroid, px: the simple estimate the fit starts
    /// from (the benchmark's anchor).
    pub centroid_px: [f64; 2],
}

/// A found nozzle.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Detection {
    /// Centre, px (pixel centres at integers).
    pub centre_px: [f64; 2],
    /// 1 sd per axis, px.
    pub uncertainty_px: f64,
    pub diagnostics: Diagnostics,
}

fn median_in_place(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, f64::total_cmp);
    *m
}

fn percentile_u8(hist: &[usize; 256], n: usize, q: f64) -> f64 {
    let target = (q * n as f64).ceil().max(1.0) as usize;
    let mut acc = 0;
    for (i, c) in hist.iter().enumerate() {
        acc += c;
        if acc >= target {
            return i as f64;
        }
    }
    255.0
}

/// Quadratic background b(u, v) in normalised coordinates.
struct Background {
    coef: [f64; 6],
    w: f64,
    h: f64,
}

impl Background {
    fn basis(&self, x: f64, y: f64) -> [f64; 6] {
        let u = x / self.w - 0.5;
        let v = y / self.h - 0.5;
        [1.0, u, v, u * u, u * v, v * v]
    }

    fn at(&self, x: f64, y: f64) -> f64 {
        let b = self.basis(x, y);
        b.iter().zip(&self.coef).map(|(a, c)| a * c).sum()
    }

    /// Robust fit on a grid of samples: least squares, then again on the samples within 2.5
    /// robust sd of the fit, four times. Returns the fit and the inliers' noise sd.
    fn fit(img: &Gray<'_>) -> (Background, f64) {
        let step = (img.width.max(img.height) / 160).max(1);
        let mut samples = Vec::new();
        for y in (0..img.height).step_by(step) {
            for x in (0..img.width).step_by(step) {
                samples.push((x as f64, y as f64, f64::from(img.data[y * img.width + x])));
            }
        }
        let mut bg = Background {
            coef: [0.0; 6],
            w: img.width as f64,
            h: img.height as f64,
        };
        let mut keep = vec![true; samples.len()];
        let mut sd = 0.0;
        for _ in 0..5 {
            let mut m = nalgebra::Matrix6::<f64>::zeros();
            let mut r = nalgebra::Vector6::<f64>::zeros();
            for (s, k) in samples.iter().zip(&keep) {
                if !k {
                    continue;
                }
                let b = nalgebra::Vector6::from(bg.basis(s.0, s.1));
                m += b * b.transpose();
                r += b * s.2;
            }
            let Some(c) = m.lu().solve(&r) else {
                break;
            };
            bg.coef.copy_from_slice(c.as_slice());
            let mut res: Vec<f64> = samples
                .iter()
                .zip(&keep)
                .filter(|(_, k)| **k)
                .map(|(s, _)| (s.2 - bg.at(s.0, s.1)).abs())
                .collect();
            sd = 1.4826 * median_in_place(&mut res);
            let lim = 2.5 * sd + 1.0;
            for (s, k) in samples.iter().zip(keep.iter_mut()) {
                *k = (s.2 - bg.at(s.0, s.1)).abs() <= lim;
            }
        }
        (bg, sd)
    }
}

/// Separable 3×3 box smoothing of a float image (edges clamped).
fn box3(src: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut tmp = vec![0f32; src.len()];
    for y in 0..h {
        for x in 0..w {
            let l = src[y * w + x.saturating_sub(1)];
            let r = src[y * w + (x + 1).min(w - 1)];
            tmp[y * w + x] = (l + src[y * w + x] + r) / 3.0;
        }
    }
    let mut out = vec![0f32; src.len()];
    for y in 0..h {
        let (yu, yd) = (y.saturating_sub(1), (y + 1).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (tmp[yu * w + x] + tmp[y * w + x] + tmp[yd * w + x]) / 3.0;
        }
    }
    out
}

#[derive(Debug, Clone)]
struct Region {
    area: usize,
    weight: f64,
    signed: f64,
    cx: f64,
    cy: f64,
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

impl Region {
    fn half_extent(&self) -> f64 {
        0.5 * ((self.x1 - self.x0 + 1).max(self.y1 - self.y0 + 1)) as f64
    }
}

/// Connected regions (8-neighbour) of `mask`, with their |residual|-weighted centroids.
fn regions(mask: &[bool], res: &[f32], w: usize, h: usize) -> Vec<Region> {
    let mut seen = vec![false; mask.len()];
    let mut out = Vec::new();
    let mut stack = Vec::new();
    for start in 0..mask.len() {
        if !mask[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut r = Region {
            area: 0,
            weight: 0.0,
            signed: 0.0,
            cx: 0.0,
            cy: 0.0,
            x0: usize::MAX,
            y0: usize::MAX,
            x1: 0,
            y1: 0,
        };
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            let a = f64::from(res[i].abs());
            r.area += 1;
            r.weight += a;
            r.signed += f64::from(res[i]);
            r.cx += a * x as f64;
            r.cy += a * y as f64;
            r.x0 = r.x0.min(x);
            r.y0 = r.y0.min(y);
            r.x1 = r.x1.max(x);
            r.y1 = r.y1.max(y);
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                        continue;
                    }
                    let j = ny as usize * w + nx as usize;
                    if mask[j] && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        r.cx /= r.weight.max(1e-12);
        r.cy /= r.weight.max(1e-12);
        out.push(r);
    }
    out
}

/// Joins regions nested in a larger one (a ring's orifice inside the ring), largest first.
fn join_nested(mut rs: Vec<Region>) -> Vec<Region> {
    rs.sort_by(|a, b| b.weight.total_cmp(&a.weight));
    let mut out: Vec<Region> = Vec::new();
    'next: for r in rs {
        for o in out.iter_mut() {
            let d = ((r.cx - o.cx).powi(2) + (r.cy - o.cy).powi(2)).sqrt();
            if d <= o.half_extent() {
                let wsum = o.weight + r.weight;
                o.cx = (o.cx * o.weight + r.cx * r.weight) / wsum;
                o.cy = (o.cy * o.weight + r.cy * r.weight) / wsum;
                o.weight = wsum;
                o.signed += r.signed;
                o.area += r.area;
                o.x0 = o.x0.min(r.x0);
                o.y0 = o.y0.min(r.y0);
                o.x1 = o.x1.max(r.x1);
                o.y1 = o.y1.max(r.y1);
                continue 'next;
            }
        }
        out.push(r);
    }
    out
}

/// Correlation of neighbouring pixels' gradients (3×3 box, then Sobel): the independent
/// samples are about this many times fewer than the edge pixels.
const GRADIENT_CORRELATION_AREA: f64 = 9.0;

struct Fit {
    c: [f64; 2],
    cov: nalgebra::Matrix2<f64>,
    radius: f64,
    scatter: f64,
    used: usize,
}

/// Radial-symmetry centre in a disc of radius `roi` about `c0`, on gradients `gx`, `gy`.
fn radial_centre(
    gx: &[f32],
    gy: &[f32],
    w: usize,
    h: usize,
    c0: [f64; 2],
    roi: f64,
    g_floor2: f64,
) -> Option<Fit> {
    let mut c = c0;
    let mut last = None;
    for _ in 0..4 {
        let x0 = (c[0] - roi).floor().max(1.0) as usize;
        let x1 = ((c[0] + roi).ceil() as usize).min(w.saturating_sub(2));
        let y0 = (c[1] - roi).floor().max(1.0) as usize;
        let y1 = ((c[1] + roi).ceil() as usize).min(h.saturating_sub(2));
        let mut m = nalgebra::Matrix2::<f64>::zeros();
        let mut b = nalgebra::Vector2::<f64>::zeros();
        let mut pts = Vec::new();
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (dx, dy) = (x as f64 - c[0], y as f64 - c[1]);
                if dx * dx + dy * dy > roi * roi {
                    continue;
                }
                let i = y * w + x;
                let (a, bb) = (f64::from(gx[i]), f64::from(gy[i]));
                let g2 = a * a + bb * bb;
                if g2 <= g_floor2 {
                    continue;
                }
                let gm = g2.sqrt();
                // Unit normal to the gradient line.
                let n = nalgebra::Vector2::new(-bb / gm, a / gm);
                let p = nalgebra::Vector2::new(x as f64, y as f64);
                let wgt = g2;
                let nn = n * n.transpose();
                m += wgt * nn;
                b += wgt * nn * p;
                pts.push((wgt, n, p));
            }
        }
        if pts.len() < 8 {
            return None;
        }
        let minv = m.try_inverse()?;
        let cn = minv * b;
        let mut meat = nalgebra::Matrix2::<f64>::zeros();
        let (mut sw, mut swr2, mut swd) = (0.0, 0.0, 0.0);
        for (wgt, n, p) in &pts {
            let r = n.dot(&(cn - p));
            meat += (wgt * wgt * r * r) * (n * n.transpose());
            sw += wgt;
            swr2 += wgt * r * r;
            swd += wgt * (cn - p).norm();
        }
        let cov = minv * meat * minv * GRADIENT_CORRELATION_AREA;
        let moved = ((cn.x - c[0]).powi(2) + (cn.y - c[1]).powi(2)).sqrt();
        c = [cn.x, cn.y];
        last = Some(Fit {
            c,
            cov,
            radius: swd / sw,
            scatter: (swr2 / sw).sqrt(),
            used: pts.len(),
        });
        if moved < 1e-3 {
            break;
        }
    }
    last
}

fn bilinear(img: &[f32], w: usize, h: usize, x: f64, y: f64) -> Option<f64> {
    if x < 0.0 || y < 0.0 || x > (w - 1) as f64 || y > (h - 1) as f64 {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let v = |xx: usize, yy: usize| f64::from(img[yy * w + xx]);
    Some(
        v(x0, y0) * (1.0 - fx) * (1.0 - fy)
            + v(x1, y0) * fx * (1.0 - fy)
            + v(x0, y1) * (1.0 - fx) * fy
            + v(x1, y1) * fx * fy,
    )
}

/// Direction of the shading correction (see [`edge_circle`]).
const SHADE_SIGN: f64 = 1.0;

/// Rays cast from the radial-symmetry centre.
const RAYS: usize = 72;

/// The outer edge found along rays from `c0` (the steepest step of the expected sign, `sign` =
/// +1 for a dark object on a lighter background, −1 for a bright one, within 0.7–1.3 of the
/// region's half extent `he`, to a parabola's sub-pixel peak), and a circle fitted to those edge
/// points by Gauss–Newton with the furthest ones left out. The edge's position along a ray is
/// not tilted by shading across the nozzle, which turns gradient directions (a dark tip lit
/// from one side moved the radial-symmetry centre by up to 0.9 px in the tests).
fn edge_circle(rs: &[f32], w: usize, h: usize, c0: [f64; 2], he: f64, sign: f64) -> Option<Fit> {
    let step = 0.25;
    let (r_lo, r_hi) = (0.6 * he, 1.35 * he);
    let mut pts: Vec<([f64; 2], f64)> = Vec::new();
    let mut rays: Vec<(f64, f64, f64, f64)> = Vec::new(); // angle, edge radius, peak, step
    for k in 0..RAYS {
        let a = std::f64::consts::TAU * k as f64 / RAYS as f64;
        let (ca, sa) = (a.cos(), a.sin());
        let mut prof = Vec::new();
        let mut r = r_lo - step;
        while r <= r_hi + step {
            prof.push(bilinear(rs, w, h, c0[0] + r * ca, c0[1] + r * sa)?);
            r += step;
        }
        // Signed derivative along the ray, central differences.
        let d: Vec<f64> = (1..prof.len() - 1)
            .map(|i| sign * (prof[i + 1] - prof[i - 1]) / (2.0 * step))
            .collect();
        let (im, dm) =
            d.iter().enumerate().fold(
                (0, f64::NEG_INFINITY),
                |b, (i, v)| if *v > b.1 { (i, *v) } else { b },
            );
        if dm <= 0.0 || im == 0 || im + 1 >= d.len() {
            continue;
        }
        let (a0, a1, a2) = (d[im - 1], d[im], d[im + 1]);
        let den = a0 - 2.0 * a1 + a2;
        let off = if den < 0.0 {
            0.5 * (a0 - a2) / den
        } else {
            0.0
        };
        let re = r_lo + (im as f64 + off) * step;
        let stepv = sign * (prof[prof.len() - 1] - prof[0]);
        rays.push((a, re, dm, stepv));
    }
    if rays.len() < RAYS / 2 {
        return None;
    }
    // Shading across the nozzle (lit from one side): the edge's strength varies as
    // 1 + s·cos(φ − φs) around it, and a blurred edge whose contrast grows outwards peaks
    // σ²·∂ln(contrast)/∂r further out. σ from the step and its steepest slope,
    // σ = step/(√(2π)·peak). Each edge point is moved back by that amount.
    let k = rays.len() as f64;
    let a0 = rays.iter().map(|r| r.2).sum::<f64>() / k;
    let a1 = 2.0 * rays.iter().map(|r| r.2 * r.0.cos()).sum::<f64>() / k;
    let b1 = 2.0 * rays.iter().map(|r| r.2 * r.0.sin()).sum::<f64>() / k;
    let mut sig: Vec<f64> = rays
        .iter()
        .filter(|r| r.3 > 0.0)
        .map(|r| r.3 / ((std::f64::consts::TAU).sqrt() * r.2))
        .collect();
    let sigma = median_in_place(&mut sig).clamp(0.0, 0.5 * he);
    let rad0 = rays.iter().map(|r| r.1).sum::<f64>() / k;
    // The correction is a first-order one: its size is kept as a systematic uncertainty.
    let u_sys = sigma * sigma * a1.hypot(b1) / a0.max(1e-9) / rad0.max(1.0);
    for &(a, re, dm, _) in &rays {
        let shade = (a1 * a.cos() + b1 * a.sin()) / a0.max(1e-9);
        let re = re - SHADE_SIGN * sigma * sigma * shade / rad0.max(1.0);
        pts.push(([c0[0] + re * a.cos(), c0[1] + re * a.sin()], dm));
    }
    let mut keep = vec![true; pts.len()];
    let (mut c, mut rad) = (c0, he);
    for round in 0..3 {
        for _ in 0..6 {
            // Gauss–Newton on r_i = |p_i − c| − R.
            let mut jtj = nalgebra::Matrix3::<f64>::zeros();
            let mut jtr = nalgebra::Vector3::<f64>::zeros();
            for ((p, _), k) in pts.iter().zip(&keep) {
                if !k {
                    continue;
                }
                let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                let d = dx.hypot(dy).max(1e-9);
                let j = nalgebra::Vector3::new(-dx / d, -dy / d, -1.0);
                jtj += j * j.transpose();
                jtr += j * (d - rad);
            }
            let delta = jtj.lu().solve(&(-jtr))?;
            c = [c[0] + delta.x, c[1] + delta.y];
            rad += delta.z;
            if delta.norm() < 1e-6 {
                break;
            }
        }
        let res: Vec<f64> = pts
            .iter()
            .map(|(p, _)| (p[0] - c[0]).hypot(p[1] - c[1]) - rad)
            .collect();
        let mut a: Vec<f64> = res
            .iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(r, _)| r.abs())
            .collect();
        let res_sd = (1.4826 * median_in_place(&mut a)).max(0.02);
        if round < 2 {
            for (r, k) in res.iter().zip(keep.iter_mut()) {
                *k = r.abs() <= 3.0 * res_sd + 0.1;
            }
        }
    }
    let used: Vec<f64> = pts
        .iter()
        .zip(&keep)
        .filter(|(_, k)| **k)
        .map(|(p, _)| (p.0[0] - c[0]).hypot(p.0[1] - c[1]) - rad)
        .collect();
    let m = used.len();
    if m < RAYS / 2 {
        return None;
    }
    let rms = (used.iter().map(|r| r * r).sum::<f64>() / (m - 3) as f64).sqrt();
    // Neighbouring rays see overlapping smoothed pixels: count them as fewer independent points.
    let indep = (m as f64).min(std::f64::consts::TAU * rad / 2.0).max(3.0);
    let var = rms * rms * 2.0 / indep + u_sys * u_sys;
    Some(Fit {
        c,
        cov: nalgebra::Matrix2::new(var, 0.0, 0.0, var),
        radius: rad,
        scatter: rms,
        used: m,
    })
}

/// Finds the nozzle in `img`, or says why not.
///
/// # Errors
/// A [`Refusal`] naming what is wrong with the picture and what is expected.
pub(crate) fn detect(img: &Gray<'_>, p: &DetectParams) -> Result<Detection, Refusal> {
    let (w, h) = (img.width, img.height);
    if w.checked_mul(h) != Some(img.data.len()) {
        return Err(Refusal::BadImage {
            detail: format!("{} bytes for {w}×{h} pixels", img.data.len()),
        });
    }
    if w < 32 || h < 32 {
        return Err(Refusal::BadImage {
            detail: format!("{w}×{h} pixels; expected at least 32×32"),
        });
    }
    let n = w * h;
    let mut hist = [0usize; 256];
    for &v in img.data {
        hist[v as usize] += 1;
    }
    let white = hist[250..].iter().sum::<usize>() as f64 / n as f64;
    let black = hist[..=5].iter().sum::<usize>() as f64 / n as f64;
    if white > p.max_clipped_fraction || black > p.max_clipped_fraction {
        return Err(Refusal::Saturated {
            white_pct: 100.0 * white,
            black_pct: 100.0 * black,
        });
    }
    let range = percentile_u8(&hist, n, 0.999) - percentile_u8(&hist, n, 0.001);
    if range < p.min_contrast {
        return Err(Refusal::TooLittleContrast {
            contrast: range,
            needed: p.min_contrast,
        });
    }
    let (bg, _) = Background::fit(img);
    let mut res = vec![0f32; n];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            res[i] = (f64::from(img.data[i]) - bg.at(x as f64, y as f64)) as f32;
        }
    }
    let rs = box3(&res, w, h);
    // Noise of the smoothed residual, from the whole picture (the nozzle is a small share).
    let mut absr: Vec<f64> = rs.iter().step_by(3).map(|v| f64::from(v.abs())).collect();
    let noise = (1.4826 * median_in_place(&mut absr)).max(0.3);
    let strongest = rs.iter().fold(0f32, |m, v| m.max(v.abs())) as f64;
    let needed = p.min_contrast.max(p.min_snr * noise);
    if strongest < needed {
        // A faint object above the noise is "too little contrast"; only noise is "no nozzle".
        if strongest >= p.min_snr * noise {
            return Err(Refusal::TooLittleContrast {
                contrast: strongest,
                needed,
            });
        }
        return Err(Refusal::NoNozzle { strongest, needed });
    }
    let thr = (0.3 * strongest).max(0.5 * needed) as f32;
    let mask: Vec<bool> = rs.iter().map(|v| v.abs() > thr).collect();
    let cands: Vec<Region> = join_nested(regions(&mask, &rs, w, h))
        .into_iter()
        .filter(|r| r.area >= p.min_area_px)
        .collect();
    let Some(first) = cands.first().cloned() else {
        return Err(Refusal::NoNozzle { strongest, needed });
    };
    let rivals: Vec<&Region> = cands
        .iter()
        .filter(|r| r.weight >= p.second_candidate_ratio * first.weight)
        .collect();
    if rivals.len() >= 2 {
        return Err(Refusal::TwoCandidates {
            count: rivals.len(),
            centres_px: rivals.iter().map(|r| [r.cx, r.cy]).collect(),
        });
    }
    if first.x0 == 0 || first.y0 == 0 || first.x1 + 1 >= w || first.y1 + 1 >= h {
        return Err(Refusal::AtEdge {
            centre_px: [first.cx, first.cy],
        });
    }
    // Gradients (Sobel) of the smoothed residual.
    let mut gx = vec![0f32; n];
    let mut gy = vec![0f32; n];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let at = |dx: i64, dy: i64| rs[(y as i64 + dy) as usize * w + (x as i64 + dx) as usize];
            gx[y * w + x] = (at(1, -1) + 2.0 * at(1, 0) + at(1, 1))
                - (at(-1, -1) + 2.0 * at(-1, 0) + at(-1, 1));
            gy[y * w + x] = (at(-1, 1) + 2.0 * at(0, 1) + at(1, 1))
                - (at(-1, -1) + 2.0 * at(0, -1) + at(1, -1));
        }
    }
    // Gradient of pure noise: Sobel of the smoothed noise has an sd of about 4·noise per axis;
    // only edges well above it vote.
    let g_floor = 3.0 * 4.0 * noise;
    let roi = 1.4 * first.half_extent() + 3.0;
    let Some(fit) = radial_centre(&gx, &gy, w, h, [first.cx, first.cy], roi, g_floor * g_floor)
    else {
        return Err(Refusal::NoNozzle { strongest, needed });
    };
    if fit.scatter > p.max_scatter_share * fit.radius.max(1.0) + 0.5 {
        return Err(Refusal::NotRound {
            scatter_px: fit.scatter,
            radius_px: fit.radius,
        });
    }
    let sign = if first.signed >= 0.0 { -1.0 } else { 1.0 };
    let Some(fit) = edge_circle(&rs, w, h, fit.c, first.half_extent(), sign) else {
        return Err(Refusal::NotRound {
            scatter_px: fit.scatter,
            radius_px: fit.radius,
        });
    };
    if fit.scatter > p.max_scatter_share * fit.radius.max(1.0) + 0.5 {
        return Err(Refusal::NotRound {
            scatter_px: fit.scatter,
            radius_px: fit.radius,
        });
    }
    let u = (0.5 * (fit.cov[(0, 0)] + fit.cov[(1, 1)])).max(0.0).sqrt();
    if !u.is_finite() || u > p.max_uncertainty_px {
        return Err(Refusal::Uncertain {
            uncertainty_px: u,
            limit_px: p.max_uncertainty_px,
        });
    }
    let [cx, cy] = fit.c;
    if cx - fit.radius < 0.0
        || cy - fit.radius < 0.0
        || cx + fit.radius > (w - 1) as f64
        || cy + fit.radius > (h - 1) as f64
    {
        return Err(Refusal::AtEdge { centre_px: fit.c });
    }
    Ok(Detection {
        centre_px: fit.c,
        uncertainty_px: u,
        diagnostics: Diagnostics {
            background: bg.at(cx, cy),
            noise_sd: noise,
            contrast: strongest,
            polarity: if first.signed >= 0.0 {
                Polarity::Bright
            } else {
                Polarity::Dark
            },
            radius_px: fit.radius,
            scatter_px: fit.scatter,
            candidates: cands.len(),
            clipped_fraction: white + black,
            edge_pixels: fit.used,
            centroid_px: [first.cx, first.cy],
        },
    })
}
