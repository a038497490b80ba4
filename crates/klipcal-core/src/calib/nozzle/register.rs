//! PURE: a clicked reading refined from the pictures (issue 27, the click flow). The person's
//! click only *locates* the nozzle; the offset between two snapshots is *measured* by
//! registering the picture around the click against the reference snapshot (the first one
//! clicked), to a few hundredths of a pixel where a finger on a phone is good to a pixel or two.
//!
//! 1. **The static background out.** The camera looks up at a moving nozzle over a background
//!    that stays where it is: a patch holding that background would be pulled toward zero
//!    shift. Each picture's lighting is fitted by the detector's robust quadratic background
//!    ([`super::background::Background`]) and subtracted, so what is left stands out because
//!    it moved with the nozzle.
//! 2. **The reference's patch is what moved.** In the first clicked snapshot, the object under
//!    the click is found in that residual (connected regions over a threshold, a ring's orifice
//!    joined to it); the patch is its bounding box plus a margin, not a square of whatever
//!    surrounds the click.
//! 3. **Whole-pixel shift by normalized cross-correlation** over the shifts the two clicks allow
//!    (their offset ± the agreement limit + 2 px). A weak peak, a second peak nearly as strong,
//!    or the best at the search's edge is refused.
//! 4. **Sub-pixel by Gauss–Newton** (Lucas–Kanade) on the shift, with a gain, an offset and a
//!    plane refitted at each step, bicubic interpolation, from the whole-pixel peak: the
//!    squared difference, which an unmoved copy minimizes exactly (issue 37: the plain
//!    correlation's maximum is pulled by the patch's rim when the nozzle fills it). Its sd
//!    comes from the residuals (Cramér–Rao), widened for the correlation of neighbouring
//!    pixels' residuals (the smoothing, JPEG blocks, blur).
//! 5. **The click checks the answer.** A refined reading farther from the click, along either
//!    axis, than 3 sd of the two clicks' stated precision (plus 3 of its own) is refused: the
//!    person said the tip is elsewhere. The caller then keeps the click as it was, and says so.
//!
//! No crate was added for this: `imageproc`'s `match_template` gives the whole-pixel
//! correlation map only (steps 3), over the whole picture unless cropped first, and none of
//! steps 1, 2, 4 or 5; the rest is nalgebra's 4×4 solve, already a dependency.

use serde::Serialize;

use super::background::{box3, join_nested, regions, Background, Region};
use super::noise::fine_noise_sd;
use super::Gray;

/// What the noise does not show: the static background's remains after the quadratic is
/// taken out, JPEG blocks fixed to the frame, the interpolation, px (1 sd). Issue 37: once the
/// sub-pixel fit was the squared difference (the plain correlation read 0.37 px on an unmoved
/// copy of kTAMV's frame, and up to 0.11 px on TAMV's photo), known shifts of the six real
/// photos (JPEG 70–90, noise, blur, a brightness change) erred 0.003–0.015 px rms, and ±2u
/// covered 93–97 % of the coordinates with this floor (93.6 % with none, 99.7 % with 0.015).
const SD_FLOOR_PX: f64 = 0.003;

/// The lighting's quadratic is fitted on about this many samples across the picture (the
/// detector uses 160): a smooth surface needs few, and a click is read while the person waits.
const BACKGROUND_SAMPLES: usize = 64;

/// The sub-pixel fit's longest step, px.
const MAX_STEP_PX: f64 = 0.5;

/// The sub-pixel fit may follow the squared difference's minimum this far from the
/// correlation's whole-pixel peak, px (each axis), inside the searched shifts. On kTAMV's
/// defocused frame under a 10 % lighting gradient the plain correlation's peak lay up to 4 px
/// from the minimum (`klipcal bench backlash`, real-photo frames: the scale's move left an
/// axis unfinished at 3 px).
const MAX_FOLLOW_PX: i64 = 6;

/// A patch cut to stay in view keeps at least this many pixels along each axis (the
/// smallest object patch the reference takes is about 24 px: 20 px² and its margins).
const MIN_CUT_PX: i64 = 24;

/// Residual correlation is summed over this many lags per axis for a shift's sd.
const LAGS: usize = 4;

/// Limits of the refinement.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RegisterParams {
    /// The object under the reference click must stand out from the background by this many
    /// grey levels …
    pub min_contrast: f64,
    /// … and by this many times the picture's noise sd.
    pub min_snr: f64,
    /// The correlation peak must reach this (1: identical up to gain and offset).
    pub min_peak: f64,
    /// A second peak at least this share of the best makes the match ambiguous.
    pub max_second_ratio: f64,
    /// The refined reading may differ from the click by this many sd of the two clicks'
    /// stated precision (each axis).
    pub agree_sd: f64,
    /// The least distance from the tap searched, px, whatever precision the tap states: a
    /// finger on a phone lands a few picture px off while the page states its zoomed screen
    /// precision (0.4 px), so a tap is only a hint (issue 37, item 6).
    pub min_reach_px: f64,
    /// Refuse a refined reading whose sd exceeds this, px.
    pub max_uncertainty_px: f64,
}

impl Default for RegisterParams {
    fn default() -> Self {
        RegisterParams {
            min_contrast: 12.0,
            min_snr: 6.0,
            min_peak: 0.7,
            max_second_ratio: 0.9,
            agree_sd: 3.0,
            min_reach_px: 6.0,
            max_uncertainty_px: 0.5,
        }
    }
}

/// Why a click is kept as it was.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum ClickRefusal {
    /// The buffer does not hold width × height pixels, or not the reference's size.
    BadImage { detail: String },
    /// Nothing stands out from the background under the reference click.
    NothingAtClick { contrast: f64, needed: f64 },
    /// The patch, or the shifts the click allows, reach beyond the picture.
    AtEdge { at_px: [f64; 2] },
    /// The best match is poor: the picture around the click does not look like the reference.
    WeakMatch { peak: f64, needed: f64 },
    /// Two places match nearly as well.
    Ambiguous { peak: f64, second: f64 },
    /// The pictures put the nozzle farther from the click than the click's precision allows.
    OffClick { distance_px: f64, limit_px: f64 },
    /// The sub-pixel fit did not settle near the whole-pixel peak.
    NotConverged,
    /// The refined reading's sd is over the limit.
    Uncertain { uncertainty_px: f64, limit_px: f64 },
}

impl std::fmt::Display for ClickRefusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ClickRefusal::BadImage { detail } => write!(f, "not a usable picture: {detail}"),
            ClickRefusal::NothingAtClick { contrast, needed } => write!(
                f,
                "nothing stands out from the background at the click ({contrast:.0} grey \
                 levels, {needed:.0} needed) to compare the other snapshots with"
            ),
            ClickRefusal::AtEdge { at_px } => write!(
                f,
                "the nozzle near ({:.0}, {:.0}) px is too close to the picture's edge to compare",
                at_px[0], at_px[1]
            ),
            ClickRefusal::WeakMatch { peak, needed } => write!(
                f,
                "the picture around the click does not match the first snapshot's nozzle \
                 (correlation {peak:.2}, {needed:.2} needed)"
            ),
            ClickRefusal::Ambiguous { peak, second } => write!(
                f,
                "two places match the first snapshot's nozzle about equally (correlation \
                 {peak:.2} and {second:.2})"
            ),
            ClickRefusal::OffClick {
                distance_px,
                limit_px,
            } => write!(
                f,
                "the pictures put the nozzle {distance_px:.1} px from the click, more than the \
                 click's precision allows ({limit_px:.1} px)"
            ),
            ClickRefusal::NotConverged => {
                write!(f, "the sub-pixel match did not settle")
            }
            ClickRefusal::Uncertain {
                uncertainty_px,
                limit_px,
            } => write!(
                f,
                "the match is uncertain by ±{uncertainty_px:.2} px, over the {limit_px:.2} px \
                 limit"
            ),
        }
    }
}

/// The reference: the first clicked snapshot's background-free patch around the object
/// under the click.
#[derive(Debug, Clone)]
pub struct Reference {
    width: usize,
    height: usize,
    click_px: [f64; 2],
    click_sd_px: f64,
    /// The patch's top-left pixel and size.
    origin: [usize; 2],
    size: [usize; 2],
    /// The patch less its mean, and its root sum of squares.
    t: Vec<f32>,
    /// The inverse of the patch's gradient energy Σ∇t∇tᵀ.
    g_inv: nalgebra::Matrix2<f64>,
    sd_px: f64,
    /// The smoothed residual the patch was made from, with 2 px around it, and the margin
    /// round the object: what a patch cut to stay in view is made from ([`Reference::cut`]).
    ext: Vec<f32>,
    margin: usize,
}

/// A refined reading.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Refined {
    /// The nozzle, px, in the reference click's frame: the reference click plus the measured
    /// shift.
    pub at_px: [f64; 2],
    /// 1 sd per axis, px.
    pub sd_px: f64,
    /// The correlation peak.
    pub peak: f64,
    /// How far the reading is from the click, px.
    pub from_click_px: f64,
}

fn check(img: &Gray<'_>) -> Result<(), ClickRefusal> {
    let (w, h) = (img.width, img.height);
    if w.checked_mul(h) != Some(img.data.len()) || w < 32 || h < 32 {
        return Err(ClickRefusal::BadImage {
            detail: format!(
                "{} bytes for {w}×{h} pixels; expected at least 32×32",
                img.data.len()
            ),
        });
    }
    Ok(())
}

/// The picture less its background over `x0..x1 × y0..y1` (half-open), row-major.
fn residual(img: &Gray<'_>, bg: &Background, x: [usize; 2], y: [usize; 2]) -> Vec<f32> {
    let mut out = Vec::with_capacity((x[1] - x[0]) * (y[1] - y[0]));
    for j in y[0]..y[1] {
        for i in x[0]..x[1] {
            out.push((f64::from(img.data[j * img.width + i]) - bg.at(i as f64, j as f64)) as f32);
        }
    }
    out
}

/// The window around a click: the picture's residual from its static background there, 3×3
/// smoothed, and the contrast an object under the click needs.
struct ClickWindow {
    bg: Background,
    /// The click's pixel.
    c: [f64; 2],
    wx: [usize; 2],
    wy: [usize; 2],
    rs: Vec<f32>,
    /// The pixel noise.
    sigma: f64,
    strongest: f64,
    needed: f64,
}

impl ClickWindow {
    /// The window, or why nothing under the click stands out.
    fn new(img: &Gray<'_>, click_px: [f64; 2], p: &RegisterParams) -> Result<Self, ClickRefusal> {
        let (w, h) = (img.width, img.height);
        let (bg, _) = Background::fit_across(img, BACKGROUND_SAMPLES);
        // A window around the click for finding the object under it.
        let l = (w.min(h) / 4).max(16) as f64;
        let cx = click_px[0].round().clamp(0.0, (w - 1) as f64);
        let cy = click_px[1].round().clamp(0.0, (h - 1) as f64);
        let wx = [(cx - l).max(0.0) as usize, ((cx + l + 1.0) as usize).min(w)];
        let wy = [(cy - l).max(0.0) as usize, ((cy + l + 1.0) as usize).min(h)];
        let (ww, wh) = (wx[1] - wx[0], wy[1] - wy[0]);
        let raw = residual(img, &bg, wx, wy);
        let rs = box3(&raw, ww, wh);
        // The pixel noise from the window's finest scale (issue 37: the residual's spread is the
        // scene's structure on a zoomed-in nozzle), and what the 3×3 box leaves of it.
        let sigma = fine_noise_sd(img, Some([wx[0], wx[1], wy[0], wy[1]]));
        let noise = sigma / 3.0;
        let strongest = f64::from(rs.iter().fold(0f32, |m, v| m.max(v.abs())));
        let needed = p.min_contrast.max(p.min_snr * noise);
        if strongest < needed {
            return Err(ClickRefusal::NothingAtClick {
                contrast: strongest,
                needed,
            });
        }
        Ok(ClickWindow {
            bg,
            c: [cx, cy],
            wx,
            wy,
            rs,
            sigma,
            strongest,
            needed,
        })
    }

    /// The box of the object under the click in the picture and its margin: the nearest
    /// region within the click's reach, or on a nozzle that fills the window the region round
    /// the click.
    fn object_box(
        &self,
        w: usize,
        h: usize,
        click_sd_px: f64,
    ) -> Result<([usize; 2], [usize; 2], usize), ClickRefusal> {
        let (wx, wy, rs) = (self.wx, self.wy, &self.rs);
        let (ww, wh) = (wx[1] - wx[0], wy[1] - wy[0]);
        let [cx, cy] = self.c;
        let thr = (0.3 * self.strongest).max(0.5 * self.needed) as f32;
        let mask: Vec<bool> = rs.iter().map(|v| v.abs() > thr).collect();
        let (kx, ky) = (cx as usize - wx[0], cy as usize - wy[0]);
        let near = |r: &Region| {
            let dx = (r.x0 as f64 - kx as f64)
                .max(kx as f64 - r.x1 as f64)
                .max(0.0);
            let dy = (r.y0 as f64 - ky as f64)
                .max(ky as f64 - r.y1 as f64)
                .max(0.0);
            dx.hypot(dy)
        };
        let reach = 3.0 * click_sd_px + 2.0;
        let obj = join_nested(regions(&mask, rs, ww, wh))
            .into_iter()
            .filter(|r| r.area >= 20 && near(r) <= reach)
            .min_by(|a, b| near(a).total_cmp(&near(b)));
        match obj {
            // The object's box in the picture, plus a margin for the blurred edge.
            Some(obj) if obj.x0 > 0 && obj.y0 > 0 && obj.x1 + 1 < ww && obj.y1 + 1 < wh => Ok((
                [wx[0] + obj.x0, wx[0] + obj.x1 + 1],
                [wy[0] + obj.y0, wy[0] + obj.y1 + 1],
                (4.0 + 0.25 * obj.half_extent()).ceil() as usize,
            )),
            _ => self.filled_box(w, h, kx, ky),
        }
    }

    /// A zoomed-in nozzle fills the window (issue 37): nothing is an object on a background, so
    /// the region round the click is the patch, if it has structure.
    fn filled_box(
        &self,
        w: usize,
        h: usize,
        kx: usize,
        ky: usize,
    ) -> Result<([usize; 2], [usize; 2], usize), ClickRefusal> {
        let (wx, wy, rs) = (self.wx, self.wy, &self.rs);
        let ww = wx[1] - wx[0];
        let [cx, cy] = self.c;
        let needed = self.needed;
        let hs = (w.min(h) / 8).clamp(12, 48);
        let (x0, y0) = (
            (cx as usize).saturating_sub(hs),
            (cy as usize).saturating_sub(hs),
        );
        let strong = (y0..(cy as usize + hs + 1).min(h))
            .flat_map(|y| (x0..(cx as usize + hs + 1).min(w)).map(move |x| (x, y)))
            .filter(|&(x, y)| (wx[0]..wx[1]).contains(&x) && (wy[0]..wy[1]).contains(&y))
            .map(|(x, y)| f64::from(rs[(y - wy[0]) * ww + x - wx[0]].abs()))
            .fold(0.0, f64::max);
        if strong < needed {
            return Err(ClickRefusal::NothingAtClick {
                contrast: f64::from(rs[ky * ww + kx].abs()),
                needed,
            });
        }
        Ok(([x0, cx as usize + hs + 1], [y0, cy as usize + hs + 1], 0))
    }
}

/// The patch's template (less the plane of what is left of the static background across it,
/// less its mean) and its gradient energy Σ∇t∇tᵀ, from the smoothed patch `ext` with 2 px
/// around it; `m` is the margin around the object.
fn template(ext: &[f32], size: [usize; 2], m: usize) -> (Vec<f32>, nalgebra::Matrix2<f64>) {
    let ew = size[0] + 4;
    let at = |i: usize, j: usize| f64::from(ext[(j + 2) * ew + i + 2]);
    let n = (size[0] * size[1]) as f64;
    let mean = (0..size[1])
        .flat_map(|j| (0..size[0]).map(move |i| (i, j)))
        .map(|(i, j)| at(i, j))
        .sum::<f64>()
        / n;
    // What is left of the static background across the patch, as a plane fitted to the
    // margin around the object: left in, it would correlate with the nozzle's gradient
    // in the next picture and shift the match.
    let mut nm = nalgebra::Matrix3::<f64>::zeros();
    let mut nb = nalgebra::Vector3::<f64>::zeros();
    for j in 0..size[1] {
        for i in 0..size[0] {
            if (m..size[0] - m).contains(&i) && (m..size[1] - m).contains(&j) {
                continue;
            }
            let b = nalgebra::Vector3::new(
                1.0,
                i as f64 - 0.5 * size[0] as f64,
                j as f64 - 0.5 * size[1] as f64,
            );
            nm += b * b.transpose();
            nb += b * at(i, j);
        }
    }
    let plane = nm
        .lu()
        .solve(&nb)
        .unwrap_or_else(|| nalgebra::Vector3::new(mean, 0.0, 0.0));
    let at = |i: usize, j: usize| {
        at(i, j)
            - plane[1] * (i as f64 - 0.5 * size[0] as f64)
            - plane[2] * (j as f64 - 0.5 * size[1] as f64)
    };
    let mean = (0..size[1])
        .flat_map(|j| (0..size[0]).map(move |i| (i, j)))
        .map(|(i, j)| at(i, j))
        .sum::<f64>()
        / n;
    let mut t = Vec::with_capacity(size[0] * size[1]);
    let mut g = nalgebra::Matrix2::<f64>::zeros();
    for j in 0..size[1] {
        for i in 0..size[0] {
            t.push((at(i, j) - mean) as f32);
            let e = |di: i64, dj: i64| {
                f64::from(ext[((j + 2) as i64 + dj) as usize * ew + ((i + 2) as i64 + di) as usize])
            };
            let gr = nalgebra::Vector2::new(0.5 * (e(1, 0) - e(-1, 0)), 0.5 * (e(0, 1) - e(0, -1)));
            g += gr * gr.transpose();
        }
    }
    (t, g)
}

impl Reference {
    /// The reference from the first clicked snapshot: `click_px` ± `click_sd_px` (1 sd).
    ///
    /// # Errors
    /// A bad buffer, nothing standing out under the click, or a nozzle at the picture's edge.
    pub fn new(
        img: &Gray<'_>,
        click_px: [f64; 2],
        click_sd_px: f64,
        p: &RegisterParams,
    ) -> Result<Reference, ClickRefusal> {
        check(img)?;
        let (w, h) = (img.width, img.height);
        let win = ClickWindow::new(img, click_px, p)?;
        let (bx, by, m) = win.object_box(w, h, click_sd_px)?;
        if bx[0] < m + 3 || by[0] < m + 3 || bx[1] + m + 3 > w || by[1] + m + 3 > h {
            return Err(ClickRefusal::AtEdge { at_px: click_px });
        }
        let px = [bx[0] - m, bx[1] + m];
        let py = [by[0] - m, by[1] + m];
        let size = [px[1] - px[0], py[1] - py[0]];
        // The patch smoothed (3×3 box: the interpolation's own smoothing of the noise then no
        // longer pulls the sub-pixel shift toward half pixels), with 2 px around it for the
        // smoothing and the gradients.
        let ext = box3(
            &residual(img, &win.bg, [px[0] - 2, px[1] + 2], [py[0] - 2, py[1] + 2]),
            size[0] + 4,
            size[1] + 4,
        );
        let (t, g) = template(&ext, size, m);
        let Some(g_inv) = g.try_inverse() else {
            return Err(ClickRefusal::NothingAtClick {
                contrast: win.strongest,
                needed: win.needed,
            });
        };
        let sigma = win.sigma;
        // The reference's own share of a reading's sd: the patch's noise over its gradient
        // energy (the Cramér–Rao bound of one picture's position), per axis; the 3×3 box
        // leaves a ninth of white noise's variance, its neighbours correlated (ρ = ⅔ per axis,
        // (1 + ρ)/(1 − ρ) = 5 fewer independent pixels along each).
        let sd_px = (25.0 * sigma * sigma / 9.0 * 0.5 * (g_inv[(0, 0)] + g_inv[(1, 1)]))
            .max(0.0)
            .sqrt()
            .hypot(SD_FLOOR_PX);
        Ok(Reference {
            width: w,
            height: h,
            click_px,
            click_sd_px,
            origin: [px[0], py[0]],
            size,
            t,
            g_inv,
            sd_px,
            ext,
            margin: m,
        })
    }

    /// The patch cut on the sides that would leave the picture when it is searched for at
    /// the whole-pixel shift `c` ± `s` (and the interpolation's 3 px): what of the nozzle
    /// stays in view over a scale move as long as the picture is wide. Every part of the
    /// patch moves with the nozzle, so a part measures the same shift. `None` when no cut is
    /// needed, or what would be left is under [`MIN_CUT_PX`] along an axis (then as much is
    /// kept), or has no structure to register.
    fn cut(&self, c: [i64; 2], s: i64) -> Option<Reference> {
        let wh = [self.width as i64, self.height as i64];
        let mut keep = [[0usize; 2]; 2];
        for a in 0..2 {
            let (o, sz) = (self.origin[a] as i64, self.size[a] as i64);
            let lo = (s + 3 - (o + c[a])).max(0);
            let hi = (o + sz + c[a] + s + 3 - wh[a]).max(0);
            let min = MIN_CUT_PX.min(sz);
            // Cut no more than leaves `min`, shared as each side needs it.
            let k = if sz - lo - hi >= min {
                1.0
            } else {
                (sz - min) as f64 / (lo + hi) as f64
            };
            let (lo, hi) = (
                (lo as f64 * k).floor() as usize,
                (hi as f64 * k).floor() as usize,
            );
            keep[a] = [lo, self.size[a] - hi];
        }
        if keep == [[0, self.size[0]], [0, self.size[1]]] {
            return None;
        }
        let size = [keep[0][1] - keep[0][0], keep[1][1] - keep[1][0]];
        let ew = self.size[0] + 4;
        let ext: Vec<f32> = (keep[1][0]..keep[1][1] + 4)
            .flat_map(|j| (keep[0][0]..keep[0][1] + 4).map(move |i| (i, j)))
            .map(|(i, j)| self.ext[j * ew + i])
            .collect();
        // The margin round the object is gone on a cut side: the plane is fitted to a rim
        // no deeper than a quarter of the patch.
        let m = self.margin.min(size[0] / 4).min(size[1] / 4);
        let (t, g) = template(&ext, size, m);
        let g_inv = g.try_inverse()?;
        Some(Reference {
            origin: [self.origin[0] + keep[0][0], self.origin[1] + keep[1][0]],
            size,
            t,
            g_inv,
            ext,
            margin: m,
            ..self.clone()
        })
    }

    /// The reference click's stated sd, px.
    pub fn click_sd_px(&self) -> f64 {
        self.click_sd_px
    }

    /// The reference reading's own sd, px: how well one picture's patch pins its position.
    pub fn sd_px(&self) -> f64 {
        self.sd_px
    }

    /// The reading in `img`, clicked at `click_px` ± `click_sd_px`, refined against the
    /// reference.
    ///
    /// # Errors
    /// A [`ClickRefusal`] saying why the click is to be kept as it was.
    pub fn refine(
        &self,
        img: &Gray<'_>,
        click_px: [f64; 2],
        click_sd_px: f64,
        p: &RegisterParams,
    ) -> Result<Refined, ClickRefusal> {
        check(img)?;
        if (img.width, img.height) != (self.width, self.height) {
            return Err(ClickRefusal::BadImage {
                detail: format!(
                    "{}×{} pixels; the first snapshot was {}×{}",
                    img.width, img.height, self.width, self.height
                ),
            });
        }
        let limit = (p.agree_sd * click_sd_px.hypot(self.click_sd_px)).max(p.min_reach_px);
        let pred = [
            click_px[0] - self.click_px[0],
            click_px[1] - self.click_px[1],
        ];
        let wanted = limit.ceil() as i64 + 2;
        let c = [pred[0].round() as i64, pred[1].round() as i64];
        // Near the picture's edge the patch is cut to what stays in view over the search …
        match self.room(c) {
            Some(room) if room >= wanted => self.refine_in(img, click_px, limit, c, wanted, p),
            _ => match self.cut(c, wanted) {
                Some(r) => r.refine_in(img, click_px, limit, c, wanted, p),
                None => self.refine_in(img, click_px, limit, c, wanted, p),
            },
        }
    }

    /// [`Reference::refine`]'s search round the whole-pixel shift `c`, ± `wanted` px where
    /// the picture holds it, and its checks against the click (± `limit` px).
    fn refine_in(
        &self,
        img: &Gray<'_>,
        click_px: [f64; 2],
        limit: f64,
        c: [i64; 2],
        wanted: i64,
        p: &RegisterParams,
    ) -> Result<Refined, ClickRefusal> {
        // … and the search cut to what the picture holds (a peak on the cut rim is then
        // refused as at the edge, not read).
        let s = self
            .room(c)
            .filter(|room| *room >= 2)
            .map(|room| room.min(wanted))
            .ok_or(ClickRefusal::AtEdge { at_px: click_px })?;
        let area = self
            .search_area(img, c, s)
            .ok_or(ClickRefusal::AtEdge { at_px: click_px })?;
        // 3. The whole-pixel peak, checked.
        let map = self.ncc_map(&area, c, s);
        let (best_shift, best) = map.best();
        if best < p.min_peak {
            return Err(ClickRefusal::WeakMatch {
                peak: best,
                needed: p.min_peak,
            });
        }
        let off = |at: [f64; 2]| (at[0] - click_px[0]).abs().max((at[1] - click_px[1]).abs());
        if s < wanted && map.at_rim(best_shift) {
            return Err(ClickRefusal::AtEdge { at_px: click_px });
        }
        if map.at_rim(best_shift) {
            let at_best = [
                self.click_px[0] + best_shift[0] as f64,
                self.click_px[1] + best_shift[1] as f64,
            ];
            return Err(ClickRefusal::OffClick {
                distance_px: off(at_best),
                limit_px: limit,
            });
        }
        let second = map.second(best_shift);
        if second >= p.max_second_ratio * best {
            return Err(ClickRefusal::Ambiguous { peak: best, second });
        }
        // 4. Sub-pixel, and its sd.
        let (d, sd) = self.subpixel(&area, &map)?;
        let at_px = [self.click_px[0] + d[0], self.click_px[1] + d[1]];
        // 5. The click checks the answer.
        let from_click = off(at_px);
        if !sd.is_finite() || sd > p.max_uncertainty_px {
            return Err(ClickRefusal::Uncertain {
                uncertainty_px: sd,
                limit_px: p.max_uncertainty_px,
            });
        }
        if from_click > limit + 3.0 * sd {
            return Err(ClickRefusal::OffClick {
                distance_px: from_click,
                limit_px: limit + 3.0 * sd,
            });
        }
        Ok(Refined {
            at_px,
            sd_px: sd,
            peak: best,
            from_click_px: (at_px[0] - click_px[0]).hypot(at_px[1] - click_px[1]),
        })
    }

    /// How far the search may reach round the whole-pixel shift `c` with the patch and the
    /// interpolation's 3 px still inside the picture; `None` when the patch at `c` is not.
    fn room(&self, c: [i64; 2]) -> Option<i64> {
        let (w, h) = (self.width as i64, self.height as i64);
        let lo = [
            self.origin[0] as i64 + c[0] - 3,
            self.origin[1] as i64 + c[1] - 3,
        ];
        let hi = [
            w - (self.origin[0] as i64 + self.size[0] as i64 + c[0] + 3),
            h - (self.origin[1] as i64 + self.size[1] as i64 + c[1] + 3),
        ];
        let room = lo[0].min(lo[1]).min(hi[0]).min(hi[1]);
        (room >= 0).then_some(room)
    }

    /// The picture's background-free, smoothed residual over every shift `c` ± `s` searched,
    /// with 3 px more for the interpolation; `None` when that reaches beyond the picture.
    fn search_area(&self, img: &Gray<'_>, c: [i64; 2], s: i64) -> Option<Area> {
        let (w, h) = (self.width as i64, self.height as i64);
        let (o, sz) = (
            [self.origin[0] as i64, self.origin[1] as i64],
            [self.size[0] as i64, self.size[1] as i64],
        );
        let rx = [o[0] + c[0] - s - 3, o[0] + sz[0] + c[0] + s + 3];
        let ry = [o[1] + c[1] - s - 3, o[1] + sz[1] + c[1] + s + 3];
        if rx[0] < 0 || ry[0] < 0 || rx[1] > w || ry[1] > h {
            return None;
        }
        let (bg, _) = Background::fit_across(img, BACKGROUND_SAMPLES);
        let rw = (rx[1] - rx[0]) as usize;
        let res = box3(
            &residual(
                img,
                &bg,
                [rx[0] as usize, rx[1] as usize],
                [ry[0] as usize, ry[1] as usize],
            ),
            rw,
            (ry[1] - ry[0]) as usize,
        );
        Some(Area {
            res,
            rw,
            at: [o[0] - rx[0], o[1] - ry[0]],
        })
    }

    /// Step 3: normalized cross-correlation at each whole-pixel shift `c` ± `s`, on every
    /// other pixel of the (smoothed) patch: it only has to find the peak's pixel, the
    /// sub-pixel fit uses them all.
    fn ncc_map(&self, area: &Area, c: [i64; 2], s: i64) -> CorrMap {
        let (pw, ph) = (self.size[0], self.size[1]);
        let side = (2 * s + 1) as usize;
        let mut map = vec![f64::NEG_INFINITY; side * side];
        let (sw, sh) = (pw.div_ceil(2), ph.div_ceil(2));
        let sub: Vec<f32> = (0..sh)
            .flat_map(|j| (0..sw).map(move |i| (i, j)))
            .map(|(i, j)| self.t[2 * j * pw + 2 * i])
            .collect();
        let sub_mean = sub.iter().map(|v| f64::from(*v)).sum::<f64>() / sub.len() as f64;
        let sub: Vec<f32> = sub.iter().map(|v| v - sub_mean as f32).collect();
        let sub_norm = sub
            .iter()
            .map(|v| f64::from(*v).powi(2))
            .sum::<f64>()
            .sqrt();
        let ns = sub.len() as f64;
        let mut row = vec![0f32; sw];
        for (k, v) in map.iter_mut().enumerate() {
            let (dx, dy) = ((k % side) as i64 - s + c[0], (k / side) as i64 - s + c[1]);
            // The patch's top-left in the area.
            let (bx, by) = ((area.at[0] + dx) as usize, (area.at[1] + dy) as usize);
            let (mut st, mut si, mut sii) = (0f64, 0f64, 0f64);
            for j in 0..sh {
                let at = (by + 2 * j) * area.rw + bx;
                for (i, r) in row.iter_mut().enumerate() {
                    *r = area.res[at + 2 * i];
                }
                let trow = &sub[j * sw..(j + 1) * sw];
                let (mut a, mut b, mut cc) = (0f32, 0f32, 0f32);
                for (iv, tv) in row.iter().zip(trow) {
                    a += iv * tv;
                    b += iv;
                    cc += iv * iv;
                }
                st += f64::from(a);
                si += f64::from(b);
                sii += f64::from(cc);
            }
            let var = (sii - si * si / ns).max(1e-9);
            *v = st / (sub_norm.max(1e-9) * var.sqrt());
        }
        CorrMap { map, side, s, c }
    }

    /// Step 4: the sub-pixel shift from the whole-pixel peak `best`, and its sd (px).
    ///
    /// Gauss–Newton on the squared difference between the patch moved by `d` (Keys' bicubic)
    /// and the reference patch times a gain, plus an offset and a plane (what is left of the
    /// static lighting), all four refitted at each step. Issue 37: maximizing the plain
    /// correlation Σ t·I(x + d) instead is biased wherever the patch's own edges carry
    /// structure (a zoomed-in nozzle fills it): Σ t·∇t over a window is its boundary's term,
    /// not zero, and on kTAMV's small frames an unmoved copy read 0.37 px off.
    ///
    /// It starts from the correlation peak's parabola, and a step is never longer than
    /// [`MAX_STEP_PX`]: on a blurred patch the first Gauss–Newton steps can overshoot. Issue 37:
    /// on kTAMV's defocused frame, with a 126×131 px patch moved 91 px, the squared
    /// difference's minimum lay 1.5–2 px from the plain correlation's peak (the correlation has
    /// no plane for what is left of the lighting); the fit follows it up to [`MAX_FOLLOW_PX`]
    /// from the peak, inside the searched shifts, where it stopped at 1.5 px (later 3 px) and
    /// the axis went unfinished.
    fn subpixel(&self, area: &Area, map: &CorrMap) -> Result<([f64; 2], f64), ClickRefusal> {
        let (pw, ph) = (self.size[0], self.size[1]);
        let model = PatchModel::new(&self.t, pw, ph).ok_or(ClickRefusal::NotConverged)?;
        let (peak, _) = map.best();
        let mut best = peak;
        let mut d = map.parabola(peak);
        for _ in 0..40 {
            let v = area.sample(d, pw, ph);
            let (coef, grad) = model.fit(&v);
            let gain = coef[0];
            if gain <= 0.0 {
                return Err(ClickRefusal::NotConverged);
            }
            let step = -(self.g_inv * grad) / (gain * gain);
            if step.norm() < 1e-3 {
                return Ok((d, self.shift_sd(&model, &v, coef)));
            }
            let step = step * (MAX_STEP_PX / step.norm()).min(1.0);
            d = [d[0] + step[0], d[1] + step[1]];
            if (d[0] - best[0] as f64).abs() > 1.5 || (d[1] - best[1] as f64).abs() > 1.5 {
                // Followed to the next whole pixel while it stays inside the searched shifts
                // and near the correlation's peak.
                best = [d[0].round() as i64, d[1].round() as i64];
                let drift = (best[0] - peak[0]).abs().max((best[1] - peak[1]).abs());
                if drift > MAX_FOLLOW_PX || !map.inside(best) {
                    return Err(ClickRefusal::NotConverged);
                }
            }
        }
        Err(ClickRefusal::NotConverged)
    }

    /// A shift's sd from the fit's residuals (both pictures' noise), widened for their
    /// neighbours' correlation (the 3×3 box, blur and JPEG blocks), with the floor.
    fn shift_sd(&self, model: &PatchModel, v: &Sampled, coef: [f64; 4]) -> f64 {
        let (pw, ph) = (self.size[0], self.size[1]);
        let resid = model.residuals(&v.v, coef);
        let rr: f64 = resid.iter().map(|r| r * r).sum();
        let sigma2 = rr / (resid.len() as f64 - 4.0).max(1.0);
        let lag = |dx: usize, dy: usize| {
            let mut a = 0.0;
            for j in 0..ph - dy {
                for i in 0..pw - dx {
                    a += resid[j * pw + i] * resid[(j + dy) * pw + i + dx];
                }
            }
            a / rr.max(1e-12)
        };
        // Per axis, 1 + 2 Σ ρ(k) over the lags the 3×3 box, a little blur and JPEG's blocks
        // reach (an AR(1) model's (1 + ρ₁)/(1 − ρ₁) took the box's ρ₁ = ⅔ for 5 where the
        // sum is 3, and overstated the sd about 1.5–2.5 × on the real photos' known shifts).
        let sum = |x: bool| {
            let s: f64 = (1..=LAGS)
                .map(|k| if x { lag(k, 0) } else { lag(0, k) })
                .sum();
            (1.0 + 2.0 * s).clamp(1.0, 40.0)
        };
        let widen = sum(true) * sum(false);
        let gain = coef[0];
        (widen * sigma2 / (gain * gain) * 0.5 * (self.g_inv[(0, 0)] + self.g_inv[(1, 1)]))
            .max(0.0)
            .sqrt()
            .hypot(SD_FLOOR_PX)
    }
}

/// The searched part of a picture: its background-free, smoothed residual, `rw` wide, and
/// where the reference patch's top-left falls in it at zero shift.
struct Area {
    res: Vec<f32>,
    rw: usize,
    at: [i64; 2],
}

/// The patch moved by `d`, and its derivatives in `d`.
struct Sampled {
    v: Vec<f64>,
    vx: Vec<f64>,
    vy: Vec<f64>,
}

impl Area {
    /// The `pw` × `ph` patch at shift `d` (Keys' bicubic), with its derivatives in `d`.
    fn sample(&self, d: [f64; 2], pw: usize, ph: usize) -> Sampled {
        let (fx, fy) = (d[0].floor(), d[1].floor());
        let (wx, dwx) = keys(d[0] - fx);
        let (wy, dwy) = keys(d[1] - fy);
        // Top-left tap of the patch's pixel (0, 0).
        let bx = (self.at[0] + fx as i64 - 1) as usize;
        let by = (self.at[1] + fy as i64 - 1) as usize;
        let mut out = Sampled {
            v: Vec::with_capacity(pw * ph),
            vx: Vec::with_capacity(pw * ph),
            vy: Vec::with_capacity(pw * ph),
        };
        for j in 0..ph {
            for i in 0..pw {
                let (mut v, mut vx, mut vy) = (0.0, 0.0, 0.0);
                for (b, (wyb, dwyb)) in wy.iter().zip(&dwy).enumerate() {
                    let at = (by + j + b) * self.rw + bx + i;
                    let (mut a, mut ax) = (0.0, 0.0);
                    for (q, pv) in self.res[at..at + 4].iter().enumerate() {
                        a += wx[q] * f64::from(*pv);
                        ax += dwx[q] * f64::from(*pv);
                    }
                    v += wyb * a;
                    vx += wyb * ax;
                    vy += dwyb * a;
                }
                out.v.push(v);
                out.vx.push(vx);
                out.vy.push(vy);
            }
        }
        out
    }
}

/// The model a moved patch is fitted with: gain × the reference patch + offset + plane.
struct PatchModel<'a> {
    t: &'a [f32],
    pw: usize,
    ph: usize,
    /// The inverse of the basis' normal matrix.
    inv: nalgebra::Matrix4<f64>,
}

impl<'a> PatchModel<'a> {
    fn new(t: &'a [f32], pw: usize, ph: usize) -> Option<PatchModel<'a>> {
        let mut m = nalgebra::Matrix4::<f64>::zeros();
        for k in 0..pw * ph {
            let b = Self::basis(t, pw, ph, k);
            m += b * b.transpose();
        }
        Some(PatchModel {
            t,
            pw,
            ph,
            inv: m.try_inverse()?,
        })
    }

    fn basis(t: &[f32], pw: usize, ph: usize, k: usize) -> nalgebra::Vector4<f64> {
        nalgebra::Vector4::new(
            f64::from(t[k]),
            1.0,
            (k % pw) as f64 - 0.5 * (pw - 1) as f64,
            (k / pw) as f64 - 0.5 * (ph - 1) as f64,
        )
    }

    /// The four coefficients fitted to `v`, and Σ residual × ∇v (the squared difference's
    /// half-gradient in the shift).
    fn fit(&self, v: &Sampled) -> ([f64; 4], nalgebra::Vector2<f64>) {
        let mut r = nalgebra::Vector4::<f64>::zeros();
        for (k, x) in v.v.iter().enumerate() {
            r += Self::basis(self.t, self.pw, self.ph, k) * *x;
        }
        let c = self.inv * r;
        let coef = [c[0], c[1], c[2], c[3]];
        let mut g = nalgebra::Vector2::<f64>::zeros();
        for (k, e) in self.residuals(&v.v, coef).iter().enumerate() {
            g += nalgebra::Vector2::new(v.vx[k], v.vy[k]) * *e;
        }
        (coef, g)
    }

    fn residuals(&self, v: &[f64], coef: [f64; 4]) -> Vec<f64> {
        v.iter()
            .enumerate()
            .map(|(k, x)| {
                let b = Self::basis(self.t, self.pw, self.ph, k);
                x - (coef[0] * b[0] + coef[1] + coef[2] * b[2] + coef[3] * b[3])
            })
            .collect()
    }
}

/// The correlation at each whole-pixel shift `c` ± `s` (`side` × `side`, row-major).
struct CorrMap {
    map: Vec<f64>,
    side: usize,
    s: i64,
    c: [i64; 2],
}

impl CorrMap {
    fn index(&self, shift: [i64; 2]) -> (i64, i64) {
        (shift[0] - self.c[0] + self.s, shift[1] - self.c[1] + self.s)
    }

    /// The best shift and its correlation.
    fn best(&self) -> ([i64; 2], f64) {
        let (k, v) = self
            .map
            .iter()
            .enumerate()
            .fold(
                (0, f64::NEG_INFINITY),
                |m, (k, v)| if *v > m.1 { (k, *v) } else { m },
            );
        let (i, j) = ((k % self.side) as i64, (k / self.side) as i64);
        ([i - self.s + self.c[0], j - self.s + self.c[1]], v)
    }

    /// The peak's sub-pixel place by a parabola through it and its neighbours along each axis
    /// (within half a pixel of `best`; `best` itself on the rim).
    fn parabola(&self, best: [i64; 2]) -> [f64; 2] {
        let (i, j) = self.index(best);
        let at = |i: i64, j: i64| self.map[j as usize * self.side + i as usize];
        let top = 2 * self.s;
        let vertex = |a: f64, b: f64, c: f64| {
            let den = a - 2.0 * b + c;
            if den < 0.0 {
                (0.5 * (a - c) / den).clamp(-0.5, 0.5)
            } else {
                0.0
            }
        };
        let dx = if i > 0 && i < top {
            vertex(at(i - 1, j), at(i, j), at(i + 1, j))
        } else {
            0.0
        };
        let dy = if j > 0 && j < top {
            vertex(at(i, j - 1), at(i, j), at(i, j + 1))
        } else {
            0.0
        };
        [best[0] as f64 + dx, best[1] as f64 + dy]
    }

    /// The shift is inside the searched ones, off their rim (its interpolation's taps are in
    /// the searched area ± 1.5 px round it).
    fn inside(&self, shift: [i64; 2]) -> bool {
        let (i, j) = self.index(shift);
        let top = 2 * self.s;
        (1..top).contains(&i) && (1..top).contains(&j)
    }

    /// The shift is on the search's rim: the peak may lie beyond.
    fn at_rim(&self, shift: [i64; 2]) -> bool {
        let (i, j) = self.index(shift);
        i == 0 || j == 0 || i == 2 * self.s || j == 2 * self.s
    }

    /// The strongest other local maximum, more than 2 px from `best`.
    fn second(&self, best: [i64; 2]) -> f64 {
        let (bi, bj) = self.index(best);
        let side = self.side;
        let map = &self.map;
        let mut second = f64::NEG_INFINITY;
        for j in 1..side - 1 {
            for i in 1..side - 1 {
                if (i as i64 - bi).abs().max((j as i64 - bj).abs()) <= 2 {
                    continue;
                }
                let v = map[j * side + i];
                let top = (-1i64..=1).all(|dj| {
                    (-1i64..=1).all(|di| {
                        (di == 0 && dj == 0)
                            || v >= map[(j as i64 + dj) as usize * side + (i as i64 + di) as usize]
                    })
                });
                if top {
                    second = second.max(v);
                }
            }
        }
        second
    }
}

/// One click of the flow, read: the reference, refined, or kept as clicked (with the reason).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClickReading {
    /// The nozzle, px, in the reference click's frame.
    pub at_px: [f64; 2],
    /// 1 sd per axis, px, relative to the reference: what the backlash and the scale see.
    pub sd_px: f64,
    /// Refined from the pictures (false: the reference itself, or kept).
    pub refined: bool,
    /// Why the click was kept as it was, if it was.
    pub kept: Option<ClickRefusal>,
}

/// The click flow's readings in order: the first click sets the [`Reference`]; each later one
/// is refined against it, or kept as clicked with the reason. When the first click cannot be
/// a reference, every click is kept as clicked (each with its own stated sd, as independent
/// readings), with that reason.
#[derive(Debug, Clone, Default)]
pub struct ClickReader {
    reference: Option<Result<Reference, ClickRefusal>>,
    params: RegisterParams,
    /// The last reading, px: where a frame the detector refused is searched.
    last_px: Option<[f64; 2]>,
    /// How far the refined readings were from their clicks: Σ squares over both axes, and
    /// the number of axes (issue 37, item 6: a tap's real spread).
    tap_sq: f64,
    tap_axes: usize,
}

impl ClickReader {
    /// Reads the click at `click_px` ± `click_sd_px` in `img`.
    pub fn read(&mut self, img: &Gray<'_>, click_px: [f64; 2], click_sd_px: f64) -> ClickReading {
        let out = self.read_inner(img, click_px, click_sd_px);
        self.last_px = Some(out.at_px);
        out
    }

    fn read_inner(&mut self, img: &Gray<'_>, click_px: [f64; 2], click_sd_px: f64) -> ClickReading {
        let p = &self.params;
        let kept = |sd_px: f64, why: ClickRefusal| ClickReading {
            at_px: click_px,
            sd_px,
            refined: false,
            kept: Some(why),
        };
        match &self.reference {
            None => {
                let r = Reference::new(img, click_px, click_sd_px, p);
                let out = match &r {
                    Ok(r) => ClickReading {
                        at_px: click_px,
                        sd_px: r.sd_px(),
                        refined: false,
                        kept: None,
                    },
                    Err(e) => kept(click_sd_px, e.clone()),
                };
                self.reference = Some(r);
                out
            }
            Some(Err(e)) => kept(click_sd_px, e.clone()),
            Some(Ok(r)) => match r.refine(img, click_px, click_sd_px, p) {
                Ok(f) => {
                    for (a, c) in f.at_px.iter().zip(click_px) {
                        self.tap_sq += (a - c).powi(2);
                    }
                    self.tap_axes += 2;
                    ClickReading {
                        at_px: f.at_px,
                        sd_px: f.sd_px,
                        refined: true,
                        kept: None,
                    }
                }
                // Kept: its error and the reference click's are both in it, as stated, or as
                // the refined clicks showed them to be when that is more.
                Err(e) => {
                    let spread = self.tap_spread_px().unwrap_or(0.0);
                    kept(click_sd_px.hypot(r.click_sd_px()).max(spread), e)
                }
            },
        }
    }

    /// The real spread of a click about where the pictures put the nozzle, in the reference
    /// click's frame (both clicks' errors), per axis, px: the rms of the refined readings'
    /// distances from their clicks, once two clicks were refined. A finger on a phone states
    /// about 2 px and lands 2.4–4.2 px off (issue 37); a kept click carries this ± when it is
    /// the larger, so a conclusion drawn from it is one its real spread allows.
    pub fn tap_spread_px(&self) -> Option<f64> {
        (self.tap_axes >= 4).then(|| (self.tap_sq / self.tap_axes as f64).sqrt())
    }
}

/// Where a frame the detector refused is searched for, as a share of the picture's shorter
/// side (1 sd about the last reading; the search reaches 3 of these): a 640×480 camera looks
/// ±60 px round it, more than a ±0.5 mm scale move at 80 px/mm.
const UNDETECTED_SEARCH_SHARE: f64 = 1.0 / 24.0;

/// The precision a detected centre is taken to have when it stands for a click
/// ([`ClickReader::read_detected`]), px: the detector's error on the bench's rendered families
/// reaches 0.2 px (p95) where its own sd says less, and the registration's search and its check
/// against the click allow 3 of these.
pub const DETECTED_CLICK_SD_PX: f64 = 0.3;

impl ClickReader {
    /// A frame the detector found the nozzle in (centre ± its sd), read as the click flow
    /// reads a click (issue 27, the camera): the first frame is the reference, each later one
    /// is registered against it. The detector finds each frame's nozzle on its own, with a
    /// sub-pixel error that depends on where the nozzle falls on the pixel grid (0.2 px p95);
    /// the registration measures the shift between two pictures of the same nozzle to a few
    /// hundredths. A frame the registration refuses is kept as detected, with the reason.
    pub fn read_detected(
        &mut self,
        img: &Gray<'_>,
        centre_px: [f64; 2],
        sd_px: f64,
    ) -> ClickReading {
        self.read(img, centre_px, sd_px.max(DETECTED_CLICK_SD_PX))
    }

    /// A frame the detector refused, measured all the same (issue 37, item 2: finding the
    /// nozzle only chooses the region): registered against the reference round the last
    /// reading. `None` when there is no reference to register against (no frame read yet,
    /// or the first one could not be a reference); otherwise the reading, or why the pictures
    /// could not give one (a weak or ambiguous match, a nozzle at the edge).
    pub fn read_undetected(
        &mut self,
        img: &Gray<'_>,
    ) -> Option<Result<ClickReading, ClickRefusal>> {
        let Some(Ok(r)) = &self.reference else {
            return None;
        };
        let last = self.last_px?;
        let sd = UNDETECTED_SEARCH_SHARE * img.width.min(img.height) as f64;
        let got = r.refine(img, last, sd, &self.params).map(|f| ClickReading {
            at_px: f.at_px,
            sd_px: f.sd_px,
            refined: true,
            kept: None,
        });
        if let Ok(g) = &got {
            self.last_px = Some(g.at_px);
        }
        Some(got)
    }

    /// Whether the first frame became the reference (a frame is registered against it).
    pub fn has_reference(&self) -> bool {
        matches!(self.reference, Some(Ok(_)))
    }

    /// A frame measured by registering the reference round `at_px`, searching ± `reach_px`
    /// along each axis (issue 37, item 2: the camera flow predicts where the nozzle is, and the
    /// registration measures it there). `None` without a reference.
    pub fn register_round(
        &self,
        img: &Gray<'_>,
        at_px: [f64; 2],
        reach_px: f64,
    ) -> Option<Result<ClickReading, ClickRefusal>> {
        let Some(Ok(r)) = &self.reference else {
            return None;
        };
        // refine() searches ± agree_sd × hypot(this sd, the reference's).
        let lim = (reach_px.max(0.5) / self.params.agree_sd).powi(2) - r.click_sd_px().powi(2);
        let sd = lim.max(0.01).sqrt();
        Some(
            r.refine(img, at_px, sd, &self.params)
                .map(|f| ClickReading {
                    at_px: f.at_px,
                    sd_px: f.sd_px,
                    refined: true,
                    kept: None,
                }),
        )
    }
}

/// Keys' cubic convolution weights (a = −½) of the four taps around a point `t` (0 ≤ t < 1)
/// past the second, and their derivatives in t.
fn keys(t: f64) -> ([f64; 4], [f64; 4]) {
    let (t2, t3) = (t * t, t * t * t);
    (
        [
            0.5 * (-t3 + 2.0 * t2 - t),
            0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
            0.5 * (-3.0 * t3 + 4.0 * t2 + t),
            0.5 * (t3 - t2),
        ],
        [
            0.5 * (-3.0 * t2 + 4.0 * t - 1.0),
            0.5 * (9.0 * t2 - 10.0 * t),
            0.5 * (-9.0 * t2 + 8.0 * t + 1.0),
            0.5 * (3.0 * t2 - 2.0 * t),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera_render::{varied_scene, Family};

    const W: usize = 320;
    const H: usize = 240;

    /// A camera of `fam` drawn from `seed`: renders the nozzle at `at` (each frame's own noise
    /// and JPEG).
    struct Cam {
        scene: crate::camera_render::Scene,
        rng: fastrand::Rng,
    }

    impl Cam {
        fn new(fam: Family, seed: u64) -> Cam {
            let mut rng = fastrand::Rng::with_seed(seed);
            let r = 12.0 + 8.0 * rng.f64();
            let scene = varied_scene(fam, W, H, [W as f64 / 2.0, H as f64 / 2.0], r, &mut rng);
            Cam { scene, rng }
        }

        fn frame(&mut self, at: [f64; 2]) -> Vec<u8> {
            let mut s = self.scene.clone();
            let d = [at[0] - s.nozzles_px[0][0], at[1] - s.nozzles_px[0][1]];
            for c in &mut s.nozzles_px {
                c[0] += d[0];
                c[1] += d[1];
            }
            s.render(&mut self.rng).unwrap().0
        }
    }

    fn gray(g: &[u8]) -> Gray<'_> {
        Gray {
            width: W,
            height: H,
            data: g,
        }
    }

    /// Clicks off by up to 2.5 px give readings whose offsets from the reference are the drawn
    /// ones within a few hundredths of a pixel, and within 3 of their stated sd, for the ring,
    /// the dark tip and a picture with two nozzles (which the detector refuses); the shifts
    /// include the scale moves' 40 px and sub-pixel ones.
    #[test]
    fn clicks_off_by_pixels_are_refined_to_the_drawn_offset() {
        let p = RegisterParams::default();
        let (mut errs, mut covered, mut n) = (Vec::new(), 0, 0);
        for (k, fam) in [Family::Ring, Family::DarkTip, Family::TwoNozzles]
            .into_iter()
            .cycle()
            .take(6)
            .enumerate()
        {
            let mut cam = Cam::new(fam, 100 + k as u64);
            let mut rng = fastrand::Rng::with_seed(k as u64);
            let slip = |rng: &mut fastrand::Rng| [5.0 * rng.f64() - 2.5, 5.0 * rng.f64() - 2.5];
            let c0 = [150.3 + 10.0 * rng.f64(), 118.7 + 6.0 * rng.f64()];
            let s0 = slip(&mut rng);
            let click0 = [c0[0] + s0[0], c0[1] + s0[1]];
            let g0 = cam.frame(c0);
            let r = Reference::new(&gray(&g0), click0, 1.5, &p)
                .unwrap_or_else(|e| panic!("{fam:?}: reference refused: {e}"));
            assert!(r.sd_px() < 0.1, "{}", r.sd_px());
            for shift in [
                [40.0, 0.0],
                [-40.0, 0.0],
                [0.0, 40.0],
                [0.37, -0.21],
                [-3.61, 2.05],
                [0.0, 0.0],
            ] {
                let at = [c0[0] + shift[0], c0[1] + shift[1]];
                let g = cam.frame(at);
                let s = slip(&mut rng);
                let click = [at[0] + s[0], at[1] + s[1]];
                let got = r
                    .refine(&gray(&g), click, 1.5, &p)
                    .unwrap_or_else(|e| panic!("{fam:?} {shift:?}: refused: {e}"));
                let e = [
                    got.at_px[0] - click0[0] - shift[0],
                    got.at_px[1] - click0[1] - shift[1],
                ];
                n += 1;
                covered += usize::from(e[0].abs().max(e[1].abs()) <= 3.0 * got.sd_px);
                errs.push(e[0].hypot(e[1]));
            }
        }
        errs.sort_by(f64::total_cmp);
        eprintln!("errors {errs:.3?}, 3 sd covered {covered}/{n}");
        // Within 0.25 px (3 µm at 80 px/mm) where the clicks were off by up to 2.5 px: the
        // noisiest camera here (the two-nozzle scene) states 0.17–0.23 px and errs up to 0.21.
        assert!(errs[errs.len() - 1] < 0.25, "{errs:?}");
        assert!(covered as f64 >= 0.9 * n as f64, "{covered}/{n}");
    }

    /// Issue 37: the scale's moves take the nozzle so far that the reference patch, searched
    /// for where it is expected, would leave the picture. Before, that was refused as at the
    /// edge and the axis went unfinished; now the patch is cut to what stays in view, and the
    /// shift is measured all the same, on TAMV's real photo.
    #[test]
    fn a_patch_that_would_leave_the_picture_is_cut_to_what_stays_in_view() {
        use crate::photo_camera::{photo, Lighting, PhotoCamera, Placement};
        let ph = photo(&crate::nozzle_photos::checkout, "tamv-nozzle").unwrap();
        let mut rng = fastrand::Rng::with_seed(37);
        let (w, h) = (400, 300);
        let home = [200.0, 150.0];
        let at = Placement {
            width: w,
            height: h,
            rotation_deg: -6.0,
            home_px: home,
            reach_px: 110.0,
            zoom: None,
        };
        let cam = PhotoCamera::new(&ph, &at, Lighting::draw(&mut rng)).unwrap();
        let g0 = cam.frame(home, &mut rng).unwrap().0;
        fn g(d: &[u8]) -> Gray<'_> {
            Gray {
                width: 400,
                height: 300,
                data: d,
            }
        }
        let p = RegisterParams::default();
        let r = Reference::new(&g(&g0), home, 1.0, &p).unwrap();
        for (shift, expect_off) in [
            ([0.0, 100.0], [3.0, -5.0]),
            ([-40.0, -100.0], [4.0, 2.0]),
            ([60.0, 98.0], [-5.0, 4.0]),
        ] {
            let truth = [home[0] + shift[0], home[1] + shift[1]];
            let gi = cam.frame(truth, &mut rng).unwrap().0;
            let click = [truth[0] + expect_off[0], truth[1] + expect_off[1]];
            // Searched ± 20 px round a point 6 px off: the uncut patch leaves the picture.
            let limit = p.agree_sd * 4.5f64.hypot(r.click_sd_px());
            let c = [
                (click[0] - home[0]).round() as i64,
                (click[1] - home[1]).round() as i64,
            ];
            let wanted = limit.ceil() as i64 + 2;
            let old = r.refine_in(&g(&gi), click, limit, c, wanted, &p);
            assert!(
                matches!(old, Err(ClickRefusal::AtEdge { .. })),
                "{shift:?}: {old:?}"
            );
            let got = r
                .refine(&g(&gi), click, 4.5, &p)
                .unwrap_or_else(|e| panic!("{shift:?}: {e}"));
            let e = [got.at_px[0] - truth[0], got.at_px[1] - truth[1]];
            assert!(
                e[0].abs().max(e[1].abs()) < 0.1 && got.sd_px < 0.1,
                "{shift:?}: {got:?}, {e:?} px off"
            );
        }
    }

    /// The static background is taken out: under a steep light gradient and vignetting, which
    /// would pull an unweighted patch toward zero shift, a 0.6 px move reads 0.6 px.
    #[test]
    fn a_static_background_does_not_pull_the_shift_toward_zero() {
        let p = RegisterParams::default();
        let mut cam = Cam::new(Family::DarkTip, 7);
        cam.scene.gradient = [90.0, -70.0];
        cam.scene.vignette = 0.4;
        cam.scene.contrast = 30.0;
        let c0 = [160.0, 120.0];
        let r = Reference::new(&gray(&cam.frame(c0)), c0, 1.0, &p).unwrap();
        let mut sum = [0.0, 0.0];
        for _ in 0..8 {
            let g = cam.frame([160.6, 120.0]);
            let got = r.refine(&gray(&g), [161.5, 119.2], 1.0, &p).unwrap();
            let e = [got.at_px[0] - 160.6, got.at_px[1] - 120.0];
            assert!(e[0].abs().max(e[1].abs()) < 3.0 * got.sd_px, "{got:?}");
            sum = [sum[0] + e[0] / 8.0, sum[1] + e[1] / 8.0];
        }
        assert!(
            sum[0].abs() < 0.04 && sum[1].abs() < 0.04,
            "mean error {sum:?} px"
        );
    }

    /// What cannot be refined is refused with the reason: a click on plain background, a
    /// snapshot without the nozzle, a click far from where the pictures put the nozzle, two
    /// nozzles within the click's reach, a picture of another size.
    #[test]
    fn what_cannot_be_refined_is_refused_with_the_reason() {
        let p = RegisterParams::default();
        let mut cam = Cam::new(Family::Ring, 3);
        let c0 = [160.0, 120.0];
        let g0 = cam.frame(c0);
        let e = Reference::new(&gray(&g0), [40.0, 40.0], 1.0, &p).unwrap_err();
        assert!(matches!(e, ClickRefusal::NothingAtClick { .. }), "{e}");
        assert!(e.to_string().contains("nothing stands out"), "{e}");
        let r = Reference::new(&gray(&g0), [161.0, 119.0], 1.0, &p).unwrap();
        // No nozzle in the snapshot.
        let mut empty = cam.scene.clone();
        empty.nozzles_px.clear();
        let ge = empty.render(&mut cam.rng).unwrap().0;
        let e = r.refine(&gray(&ge), [170.0, 120.0], 1.0, &p).unwrap_err();
        assert!(matches!(e, ClickRefusal::WeakMatch { .. }), "{e}");
        // The nozzle drawn 8 px from where a click stated ±0.5 px puts it.
        let g = cam.frame([178.0, 120.0]);
        let e = r.refine(&gray(&g), [170.0, 120.0], 0.5, &p).unwrap_err();
        assert!(
            matches!(e, ClickRefusal::OffClick { distance_px, .. } if distance_px >= 5.0),
            "{e}"
        );
        assert!(
            e.to_string().contains("more than the click's precision"),
            "{e}"
        );
        // Two nozzles 3 radii apart, clicked between them with a precision vaguer than that.
        let mut two = Cam::new(Family::Ring, 3);
        let rad = two.scene.radius_px;
        two.scene.nozzles_px = vec![c0, [c0[0] + 3.0 * rad, c0[1]]];
        let g0 = two.frame(c0);
        let r2 = Reference::new(&gray(&g0), c0, 1.0, &p).unwrap();
        let g = two.frame([c0[0] + 10.0, c0[1]]);
        let e = r2
            .refine(&gray(&g), [c0[0] + 10.0 + 1.5 * rad, c0[1]], 12.0, &p)
            .unwrap_err();
        assert!(matches!(e, ClickRefusal::Ambiguous { .. }), "{e}");
        let small = vec![0u8; 100 * 80];
        let e = r
            .refine(
                &Gray {
                    width: 100,
                    height: 80,
                    data: &small,
                },
                [50.0, 40.0],
                1.0,
                &p,
            )
            .unwrap_err();
        assert!(
            e.to_string().contains("the first snapshot was 320×240"),
            "{e}"
        );
    }

    /// The click flow's reader: the first click is the reference (its own small sd), a later
    /// one is refined; one the pictures contradict is kept as clicked with the two clicks'
    /// sd and the reason; when the first click finds nothing, every click is kept with its own.
    #[test]
    fn the_reader_keeps_a_click_it_cannot_refine_and_says_why() {
        let mut cam = Cam::new(Family::DarkTip, 9);
        let c0 = [150.0, 110.0];
        let mut rd = ClickReader::default();
        let g0 = cam.frame(c0);
        let first = rd.read(&gray(&g0), [151.0, 109.5], 1.0);
        assert!(
            !first.refined && first.kept.is_none() && first.sd_px < 0.2,
            "{first:?}"
        );
        assert_eq!(first.at_px, [151.0, 109.5]);
        let g = cam.frame([160.3, 110.0]);
        let r = rd.read(&gray(&g), [161.0, 111.0], 1.0);
        assert!(r.refined && r.kept.is_none(), "{r:?}");
        assert!(
            (r.at_px[0] - 161.3).abs() < 0.2 && (r.at_px[1] - 109.5).abs() < 0.2,
            "{r:?}"
        );
        // Clicked 9 px from where the pictures put it, at ±0.5 px: kept, and said why.
        let g = cam.frame([140.0, 110.0]);
        let r = rd.read(&gray(&g), [149.0, 110.0], 0.5);
        assert!(!r.refined && r.at_px == [149.0, 110.0], "{r:?}");
        assert!((r.sd_px - 0.5f64.hypot(1.0)).abs() < 1e-12, "{r:?}");
        assert!(
            matches!(r.kept, Some(ClickRefusal::OffClick { .. })),
            "{r:?}"
        );
        // Nothing under the first click: every click as clicked, each with its own sd.
        let mut rd = ClickReader::default();
        let r = rd.read(&gray(&g0), [30.0, 30.0], 1.0);
        assert!(
            matches!(r.kept, Some(ClickRefusal::NothingAtClick { .. })),
            "{r:?}"
        );
        let r = rd.read(&gray(&g), [140.5, 110.0], 2.0);
        assert!(
            !r.refined && r.sd_px == 2.0 && r.at_px == [140.5, 110.0],
            "{r:?}"
        );
        assert!(
            matches!(r.kept, Some(ClickRefusal::NothingAtClick { .. })),
            "{r:?}"
        );
    }

    /// Issue 37, item 6: a tap is only a hint. Taps landing up to ±4 px off while stating
    /// ±1 px are refined to the drawn offsets; a later one that cannot be refined (no nozzle
    /// in its snapshot) is kept with the taps' real spread as its ±, not the stated ±1.4.
    #[test]
    fn a_kept_tap_carries_the_taps_real_spread() {
        let mut cam = Cam::new(Family::Ring, 21);
        let mut rng = fastrand::Rng::with_seed(21);
        let mut rd = ClickReader::default();
        let slip = |rng: &mut fastrand::Rng| [8.0 * rng.f64() - 4.0, 8.0 * rng.f64() - 4.0];
        let c0 = [155.0, 115.0];
        let s0 = slip(&mut rng);
        let click0 = [c0[0] + s0[0], c0[1] + s0[1]];
        rd.read(&gray(&cam.frame(c0)), click0, 1.0);
        assert!(rd.tap_spread_px().is_none());
        for k in 0..6 {
            let at = [c0[0] + 3.0 * f64::from(k), c0[1] - 0.7 * f64::from(k)];
            let s = slip(&mut rng);
            let r = rd.read(&gray(&cam.frame(at)), [at[0] + s[0], at[1] + s[1]], 1.0);
            assert!(r.refined, "{k}: {r:?}");
            let e = [
                r.at_px[0] - click0[0] - (at[0] - c0[0]),
                r.at_px[1] - click0[1] - (at[1] - c0[1]),
            ];
            assert!(e[0].abs().max(e[1].abs()) < 0.2, "{k}: {e:?}");
        }
        let spread = rd.tap_spread_px().unwrap();
        assert!(spread > 1.0f64.hypot(1.0), "{spread}");
        let mut empty = cam.scene.clone();
        empty.nozzles_px.clear();
        let ge = empty.render(&mut cam.rng).unwrap().0;
        let r = rd.read(&gray(&ge), [170.0, 112.0], 1.0);
        assert!(!r.refined && r.kept.is_some(), "{r:?}");
        assert!((r.sd_px - spread).abs() < 1e-12, "{r:?} {spread}");
    }

    /// Issue 37, item 2: a frame the detector refuses (a second nozzle-like thing came into
    /// view: "two candidates") is still measured, by registering the region round the last
    /// reading against the first frame's; without a reference there is nothing to register.
    #[test]
    fn a_frame_the_detector_refuses_is_measured_by_registration() {
        let p = super::super::DetectParams::default();
        let mut cam = Cam::new(Family::DarkTip, 11);
        let mut rd = ClickReader::default();
        let c0 = [150.0, 110.0];
        let g0 = cam.frame(c0);
        assert!(rd.read_undetected(&gray(&g0)).is_none());
        let d0 = super::super::detect(&gray(&g0), &p).unwrap();
        let first = rd.read_detected(&gray(&g0), d0.centre_px, d0.uncertainty_px);
        cam.scene.nozzles_px = vec![c0, [c0[0] + 120.0, c0[1] + 70.0]];
        let mut at = c0;
        for step in [[0.4, -0.3], [6.2, 3.1], [-12.5, 0.7], [0.0, 0.0]] {
            at = [at[0] + step[0], at[1] + step[1]];
            let g = cam.frame(at);
            let e = super::super::detect(&gray(&g), &p).unwrap_err();
            assert!(
                matches!(e, super::super::Refusal::TwoCandidates { .. }),
                "{e}"
            );
            let r = rd
                .read_undetected(&gray(&g))
                .expect("a reference")
                .unwrap_or_else(|e| panic!("{at:?}: {e}"));
            let err = [
                r.at_px[0] - first.at_px[0] - (at[0] - c0[0]),
                r.at_px[1] - first.at_px[1] - (at[1] - c0[1]),
            ];
            assert!(r.refined && r.sd_px < 0.2, "{r:?}");
            assert!(
                err[0].abs().max(err[1].abs()) <= (3.0 * r.sd_px).max(0.1),
                "{at:?}: off by {err:?}, sd {}",
                r.sd_px
            );
        }
    }

    /// The camera's readings (issue 27): each frame's detected centre registered against the
    /// first frame's. The detector's own error depends on where the nozzle falls on the pixel
    /// grid and does not cancel between two positions a few µm apart; the registered shift
    /// does. Over sub-pixel to 12 px shifts of the ring and the dark tip, the registered
    /// offsets are within a few hundredths of a pixel, several times closer than the
    /// detector's (the camera's own error on the bench's play-free model 0.74 → 0.13 µm sd).
    #[test]
    fn detected_frames_registered_against_the_first_read_the_shift_closer_than_detection() {
        let (mut reg_sq, mut det_sq, mut n) = (0.0, 0.0, 0);
        for (k, fam) in [Family::Ring, Family::DarkTip]
            .into_iter()
            .cycle()
            .take(6)
            .enumerate()
        {
            let mut cam = Cam::new(fam, 300 + k as u64);
            let mut rng = fastrand::Rng::with_seed(k as u64);
            let mut reader = ClickReader::default();
            let c0 = [150.0 + 10.0 * rng.f64(), 110.0 + 10.0 * rng.f64()];
            let mut first_det = None;
            for i in 0..12 {
                let shift = if i == 0 {
                    [0.0, 0.0]
                } else {
                    [12.0 * rng.f64() - 6.0, 12.0 * rng.f64() - 6.0]
                };
                let at = [c0[0] + shift[0], c0[1] + shift[1]];
                let g = cam.frame(at);
                let d = super::super::detect(&gray(&g), &super::super::DetectParams::default())
                    .unwrap_or_else(|e| panic!("{fam:?}: detection refused: {e}"));
                let r = reader.read_detected(&gray(&g), d.centre_px, d.uncertainty_px);
                assert!(r.kept.is_none(), "{fam:?} {shift:?}: kept: {:?}", r.kept);
                let f = *first_det.get_or_insert(d.centre_px);
                if i == 0 {
                    assert_eq!(r.at_px, d.centre_px);
                    continue;
                }
                assert!(r.refined);
                for a in 0..2 {
                    reg_sq += (r.at_px[a] - f[a] - shift[a]).powi(2);
                    det_sq += (d.centre_px[a] - f[a] - shift[a]).powi(2);
                    n += 1;
                }
            }
        }
        let (reg, det) = ((reg_sq / n as f64).sqrt(), (det_sq / n as f64).sqrt());
        assert!(
            reg < 0.04 && reg < det / 2.0,
            "registered rms {reg:.3} px, detected {det:.3} px"
        );
    }
}
