//! The picture's pixel noise, measured where noise lives: at the finest scale.
//!
//! Issue 37: the noise used to be the spread of what was left after a smooth background was
//! taken out of the whole picture. On a real nozzle camera, zoomed in, that remainder *is* the
//! scene (hex flats, the cone, machining marks, filament): 39–94 grey levels on TAMV's and
//! kTAMV's photographs against a pixel-to-pixel noise of 1–3, so eight times it was more than
//! anything in the picture reached and every real nozzle was refused.
//!
//! Here the noise is Immerkær's (1996) estimator made robust: the picture convolved with the
//! difference of two Laplacians
//! ```text
//!  1 −2  1
//! −2  4 −2
//!  1 −2  1
//! ```
//! which cancels any plane and any quadratic ramp (the lighting, the blur of an edge along
//! either axis) and turns white noise of sd σ into 6σ. The median of its magnitude (× 1.4826
//! for a normal sd) leaves out the minority of pixels on edges and texture, which the mean of
//! Immerkær's original counts in. Detection, the click's refinement by registration and the
//! camera flow's "still" test (which compares frames within their stated sd, themselves
//! from this noise) all read this one figure.

use super::background::median_in_place;
use super::Gray;

/// Below this the estimate is taken as this, grey levels: an 8-bit picture's own rounding
/// (1/√12 ≈ 0.29), which JPEG's flat blocks can hide from the fine scale.
pub const NOISE_FLOOR: f64 = 0.3;

/// Pixel noise sd (grey levels, one pixel) of `img` over the box `x0..x1 × y0..y1`
/// (half-open, clipped to the picture; `None`: the whole picture), from the finest scale.
pub fn fine_noise_sd(img: &Gray<'_>, region: Option<[usize; 4]>) -> f64 {
    let (w, h) = (img.width, img.height);
    if w < 3 || h < 3 || img.data.len() < w * h {
        return NOISE_FLOOR;
    }
    let [x0, x1, y0, y1] = region.unwrap_or([0, w, 0, h]);
    let (x0, y0) = (x0.max(1), y0.max(1));
    let (x1, y1) = (x1.min(w - 1), y1.min(h - 1));
    if x1 <= x0 || y1 <= y0 {
        return NOISE_FLOOR;
    }
    // At most about 40 000 samples: the median settles long before.
    let n = (x1 - x0) * (y1 - y0);
    let step = ((n as f64 / 40_000.0).sqrt().ceil() as usize).max(1);
    let px = |x: usize, y: usize| f64::from(img.data[y * w + x]);
    let mut m = Vec::with_capacity(n / (step * step) + 1);
    for y in (y0..y1).step_by(step) {
        for x in (x0..x1).step_by(step) {
            let v = px(x - 1, y - 1) + px(x + 1, y - 1) + px(x - 1, y + 1) + px(x + 1, y + 1)
                - 2.0 * (px(x, y - 1) + px(x - 1, y) + px(x + 1, y) + px(x, y + 1))
                + 4.0 * px(x, y);
            m.push(v.abs());
        }
    }
    (1.4826 * median_in_place(&mut m) / 6.0).max(NOISE_FLOOR)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn normal(rng: &mut fastrand::Rng) -> f64 {
        let u = rng.f64().max(1e-12);
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.f64()).cos()
    }

    /// White noise of sd 3 on a steep quadratic ramp and a sharp-edged disc reads 3 ± 10 %:
    /// the ramp is cancelled, the disc's edge is a minority the median leaves out; so does a
    /// window of the picture.
    #[test]
    fn noise_on_a_ramp_and_an_edge_reads_the_drawn_sd() {
        let (w, h) = (320, 240);
        let mut rng = fastrand::Rng::with_seed(5);
        let mut a = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (u, v) = (x as f64 / w as f64, y as f64 / h as f64);
                let disc = if (x as f64 - 160.0).hypot(y as f64 - 120.0) < 40.0 {
                    -70.0
                } else {
                    0.0
                };
                let base = 90.0 + 60.0 * u + 40.0 * v * v + disc;
                a.push((base + 3.0 * normal(&mut rng)).round().clamp(0.0, 255.0) as u8);
            }
        }
        let ga = Gray {
            width: w,
            height: h,
            data: &a,
        };
        let s = fine_noise_sd(&ga, None);
        assert!((s - 3.0).abs() < 0.3, "{s}");
        let part = fine_noise_sd(&ga, Some([100, 220, 80, 160]));
        assert!((part - 3.0).abs() < 0.4, "{part}");
    }
}
