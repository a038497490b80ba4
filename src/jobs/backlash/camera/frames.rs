//! Reading the nozzle in the camera's frames: a frame fetched and searched, kept for the page;
//! frames taken until the nozzle is still ([`settled`]); a snapshot for the person to click in.

use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::super::snapshot::SnapshotInfo;
use super::super::Backlash;
use super::Webcam;
use crate::calib::nozzle::{
    self, ClickReader, ClickReading, DetectParams, Detection, Gray, Refusal,
};
use crate::jobs::user;

/// Frames that must agree before a reading is taken. Two were not enough: a nozzle ringing
/// after a move can be caught at the same phase twice running (frames about one period apart),
/// and on the bench's CoreXY camera test that read A 2.1 µm high (0.0621 mm against 0.060
/// drawn, every cycle); three frames at different phases must all agree.
const STILL_FRAMES: usize = 3;

/// One frame's finding: the nozzle's centre and its 1 sd, px.
type Frame = ([f64; 2], f64);

/// The reading once the last [`STILL_FRAMES`] frames agree pairwise ([`still`]): the mean of
/// the frames after the oldest of them, and its 1 sd, px.
///
/// The oldest frame of the agreeing window is the one that ended the ringing: it agrees with
/// the others within 3σ of the detection's noise, which lets through a tail of the ringing of
/// about a tenth of a pixel, 1–2 µm. When frames come slowly (a loaded host, a slow camera)
/// the first frame after the settle is the only one taken while the nozzle still rings, and it
/// is in the window with two still ones; at a fixed settle its phase is the same after every
/// move, so its tail went into every reading alike. On the bench's CoreXY camera under load
/// (frames 0.5 s apart, the first one 0.2 s after the move with 1–1.8 µm of ringing left), A
/// read 1.7 µm high, every cycle 1.2–2.4 µm high. The oldest frame shows that the nozzle has
/// stopped; the frames after it are the reading.
fn settled(last: &[Frame]) -> Option<Frame> {
    if last.len() < STILL_FRAMES
        || last
            .iter()
            .enumerate()
            .any(|(i, a)| last[i + 1..].iter().any(|b| !still(a, b)))
    {
        return None;
    }
    let after = &last[last.len() - (STILL_FRAMES - 1)..];
    let n = after.len() as f64;
    let mean = |k: usize| after.iter().map(|f| f.0[k]).sum::<f64>() / n;
    let var: f64 = after.iter().map(|f| f.1.powi(2)).sum();
    Some(([mean(0), mean(1)], var.sqrt() / n))
}

/// Two frames of a still nozzle agree within their uncertainty (3σ of the difference, and at
/// least 0.05 px): the ringing after a move has died out.
fn still(a: &Frame, b: &Frame) -> bool {
    let lim = (3.0 * a.1.hypot(b.1)).max(0.05);
    (a.0[0] - b.0[0]).abs() <= lim && (a.0[1] - b.0[1]).abs() <= lim
}

/// One reading: the mean of the still frames ([`settled`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Seen {
    pub centre_px: [f64; 2],
    pub uncertainty_px: f64,
    /// Frames taken, and refused by detection.
    pub frames: usize,
    pub refused: usize,
    /// A click refined from the pictures ([`crate::calib::nozzle::ClickReader`]).
    #[serde(default)]
    pub refined: bool,
    /// Why a click was kept as it was, if it was.
    #[serde(default)]
    pub kept: Option<String>,
}

/// What a frame gave.
pub(super) enum Look {
    /// The nozzle found, and with a [`Registration`] the frame read against its first frame.
    Found(Detection, Option<ClickReading>),
    /// The detector refused the frame, but the region of the measurement's first frame was
    /// found in it by registration round the last reading (issue 37, item 2): a reading all
    /// the same, and the detector's reason.
    Registered(ClickReading, Refusal),
    Refused(Refusal),
}

/// The measurement's frames read against its first one ([`ClickReader::read_detected`]):
/// the detector finds the nozzle in each frame on its own, with a sub-pixel error that depends
/// on where it falls on the pixel grid; registered against the first frame, the shift between
/// two pictures of the same nozzle is measured to a few hundredths of a pixel. Shared with the
/// blocking task that reads each frame.
pub(super) type Registration = std::sync::Arc<std::sync::Mutex<ClickReader>>;

impl Backlash {
    /// A snapshot for the person to click in (no detection): kept for the page; its number,
    /// size and grey pixels (the click is refined from them).
    pub(in crate::jobs::backlash) async fn snapshot_for_click(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        id: i64,
        what: &str,
    ) -> anyhow::Result<(u64, [usize; 2], Vec<u8>)> {
        let bytes = self.fetch(http, cam).await?;
        let name = cam.name.clone();
        let jpeg = bytes.clone();
        let (w, h, grey) = tokio::task::spawn_blocking(move || {
            crate::calib::nozzle::decode_gray(&bytes)
                .map_err(|e| user(format!("webcam '{name}': {e:#}")))
        })
        .await??;
        let seq = self.frames.keep(
            id,
            jpeg,
            SnapshotInfo {
                seq: 0,
                width: w,
                height: h,
                what: what.to_string(),
                centre_px: None,
                radius_px: None,
                uncertainty_px: None,
                refused: None,
                click: false,
                hint_px: None,
                zoom: None,
            },
        );
        Ok((seq, [w, h], grey))
    }

    /// One frame, fetched and searched; kept for the page as `keep` = (session, what) says.
    pub(super) async fn look(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        keep: Option<(i64, &str)>,
        reg: Option<&Registration>,
    ) -> anyhow::Result<Look> {
        let reg = reg.cloned();
        let bytes = self.fetch(http, cam).await?;
        let name = cam.name.clone();
        let jpeg = bytes.clone();
        let (w, h, look) = tokio::task::spawn_blocking(move || {
            let (w, h, grey) = crate::calib::nozzle::decode_gray(&bytes)
                .map_err(|e| user(format!("webcam '{name}': {e:#}")))?;
            let found = nozzle::detect(
                &Gray {
                    width: w,
                    height: h,
                    data: &grey,
                },
                &DetectParams::default(),
            );
            anyhow::Ok((
                w,
                h,
                match found {
                    Ok(d) => {
                        let r = reg.map(|reg| {
                            reg.lock()
                                .unwrap_or_else(std::sync::PoisonError::into_inner)
                                .read_detected(
                                    &Gray {
                                        width: w,
                                        height: h,
                                        data: &grey,
                                    },
                                    d.centre_px,
                                    d.uncertainty_px,
                                )
                        });
                        Look::Found(d, r)
                    }
                    Err(refusal) => {
                        let got = reg.and_then(|reg| {
                            reg.lock()
                                .unwrap_or_else(std::sync::PoisonError::into_inner)
                                .read_undetected(&Gray {
                                    width: w,
                                    height: h,
                                    data: &grey,
                                })
                        });
                        match got {
                            Some(Ok(r)) => Look::Registered(r, refusal),
                            _ => Look::Refused(refusal),
                        }
                    }
                },
            ))
        })
        .await??;
        if let Some((session, what)) = keep {
            let (found, refused) = match &look {
                Look::Found(d, _) => (Some(d), None),
                Look::Registered(_, r) | Look::Refused(r) => (None, Some(r.to_string())),
            };
            let registered = match &look {
                Look::Registered(r, _) => Some(r),
                _ => None,
            };
            self.frames.keep(
                session,
                jpeg,
                SnapshotInfo {
                    seq: 0,
                    width: w,
                    height: h,
                    what: what.to_string(),
                    centre_px: found.map(|d| d.centre_px).or(registered.map(|r| r.at_px)),
                    radius_px: found.map(|d| d.diagnostics.radius_px),
                    uncertainty_px: found
                        .map(|d| d.uncertainty_px)
                        .or(registered.map(|r| r.sd_px)),
                    refused: refused.map(|r| {
                        if registered.is_some() {
                            format!("{r} (read by registration against the first frame)")
                        } else {
                            r
                        }
                    }),
                    click: false,
                    hint_px: None,
                    zoom: None,
                },
            );
        }
        Ok(look)
    }

    /// The nozzle once it is still: waits out the move, then frames until three agree
    /// ([`settled`]); a refused frame is taken again (five in a row: the reason). Each frame is
    /// read against the measurement's first through `reg`; one the registration refuses is
    /// kept as detected, and said so; one the detector refuses is measured by registration
    /// alone when the first frame's region is found in it round the last reading (issue 37).
    pub(super) async fn sight(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        id: i64,
        what: &str,
        reg: &Registration,
    ) -> anyhow::Result<Seen> {
        self.settle_after_move(0.0).await?;
        let (mut frames, mut refused, mut in_a_row) = (0, 0, 0);
        let mut last: Vec<Frame> = Vec::new();
        let mut kept: Vec<Option<String>> = Vec::new();
        while frames < 14 {
            frames += 1;
            let look = self.look(http, cam, Some((id, what)), Some(reg)).await?;
            // A frame the detector refused but registration read counts as refused by
            // detection, and is a reading.
            refused += usize::from(matches!(look, Look::Registered(..)));
            let seen = match look {
                Look::Found(d, r) => Ok(r.map_or((d.centre_px, d.uncertainty_px, None), |r| {
                    (r.at_px, r.sd_px, r.kept.map(|k| k.to_string()))
                })),
                Look::Registered(r, _) => Ok((r.at_px, r.sd_px, None)),
                Look::Refused(r) => Err(r),
            };
            match seen {
                Ok((at, sd, why)) => {
                    in_a_row = 0;
                    last.push((at, sd));
                    kept.push(why);
                    if kept.len() > STILL_FRAMES {
                        kept.remove(0);
                    }
                    if last.len() > STILL_FRAMES {
                        last.remove(0);
                    }
                    if let Some((centre_px, uncertainty_px)) = settled(&last) {
                        // The frames read: registered, or one kept as detected (the reason).
                        let read = &kept[kept.len() - (STILL_FRAMES - 1)..];
                        let why = read.iter().flatten().next().cloned();
                        return Ok(Seen {
                            centre_px,
                            uncertainty_px,
                            frames,
                            refused,
                            refined: why.is_none(),
                            kept: why,
                        });
                    }
                }
                Err(r) => {
                    refused += 1;
                    in_a_row += 1;
                    if in_a_row >= 5 {
                        return Err(user(format!(
                            "webcam '{}': five frames in a row without a sure nozzle: {r}",
                            cam.name
                        )));
                    }
                }
            }
        }
        Err(user(format!(
            "webcam '{}': the nozzle did not keep still over {frames} frames; check that the \
             camera is mounted firmly, or raise [backlash] camera_settle_s",
            cam.name
        )))
    }

    /// Waits until Klipper has finished the moves (M400), then `camera_settle_s` (at least
    /// `min_s`) for the nozzle to stop ringing: before a detected reading and before a
    /// snapshot to click in.
    pub(in crate::jobs::backlash) async fn settle_after_move(
        &self,
        min_s: f64,
    ) -> anyhow::Result<()> {
        self.core.m().gcode("M400").await?;
        let settle = self.settings.camera_settle_s.max(min_s).clamp(0.0, 10.0);
        tokio::time::sleep(Duration::from_secs_f64(settle)).await;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The reading [`Backlash::sight`] takes from frames of a nozzle ringing after a move
    /// (`ring_px` at the move, decaying in 0.12 s, 15 Hz, as the bench camera draws it), the
    /// first frame `settle_s` after the move and then one every `every_s`; detection sd
    /// 0.03 px, no noise drawn (the frames are the ringing alone).
    fn reading_of_ringing(ring_px: f64, settle_s: f64, every_s: f64) -> [f64; 2] {
        let mut last: Vec<Frame> = Vec::new();
        for k in 0..14 {
            let t = settle_s + every_s * f64::from(k);
            let a = ring_px * (-t / 0.12).exp() * (std::f64::consts::TAU * 15.0 * t).cos();
            last.push(([a, a], 0.03));
            if last.len() > STILL_FRAMES {
                last.remove(0);
            }
            if let Some((c, _)) = settled(&last) {
                return c;
            }
        }
        panic!("never still");
    }

    #[test]
    fn the_ringings_tail_in_the_first_still_frame_is_not_in_the_reading() {
        // Frames 0.5 s apart (a loaded host), the first 0.2 s after the move, when 0.11 px of
        // a 0.6 px ring is left and agrees with the still frames within 3σ: with the oldest
        // frame in the mean the reading was 0.038 px (0.5 µm at 70 px/mm) off, the same sign
        // after every move.
        let slow = reading_of_ringing(0.6, 0.2, 0.5);
        assert!(slow[0].abs() < 0.002, "{slow:?}");
        // Frames 0.1 s apart (an idle host) see the ringing and wait it out.
        let fast = reading_of_ringing(0.6, 0.2, 0.1);
        assert!(fast[0].abs() < 0.01, "{fast:?}");
        // Frames that disagree are no reading; the reading's sd is of the frames averaged.
        assert!(settled(&[([0.0, 0.0], 0.03), ([0.2, 0.0], 0.03), ([0.0, 0.0], 0.03)]).is_none());
        let (c, u) =
            settled(&[([0.09, 0.0], 0.03), ([0.0, 0.0], 0.03), ([0.0, 0.0], 0.03)]).unwrap();
        assert!(
            c[0].abs() < 1e-12 && (u - 0.03 / 2f64.sqrt()).abs() < 1e-12,
            "{c:?} {u}"
        );
    }
}
