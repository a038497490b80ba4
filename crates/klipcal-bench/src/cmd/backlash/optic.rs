//! The second camera's photographs ([`crate::cmd::optic_render`]: a shaded hex or cone nozzle
//! under a ring light, through a distorting lens onto a Bayer sensor, colour JPEG) through the
//! detector, for `klipcal bench backlash`; and the one figure both renderers report (issue 37:
//! found within 0.5 px on ≥ 95 % of the pictures that show a nozzle, 0 wrong).

use crate::calib::nozzle::{self, DetectParams, Gray};
use crate::cmd::optic_render::{self, Kind};
use crate::cmd::par::par_map;

/// The photographs' size, as the first renderer's bench.
const W: usize = 640;
const H: usize = 480;
/// A found tip off by more than this is a wrong number.
const WRONG_PX: f64 = 1.0;

/// One family's outcome: errors of the found (px), the refusals' reasons, wrong answers.
#[derive(Debug, Default)]
struct Tally {
    errors_px: Vec<f64>,
    reasons: std::collections::BTreeMap<String, usize>,
    wrong: usize,
    n: usize,
}

/// What one photograph gave: the error when found (px), else the refusal's reason.
fn one(kind: Kind, seed: u64) -> anyhow::Result<Result<f64, String>> {
    let mut rng = fastrand::Rng::with_seed(seed);
    let ro = 4.0 + 10.0 * rng.f64();
    let shot = optic_render::varied(kind, W, H, ro, 150.0, &mut rng);
    let (grey, _) = shot.photograph(&mut rng)?;
    let img = Gray {
        width: W,
        height: H,
        data: &grey,
    };
    Ok(match nozzle::detect(&img, &DetectParams::default()) {
        Ok(d) => {
            let t = shot.tips_px().first().copied().unwrap_or([f64::NAN; 2]);
            Ok((d.centre_px[0] - t[0]).hypot(d.centre_px[1] - t[1]))
        }
        Err(r) => Err(super::camera::refusal_name(&r)),
    })
}

/// The summary line of one renderer; whether it meets the target.
fn renderer_line(name: &str, near: usize, shown: usize, wrong: usize) -> bool {
    let pct = 100.0 * near as f64 / shown.max(1) as f64;
    let good = pct >= 95.0 && wrong == 0;
    println!(
        "    {name}: found within 0.5 px {near}/{shown} = {pct:.1} % of the pictures with a nozzle \
         (target ≥ 95 %)   wrong (found off by > {WRONG_PX} px, or found where it must refuse) \
         {wrong} (target 0)   {}",
        if good { "PASS" } else { "FAIL" }
    );
    good
}

/// Both renderers' figure (`n` pictures per family each), the second's per family; whether
/// every target is met. The first renderer's families are the ones `camera`'s lines detail
/// (the same seed: the same pictures).
pub(super) fn bench_renderers(n: usize, seed: u64) -> anyhow::Result<bool> {
    println!(
        "  rendered nozzles, per renderer (issue 37: found within 0.5 px on ≥ 95 % of the \
         pictures with a nozzle, 0 wrong)"
    );
    let (mut near, mut shown, mut wrong) = (0, 0, 0);
    for (fam, t) in super::camera::bench_detection(n, seed)? {
        wrong += t.wrong;
        if !fam.must_refuse() {
            near += t.errors_px.iter().filter(|e| **e <= 0.5).count();
            shown += t.n;
        }
    }
    let first = renderer_line(
        "renderer 1 (camera_render: flat discs, grey, JPEG; its families below)",
        near,
        shown,
        wrong,
    );
    Ok(bench_optic(n, seed)? && first)
}

/// `n` photographs per family from the second camera through the detector; whether every
/// target is met.
fn bench_optic(n: usize, seed: u64) -> anyhow::Result<bool> {
    println!(
        "  second camera (optic_render, written apart from camera_render and the detector): {n} \
         {W}×{H} photographs per family: shaded brass hex and steel cone nozzles (orifice r 4–14 \
         px, flat tip, chamfer, cone, turning marks, ooze), a white or coloured ring light with \
         highlights and a side lamp, a sparkling bed, radial distortion ±0.12, vignetting, \
         pillbox defocus 0–2.5 px, RGGB Bayer sensor with shot and read noise, colour JPEG q \
         60–95"
    );
    let jobs: Vec<(Kind, u64)> = Kind::ALL
        .iter()
        .flat_map(|k| (0..n as u64).map(move |i| (*k, seed ^ 0x0071c ^ (i << 8) ^ *k as u64)))
        .collect();
    let results = par_map(&jobs, |(k, s)| one(*k, *s));
    let mut tallies: Vec<(Kind, Tally)> =
        Kind::ALL.iter().map(|k| (*k, Tally::default())).collect();
    for ((kind, _), r) in jobs.iter().zip(results) {
        let t = &mut tallies
            .iter_mut()
            .find(|t| t.0 == *kind)
            .expect("every kind")
            .1;
        t.n += 1;
        match r? {
            Ok(_) if kind.must_refuse() => t.wrong += 1,
            Ok(e) => {
                t.wrong += usize::from(e.is_nan() || e > WRONG_PX);
                t.errors_px.push(e);
            }
            Err(reason) => *t.reasons.entry(reason).or_default() += 1,
        }
    }
    let (mut near, mut shown, mut wrong) = (0, 0, 0);
    for (kind, t) in &tallies {
        wrong += t.wrong;
        let refused: usize = t.reasons.values().sum();
        if kind.must_refuse() {
            println!(
                "    {:<30} refused {refused:3}/{:<3} wrong {} (target 0)   reasons {:?}",
                kind.name(),
                t.n,
                t.wrong,
                t.reasons
            );
        } else {
            let within = t.errors_px.iter().filter(|e| **e <= 0.5).count();
            let mut e = t.errors_px.clone();
            e.sort_by(f64::total_cmp);
            let p95 = e
                .get((e.len() * 95).div_ceil(100).saturating_sub(1))
                .copied();
            println!(
                "    {:<30} found within 0.5 px {within}/{}   p95 error {:.3} px   refused \
                 {refused} {:?}   wrong {} (target 0)",
                kind.name(),
                t.n,
                p95.unwrap_or(f64::NAN),
                t.reasons,
                t.wrong
            );
            near += within;
            shown += t.n;
        }
    }
    Ok(renderer_line(
        "renderer 2 (optic_render)",
        near,
        shown,
        wrong,
    ))
}
