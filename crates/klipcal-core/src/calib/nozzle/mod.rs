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
//!
//! This file holds the types and [`detect`], the method's steps in order; the background and
//! the candidates are in `background`, the sub-pixel centre in `centre`. A person's click on
//! the nozzle, in a picture the detector cannot read, is refined from the pictures in
//! `register` ([`Reference`]).

use serde::Serialize;

use background::{box3, join_nested, median_in_place, percentile_u8, regions, Background, Region};
use centre::{edge_circle, radial_centre};

mod background;
mod centre;
mod decode;
mod register;

pub use decode::decode_gray;
pub use register::{ClickReader, ClickReading};

/// What the edge fit's least-squares covariance leaves out of a centre's error, px: it treats
/// the residuals as independent, but the smoothing correlates neighbouring pixels and JPEG's
/// 8×8 blocks add structured error. On the bench's renderings (JPEG q 60–95, blur sd
/// 0.6–2.5 px, noise sd 1–5, both families) the errors were 1.2× the fit's σ at every noise
/// level, and both coordinates fell within ±2 × the fit's σ on 80–82 % of pictures, against
/// the 91 % of two normal coordinates at 95 % each. This much in quadrature brings that to
/// 93–94 % (`klipcal bench backlash`).
const UNMODELLED_SD_PX: f64 = 0.04;

/// A grey image borrowed from its decoder: row-major, one byte per pixel.
#[derive(Debug, Clone, Copy)]
pub struct Gray<'a> {
    pub width: usize,
    pub height: usize,
    pub data: &'a [u8],
}

/// Limits of the detection. The defaults suit 320×240 to 1920×1080 snapshots of a nozzle that
/// spans a few percent of the frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DetectParams {
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
pub enum Refusal {
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
pub enum Polarity {
    Bright,
    Dark,
}

/// What the detection saw, for a person checking their camera.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Diagnostics {
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
pub struct Detection {
    /// Centre, px (pixel centres at integers).
    pub centre_px: [f64; 2],
    /// 1 sd per axis, px.
    pub uncertainty_px: f64,
    pub diagnostics: Diagnostics,
}

/// Finds the nozzle in `img`, or says why not.
///
/// # Errors
/// A [`Refusal`] naming what is wrong with the picture and what is expected.
pub fn detect(img: &Gray<'_>, p: &DetectParams) -> Result<Detection, Refusal> {
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
    // The fit's own covariance, and in quadrature what it leaves out (issue 27).
    let u = (0.5 * (fit.cov[(0, 0)] + fit.cov[(1, 1)]))
        .max(0.0)
        .sqrt()
        .hypot(UNMODELLED_SD_PX);
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
