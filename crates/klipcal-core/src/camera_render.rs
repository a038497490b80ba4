//! The nozzle camera drawn for tests and `klipcal bench backlash` (issue 27): a nozzle seen from
//! below at a sub-pixel position, as a bright ring or a dark tip on a lit background, with
//! uneven lighting, defocus, noise and JPEG compression through the same `image` crate the
//! offline command decodes with; and the pictures detection must refuse (empty, two nozzles,
//! saturated, flat). Not on the daemon's runtime path.
//!
//! Pixel (i, j) covers [i − ½, i + ½] × [j − ½, j + ½], so its centre is (i, j) as in
//! [`crate::calib::nozzle`]. Edges are drawn analytically — a disc blurred by a Gaussian of sd
//! `blur_px` has the profile ½·erfc((r − R)/(√2·σ)) — and averaged over 4×4 sub-pixels near
//! an edge, so the drawn centre is exact to far below the detection's precision.

use anyhow::Context;

/// How the nozzle looks from below.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Look {
    /// A lit nozzle face: a bright annulus around a dark orifice.
    Ring,
    /// A dark tip against the light, with a lighter orifice and shading from one side.
    DarkTip,
}

/// Everything that makes one picture.
#[derive(Debug, Clone)]
pub struct Scene {
    pub width: usize,
    pub height: usize,
    pub look: Look,
    /// Nozzle centres, px (two for the "two nozzles" family, none for "empty").
    pub nozzles_px: Vec<[f64; 2]>,
    /// Outer radius of the nozzle, px.
    pub radius_px: f64,
    /// Background level at the centre of the picture, grey levels.
    pub background: f64,
    /// Background change across the picture from left to right and top to bottom, levels.
    pub gradient: [f64; 2],
    /// Vignetting: the corners darker by this share.
    pub vignette: f64,
    /// How far the nozzle stands out from the background, levels.
    pub contrast: f64,
    /// Shading across the nozzle from one side, share of the contrast.
    pub shading: f64,
    /// Defocus blur, Gaussian sd, px.
    pub blur_px: f64,
    /// Sensor noise sd, levels.
    pub noise_sd: f64,
    /// Exposure gain applied before clipping to 0–255 (over 1 saturates).
    pub gain: f64,
    /// JPEG quality (1–100), or None for the raw picture.
    pub jpeg_quality: Option<u8>,
}

fn erfc(x: f64) -> f64 {
    // Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7).
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * z);
    let y = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))))
        * (-z * z).exp();
    if x >= 0.0 {
        y
    } else {
        2.0 - y
    }
}

/// 1 inside a disc of radius `r0`, 0 outside, blurred by `s`.
fn disc(r: f64, r0: f64, s: f64) -> f64 {
    0.5 * erfc((r - r0) / (std::f64::consts::SQRT_2 * s))
}

fn gauss(rng: &mut fastrand::Rng) -> f64 {
    let u = 1.0 - rng.f64();
    let v = rng.f64();
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

impl Scene {
    /// The nozzle's intensity offset from the background at distance (dx, dy) from its centre.
    fn nozzle(&self, dx: f64, dy: f64) -> f64 {
        let r = (dx * dx + dy * dy).sqrt();
        let (rr, s, c) = (self.radius_px, self.blur_px.max(0.3), self.contrast);
        let shade = 1.0 + self.shading * dx / rr;
        match self.look {
            Look::Ring => {
                c * shade * (disc(r, rr, s) - disc(r, 0.55 * rr, s))
                    - 0.6 * c * disc(r, 0.3 * rr, s)
            }
            Look::DarkTip => -c * shade * disc(r, rr, s) + 0.4 * c * disc(r, 0.22 * rr, s),
        }
    }

    fn lit(&self, x: f64, y: f64) -> f64 {
        let (w, h) = (self.width as f64, self.height as f64);
        let (u, v) = (x / w - 0.5, y / h - 0.5);
        let vig = 1.0 - self.vignette * 2.0 * (u * u + v * v);
        (self.background + self.gradient[0] * u + self.gradient[1] * v) * vig
    }

    /// The grey picture before the JPEG step.
    pub fn raw(&self, rng: &mut fastrand::Rng) -> Vec<u8> {
        let (w, h) = (self.width, self.height);
        let edge_band = 3.0 * self.blur_px.max(0.3) + 1.5;
        let radii = [1.0, 0.55, 0.3, 0.22];
        let mut out = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f64, y as f64);
                let mut v = self.lit(fx, fy);
                for c in &self.nozzles_px {
                    let (dx, dy) = (fx - c[0], fy - c[1]);
                    let r = (dx * dx + dy * dy).sqrt();
                    if r > self.radius_px + edge_band + 1.0 {
                        continue;
                    }
                    let near = radii
                        .iter()
                        .any(|k| (r - k * self.radius_px).abs() < edge_band);
                    if near {
                        let mut acc = 0.0;
                        for sy in 0..4 {
                            for sx in 0..4 {
                                let ox = (f64::from(sx) + 0.5) / 4.0 - 0.5;
                                let oy = (f64::from(sy) + 0.5) / 4.0 - 0.5;
                                acc += self.nozzle(dx + ox, dy + oy);
                            }
                        }
                        v += acc / 16.0;
                    } else {
                        v += self.nozzle(dx, dy);
                    }
                }
                let v = (v * self.gain + self.noise_sd * gauss(rng)).round();
                out[y * w + x] = v.clamp(0.0, 255.0) as u8;
            }
        }
        out
    }

    /// The picture as the camera serves it: raw, or JPEG-encoded and decoded again through the
    /// `image` crate. Returns the grey pixels and, for JPEG, the file's bytes.
    pub fn render(&self, rng: &mut fastrand::Rng) -> anyhow::Result<(Vec<u8>, Option<Vec<u8>>)> {
        let raw = self.raw(rng);
        let Some(q) = self.jpeg_quality else {
            return Ok((raw, None));
        };
        let jpeg = encode_jpeg(&raw, self.width, self.height, q)?;
        let (_, _, grey) = decode_gray(&jpeg)?;
        Ok((grey, Some(jpeg)))
    }
}

/// Grey pixels as a JPEG file.
pub fn encode_jpeg(grey: &[u8], w: usize, h: usize, quality: u8) -> anyhow::Result<Vec<u8>> {
    let mut buf = Vec::new();
    let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut buf, quality);
    enc.encode(
        grey,
        u32::try_from(w)?,
        u32::try_from(h)?,
        image::ExtendedColorType::L8,
    )
    .context("JPEG encoding")?;
    Ok(buf)
}

pub use crate::calib::nozzle::decode_gray;

/// The families of pictures the benchmark and the tests draw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Family {
    /// A bright ring, lighting/blur/noise/JPEG varied: detection must find it.
    Ring,
    /// A dark tip, varied the same way: detection must find it.
    DarkTip,
    /// Nothing in view: must refuse.
    Empty,
    /// Two nozzles: must refuse.
    TwoNozzles,
    /// Overexposed: must refuse.
    Saturated,
    /// A flat picture: must refuse.
    Flat,
}

impl Family {
    pub const ALL: [Family; 6] = [
        Family::Ring,
        Family::DarkTip,
        Family::Empty,
        Family::TwoNozzles,
        Family::Saturated,
        Family::Flat,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Family::Ring => "bright ring",
            Family::DarkTip => "dark tip",
            Family::Empty => "empty (must refuse)",
            Family::TwoNozzles => "two nozzles (must refuse)",
            Family::Saturated => "saturated (must refuse)",
            Family::Flat => "flat (must refuse)",
        }
    }

    pub fn must_refuse(self) -> bool {
        !matches!(self, Family::Ring | Family::DarkTip)
    }
}

/// The camera's own variation for one setting up: lighting, defocus, noise and JPEG quality
/// drawn from the ranges a printer's nozzle camera shows. The nozzle at `centre_px`.
pub fn varied_scene(
    family: Family,
    w: usize,
    h: usize,
    centre_px: [f64; 2],
    radius_px: f64,
    rng: &mut fastrand::Rng,
) -> Scene {
    let u = |rng: &mut fastrand::Rng, a: f64, b: f64| a + (b - a) * rng.f64();
    let mut s = Scene {
        width: w,
        height: h,
        look: if family == Family::DarkTip || (family == Family::TwoNozzles && rng.bool()) {
            Look::DarkTip
        } else {
            Look::Ring
        },
        nozzles_px: vec![centre_px],
        radius_px,
        background: u(rng, 90.0, 170.0),
        gradient: [u(rng, -40.0, 40.0), u(rng, -40.0, 40.0)],
        vignette: u(rng, 0.0, 0.3),
        contrast: u(rng, 35.0, 75.0),
        shading: u(rng, -0.3, 0.3),
        blur_px: u(rng, 0.6, 2.5),
        noise_sd: u(rng, 1.0, 5.0),
        gain: 1.0,
        jpeg_quality: Some(rng.u8(60..=95)),
    };
    match family {
        Family::Ring | Family::DarkTip => {}
        Family::Empty => s.nozzles_px.clear(),
        Family::TwoNozzles => {
            // A second nozzle (an IDEX's other toolhead) a few radii away, inside the frame.
            let a = u(rng, 0.0, std::f64::consts::TAU);
            let d = u(rng, 2.6, 4.0) * radius_px;
            let c2 = [
                (centre_px[0] + d * a.cos()).clamp(radius_px + 4.0, w as f64 - radius_px - 5.0),
                (centre_px[1] + d * a.sin()).clamp(radius_px + 4.0, h as f64 - radius_px - 5.0),
            ];
            s.nozzles_px.push(c2);
        }
        Family::Saturated => s.gain = u(rng, 1.15, 1.6) * 255.0 / s.background,
        Family::Flat => {
            s.nozzles_px.clear();
            s.gradient = [0.0, 0.0];
            s.vignette = 0.0;
            s.noise_sd = u(rng, 0.5, 1.5);
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::nozzle::{detect, DetectParams, Gray, Refusal};

    const W: usize = 320;
    const H: usize = 240;

    /// Renders `n` varied pictures of `fam` (JPEG) and detects each: (true centre, result).
    fn run(
        fam: Family,
        n: usize,
        seed: u64,
    ) -> Vec<([f64; 2], Result<crate::calib::nozzle::Detection, Refusal>)> {
        let mut rng = fastrand::Rng::with_seed(seed);
        (0..n)
            .map(|_| {
                let c = [
                    W as f64 / 2.0 + 60.0 * (rng.f64() - 0.5),
                    H as f64 / 2.0 + 40.0 * (rng.f64() - 0.5),
                ];
                let r = 12.0 + 10.0 * rng.f64();
                let s = varied_scene(fam, W, H, c, r, &mut rng);
                let (g, jpeg) = s.render(&mut rng).unwrap();
                assert!(jpeg.is_some_and(|j| j.starts_with(&[0xFF, 0xD8])));
                let d = detect(
                    &Gray {
                        width: W,
                        height: H,
                        data: &g,
                    },
                    &DetectParams::default(),
                );
                (c, d)
            })
            .collect()
    }

    #[test]
    fn each_family_is_found_within_its_stated_error() {
        let mut fails = Vec::new();
        for fam in [Family::Ring, Family::DarkTip] {
            let got = run(fam, 40, 11);
            let mut errs = Vec::new();
            let mut covered = 0;
            for (c, d) in &got {
                let d = d
                    .as_ref()
                    .unwrap_or_else(|r| panic!("{fam:?} refused: {r}"));
                let (ex, ey) = (d.centre_px[0] - c[0], d.centre_px[1] - c[1]);
                errs.push(ex.hypot(ey));
                if ex.abs() <= 2.0 * d.uncertainty_px && ey.abs() <= 2.0 * d.uncertainty_px {
                    covered += 1;
                }
            }
            errs.sort_by(f64::total_cmp);
            eprintln!("{fam:?}: errors {errs:.3?} covered {covered}/40");
            // Worst of 40 within 0.4 px (5 µm at 80 px/mm). Both coordinates within the stated
            // ±2u on 35 of 40 each (two normal coordinates at 95 % each: 36.4 of 40); 28–31
            // before the detector added what its fit's covariance leaves out (issue 27).
            if errs[errs.len() - 1] > 0.4 {
                fails.push(format!("{fam:?}: worst error {:.3} px", errs[39]));
            }
            if covered < 33 {
                fails.push(format!("{fam:?}: ±2u covered only {covered} of 40"));
            }
        }
        assert!(fails.is_empty(), "{fails:?}");
    }

    #[test]
    fn a_nozzle_cut_by_the_frame_or_a_short_buffer_is_refused() {
        let mut rng = fastrand::Rng::with_seed(2);
        let mut s = varied_scene(Family::DarkTip, W, H, [6.0, 120.0], 18.0, &mut rng);
        s.jpeg_quality = None;
        let g = s.raw(&mut rng);
        let img = Gray {
            width: W,
            height: H,
            data: &g,
        };
        let r = detect(&img, &DetectParams::default()).unwrap_err();
        assert!(matches!(r, Refusal::AtEdge { .. }), "{r}");
        let short = Gray {
            width: W,
            height: H,
            data: &g[..W * H - 1],
        };
        let r = detect(&short, &DetectParams::default()).unwrap_err();
        assert!(r.to_string().contains("bytes for 320×240"), "{r}");
    }

    #[test]
    fn pictures_without_one_sure_nozzle_are_refused_with_the_reason() {
        for (fam, want) in [
            (Family::Empty, "no_nozzle|no_tip"),
            (Family::TwoNozzles, "two_candidates"),
            (Family::Saturated, "saturated"),
            (Family::Flat, "too_little_contrast"),
        ] {
            for (_, d) in run(fam, 12, 5) {
                let r = d.expect_err(fam.name());
                let v = serde_json::to_value(&r).unwrap();
                let reason = v["reason"].as_str().unwrap_or_default();
                assert!(want.split('|').any(|w| w == reason), "{fam:?}: {r}");
                assert!(!r.to_string().is_empty());
            }
        }
    }
}
