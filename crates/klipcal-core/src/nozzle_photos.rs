//! The real nozzle photographs of `tests/fixtures/nozzle` (issue 37), for the tests and
//! `klipcal bench backlash`: each source file as published (its bytes handed in by the caller,
//! who reads them from the source checkout: this crate does no I/O), cropped,
//! doubled or with a faded copy pasted in as `manifest.json` says, with its hand label and
//! the outcome a person expects; and the known shifts made of them, read by registration.

use std::path::{Path, PathBuf};

use anyhow::Context;

/// The bytes of one file of the fixtures' folder ([`dir`]), by its name there: the caller's
/// reader (the bench's and the tests' read the source checkout).
pub type Fixtures<'a> = &'a dyn Fn(&str) -> anyhow::Result<Vec<u8>>;
use serde::Deserialize;

use crate::calib::nozzle::{decode_gray, Gray, Reference, RegisterParams};

/// What a picture must give.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Expect {
    /// A nozzle a person sees at once: found within max(3 px, the label's uncertainty).
    Found,
    /// No nozzle, two, or one too faint to be sure of: refused.
    Refused,
    /// A person cannot be sure: refused, or found within 10 px.
    Either,
}

#[derive(Debug, Deserialize)]
struct Insert {
    from: String,
    shrink: usize,
    contrast: f64,
    at: [usize; 2],
}

#[derive(Debug, Deserialize)]
struct Entry {
    name: String,
    from: String,
    #[serde(default)]
    crop: Option<[usize; 4]>,
    #[serde(default)]
    shrink: Option<usize>,
    #[serde(default)]
    pair: bool,
    #[serde(default)]
    insert: Option<Insert>,
    expect: Expect,
    #[serde(default)]
    tip_px: Option<[f64; 2]>,
    #[serde(default)]
    tip_sd_px: Option<f64>,
    /// What the picture shows, for a person reading the manifest.
    #[allow(dead_code)]
    note: String,
}

#[derive(Debug, Deserialize)]
struct Manifest {
    pictures: Vec<Entry>,
}

/// One picture, decoded to grey.
#[derive(Debug, Clone)]
pub struct Photo {
    pub name: String,
    /// The source file it is made from (`tamv-nozzle.jpg`).
    pub source: String,
    pub width: usize,
    pub height: usize,
    pub grey: Vec<u8>,
    pub expect: Expect,
    /// The hand label of the tip, px, and its 1 sd.
    pub tip_px: Option<[f64; 2]>,
    pub tip_sd_px: f64,
}

impl Photo {
    pub fn gray(&self) -> crate::calib::nozzle::Gray<'_> {
        crate::calib::nozzle::Gray {
            width: self.width,
            height: self.height,
            data: &self.grey,
        }
    }
}

/// The fixtures' folder in the source checkout (where a caller's [`Fixtures`] reads).
#[must_use]
pub fn dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/nozzle")
}

/// The tests' [`Fixtures`]: the source checkout's files.
#[cfg(test)]
#[allow(
    clippy::disallowed_methods,
    reason = "the tests read the checkout's fixtures"
)]
pub(crate) fn checkout(file: &str) -> anyhow::Result<Vec<u8>> {
    Ok(std::fs::read(dir().join(file))?)
}

fn read(files: Fixtures, file: &str) -> anyhow::Result<(usize, usize, Vec<u8>)> {
    let bytes = files(file).with_context(|| format!("reading {file} of {}", dir().display()))?;
    decode_gray(&bytes).with_context(|| format!("decoding {file}"))
}

fn crop(w: usize, h: usize, g: &[u8], c: [usize; 4]) -> anyhow::Result<(usize, usize, Vec<u8>)> {
    let [x, y, cw, ch] = c;
    anyhow::ensure!(x + cw <= w && y + ch <= h, "crop {c:?} outside {w}×{h}");
    let mut out = Vec::with_capacity(cw * ch);
    for j in y..y + ch {
        out.extend_from_slice(&g[j * w + x..j * w + x + cw]);
    }
    Ok((cw, ch, out))
}

/// Every picture of the manifest, in its order.
///
/// # Errors
/// A missing or unreadable file, a malformed manifest, a crop outside its source.
pub fn load(files: Fixtures) -> anyhow::Result<Vec<Photo>> {
    let text = files("manifest.json")
        .with_context(|| format!("reading manifest.json of {}", dir().display()))?;
    let m: Manifest = serde_json::from_slice(&text).context("manifest.json")?;
    m.pictures
        .into_iter()
        .map(|e| {
            let (mut w, mut h, mut g) = read(files, &e.from)?;
            if let Some(c) = e.crop {
                (w, h, g) = crop(w, h, &g, c).with_context(|| e.name.clone())?;
            }
            if let Some(k) = e.shrink {
                (w, h, g) = shrink(w, h, &g, k);
            }
            if e.pair {
                let mut out = Vec::with_capacity(2 * w * h);
                for j in 0..h {
                    out.extend_from_slice(&g[j * w..(j + 1) * w]);
                    out.extend_from_slice(&g[j * w..(j + 1) * w]);
                }
                (w, g) = (2 * w, out);
            }
            if let Some(ins) = &e.insert {
                paste(files, ins, w, h, &mut g).with_context(|| e.name.clone())?;
            }
            Ok(Photo {
                name: e.name,
                source: e.from,
                width: w,
                height: h,
                grey: g,
                expect: e.expect,
                tip_px: e.tip_px,
                tip_sd_px: e.tip_sd_px.unwrap_or(0.0),
            })
        })
        .collect()
}

/// The picture shrunk `k` times by block averaging.
fn shrink(w: usize, h: usize, g: &[u8], k: usize) -> (usize, usize, Vec<u8>) {
    let k = k.max(1);
    let (tw, th) = (w / k, h / k);
    let mut out = Vec::with_capacity(tw * th);
    for j in 0..th {
        for i in 0..tw {
            let mut a = 0u32;
            for y in j * k..(j + 1) * k {
                for x in i * k..(i + 1) * k {
                    a += u32::from(g[y * w + x]);
                }
            }
            out.push(((a as f64) / (k * k) as f64).round() as u8);
        }
    }
    (tw, th, out)
}

/// A copy of another source shrunk by block averaging, its contrast scaled about its mean,
/// pasted at `at` (its deviation from its own mean added to the picture).
fn paste(files: Fixtures, ins: &Insert, w: usize, h: usize, g: &mut [u8]) -> anyhow::Result<()> {
    let (sw, sh, s) = read(files, &ins.from)?;
    let k = ins.shrink.max(1);
    let (tw, th) = (sw / k, sh / k);
    let mut t = vec![0f64; tw * th];
    for (j, row) in t.chunks_mut(tw).enumerate() {
        for (i, v) in row.iter_mut().enumerate() {
            let mut a = 0.0;
            for y in j * k..(j + 1) * k {
                for x in i * k..(i + 1) * k {
                    a += f64::from(s[y * sw + x]);
                }
            }
            *v = a / (k * k) as f64;
        }
    }
    let mean = t.iter().sum::<f64>() / t.len().max(1) as f64;
    let [ax, ay] = ins.at;
    anyhow::ensure!(ax + tw <= w && ay + th <= h, "insert outside the picture");
    for j in 0..th {
        for i in 0..tw {
            let p = &mut g[(ay + j) * w + ax + i];
            let v = f64::from(*p) + ins.contrast * (t[j * tw + i] - mean);
            *p = v.round().clamp(0.0, 255.0) as u8;
        }
    }
    Ok(())
}

// ----- known shifts of the real photos (issue 37) -----

fn lanczos(x: f64) -> f64 {
    if x.abs() < 1e-9 {
        return 1.0;
    }
    if x.abs() >= 3.0 {
        return 0.0;
    }
    let px = std::f64::consts::PI * x;
    3.0 * px.sin() * (px / 3.0).sin() / (px * px)
}

/// The picture moved by `d` px (content at x goes to x + d), Lanczos-3, edges clamped.
fn shifted(p: &Photo, d: [f64; 2]) -> Vec<f64> {
    let (w, h) = (p.width, p.height);
    let taps = |f: f64| -> ([f64; 6], i64) {
        let base = f.floor() as i64 - 2;
        let mut k = [0.0; 6];
        for (i, v) in k.iter_mut().enumerate() {
            *v = lanczos(f - (base + i as i64) as f64);
        }
        let s: f64 = k.iter().sum();
        k.iter_mut().for_each(|v| *v /= s);
        (k, base)
    };
    let (kx, bx) = taps(-d[0]);
    let (ky, by) = taps(-d[1]);
    let at = |x: i64, y: i64| {
        f64::from(p.grey[y.clamp(0, h as i64 - 1) as usize * w + x.clamp(0, w as i64 - 1) as usize])
    };
    let mut out = vec![0.0; w * h];
    for y in 0..h as i64 {
        for x in 0..w as i64 {
            let mut v = 0.0;
            for (j, wy) in ky.iter().enumerate() {
                for (i, wx) in kx.iter().enumerate() {
                    v += wy * wx * at(x + bx + i as i64, y + by + j as i64);
                }
            }
            out[(y as usize) * w + x as usize] = v;
        }
    }
    out
}

fn gray(w: usize, h: usize, g: &[u8]) -> Gray<'_> {
    Gray {
        width: w,
        height: h,
        data: g,
    }
}

fn normal(rng: &mut fastrand::Rng) -> f64 {
    let u = rng.f64().max(1e-12);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.f64()).cos()
}

/// A camera's frame of `px`: a brightness change, a little blur, noise, JPEG at 70–90.
fn frame(px: &[f64], w: usize, h: usize, rng: &mut fastrand::Rng) -> Vec<u8> {
    let gain = 0.9 + 0.2 * rng.f64();
    let offset = 10.0 * rng.f64() - 5.0;
    let a = 0.15 * rng.f64();
    let noise = 0.5 + 2.0 * rng.f64();
    let q = rng.u8(70..=90);
    let mut raw = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let at = |xx: usize, yy: usize| px[yy * w + xx];
            let (xl, xr) = (x.saturating_sub(1), (x + 1).min(w - 1));
            let (yu, yd) = (y.saturating_sub(1), (y + 1).min(h - 1));
            let bx = a * at(xl, y) + (1.0 - 2.0 * a) * at(x, y) + a * at(xr, y);
            let by = a * at(x, yu) + (1.0 - 2.0 * a) * at(x, y) + a * at(x, yd);
            let v = gain * (0.5 * (bx + by)) + offset + noise * normal(rng);
            raw.push(v.round().clamp(0.0, 255.0) as u8);
        }
    }
    let jpeg = crate::camera_render::encode_jpeg(&raw, w, h, q).unwrap();
    decode_gray(&jpeg).unwrap().2
}

/// What the registration made of the known shifts.
#[derive(Debug, Default)]
pub struct ShiftTally {
    /// |found − known|, px, sorted.
    pub errors_px: Vec<f64>,
    /// Coordinates within ±2 × the stated sd, of all coordinates.
    pub covered: usize,
    pub axes: usize,
    /// Pairs the registration refused, with the reason.
    pub refused: Vec<String>,
    /// Each photo's worst error, px.
    pub worst: Vec<(String, f64)>,
}

impl ShiftTally {
    pub fn within_pct(&self) -> f64 {
        let n = self.errors_px.len().max(1) as f64;
        100.0 * self.errors_px.iter().filter(|e| **e <= 0.3).count() as f64 / n
    }

    pub fn median_px(&self) -> f64 {
        self.errors_px
            .get(self.errors_px.len() / 2)
            .copied()
            .unwrap_or(f64::NAN)
    }

    pub fn cover_pct(&self) -> f64 {
        100.0 * self.covered as f64 / self.axes.max(1) as f64
    }
}

/// Known shifts of each unambiguous photo (`per` pairs each: Lanczos-3 sub-pixel moves up to
/// ±3 px, each frame re-encoded as JPEG 70–90 with noise, a brightness change and a little
/// blur), read by registering the region round the hand-labelled tip (a click ±1 px) against
/// the reference frame ([`crate::calib::nozzle::ClickReader`]'s [`Reference`]).
pub fn known_shifts(photos: &[Photo], per: usize, seed: u64) -> ShiftTally {
    let p = RegisterParams::default();
    let mut rng = fastrand::Rng::with_seed(seed);
    let mut t = ShiftTally::default();
    for ph in photos.iter().filter(|q| q.expect == Expect::Found) {
        let Some(tip) = ph.tip_px else { continue };
        let (w, h) = (ph.width, ph.height);
        let g0 = frame(&shifted(ph, [0.0, 0.0]), w, h, &mut rng);
        let r = match Reference::new(&gray(w, h, &g0), tip, 1.0, &p) {
            Ok(r) => r,
            Err(e) => {
                t.refused.push(format!("{}: reference: {e}", ph.name));
                continue;
            }
        };
        t.worst.push((ph.name.clone(), 0.0));
        for _ in 0..per {
            let d = [6.0 * rng.f64() - 3.0, 6.0 * rng.f64() - 3.0];
            let g = frame(&shifted(ph, d), w, h, &mut rng);
            let click = [
                tip[0] + d[0] + rng.f64() - 0.5,
                tip[1] + d[1] + rng.f64() - 0.5,
            ];
            match r.refine(&gray(w, h, &g), click, 1.0, &p) {
                Ok(f) => {
                    let e = [f.at_px[0] - tip[0] - d[0], f.at_px[1] - tip[1] - d[1]];
                    t.errors_px.push(e[0].hypot(e[1]));
                    if let Some(wst) = t.worst.last_mut() {
                        wst.1 = wst.1.max(e[0].hypot(e[1]));
                    }
                    for v in e {
                        t.axes += 1;
                        t.covered += usize::from(v.abs() <= 2.0 * f.sd_px);
                    }
                }
                Err(e) => t.refused.push(format!("{} {d:.2?}: {e}", ph.name)),
            }
        }
    }
    t.errors_px.sort_by(f64::total_cmp);
    t
}
