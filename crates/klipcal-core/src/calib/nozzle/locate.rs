//! Where in the picture the nozzle is: a radial-symmetry vote (after Loy and Zelinsky's fast
//! radial symmetry transform, 2003), before any sub-pixel fit.
//!
//! Real nozzle cameras are zoomed in (issue 37): the hex flats, the cone and the tip fill the
//! view, so nothing "stands out from a background" — the background *is* the nozzle. What marks
//! the tip is that several edges (the orifice, the ring round it, the cone) are circles about
//! one point. Every edge pixel votes, at each radius of a geometric ladder, for the point that
//! far along its gradient, both ways (a dark and a bright centre), with a weight of its
//! gradient over the circle's length, so a whole circle of any size scores its edge strength
//! and circles about one point add up. Texture, sparkles and straight edges spread their
//! votes; a speck votes at one small radius only.

/// One peak of the vote map: the centre, px, and its score (grey levels per px).
#[derive(Debug, Clone, Copy)]
pub(super) struct Peak {
    pub(super) c: [f64; 2],
    pub(super) score: f64,
}

/// The vote map's peaks, strongest first (local maxima with at least a third of the best's
/// score, at most [`MAX_PEAKS`]).
#[derive(Debug, Clone)]
pub(super) struct Votes {
    pub(super) peaks: Vec<Peak>,
}

/// Peaks examined by the fit: the tip is among the strongest few on every real photo tried.
const MAX_PEAKS: usize = 10;

/// The vote map is made on the picture pooled to at most this many pixels along its longer
/// side: a 1920×1080 snapshot votes at 480×270.
const VOTE_SIDE: usize = 480;

fn pool(rs: &[f32], w: usize, h: usize, s: usize) -> (Vec<f32>, usize, usize) {
    let (pw, ph) = (w / s, h / s);
    let mut out = vec![0f32; pw * ph];
    for (j, row) in out.chunks_mut(pw).enumerate() {
        for (i, v) in row.iter_mut().enumerate() {
            let mut a = 0f32;
            for y in j * s..(j + 1) * s {
                for x in i * s..(i + 1) * s {
                    a += rs[y * w + x];
                }
            }
            *v = a / (s * s) as f32;
        }
    }
    (out, pw, ph)
}

/// Sobel gradients (edges left at zero).
fn sobel(rs: &[f32], w: usize, h: usize) -> (Vec<f32>, Vec<f32>) {
    let mut gx = vec![0f32; w * h];
    let mut gy = vec![0f32; w * h];
    for y in 1..h.saturating_sub(1) {
        for x in 1..w - 1 {
            let at = |dx: i64, dy: i64| rs[(y as i64 + dy) as usize * w + (x as i64 + dx) as usize];
            gx[y * w + x] = (at(1, -1) + 2.0 * at(1, 0) + at(1, 1))
                - (at(-1, -1) + 2.0 * at(-1, 0) + at(-1, 1));
            gy[y * w + x] = (at(-1, 1) + 2.0 * at(0, 1) + at(1, 1))
                - (at(-1, -1) + 2.0 * at(0, -1) + at(1, -1));
        }
    }
    (gx, gy)
}

/// The vote map of the smoothed picture `rs` (`w`×`h`), edges whose Sobel gradient exceeds
/// `g_floor` voting at radii from 2 px to `r_max` px (of the full picture); peaks closer than
/// `apart` px to the best are its own.
pub(super) fn vote(
    rs: &[f32],
    w: usize,
    h: usize,
    g_floor: f64,
    r_max: f64,
    coarse: usize,
) -> Option<Votes> {
    let s = w.max(h).div_ceil(VOTE_SIDE).max(1) * coarse.max(1);
    let (pooled, pw, ph) = if s > 1 {
        pool(rs, w, h, s)
    } else {
        (rs.to_vec(), w, h)
    };
    if pw < 8 || ph < 8 {
        return None;
    }
    let (gx, gy) = sobel(&pooled, pw, ph);
    // Pooling by s averages s² pixels' noise: the floor shrinks with it.
    let floor = g_floor / s as f64;
    let r_hi = (r_max / s as f64).max(3.0);
    let mut radii = Vec::new();
    let mut r = 2.0f64;
    while r <= r_hi {
        radii.push(r);
        r *= 1.2;
    }
    // The voting edges, once.
    let mut edges = Vec::new();
    for y in 1..ph - 1 {
        for x in 1..pw - 1 {
            let i = y * pw + x;
            let (a, b) = (f64::from(gx[i]), f64::from(gy[i]));
            let g = a.hypot(b);
            if g > floor {
                edges.push((x as f64, y as f64, a / g, b / g, g));
            }
        }
    }
    let mut map = vec![0f32; pw * ph];
    let mut one = vec![0f32; pw * ph];
    for &n in &radii {
        one.iter_mut().for_each(|v| *v = 0.0);
        for &(x, y, ux, uy, g) in &edges {
            let wgt = (g / (std::f64::consts::TAU * n).sqrt()) as f32;
            // + at the centre of a bright disc (the gradient points up the slope, inwards),
            // − at a dark one's: along one circle the votes agree, across texture they cancel.
            for (sgn, sw) in [(1.0, wgt), (-1.0, -wgt)] {
                let (vx, vy) = (x + sgn * n * ux, y + sgn * n * uy);
                if vx < 0.0 || vy < 0.0 || vx > (pw - 1) as f64 || vy > (ph - 1) as f64 {
                    continue;
                }
                let (x0, y0) = (vx.floor() as usize, vy.floor() as usize);
                let (fx, fy) = ((vx - x0 as f64) as f32, (vy - y0 as f64) as f32);
                let (x1, y1) = ((x0 + 1).min(pw - 1), (y0 + 1).min(ph - 1));
                one[y0 * pw + x0] += sw * (1.0 - fx) * (1.0 - fy);
                one[y0 * pw + x1] += sw * fx * (1.0 - fy);
                one[y1 * pw + x0] += sw * (1.0 - fx) * fy;
                one[y1 * pw + x1] += sw * fx * fy;
            }
        }
        // A circle between two rungs of the ladder votes on a small ring about its centre:
        // blurred over a tenth of the radius (twice: a triangle), the ring is a peak again.
        let b = ((0.1 * n).round() as usize).max(1);
        let blurred = box_blur(&box_blur(&one, pw, ph, b), pw, ph, b);
        for (m, v) in map.iter_mut().zip(&blurred) {
            *m += v.abs();
        }
    }
    let at = |i: usize| {
        let (x, y) = ((i % pw) as f64, (i / pw) as f64);
        let k = s as f64;
        [k * x + 0.5 * (k - 1.0), k * y + 0.5 * (k - 1.0)]
    };
    let top = map.iter().fold(0f32, |m, v| m.max(*v));
    let mut maxima: Vec<usize> = Vec::new();
    for y in 1..ph - 1 {
        for x in 1..pw - 1 {
            let i = y * pw + x;
            let v = map[i];
            if v < top / 3.0 {
                continue;
            }
            let local = (-1i64..=1).all(|dy| {
                (-1i64..=1).all(|dx| {
                    let j = (y as i64 + dy) as usize * pw + (x as i64 + dx) as usize;
                    map[j] < v || (map[j] == v && j >= i)
                })
            });
            if local {
                maxima.push(i);
            }
        }
    }
    maxima.sort_by(|a, b| map[*b].total_cmp(&map[*a]));
    let mut peaks: Vec<Peak> = Vec::new();
    for i in maxima {
        let c = at(i);
        // Peaks a few pixels apart are one hill's shoulders.
        if peaks
            .iter()
            .any(|p| (p.c[0] - c[0]).hypot(p.c[1] - c[1]) < 4.0 * s as f64)
        {
            continue;
        }
        peaks.push(Peak {
            c,
            score: f64::from(map[i]),
        });
        if peaks.len() == MAX_PEAKS {
            break;
        }
    }
    (!peaks.is_empty()).then_some(Votes { peaks })
}

/// The strong circular edges about `c` in the smoothed picture `rs`, innermost first: the mean
/// profile over 72 rays out to `r_max`, its slope, and the peaks of |slope| with at least
/// `share` of the largest. Each is (radius px, slope: > 0 where the edge is darker inside).
pub(super) fn ring_edges(
    rs: &[f32],
    w: usize,
    h: usize,
    c: [f64; 2],
    r_max: f64,
    share: f64,
) -> Option<Vec<(f64, f64)>> {
    let step = 0.5;
    let n = (r_max / step) as usize;
    if n < 6 {
        return None;
    }
    let mut prof = vec![0.0f64; n];
    let mut cnt = vec![0usize; n];
    for k in 0..72 {
        let a = std::f64::consts::TAU * k as f64 / 72.0;
        let (ca, sa) = (a.cos(), a.sin());
        for (i, (p, q)) in prof.iter_mut().zip(cnt.iter_mut()).enumerate() {
            let r = step * (i as f64 + 1.0);
            let (x, y) = (c[0] + r * ca, c[1] + r * sa);
            if x < 0.0 || y < 0.0 || x > (w - 1) as f64 || y > (h - 1) as f64 {
                continue;
            }
            let (xi, yi) = (x.round() as usize, y.round() as usize);
            *p += f64::from(rs[yi * w + xi]);
            *q += 1;
        }
    }
    let prof: Vec<f64> = prof
        .iter()
        .zip(&cnt)
        .map(|(p, q)| if *q > 36 { p / *q as f64 } else { f64::NAN })
        .collect();
    let d: Vec<f64> = (1..n - 1)
        .map(|i| (prof[i + 1] - prof[i - 1]) / (2.0 * step))
        .collect();
    let top = d
        .iter()
        .filter(|v| v.is_finite())
        .fold(0f64, |m, v| m.max(v.abs()));
    if top <= 0.0 {
        return None;
    }
    Some(
        (1..d.len() - 1)
            .filter(|&i| {
                let v = d[i].abs();
                v.is_finite() && v >= share * top && v >= d[i - 1].abs() && v >= d[i + 1].abs()
            })
            .map(|i| (step * (i as f64 + 2.0), d[i]))
            .collect(),
    )
}

/// Box blur of half-width `b` along x then y (edges clamped), by running sums.
fn box_blur(src: &[f32], w: usize, h: usize, b: usize) -> Vec<f32> {
    let pass = |src: &[f32], len: usize, count: usize, at: &dyn Fn(usize, usize) -> usize| {
        let mut out = vec![0f32; src.len()];
        for line in 0..count {
            let mut acc = 0f32;
            let k = (2 * b + 1) as f32;
            let get = |i: i64| src[at(line, i.clamp(0, len as i64 - 1) as usize)];
            for i in -(b as i64)..=(b as i64) {
                acc += get(i);
            }
            for i in 0..len {
                out[at(line, i)] = acc / k;
                acc += get(i as i64 + b as i64 + 1) - get(i as i64 - b as i64);
            }
        }
        out
    };
    let t = pass(src, w, h, &|line, i| line * w + i);
    pass(&t, h, w, &|line, i| i * w + line)
}
