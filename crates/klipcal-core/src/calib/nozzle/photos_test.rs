//! The detector and the registration on real photographs (issue 37, `tests/fixtures/nozzle`:
//! TAMV's, kTAMV's and Axiscope's published nozzle pictures, with the pictures a person must refuse).

use super::*;
use crate::nozzle_photos::{known_shifts, load, Expect, Photo};

/// One picture's outcome against its hand label: Ok(distance px) when found.
fn outcome(p: &Photo) -> Result<f64, Refusal> {
    detect(&p.gray(), &DetectParams::default()).map(|d| {
        let t = p.tip_px.unwrap_or([f64::NAN; 2]);
        (d.centre_px[0] - t[0]).hypot(d.centre_px[1] - t[1])
    })
}

/// Real nozzles are found where a person puts the tip (within max(3 px, the label's sd)): 5 of
/// the 6 unambiguous pictures (issue 37's target is 80 %, `klipcal bench backlash` reports it;
/// kTAMV's settings frame, whose orifice is closed on 17 % of its round, is refused; the
/// closest TAMV window is found since the vote retries at twice its scale), no position
/// more than 10 px off is ever given, and every picture a person must refuse (no nozzle, a
/// test card, two nozzles, a tiny faint tip among sparkles) is refused with a reason. With
/// the noise taken from the smooth background's residual (the estimator before issue 37)
/// every real nozzle was refused.
#[test]
fn real_photos_are_found_or_refused_as_a_person_would() {
    let photos = load(&crate::nozzle_photos::checkout).unwrap();
    let (mut want, mut near, mut fails) = (0, 0, Vec::new());
    for p in &photos {
        let got = outcome(p);
        eprintln!("{:22} {:?}: {got:?}", p.name, p.expect);
        match (p.expect, &got) {
            (Expect::Found, _) => {
                want += 1;
                near += usize::from(got.as_ref().is_ok_and(|d| *d <= p.tip_sd_px.max(3.0)));
            }
            (Expect::Refused, Ok(_)) => fails.push(format!("{}: found, must refuse", p.name)),
            _ => {}
        }
        if let Ok(d) = got {
            if p.expect != Expect::Refused && d > 10.0 {
                fails.push(format!("{}: found {d:.1} px off", p.name));
            }
        }
        if let Err(r) = &got {
            assert!(
                r.to_string().contains(';') || r.to_string().contains('—'),
                "{r}"
            );
        }
    }
    assert!(want >= 5 && photos.len() >= 10, "{} pictures", photos.len());
    if near < 5 {
        fails.push(format!("found near the label on {near} of {want}"));
    }
    assert!(fails.is_empty(), "{fails:?}");
}

/// The pixel noise of a real, zoomed-in nozzle photo is a few grey levels, not the scene:
/// TAMV's picture reads under 2 (its smooth-background residual is about 60). With the
/// detector's noise taken back from that residual (put back and run, issue 37) this test and
/// the one above failed: every real nozzle refused ("344.2 grey levels, 702.5 needed").
#[test]
fn the_noise_of_a_real_photo_is_its_pixels_not_its_scene() {
    let photos = load(&crate::nozzle_photos::checkout).unwrap();
    let tamv = photos.iter().find(|p| p.name == "tamv-nozzle").unwrap();
    let n = fine_noise_sd(&tamv.gray(), None);
    assert!((0.3..2.0).contains(&n), "{n}");
    let d = detect(&tamv.gray(), &DetectParams::default()).unwrap();
    assert!(d.diagnostics.noise_sd < 2.0, "{:?}", d.diagnostics);
}

/// Known shifts of each real nozzle photo (Lanczos-3 sub-pixel moves up to ±3 px, re-encoded
/// as JPEG 70–90, with noise, a brightness change and a little blur), read by registering the
/// region round the tip against the reference frame; the region comes from the hand label (a
/// click ±0.5 px), so the picture detection refuses (TAMV's closest window, kTAMV's settings
/// frame) is measured too. Issue 37's targets: |found − known| ≤ 0.3 px on ≥ 90 % of the
/// pairs, median ≤ 0.1 px, each coordinate within ±2 × its stated sd on 93–97 % (held here to
/// 90–99 %: 240 coordinates). Before the sub-pixel fit was the squared difference, kTAMV's
/// small defocused frames had 42 % within 0.3 px, median 0.31, an unmoved copy read 0.37 px
/// off (`register`'s step 4). With the reference's noise taken back from the smooth
/// background's residual (the estimator before issue 37, put back and run), every photo's
/// reference was refused ("179 grey levels, 487 needed" on TAMV's) and this test failed.
#[test]
fn known_shifts_of_real_photos_are_measured_by_registration() {
    let photos = load(&crate::nozzle_photos::checkout).unwrap();
    let t = known_shifts(&photos, 20, 37);
    eprintln!(
        "within {:.1} % median {:.3} cover {:.1} % worst {:?} refused {:?}",
        t.within_pct(),
        t.median_px(),
        t.cover_pct(),
        t.worst,
        t.refused
    );
    let n = t.errors_px.len();
    assert!(
        n >= 120 && t.refused.is_empty(),
        "{n} measured, refused {:?}",
        t.refused
    );
    assert!(
        t.within_pct() >= 90.0,
        "{:.1} % within 0.3 px",
        t.within_pct()
    );
    assert!(t.median_px() <= 0.1, "median {:.3}", t.median_px());
    let cov = t.cover_pct();
    assert!((90.0..=99.0).contains(&cov), "±2u covered {cov:.1} %");
    for (name, worst) in &t.worst {
        assert!(*worst <= 0.3, "{name}: worst {worst:.3} px");
    }
}

/// TAMV's photo as a 1920×1080 snapshot (scaled ×3 bilinearly, the middle 1080 rows: the
/// orifice's radius 66 px) is found where the scaling puts the hand label, and as a 320×240
/// one (halved) too: issue 37's item 8, 320×240 to 1920×1080.
#[test]
fn a_real_photo_is_found_from_320x240_to_1920x1080() {
    let photos = load(&crate::nozzle_photos::checkout).unwrap();
    let tamv = photos.iter().find(|p| p.name == "tamv-nozzle").unwrap();
    let (w, h) = (tamv.width, tamv.height);
    let at = |x: f64, y: f64| {
        let (x, y) = (x.clamp(0.0, (w - 1) as f64), y.clamp(0.0, (h - 1) as f64));
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let g = |i: usize, j: usize| f64::from(tamv.grey[j * w + i]);
        (1.0 - fy) * ((1.0 - fx) * g(x0, y0) + fx * g(x1, y0))
            + fy * ((1.0 - fx) * g(x0, y1) + fx * g(x1, y1))
    };
    for (k, ow, oh, top) in [(3.0, 1920, 1080, 180.0), (0.5, 320, 240, 0.0)] {
        let mut g = Vec::with_capacity(ow * oh);
        for j in 0..oh {
            for i in 0..ow {
                let (x, y) = ((i as f64 + 0.5) / k - 0.5, (j as f64 + top + 0.5) / k - 0.5);
                g.push(at(x, y).round() as u8);
            }
        }
        let img = Gray {
            width: ow,
            height: oh,
            data: &g,
        };
        let d = detect(&img, &DetectParams::default())
            .unwrap_or_else(|e| panic!("{ow}×{oh}: refused: {e}"));
        let t = tamv.tip_px.unwrap();
        let want = [(t[0] + 0.5) * k - 0.5, (t[1] + 0.5) * k - 0.5 - top];
        let off = (d.centre_px[0] - want[0]).hypot(d.centre_px[1] - want[1]);
        assert!(
            off <= 3.0f64.max(k * 1.0),
            "{ow}×{oh}: {off:.2} px off, {d:?}"
        );
    }
}

/// Issue 37: TAMV's photo (a bright nozzle on a dark ground) under a dimmer light, as the bench
/// camera draws it (gain 0.85, offset −10, 10 % less light at the far edges), is black over more than 60 % of the view with the
/// nozzle plain; the detector took it for saturated and the camera flow could not start. It is
/// no longer refused as saturated; a picture black all over still is.
#[test]
fn a_bright_nozzle_on_a_dark_ground_is_not_saturated() {
    use crate::photo_camera::{photo, Lighting, PhotoCamera, Placement};
    let ph = photo(&crate::nozzle_photos::checkout, "tamv-nozzle").unwrap();
    let at = Placement {
        width: 400,
        height: 300,
        rotation_deg: 3.0,
        home_px: [200.0, 150.0],
        reach_px: 75.0,
        zoom: None,
    };
    let light = Lighting {
        gain: 0.85,
        offset: -10.0,
        gradient: [-0.1, -0.1],
        flicker: 0.0,
        flicker_offset: 0.0,
        noise_sd: 0.5,
        quality: 85,
    };
    let cam = PhotoCamera::new(&ph, &at, light).unwrap();
    let mut rng = fastrand::Rng::with_seed(37);
    let tip = [203.4, 147.8];
    let g = cam.frame(tip, &mut rng).unwrap().0;
    let black = g.iter().filter(|v| **v <= 5).count() as f64 / g.len() as f64;
    assert!(black > 0.6, "{black}");
    let img = Gray {
        width: 400,
        height: 300,
        data: &g,
    };
    // Where the detector puts it is the camera flow's locator only (on this photo it may pick
    // another round feature of the nozzle, which the registration disregards: camera/meter.rs).
    let got = detect(&img, &DetectParams::default());
    assert!(!matches!(got, Err(Refusal::Saturated { .. })), "{got:?}");
    let dark = vec![2u8; 400 * 300];
    let e = detect(
        &Gray {
            width: 400,
            height: 300,
            data: &dark,
        },
        &DetectParams::default(),
    )
    .unwrap_err();
    assert!(matches!(e, Refusal::Saturated { .. }), "{e}");
}
