//! The picture's lighting taken out and its candidates found: the robust quadratic background,
//! the 3×3 box filter, the connected regions that stand out from the background (the nested
//! parts of a ring joined to it).

use super::Gray;

pub(super) fn median_in_place(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, f64::total_cmp);
    *m
}

pub(super) fn percentile_u8(hist: &[usize; 256], n: usize, q: f64) -> f64 {
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
pub(super) struct Background {
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

    pub(super) fn at(&self, x: f64, y: f64) -> f64 {
        let b = self.basis(x, y);
        b.iter().zip(&self.coef).map(|(a, c)| a * c).sum()
    }

    /// Robust fit on a grid of samples: least squares, then again on the samples within 2.5
    /// robust sd of the fit, four times. Returns the fit and the inliers' noise sd.
    pub(super) fn fit(img: &Gray<'_>) -> (Background, f64) {
        Self::fit_across(img, 160)
    }

    /// [`Background::fit`] on a grid of about `across` samples along the picture's longer side.
    pub(super) fn fit_across(img: &Gray<'_>, across: usize) -> (Background, f64) {
        let step = (img.width.max(img.height) / across.max(1)).max(1);
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
pub(super) fn box3(src: &[f32], w: usize, h: usize) -> Vec<f32> {
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
pub(super) struct Region {
    pub(super) area: usize,
    pub(super) weight: f64,
    pub(super) signed: f64,
    pub(super) cx: f64,
    pub(super) cy: f64,
    pub(super) x0: usize,
    pub(super) y0: usize,
    pub(super) x1: usize,
    pub(super) y1: usize,
}

impl Region {
    pub(super) fn half_extent(&self) -> f64 {
        0.5 * ((self.x1 - self.x0 + 1).max(self.y1 - self.y0 + 1)) as f64
    }
}

/// Connected regions (8-neighbour) of `mask`, with their |residual|-weighted centroids.
pub(super) fn regions(mask: &[bool], res: &[f32], w: usize, h: usize) -> Vec<Region> {
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
pub(super) fn join_nested(mut rs: Vec<Region>) -> Vec<Region> {
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
