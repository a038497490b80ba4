//! The sub-pixel centre: the edge circle fitted along rays from a first guess, with its
//! uncertainty and how closed the edge is all round.

use super::background::median_in_place;

#[derive(Clone)]
pub(super) struct Fit {
    pub(super) c: [f64; 2],
    pub(super) cov: nalgebra::Matrix2<f64>,
    pub(super) radius: f64,
    pub(super) scatter: f64,
    pub(super) used: usize,
    /// How closed the edge is: the weakest of eight 45° sectors' mean edge slope over the
    /// mean of all (1: the same all round; 0: a sector without an edge).
    pub(super) closed: f64,
    /// The edge's height: the median over the rays of the level's rise across it, grey levels.
    pub(super) step: f64,
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
pub(super) fn edge_circle(
    rs: &[f32],
    w: usize,
    h: usize,
    c0: [f64; 2],
    he: f64,
    sign: f64,
) -> Option<Fit> {
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
        closed: closedness(&rays),
        step: {
            let mut st: Vec<f64> = rays.iter().map(|r| r.3).collect();
            median_in_place(&mut st)
        },
    })
}

/// The weakest 45° sector's mean edge slope over the mean of all rays (`rays`: angle, edge
/// radius, slope, step), 0 when a sector has no ray with an edge.
fn closedness(rays: &[(f64, f64, f64, f64)]) -> f64 {
    let mut sum = [0.0f64; 8];
    for &(a, _, dm, _) in rays {
        let k = ((a / std::f64::consts::TAU * 8.0).floor() as usize).min(7);
        sum[k] += dm;
    }
    let all = rays.iter().map(|r| r.2).sum::<f64>() / RAYS as f64;
    let per = (RAYS / 8) as f64;
    (0..8)
        .map(|k| sum[k] / per / all.max(1e-12))
        .fold(f64::INFINITY, f64::min)
        .min(1.0)
}
