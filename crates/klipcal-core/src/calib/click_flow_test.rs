//! Issue 37, item 6 (a tap is only a hint): the click flow's readings through the daemon's
//! statistics, on the case. In real Mainsail at phone size the taps landed 2.4–4.2 px
//! from the nozzle while stating a click precision of 1.9–2.2 px; clicks 2–6 were kept as
//! clicked, Y read 0.0612 ± 0.0046 mm for 0.050 mm of play on both axes, and the answer said
//! "X and Y differ… part of the play is not in the motors and belts".
//!
//! Each measurement runs the daemon's steps (`jobs::backlash::camera`): X and Y at −0.5, 0,
//! +0.5 mm approached moving + (the scale), then 5 cycles along the axis, each reading a tap on
//! a rendered snapshot read by a fresh [`ClickReader`]; the scale by
//! [`CameraScale::from_sightings`], the cycles by [`camera_scale::approaches`], the statistics
//! by [`camera_scale::camera_params`] and [`backlash::analyse`] as `CameraReport::params` sets
//! them, and the CoreXY answer by [`backlash::corexy_xy_answer`].

use std::collections::BTreeMap;

use super::backlash::{self, AxisResult, BacklashParams, Cycle};
use super::backlash_guide::GuideAxis;
use super::camera_scale::{self, CameraScale, Sighting};
use super::nozzle::{ClickReader, ClickReading, Gray};
use crate::camera_render::{varied_scene, Family, Scene};

const W: usize = 320;
const H: usize = 240;
/// The camera: px per mm, its turn, and where the camera point is in the picture.
const PX_PER_MM: f64 = 80.0;
const TURN_DEG: f64 = 3.0;
const ORIGIN_PX: [f64; 2] = [160.0, 120.0];
/// The play on both axes, mm.
const PLAY_MM: f64 = 0.050;

/// A snapshot of the nozzle at machine offset `mm` from the camera point.
fn to_px(mm: [f64; 2]) -> [f64; 2] {
    let (s, c) = TURN_DEG.to_radians().sin_cos();
    [
        ORIGIN_PX[0] + PX_PER_MM * (c * mm[0] - s * mm[1]),
        ORIGIN_PX[1] + PX_PER_MM * (s * mm[0] + c * mm[1]),
    ]
}

/// How a reading is taken: the tap read by registration on a rendered snapshot, or the tap
/// kept as clicked with its stated ± (what the reader gives when the first tap cannot be a
/// reference).
#[derive(Clone, Copy, PartialEq)]
enum Read {
    Registered,
    KeptAsClicked,
}

/// One person's tap: 2.4–4.2 px from the nozzle in any direction, stating 1.9–2.2 px.
fn tap(truth: [f64; 2], rng: &mut fastrand::Rng) -> ([f64; 2], f64) {
    let r = 2.4 + 1.8 * rng.f64();
    let a = std::f64::consts::TAU * rng.f64();
    (
        [truth[0] + r * a.cos(), truth[1] + r * a.sin()],
        1.9 + 0.3 * rng.f64(),
    )
}

struct Flow {
    scene: Scene,
    read: Read,
    reader: ClickReader,
    rng: fastrand::Rng,
    refined: usize,
}

impl Flow {
    fn reading(&mut self, mm: [f64; 2]) -> ClickReading {
        let truth = to_px(mm);
        let (at, sd) = tap(truth, &mut self.rng);
        if self.read == Read::KeptAsClicked {
            return ClickReading {
                at_px: at,
                sd_px: sd,
                refined: false,
                kept: None,
            };
        }
        let mut s = self.scene.clone();
        s.nozzles_px = vec![truth];
        let (g, _) = s.render(&mut self.rng).expect("rendered");
        let img = Gray {
            width: W,
            height: H,
            data: &g,
        };
        let r = self.reader.read(&img, at, sd);
        self.refined += usize::from(r.refined);
        r
    }

    /// One measurement along `axis` (X or Y), `cycles` cycles: its result.
    fn measure(&mut self, axis: GuideAxis, cycles: usize) -> AxisResult {
        // Where the play leaves the nozzle: a move + stops b/2 short, a move − b/2 past.
        let lag = |moving_plus: bool| {
            if moving_plus {
                -PLAY_MM / 2.0
            } else {
                PLAY_MM / 2.0
            }
        };
        let mut sightings: [Vec<Sighting>; 2] = [Vec::new(), Vec::new()];
        // The other axis stays where its last move left it.
        let mut other = [lag(false), lag(false)];
        for k in 0..2 {
            for t in [-0.5, 0.0, 0.5] {
                let mut mm = other;
                mm[k] = t + lag(true);
                let r = self.reading(mm);
                sightings[k].push(Sighting {
                    commanded_mm: t,
                    centre_px: r.at_px,
                    uncertainty_px: r.sd_px.max(0.01),
                });
            }
            // Back to the point, moving −.
            other[k] = lag(false);
        }
        let scale = CameraScale::from_sightings(&sightings[0], &sightings[1]).expect("a scale");
        let reference = sightings[0][1].centre_px;
        let k = usize::from(axis == GuideAxis::Y);
        let (mut got, mut sd_px) = (Vec::<Cycle>::new(), 0f64);
        for _ in 0..cycles {
            let mut plus = other;
            plus[k] = lag(true);
            let p = self.reading(plus);
            let mut minus = other;
            minus[k] = lag(false);
            let m = self.reading(minus);
            sd_px = sd_px.max(p.sd_px).max(m.sd_px);
            got.push(camera_scale::approaches(&scale, axis, p.at_px, m.at_px, reference).cycle);
        }
        let along = scale.px_per_mm_along(axis);
        let params = camera_scale::camera_params(
            &BacklashParams::default(),
            sd_px,
            along,
            scale.rel_sd() * along,
            self.refined > 0,
        );
        backlash::analyse("axis", &got, None, &params).expect("a result")
    }
}

/// X and Y of one printer measured by taps, each measurement with its own reader.
fn printer(read: Read, seed: u64) -> (BTreeMap<String, AxisResult>, usize) {
    let mut rng = fastrand::Rng::with_seed(seed);
    let scene = varied_scene(
        Family::Ring,
        W,
        H,
        ORIGIN_PX,
        12.0 + 6.0 * rng.f64(),
        &mut rng,
    );
    let mut out = BTreeMap::new();
    let mut refined = 0;
    for (name, axis) in [("x", GuideAxis::X), ("y", GuideAxis::Y)] {
        let mut f = Flow {
            scene: scene.clone(),
            read,
            reader: ClickReader::default(),
            rng: fastrand::Rng::with_seed(rng.u64(..)),
            refined: 0,
        };
        out.insert(name.to_string(), f.measure(axis, 5));
        refined += f.refined;
    }
    (out, refined)
}

/// The taps on rendered snapshots: the registration takes over from every tap after
/// the first (15 of the 16 readings of each measurement refined), each axis reads the play
/// within a few µm, and X and Y are never called different.
#[test]
fn taps_a_few_pixels_off_are_refined_and_x_and_y_agree() {
    for seed in 0..4 {
        let (r, refined) = printer(Read::Registered, 370 + seed);
        assert_eq!(
            refined, 30,
            "seed {seed}: {refined} of 30 later taps refined"
        );
        for (k, v) in &r {
            let e = v.backlash_mm - PLAY_MM;
            assert!(e.abs() < 0.003, "seed {seed} {k}: {v:?}");
        }
        let t = backlash::corexy_xy_answer(&r).expect("an answer");
        assert!(t.contains("X and Y agree"), "seed {seed}: {t}");
    }
}

/// The same taps kept as clicked (the first tap could not be a reference, so none is
/// refined), each with its stated ± of about 2 px: the cycles' own scatter carries the taps'
/// real spread into the ±, so the truth stays within ±2u of nearly every axis and "X and Y
/// differ" (beyond 3 combined sd) is not said of equal axes. Over 100 printers (2026-12-02:
/// ±2u covered 195 of 200 axes, "differ" 0 of 100, at 2 sd also 0).
#[test]
fn taps_kept_as_clicked_carry_their_real_spread_and_do_not_make_x_and_y_differ() {
    let (mut differ, mut differ_2sd, mut covered, mut axes) = (0, 0, 0, 0);
    for seed in 0..100 {
        let (r, _) = printer(Read::KeptAsClicked, 3700 + seed);
        for v in r.values() {
            axes += 1;
            covered += usize::from((v.backlash_mm - PLAY_MM).abs() <= 2.0 * v.uncertainty_mm);
        }
        let t = backlash::corexy_xy_answer(&r).expect("an answer");
        differ += usize::from(t.contains("X and Y differ"));
        let (x, y) = (&r["x"], &r["y"]);
        differ_2sd += usize::from(
            (x.backlash_mm - y.backlash_mm).abs() > 2.0 * x.uncertainty_mm.hypot(y.uncertainty_mm),
        );
    }
    eprintln!("differ {differ}/100 (at 2 sd: {differ_2sd}), ±2u covers {covered}/{axes}");
    assert!(
        covered * 100 >= 90 * axes,
        "±2u covered {covered} of {axes}"
    );
    assert!(
        differ <= 1,
        "{differ} of 100 equal printers called different"
    );
}
