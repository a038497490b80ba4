//! The detector and the registration on real photographs (issue 37, `tests/fixtures/nozzle`:
//! TAMV's and kTAMV's published nozzle pictures, with the pictures a person must refuse).

use super::*;
use crate::nozzle_photos::{known_shifts, load, Expect, Photo};

/// One picture's outcome against its hand label: Ok(distance px) when found.
fn outcome(p: &Photo) -> Result<f64, Refusal> {
    detect(&p.gray(), &DetectParams::default()).map(|d| {
        let t = p.tip_px.unwrap_or([f64::NAN; 2]);
        (d.centre_px[0] - t[0]).hypot(d.centre_px[1] - t[1])
    })
}

/// Real nozzles are found where a person puts the tip (within max(3 px, the label's sd)): 4 of
/// the 6 unambiguous pictures today (issue 37's target is 80 %, `klipcal bench backlash`
/// reports it; kTAMV's settings frame and the closest TAMV window are refused), no position
/// more than 10 px off is ever given, and every picture a person must refuse (no nozzle, a
/// test card, two nozzles, a tiny faint tip among sparkles) is refused with a reason. With
/// the noise taken from the smooth background's residual (the estimator before issue 37)
/// every real nozzle was refused.
#[test]
fn real_photos_are_found_or_refused_as_a_person_would() {
    let photos = load().unwrap();
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
    if near < 4 {
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
    let photos = load().unwrap();
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
    let photos = load().unwrap();
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
