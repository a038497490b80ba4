//! Reading the nozzle in the camera's frames: a frame fetched and searched, kept for the page;
//! frames taken until the nozzle is still ([`settled`]); a snapshot for the person to click in.

use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::super::snapshot::SnapshotInfo;
use super::super::Backlash;
use super::meter::{Expect, FrameRefusal, Meter, Reading};
use super::Webcam;
use crate::calib::nozzle::{self, DetectParams, Detection, Gray, Refusal};
use crate::jobs::user;

/// Frames that must agree before a reading is taken. Two were not enough: a nozzle ringing
/// after a move can be caught at the same phase twice running (frames about one period apart),
/// and on the bench's CoreXY camera test that read A 2.1 µm high (0.0621 mm against 0.060
/// drawn, every cycle); three frames at different phases must all agree.
const STILL_FRAMES: usize = 3;

/// The still nozzle's next frame is searched this far (px, each axis) round the frame before
/// (or a third of the reading's own reach, if more): the ringing's tail, the mount's drift.
const STILL_REACH_PX: f64 = 3.0;

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

/// What a frame gave: the detector's finding, and with a [`Registration`] the frame measured
/// against the measurement's first ([`Meter::read`]).
pub(super) struct Look {
    pub found: Result<Detection, Refusal>,
    pub read: Option<Result<Reading, FrameRefusal>>,
}

/// The measurement's frames, measured by registering its first frame's nozzle region round
/// where the nozzle is expected ([`Meter`], issue 37, item 2); shared with the blocking task
/// that reads each frame.
pub(super) type Registration = std::sync::Arc<std::sync::Mutex<Meter>>;

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
        reg: Option<(&Registration, Option<Expect>)>,
    ) -> anyhow::Result<Look> {
        let (reg, expect) = reg.map_or((None, None), |(r, e)| (Some(r), e));
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
            let read = reg.map(|reg| {
                reg.lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .read(
                        &Gray {
                            width: w,
                            height: h,
                            data: &grey,
                        },
                        found
                            .as_ref()
                            .map(|d| (d.centre_px, d.uncertainty_px))
                            .map_err(ToString::to_string),
                        expect,
                    )
            });
            anyhow::Ok((w, h, Look { found, read }))
        })
        .await??;
        if let Some((session, what)) = keep {
            self.keep_frame(session, what, jpeg, [w, h], &look);
        }
        Ok(look)
    }

    /// A frame kept for the page with what was read in it: the registered reading, else the
    /// detector's; the refusal, and when the registration refused a frame the detector found a
    /// nozzle in, that reason.
    fn keep_frame(&self, session: i64, what: &str, jpeg: Vec<u8>, size: [usize; 2], look: &Look) {
        let read = look.read.as_ref().and_then(|r| r.as_ref().ok());
        let found = look.found.as_ref().ok();
        let refused = match (&look.read, &look.found) {
            (Some(Err(r)), _) => Some(r.to_string()),
            (Some(Ok(_)), Err(r)) => Some(format!(
                "{r} (read by registration against the first frame)"
            )),
            (None, Err(r)) => Some(r.to_string()),
            _ => None,
        };
        self.frames.keep(
            session,
            jpeg,
            SnapshotInfo {
                seq: 0,
                width: size[0],
                height: size[1],
                what: what.to_string(),
                centre_px: read
                    .map(|r| r.at_px)
                    .or(found.map(|d| d.centre_px))
                    .filter(|_| !matches!(look.read, Some(Err(_)))),
                radius_px: found.map(|d| d.diagnostics.radius_px),
                uncertainty_px: read
                    .map(|r| r.sd_px)
                    .or(found.map(|d| d.uncertainty_px))
                    .filter(|_| !matches!(look.read, Some(Err(_)))),
                refused,
                click: false,
                hint_px: None,
                zoom: None,
            },
        );
    }

    /// The nozzle once it is still: waits out the move, then frames until three agree
    /// ([`settled`]). Each frame is measured by registration against the measurement's first
    /// ([`Meter`]): the first frame of the reading round `expect` (where the commanded move puts
    /// the nozzle; None: where the detector finds it), the next ones round the frame before. A
    /// frame neither registration nor detection reads, or where they disagree with the
    /// reference matching at both places, is taken again (five in a row: the reason).
    pub(super) async fn sight(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        at: (i64, &str),
        reg: &Registration,
        expect: Option<Expect>,
    ) -> anyhow::Result<Seen> {
        let (id, what) = at;
        self.settle_after_move(0.0).await?;
        let (mut frames, mut refused, mut in_a_row) = (0, 0, 0);
        let mut last: Vec<Frame> = Vec::new();
        let mut near = expect;
        while frames < 14 {
            frames += 1;
            let look = self
                .look(http, cam, Some((id, what)), Some((reg, near)))
                .await?;
            // A frame the detector refused but registration read counts as refused by
            // detection, and is a reading.
            refused += usize::from(look.found.is_err());
            match look.read {
                Some(Ok(r)) => {
                    in_a_row = 0;
                    // The still nozzle's next frame is where this one was.
                    near = Some(Expect {
                        at_px: r.at_px,
                        reach_px: expect.map_or(0.0, |e| e.reach_px / 3.0).max(STILL_REACH_PX),
                    });
                    last.push((r.at_px, r.sd_px));
                    if last.len() > STILL_FRAMES {
                        last.remove(0);
                    }
                    if let Some((centre_px, uncertainty_px)) = settled(&last) {
                        return Ok(Seen {
                            centre_px,
                            uncertainty_px,
                            frames,
                            refused,
                            refined: true,
                            kept: None,
                        });
                    }
                }
                other => {
                    refused += usize::from(look.found.is_ok());
                    in_a_row += 1;
                    let why = match (other, look.found) {
                        (Some(Err(r)), _) => r.to_string(),
                        (_, Err(r)) => r.to_string(),
                        _ => "no reading".to_string(),
                    };
                    if in_a_row >= 5 {
                        return Err(user(format!(
                            "webcam '{}': five frames in a row without a sure nozzle: {why}",
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
