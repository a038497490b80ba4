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

use background::{box3, percentile_u8, Background};
use centre::{edge_circle, Fit};
use locate::{ring_edges, vote};

mod background;
mod centre;
mod decode;
mod locate;
mod noise;
mod register;

pub use decode::decode_gray;
pub use noise::fine_noise_sd;
pub use register::{
    ClickReader, ClickReading, ClickRefusal, Reference, RegisterParams, DETECTED_CLICK_SD_PX,
};

/// What the edge fit's least-squares covariance leaves out of a centre's error, px: it treats
/// the residuals as independent, but the smoothing correlates neighbouring pixels and JPEG's
/// 8×8 blocks add structured error. Issue 27 measured 0.04 px on the bench's renderings; since
/// issue 37 the edge is found from a vote's peak and several concentric circles are averaged,
/// and on the same renderings (40 of each family, JPEG q 60–95, blur sd 0.6–2.5 px, noise sd
/// 1–5) both coordinates fell within ±2u on 27 of 40 dark tips with 0.04 and 35 of 40 with
/// this (`cmd::camera_render` tests).
const UNMODELLED_SD_PX: f64 = 0.08;

/// The tip's edge is the innermost circle about the vote's peak whose slope reaches this share
/// of the strongest (the orifice inside the ring inside the cone).
const INNER_SHARE: f64 = 0.4;

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
    /// Refuse when more than this fraction of pixels is clipped white (≥ 250) …
    pub max_clipped_fraction: f64,
    /// … or black (≤ 5): a zoomed-in nozzle's cone is often black over a third of the view,
    /// and TAMV's photo (a bright nozzle on a dark ground) under a dimmer light (gain 0.85,
    /// offset −10) is black over 64 % with the nozzle plain: what is in the nozzle's light
    /// is what counts, the contrast checks refuse a nozzle lost in the dark.
    pub max_black_fraction: f64,
    /// The nozzle must stand out from the background by at least this many grey levels.
    pub min_contrast: f64,
    /// … and by this many times the picture's noise sd.
    pub min_snr: f64,
    /// A candidate smaller than this (pixels) is a speck, not a nozzle.
    pub min_area_px: usize,
    /// A second tip with at least this share of the first one's vote makes the picture
    /// ambiguous: refused as "two candidates".
    pub second_candidate_ratio: f64,
    /// Refuse an answer whose uncertainty (1 sd per axis) exceeds this, px.
    pub max_uncertainty_px: f64,
    /// A tip's edge is closed all round: its weakest 45° sector's mean slope is at least this
    /// share of the mean (texture blobs: 0–0.5; real tips 0.7–0.9).
    pub min_closed: f64,
    /// The tip's vote must be at least this share of the strongest round structure in view,
    /// or something else (sparkles, reflections) outshines it.
    pub min_vote_share: f64,
    /// Refuse when the gradient lines scatter about the centre by more than this share of the
    /// radius (weighted rms): not a round object.
    pub max_scatter_share: f64,
}

impl Default for DetectParams {
    fn default() -> Self {
        DetectParams {
            max_clipped_fraction: 0.2,
            max_black_fraction: 0.85,
            min_contrast: 12.0,
            min_snr: 8.0,
            min_area_px: 20,
            second_candidate_ratio: 0.5,
            max_uncertainty_px: 0.5,
            min_closed: 0.65,
            min_vote_share: 0.6,
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
    /// Round things in view, but none a dark orifice or tip closed all round.
    NoTip { round: usize },
    /// A tip, but fainter than other round structure in view (sparkles, reflections).
    Outshone { centre_px: [f64; 2], share_pct: f64 },
    /// The object touches the frame, so its centre cannot be measured.
    AtEdge { centre_px: [f64; 2] },
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
            Refusal::NoTip { round } => write!(
                f,
                "no nozzle tip: nothing in view is a dark orifice or tip with an edge closed all \
                 round ({round} other round thing(s): bright specks, reflections, texture); bring \
                 the nozzle's tip over the camera, in focus, lit from the side or below"
            ),
            Refusal::Outshone {
                centre_px,
                share_pct,
            } => write!(
                f,
                "not sure: the dark round spot at ({:.0}, {:.0}) px stands out only {share_pct:.0} \
                 % as much as other round things in view (sparkles, reflections, texture); zoom \
                 in on the tip, focus, and light it evenly",
                centre_px[0], centre_px[1]
            ),
            Refusal::AtEdge { centre_px } => write!(
                f,
                "the nozzle touches the edge of the picture (near ({:.0}, {:.0}) px); move it \
                 towards the middle of the camera's view",
                centre_px[0], centre_px[1]
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
    /// Pixel noise sd, grey levels, from the picture's finest scale ([`fine_noise_sd`]).
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
    let clipped = check_exposure(img, p)?;
    let (w, h) = (img.width, img.height);
    let (bg, _) = Background::fit(img);
    let mut res = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            res[i] = (f64::from(img.data[i]) - bg.at(x as f64, y as f64)) as f32;
        }
    }
    let rs = box3(&res, w, h);
    // The pixel noise from the finest scale (issue 37), and what the 3×3 box leaves of it.
    let pixel_noise = fine_noise_sd(img, None);
    let noise = pixel_noise / 3.0;
    let strongest = rs.iter().fold(0f32, |m, v| m.max(v.abs())) as f64;
    let needed = p.min_contrast.max(p.min_snr * noise);
    if strongest < needed {
        return Err(Refusal::NoNozzle { strongest, needed });
    }
    let field = Field {
        rs: &rs,
        w,
        h,
        r_max: 0.45 * w.min(h) as f64,
    };
    // The vote at the picture's own scale and, when no tip is among its peaks, once at twice
    // it: fine texture (a knurled ring, machining marks) can outvote a tip at full resolution
    // where a coarser vote sees the tip's circles (issue 37: TAMV's photo cropped to 320×240
    // had no vote peak near its tip). The fine scale's reason is the one given.
    let tip = match field.find_tip(noise, 1, p) {
        Err(e @ (Refusal::NoTip { .. } | Refusal::NoNozzle { .. })) => {
            field.find_tip(noise, 2, p).map_err(|_| e)
        }
        other => other,
    }
    .map_err(|e| match e {
        Refusal::NoNozzle { .. } => Refusal::NoNozzle { strongest, needed },
        e => e,
    })?;
    let fit = &tip.fit;
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
            noise_sd: pixel_noise,
            contrast: strongest,
            polarity: Polarity::Dark,
            radius_px: fit.radius,
            scatter_px: fit.scatter,
            candidates: tip.candidates,
            clipped_fraction: clipped,
            edge_pixels: fit.used,
            centroid_px: tip.peak,
        },
    })
}

/// Step 1: the buffer's size, clipping and contrast; the clipped share (white + black).
fn check_exposure(img: &Gray<'_>, p: &DetectParams) -> Result<f64, Refusal> {
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
    if white > p.max_clipped_fraction || black > p.max_black_fraction {
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
    Ok(white + black)
}

/// The tip a vote found: its fit, the strongest peak (the benchmark's anchor) and how many
/// tips were in view.
struct Tip {
    fit: Fit,
    peak: [f64; 2],
    candidates: usize,
}

/// The smoothed residual, for fitting the nozzle about a vote's peak.
struct Field<'a> {
    rs: &'a [f32],
    w: usize,
    h: usize,
    r_max: f64,
}

impl Field<'_> {
    fn to_frame(&self, c: [f64; 2]) -> f64 {
        c[0].min(c[1])
            .min((self.w - 1) as f64 - c[0])
            .min((self.h - 1) as f64 - c[1])
    }

    /// Steps 3–4: the vote (pooled `coarse` times more than its own scale), each strong peak
    /// fitted, the tips (a dark edge closed all round) one per place, strongest vote first;
    /// refused when none, when other round structure outshines it, or when two are alike.
    fn find_tip(&self, noise: f64, coarse: usize, p: &DetectParams) -> Result<Tip, Refusal> {
        let (w, h) = (self.w, self.h);
        // Gradients (Sobel) of the smoothed residual. Gradient of pure noise: Sobel of the
        // smoothed noise has an sd of about 4·noise per axis; only edges well above it vote.
        let g_floor = 3.0 * 4.0 * noise;
        let Some(votes) = vote(self.rs, w, h, g_floor, self.r_max, coarse) else {
            return Err(Refusal::NoNozzle {
                strongest: 0.0,
                needed: 0.0,
            });
        };
        let top = votes.peaks[0].score;
        let mut tips: Vec<(f64, Fit)> = Vec::new();
        let (mut fitted, mut strongest_refusal) = (0, None);
        // A tip's own edge rises by as much as the nozzle must stand out (issue 37: a dark
        // mottle of an out-of-focus bed, round and closed, rose 1.5 grey levels where the real
        // photos' orifices rise 54–211).
        let min_step = p.min_contrast.max(p.min_snr * noise);
        for pk in &votes.peaks {
            match self.fit_at(pk.c, min_step, p) {
                Ok(fit) => {
                    fitted += 1;
                    let part_of =
                        |f: &Fit| (f.c[0] - fit.c[0]).hypot(f.c[1] - fit.c[1]) < f.radius.max(3.0);
                    if fit.closed >= p.min_closed && !tips.iter().any(|(_, f)| part_of(f)) {
                        tips.push((pk.score, fit));
                    }
                }
                Err(e) => {
                    if pk.c == votes.peaks[0].c {
                        strongest_refusal = Some(e);
                    }
                }
            }
        }
        let Some((score, fit)) = tips.first().map(|t| (t.0, t.1.clone())) else {
            // The strongest structure at the frame (a nozzle cut by it votes for its centre,
            // just inside) says so; anything else is no tip.
            let c = votes.peaks[0].c;
            let near_frame = self.to_frame(c) < (0.05 * w.min(h) as f64).max(4.0);
            return Err(match strongest_refusal {
                Some(e @ Refusal::AtEdge { .. }) => e,
                _ if near_frame => Refusal::AtEdge { centre_px: c },
                _ => Refusal::NoTip { round: fitted },
            });
        };
        if score < p.min_vote_share * top {
            return Err(Refusal::Outshone {
                centre_px: fit.c,
                share_pct: 100.0 * score / top,
            });
        }
        let rivals: Vec<[f64; 2]> = tips
            .iter()
            .filter(|t| t.0 >= p.second_candidate_ratio * score)
            .map(|t| t.1.c)
            .collect();
        if rivals.len() >= 2 {
            return Err(Refusal::TwoCandidates {
                count: rivals.len(),
                centres_px: rivals,
            });
        }
        Ok(Tip {
            fit,
            peak: votes.peaks[0].c,
            candidates: tips.len(),
        })
    }

    /// The innermost strong circle about `c0` ([`inner_edge`]), its centre by radial symmetry,
    /// then its edge fitted along rays ([`edge_circle`]): the fit and the sign of the edge
    /// (+1: darker inside), or why this peak is not a round nozzle. The tip's edge must rise
    /// by `min_step` grey levels (median over the rays).
    fn fit_at(&self, c0: [f64; 2], min_step: f64, p: &DetectParams) -> Result<Fit, Refusal> {
        let (rs, w, h) = (self.rs, self.w, self.h);
        let reach = self.to_frame(c0).min(self.r_max);
        if reach < 4.0 {
            return Err(Refusal::AtEdge { centre_px: c0 });
        }
        let edges = ring_edges(rs, w, h, c0, reach, INNER_SHARE).unwrap_or_default();
        let round = |f: &Fit| f.scatter <= p.max_scatter_share * f.radius.max(1.0) + 0.5;
        // The edge along rays from the peak, then again from that circle's centre: the rays'
        // steepest steps do not heed the texture inside the tip, which turns gradients.
        let fit_edge = |r: f64, slope: f64| {
            let sign = slope.signum();
            let first = edge_circle(rs, w, h, c0, r, sign)
                .filter(|f| round(f) && (f.c[0] - c0[0]).hypot(f.c[1] - c0[1]) <= r.max(3.0))?;
            edge_circle(rs, w, h, first.c, first.radius, sign)
                .filter(|f| round(f) && f.closed >= p.min_closed)
        };
        // The tip: the innermost edge darker inside (an orifice, a dark tip; a bright speck's
        // edge is passed over) that is round and closed all round.
        let Some((k, tip)) = edges
            .iter()
            .enumerate()
            .filter(|(_, e)| e.1 > 0.0)
            .find_map(|(k, e)| {
                fit_edge(e.0, e.1)
                    .filter(|f| f.step >= min_step)
                    .map(|f| (k, f))
            })
        else {
            return Err(Refusal::NoTip { round: 0 });
        };
        // The circles about it (a ring round an orifice, the cone), each a measurement of the
        // same centre: those that agree with the tip's within their errors are averaged by
        // their weights.
        let var = |f: &Fit| 0.5 * (f.cov[(0, 0)] + f.cov[(1, 1)]).max(1e-6);
        let mut used = vec![(tip.c, var(&tip))];
        for e in edges
            .iter()
            .skip(k + 1)
            .filter(|e| e.0 <= 3.0 * tip.radius + 10.0)
        {
            if let Some(f) = fit_edge(e.0, e.1) {
                let d = (f.c[0] - tip.c[0]).hypot(f.c[1] - tip.c[1]);
                if d <= (3.0 * (var(&f) + var(&tip)).sqrt() + 0.1).max(1.0) {
                    used.push((f.c, var(&f)));
                }
            }
        }
        let sw: f64 = used.iter().map(|u| 1.0 / u.1).sum();
        let c = [
            used.iter().map(|u| u.0[0] / u.1).sum::<f64>() / sw,
            used.iter().map(|u| u.0[1] / u.1).sum::<f64>() / sw,
        ];
        // The circles' own errors, and how far they disagree (shading moves each edge its own
        // way): per axis.
        let spread = used
            .iter()
            .map(|u| ((u.0[0] - c[0]).powi(2) + (u.0[1] - c[1]).powi(2)) / (2.0 * u.1))
            .sum::<f64>()
            / sw;
        let v = 1.0 / sw + spread;
        let mut out = tip;
        out.c = c;
        out.cov = nalgebra::Matrix2::new(v, 0.0, 0.0, v);
        Ok(out)
    }
}

#[cfg(test)]
mod photos_test;
