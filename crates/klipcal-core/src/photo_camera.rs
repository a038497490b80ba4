//! A nozzle camera whose frames are a real photograph (issue 37, item 5): one of
//! `tests/fixtures/nozzle`'s hand-labelled photos, magnified, turned by the camera's rotation
//! and moved so that its labelled tip lands where the simulated nozzle is, resampled with a
//! Lanczos-3 kernel (never the nearest pixel); then the camera's lighting (a gain, an offset
//! and a gradient across the frame, drawn once per camera, with a small flicker per frame),
//! fresh sensor noise, and JPEG re-compression at a quality of 70–90. The frame is cropped
//! from the magnified photo so that its edges never show while the tip stays within `reach`
//! of where the camera was set up; beyond that, what lies outside the photo is its mean grey.
//!
//! One implementation for the bench's snapshot server (`klipcal bench camera` with
//! `"photo": …`) and the in-process end-to-end lines of `klipcal bench backlash`. Feature
//! `sim` only: never in the printer's build.

use anyhow::Context;

use crate::calib::nozzle::decode_gray;
use crate::camera_render::encode_jpeg;
use crate::nozzle_photos::{self, Expect, Photo};

/// Lanczos-3 kernel samples per pixel of its argument (0 ≤ |t| < 3).
const LUT_PER_PX: usize = 512;
/// Lanczos-3's reach, px.
const TAPS: usize = 6;
/// Kept between a magnified photo's edge and the frame: the kernel's reach (2 px before the
/// sample, 3 after) and half a pixel.
const EDGE_PX: f64 = 3.5;

/// The labelled photo of the manifest named `name`: a picture's name (`ktamv-frame`), or a
/// source file's name (`tamv-nozzle.jpg`: its first picture a person finds the nozzle in).
///
/// # Errors
/// The fixtures cannot be read, no such picture, or one without a hand-labelled tip.
pub fn photo(files: nozzle_photos::Fixtures, name: &str) -> anyhow::Result<Photo> {
    let all = nozzle_photos::load(files)?;
    let usable: Vec<String> = all
        .iter()
        .filter(|p| p.tip_px.is_some() && p.expect == Expect::Found)
        .map(|p| p.name.clone())
        .collect();
    let pick = all
        .iter()
        .position(|p| p.name == name)
        .or_else(|| {
            all.iter()
                .position(|p| p.source == name && p.expect == Expect::Found)
        })
        .with_context(|| {
            format!(
                "photo {name:?}: not in tests/fixtures/nozzle/manifest.json; expected one of \
                 {usable:?} or a source file's name"
            )
        })?;
    let p = all.into_iter().nth(pick).context("photo index")?;
    anyhow::ensure!(
        p.tip_px.is_some() && p.expect == Expect::Found,
        "photo {name:?}: a picture without one sure, hand-labelled nozzle cannot be moved to \
         the simulated nozzle's position; expected one of {usable:?}"
    );
    Ok(p)
}

/// The camera's lighting, noise and compression, drawn once per camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lighting {
    /// Exposure gain on the photo's grey levels.
    pub gain: f64,
    /// Offset, grey levels.
    pub offset: f64,
    /// Illumination change from the frame's centre to its right and bottom edges, share.
    pub gradient: [f64; 2],
    /// Per-frame flicker of the gain (sd, share) and of the offset (sd, levels).
    pub flicker: f64,
    pub flicker_offset: f64,
    /// Sensor noise sd, grey levels, drawn afresh for every frame.
    pub noise_sd: f64,
    /// JPEG quality.
    pub quality: u8,
}

impl Lighting {
    /// Drawn from the ranges a printer's nozzle camera shows.
    pub fn draw(rng: &mut fastrand::Rng) -> Lighting {
        let mut u = |a: f64, b: f64| a + (b - a) * rng.f64();
        Lighting {
            gain: u(0.85, 1.15),
            offset: u(-10.0, 10.0),
            gradient: [u(-0.1, 0.1), u(-0.1, 0.1)],
            flicker: 0.01,
            flicker_offset: 1.0,
            noise_sd: u(0.5, 2.5),
            quality: rng.u8(70..=90),
        }
    }
}

/// How the photo is laid on the frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    /// Frame size, px.
    pub width: usize,
    pub height: usize,
    /// The camera's rotation: the photo turned by this in the frame (y down), degrees.
    pub rotation_deg: f64,
    /// Where the tip is when the camera is set up, px, and how far it may go from there in x
    /// and y with no edge showing, px.
    pub home_px: [f64; 2],
    pub reach_px: f64,
    /// The photo's magnification; None: the least (at least 1) that keeps its edges out of the
    /// frame over the reach.
    pub zoom: Option<f64>,
}

/// A camera looking at a real photo (see the module's text).
#[derive(Debug, Clone)]
pub struct PhotoCamera {
    /// The photo's manifest name.
    pub name: String,
    src: Vec<f32>,
    sw: usize,
    sh: usize,
    tip: [f64; 2],
    mean: f64,
    pub width: usize,
    pub height: usize,
    pub zoom: f64,
    cos: f64,
    sin: f64,
    pub light: Lighting,
    lut: Vec<f32>,
}

fn lanczos3(t: f64) -> f64 {
    let t = t.abs();
    if t < 1e-9 {
        return 1.0;
    }
    if t >= 3.0 {
        return 0.0;
    }
    let pt = std::f64::consts::PI * t;
    3.0 * pt.sin() * (pt / 3.0).sin() / (pt * pt)
}

fn normal(rng: &mut fastrand::Rng) -> f64 {
    let u = rng.f64().max(1e-12);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.f64()).cos()
}

impl PhotoCamera {
    /// The camera on `photo` (a labelled one: [`photo`]).
    ///
    /// # Errors
    /// A photo without a tip label, a frame or reach out of range, or a zoom too small to keep
    /// the photo's edges out of the frame (with the zoom that would).
    pub fn new(photo: &Photo, at: &Placement, light: Lighting) -> anyhow::Result<PhotoCamera> {
        let tip = photo
            .tip_px
            .with_context(|| format!("photo {}: no hand-labelled tip", photo.name))?;
        anyhow::ensure!(
            (16..=4096).contains(&at.width) && (16..=4096).contains(&at.height),
            "frame {}×{}: expected 16..4096 px",
            at.width,
            at.height
        );
        anyhow::ensure!(
            at.reach_px.is_finite()
                && at.reach_px >= 0.0
                && at.rotation_deg.is_finite()
                && at.home_px.iter().all(|v| v.is_finite()),
            "reach, rotation and home must be finite (reach ≥ 0)"
        );
        let (sin, cos) = at.rotation_deg.to_radians().sin_cos();
        let mut cam = PhotoCamera {
            name: photo.name.clone(),
            src: photo.grey.iter().map(|&v| f32::from(v)).collect(),
            sw: photo.width,
            sh: photo.height,
            tip,
            mean: photo.grey.iter().map(|&v| f64::from(v)).sum::<f64>()
                / photo.grey.len().max(1) as f64,
            width: at.width,
            height: at.height,
            zoom: 1.0,
            cos,
            sin,
            light,
            lut: (0..=3 * LUT_PER_PX)
                .map(|i| lanczos3(i as f64 / LUT_PER_PX as f64) as f32)
                .collect(),
        };
        let need = cam.zoom_needed(at.home_px, at.reach_px).with_context(|| {
            format!(
                "photo {} ({}×{}, tip at {:.1?})",
                photo.name, photo.width, photo.height, tip
            )
        })?;
        cam.zoom = match at.zoom {
            None => need.max(1.0),
            Some(z) => {
                anyhow::ensure!(
                    z.is_finite() && (1.0..=16.0).contains(&z),
                    "zoom {z}: expected 1..16 (a photo is magnified, never shrunk)"
                );
                anyhow::ensure!(
                    z >= need,
                    "zoom {z}: the photo {}'s edges would show in a {}×{} frame with the tip \
                     ±{:.0} px from {:.0?}; at least {need:.2} is needed (or a smaller frame)",
                    photo.name,
                    at.width,
                    at.height,
                    at.reach_px,
                    at.home_px
                );
                z
            }
        };
        Ok(cam)
    }

    /// The photo coordinates of frame pixel `q` with the tip at `tip_px` in the frame.
    fn to_photo(&self, q: [f64; 2], tip_px: [f64; 2], zoom: f64) -> [f64; 2] {
        let v = [q[0] - tip_px[0], q[1] - tip_px[1]];
        // The photo turned by the rotation in the frame: undo it.
        let u = [
            self.cos * v[0] + self.sin * v[1],
            -self.sin * v[0] + self.cos * v[1],
        ];
        [self.tip[0] + u[0] / zoom, self.tip[1] + u[1] / zoom]
    }

    /// The least magnification that keeps the kernel inside the photo for every frame pixel
    /// while the tip is within `reach` (a square) of `home`. The constraints are linear in the
    /// frame corner and the tip, so their corners decide.
    fn zoom_needed(&self, home: [f64; 2], reach: f64) -> anyhow::Result<f64> {
        let lo = [EDGE_PX, EDGE_PX];
        let hi = [
            self.sw as f64 - 1.0 - EDGE_PX,
            self.sh as f64 - 1.0 - EDGE_PX,
        ];
        anyhow::ensure!(
            (0..2).all(|k| self.tip[k] > lo[k] && self.tip[k] < hi[k]),
            "the tip is at the photo's edge"
        );
        let mut need = 0.0f64;
        let (fw, fh) = (self.width as f64 - 1.0, self.height as f64 - 1.0);
        for q in [[0.0, 0.0], [fw, 0.0], [0.0, fh], [fw, fh]] {
            for d in [[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]] {
                let t = [home[0] + reach * d[0], home[1] + reach * d[1]];
                let u = self.to_photo(q, t, 1.0);
                for k in 0..2 {
                    let off = u[k] - self.tip[k];
                    let room = if off > 0.0 {
                        hi[k] - self.tip[k]
                    } else {
                        self.tip[k] - lo[k]
                    };
                    need = need.max(off.abs() / room);
                }
            }
        }
        Ok(need)
    }

    fn kernel(&self, t: f64) -> f64 {
        let x = t.abs() * LUT_PER_PX as f64;
        let i = x as usize;
        if i >= 3 * LUT_PER_PX {
            return 0.0;
        }
        let f = x - i as f64;
        f64::from(self.lut[i]) * (1.0 - f) + f64::from(self.lut[i + 1]) * f
    }

    /// The photo's grey level at photo coordinates `u` (Lanczos-3, weights normalised); its
    /// mean grey outside the photo.
    fn sample(&self, u: [f64; 2]) -> f64 {
        let (sw, sh) = (self.sw as i64, self.sh as i64);
        if !(u[0] >= -0.5 && u[1] >= -0.5 && u[0] <= sw as f64 - 0.5 && u[1] <= sh as f64 - 0.5) {
            return self.mean;
        }
        let (bx, by) = (u[0].floor() as i64 - 2, u[1].floor() as i64 - 2);
        let mut wx = [0.0; TAPS];
        let mut wy = [0.0; TAPS];
        for i in 0..TAPS {
            wx[i] = self.kernel(u[0] - (bx + i as i64) as f64);
            wy[i] = self.kernel(u[1] - (by + i as i64) as f64);
        }
        let (sx, sy): (f64, f64) = (wx.iter().sum(), wy.iter().sum());
        let inside = bx >= 0 && by >= 0 && bx + TAPS as i64 <= sw && by + TAPS as i64 <= sh;
        let mut acc = 0.0;
        for (j, wj) in wy.iter().enumerate() {
            let y = by + j as i64;
            let row = if inside {
                y as usize
            } else {
                y.clamp(0, sh - 1) as usize
            } * self.sw;
            let mut r = 0.0;
            for (i, wi) in wx.iter().enumerate() {
                let x = (bx + i as i64).clamp(0, sw - 1) as usize;
                r += wi * f64::from(self.src[row + x]);
            }
            acc += wj * r;
        }
        acc / (sx * sy)
    }

    /// The photo moved so that its tip is at `tip_px` in the frame: no lighting, noise or
    /// compression (row by row, grey levels).
    pub fn clean(&self, tip_px: [f64; 2]) -> Vec<f64> {
        let mut out = Vec::with_capacity(self.width * self.height);
        for y in 0..self.height {
            for x in 0..self.width {
                out.push(self.sample(self.to_photo([x as f64, y as f64], tip_px, self.zoom)));
            }
        }
        out
    }

    /// The lighting, this frame's flicker and noise, rounded to grey levels.
    fn expose(&self, clean: &[f64], rng: &mut fastrand::Rng) -> Vec<u8> {
        let l = &self.light;
        let gain = l.gain * (1.0 + l.flicker * normal(rng));
        let offset = l.offset + l.flicker_offset * normal(rng);
        let (w, h) = (self.width as f64, self.height as f64);
        clean
            .iter()
            .enumerate()
            .map(|(k, &v)| {
                let (x, y) = ((k % self.width) as f64, (k / self.width) as f64);
                let lit =
                    1.0 + 2.0 * l.gradient[0] * (x / w - 0.5) + 2.0 * l.gradient[1] * (y / h - 0.5);
                let g = v * gain * lit + offset + l.noise_sd * normal(rng);
                g.round().clamp(0.0, 255.0) as u8
            })
            .collect()
    }

    /// One frame with the tip at `tip_px`, as the camera serves it: the grey pixels the JPEG
    /// decodes to, and the JPEG.
    ///
    /// # Errors
    /// The JPEG step failed.
    pub fn frame(
        &self,
        tip_px: [f64; 2],
        rng: &mut fastrand::Rng,
    ) -> anyhow::Result<(Vec<u8>, Vec<u8>)> {
        let raw = self.expose(&self.clean(tip_px), rng);
        self.compress(&raw)
    }

    /// A dropped frame: the photo's mean grey, lit and noisy, nothing in view.
    ///
    /// # Errors
    /// The JPEG step failed.
    pub fn blank(&self, rng: &mut fastrand::Rng) -> anyhow::Result<(Vec<u8>, Vec<u8>)> {
        let flat = vec![self.mean; self.width * self.height];
        let raw = self.expose(&flat, rng);
        self.compress(&raw)
    }

    fn compress(&self, raw: &[u8]) -> anyhow::Result<(Vec<u8>, Vec<u8>)> {
        let jpeg = encode_jpeg(raw, self.width, self.height, self.light.quality)?;
        let (_, _, grey) = decode_gray(&jpeg)?;
        Ok((grey, jpeg))
    }
}

/// Normalised correlation of a clean picture (as [`PhotoCamera::clean`] makes it) and a
/// decoded snapshot of the same size: 1 for the same picture, about 0 for unrelated ones.
#[must_use]
pub fn ncc(a: &[f64], b: &[u8]) -> f64 {
    let n = a.len() as f64;
    let ma = a.iter().sum::<f64>() / n;
    let mb = b.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, &y) in a.iter().zip(b) {
        let (x, y) = (x - ma, f64::from(y) - mb);
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    ab / (aa * bb).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::nozzle::{Gray, Reference, RegisterParams};

    fn placement(w: usize, h: usize, rot: f64, reach: f64) -> Placement {
        Placement {
            width: w,
            height: h,
            rotation_deg: rot,
            home_px: [w as f64 / 2.0, h as f64 / 2.0],
            reach_px: reach,
            zoom: None,
        }
    }

    /// At zoom 1 and no rotation, a whole-pixel move is the photo itself, pixel for pixel; a
    /// half-pixel move lies between its neighbours (no nearest pixel).
    #[test]
    fn whole_pixel_moves_copy_the_photo_and_half_pixels_interpolate() {
        let p = photo(&crate::nozzle_photos::checkout, "tamv-nozzle").unwrap();
        let mut at = placement(320, 240, 0.0, 10.0);
        at.zoom = Some(1.0);
        let cam =
            PhotoCamera::new(&p, &at, Lighting::draw(&mut fastrand::Rng::with_seed(1))).unwrap();
        let tip = p.tip_px.unwrap();
        // The tip at (160 + f, 120): frame pixel (x, y) shows photo (x − 160 + tip.x, …).
        let t = [160.0 + tip[0].fract(), 120.0 + tip[1].fract()];
        let c = cam.clean(t);
        let (dx, dy) = (tip[0].floor() as usize - 160, tip[1].floor() as usize - 120);
        for (x, y) in [(10, 10), (160, 120), (300, 200)] {
            let want = f64::from(p.grey[(y + dy) * p.width + x + dx]);
            assert!(
                (c[y * 320 + x] - want).abs() < 0.02,
                "({x}, {y}): {} vs {want}",
                c[y * 320 + x]
            );
        }
        let h = cam.clean([t[0] + 0.5, t[1]]);
        let mut between = 0;
        for x in 20..300 {
            let (a, b) = (c[120 * 320 + x - 1], c[120 * 320 + x]);
            let v = h[120 * 320 + x];
            between +=
                usize::from(v >= a.min(b) - 3.0 && v <= a.max(b) + 3.0 && (a - b).abs() > 8.0);
        }
        assert!(between > 20, "{between}");
    }

    /// The auto zoom keeps the edges out: with the tip anywhere in the reach, turned, no frame
    /// pixel samples outside the photo; a zoom below it is refused with the zoom needed.
    #[test]
    fn edges_never_show_within_the_reach_and_a_short_zoom_is_refused() {
        for name in ["tamv-nozzle", "ktamv-frame"] {
            let p = photo(&crate::nozzle_photos::checkout, name).unwrap();
            let at = placement(320, 240, 12.0, 40.0);
            let cam = PhotoCamera::new(&p, &at, Lighting::draw(&mut fastrand::Rng::with_seed(2)))
                .unwrap();
            assert!(cam.zoom >= 1.0);
            for d in [[-40.0, -40.0], [40.0, -40.0], [-40.0, 40.0], [40.0, 40.0]] {
                let t = [160.0 + d[0], 120.0 + d[1]];
                for q in [[0.0, 0.0], [319.0, 0.0], [0.0, 239.0], [319.0, 239.0]] {
                    let u = cam.to_photo(q, t, cam.zoom);
                    assert!(
                        u[0] >= 2.0
                            && u[1] >= 2.0
                            && u[0] <= p.width as f64 - 4.0
                            && u[1] <= p.height as f64 - 4.0,
                        "{name}: {q:?} with the tip at {t:?} samples {u:?} of {}×{}",
                        p.width,
                        p.height
                    );
                }
            }
            let mut short = at;
            short.zoom = Some((cam.zoom * 0.9).max(1.0));
            if cam.zoom > 1.05 {
                let e = PhotoCamera::new(&p, &short, cam.light).unwrap_err();
                assert!(format!("{e:#}").contains("is needed"), "{e:#}");
            }
        }
        let e = photo(&crate::nozzle_photos::checkout, "tamv-test-card").unwrap_err();
        assert!(format!("{e:#}").contains("hand-labelled"), "{e:#}");
        let e = photo(&crate::nozzle_photos::checkout, "nozzle.png").unwrap_err();
        assert!(format!("{e:#}").contains("ktamv-frame"), "{e:#}");
        assert_eq!(
            photo(&crate::nozzle_photos::checkout, "tamv-nozzle.jpg")
                .unwrap()
                .name,
            "tamv-nozzle"
        );
        assert_eq!(
            photo(&crate::nozzle_photos::checkout, "ktamv-double_camera.jpg")
                .unwrap()
                .name,
            "ktamv-frame"
        );
    }

    /// The tip lands where it is put: frames with the tip at known sub-pixel positions, turned
    /// and magnified, lit, noisy and JPEG-compressed, registered against the first, give the
    /// known moves back.
    #[test]
    fn registered_frames_give_the_known_moves_back() {
        let p = RegisterParams::default();
        let mut rng = fastrand::Rng::with_seed(9);
        for name in ["tamv-nozzle", "ktamv-frame"] {
            let ph = photo(&crate::nozzle_photos::checkout, name).unwrap();
            let cam = PhotoCamera::new(
                &ph,
                &placement(320, 240, -8.0, 30.0),
                Lighting::draw(&mut rng),
            )
            .unwrap();
            let home = [160.0, 120.0];
            let (g0, _) = cam.frame(home, &mut rng).unwrap();
            let r = Reference::new(
                &Gray {
                    width: 320,
                    height: 240,
                    data: &g0,
                },
                home,
                1.0,
                &p,
            )
            .unwrap();
            let mut worst = 0.0f64;
            for _ in 0..8 {
                let d = [50.0 * rng.f64() - 25.0, 50.0 * rng.f64() - 25.0];
                let t = [home[0] + d[0], home[1] + d[1]];
                let (g, jpeg) = cam.frame(t, &mut rng).unwrap();
                assert!(jpeg.starts_with(&[0xFF, 0xD8]));
                let f = r
                    .refine(
                        &Gray {
                            width: 320,
                            height: 240,
                            data: &g,
                        },
                        [t[0] + 0.7, t[1] - 0.6],
                        1.0,
                        &p,
                    )
                    .unwrap();
                worst = worst.max((f.at_px[0] - t[0]).hypot(f.at_px[1] - t[1]));
            }
            eprintln!("{name}: zoom {:.2}, worst {worst:.3} px", cam.zoom);
            assert!(worst < 0.15, "{name}: worst {worst:.3} px");
        }
    }
}
