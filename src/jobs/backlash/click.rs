//! The click-in-snapshot flow (issue 27 Build 4): for a camera whose picture the detector cannot
//! read, the person clicks the nozzle's tip in each snapshot on klipcal's page instead of
//! jogging to a crosshair. `KLIPCAL_BACKLASH_CLICK AXIS= CYCLES= CARRIAGE=` runs the camera
//! measurement's procedure ([`super::camera`]: scale and rotation from ±0.5 mm moves, then the
//! cycles from each side) with a click in place of each detected reading; the page posts each
//! click as `_KLIPCAL_BACKLASH_TIP X= Y= FRAME= SD=` (`POST /api/backlash/tip`). The clicks go
//! through the same statistics and apply path: 6 + 2 per cycle clicks (16 for 5 cycles) against
//! the guided jog flow's ~250–300 presses.
//!
//! The click only *locates* the nozzle: the first click's snapshot is the reference, and every
//! later click is refined by registering its snapshot against it
//! ([`crate::calib::nozzle::ClickReader`]), so the offsets come from the pictures to a few
//! hundredths of a pixel. A click the pictures cannot refine (no clear match, or one farther
//! from the click than its stated precision allows) is kept as clicked, with its own ±, and
//! the console and the status say which and why.

use std::sync::Mutex;

use tokio::sync::oneshot;

use super::camera::{CameraRequest, Seen, Webcam};
use super::{Backlash, BacklashCall, TITLE};
use crate::calib::nozzle::{ClickReader, Gray};
use crate::jobs::core::table::{arg, ArgKind, ArgSpec, Args, Op, OpSpec};
use crate::jobs::user;

/// Starts the flow (the camera measurement's arguments).
pub(super) const START_OP: Op<BacklashCall> = Op {
    spec: OpSpec::remote(
        "klipcal_backlash_click",
        "KLIPCAL_BACKLASH_CLICK",
        "backlash/click",
        "measure backlash by clicking the nozzle's tip in camera snapshots on klipcal's page (no detection, no jogging): AXIS=X or Y (A/B on CoreXY), CYCLES=5, CARRIAGE=0|1 on dual_carriage",
        &[
            super::camera::AXIS_ARG,
            super::CYCLES_ARG,
            super::CARRIAGE_ARG,
        ],
    ),
    parse: |a| {
        Ok(BacklashCall::Camera(CameraRequest {
            clicks: true,
            ..CameraRequest::from_args(a)?
        }))
    },
};

/// `X=`: the tip's column.
const TIP_X: ArgSpec = arg(
    "x",
    ArgKind::Number {
        min: -1.0,
        max: 8192.0,
    },
    "321.5",
    "a pixel column of the picture",
    "",
    "the tip's column, px (pixel centres at whole numbers)",
);
/// `Y=`: the tip's row.
const TIP_Y: ArgSpec = arg(
    "y",
    ArgKind::Number {
        min: -1.0,
        max: 8192.0,
    },
    "240.25",
    "a pixel row of the picture",
    "",
    "the tip's row, px",
);
/// `FRAME=`: the snapshot clicked in.
const TIP_FRAME: ArgSpec = arg(
    "frame",
    ArgKind::Whole {
        min: 1,
        max: 1_000_000_000,
    },
    "7",
    "the snapshot's number the page shows",
    "",
    "the snapshot clicked in",
);
/// `SD=`: the click's precision.
const TIP_SD: ArgSpec = arg(
    "sd",
    ArgKind::Number {
        min: 0.01,
        max: 50.0,
    },
    "0.5",
    "0.01..50 px",
    "1",
    "how precisely the click places the tip, px (1 sd; the page sends its zoom's)",
);

/// One click, as the page sends it.
pub(super) const TIP_OP: Op<BacklashCall> = Op {
    spec: OpSpec::remote(
        "klipcal_backlash_tip",
        "_KLIPCAL_BACKLASH_TIP",
        "backlash/tip",
        "the nozzle's tip clicked in the snapshot waiting on klipcal's page: X= Y= in the picture's pixels, FRAME= its number, SD= the click's precision in pixels",
        &[
            TIP_X,
            TIP_Y,
            TIP_FRAME,
            TIP_SD,
        ],
    ),
    parse: |a| Ok(BacklashCall::Tip(TipRequest::from_args(a)?)),
};

/// `_KLIPCAL_BACKLASH_TIP`.
#[derive(Debug, Clone, PartialEq)]
pub struct TipRequest {
    pub at_px: [f64; 2],
    pub frame: u64,
    pub sd_px: f64,
}

impl TipRequest {
    fn from_args(a: &Args) -> anyhow::Result<Self> {
        let need = |k: &str| {
            user(format!(
                "_KLIPCAL_BACKLASH_TIP: {} is required; expected X=, Y= (the tip in the \
                 picture's pixels) and FRAME= (the snapshot's number)",
                k.to_uppercase()
            ))
        };
        let x = a.num(&TIP_X)?.ok_or_else(|| need(TIP_X.name))?;
        let y = a.num(&TIP_Y)?.ok_or_else(|| need(TIP_Y.name))?;
        let frame = a.int(&TIP_FRAME)?.ok_or_else(|| need(TIP_FRAME.name))?;
        Ok(Self {
            at_px: [x, y],
            frame: u64::try_from(frame).unwrap_or(0),
            sd_px: a.num(&TIP_SD)?.unwrap_or(1.0),
        })
    }
}

/// A snapshot waiting for its click.
struct Pending {
    session: i64,
    seq: u64,
    size: [usize; 2],
    tx: oneshot::Sender<([f64; 2], f64)>,
}

/// A snapshot to click in is taken at least this long after the move (s). The detector waits
/// for three frames that agree; a click has one snapshot, and the refined reading sees the
/// nozzle still ringing: on the bench (10 µm ring decaying in 0.12 s) a snapshot 0.2 s after
/// each move read 0.06 mm of play 2.8–3.0 µm high, the ring's tail along each approach's move.
/// The person takes longer than this to click anyway.
pub(crate) const CLICK_SETTLE_S: f64 = 1.0;

/// The page's zoom on a snapshot before the camera point's place in the picture is known (the
/// ±0.5 mm scale moves, 40 px apart at 80 px/mm, stay in view) and after it (the cycles' two
/// approaches differ by the backlash only: the finger's slip is half as large in the picture).
pub const ZOOM_SCALE: f64 = 4.0;
pub const ZOOM_CYCLES: f64 = 8.0;

/// The one snapshot waiting for a click, if any, the last click and the camera point's place
/// in the picture (where the page zooms).
#[derive(Default)]
pub(crate) struct Clicks {
    pending: Mutex<Option<Pending>>,
    last: Mutex<Option<(i64, [f64; 2])>>,
    point: Mutex<Option<(i64, [f64; 2])>>,
    /// The session's reference snapshot and how its clicks are read.
    reader: Mutex<Option<(i64, ClickReader)>>,
}

impl Clicks {
    fn lock_pending(&self) -> std::sync::MutexGuard<'_, Option<Pending>> {
        self.pending
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Where the page zooms for `session`, px, and by how much: on the camera point once the
    /// scale is known, else on the last click.
    pub(crate) fn hint(&self, session: i64) -> Option<([f64; 2], f64)> {
        let of = |m: &Mutex<Option<(i64, [f64; 2])>>| {
            m.lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .filter(|(s, _)| *s == session)
                .map(|(_, p)| p)
        };
        of(&self.point)
            .map(|p| (p, ZOOM_CYCLES))
            .or_else(|| of(&self.last).map(|p| (p, ZOOM_SCALE)))
    }

    /// A new measurement of `session` starts: no zoom yet, no reference snapshot.
    pub(crate) fn forget(&self, session: i64) {
        for m in [&self.last, &self.point] {
            let mut g = m.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            if g.is_some_and(|(s, _)| s == session) {
                *g = None;
            }
        }
        *self
            .reader
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = None;
    }

    /// `session`'s click reader (a new one, whose first click will be the reference, if none).
    fn take_reader(&self, session: i64) -> ClickReader {
        self.reader
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take()
            .filter(|(s, _)| *s == session)
            .map(|(_, r)| r)
            .unwrap_or_default()
    }

    /// The camera point is at `at_px` in `session`'s pictures.
    pub(crate) fn point_at(&self, session: i64, at_px: [f64; 2]) {
        *self
            .point
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some((session, at_px));
    }

    /// The snapshot `seq` of `session` is waiting for its click.
    pub(crate) fn waiting(&self, session: i64, seq: u64) -> bool {
        self.lock_pending()
            .as_ref()
            .is_some_and(|p| p.session == session && p.seq == seq)
    }
}

impl Backlash {
    /// One reading by a click: waits out the move, takes a snapshot, shows it on the page and
    /// waits for the person's click on the nozzle's tip.
    pub(super) async fn ask_click(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        id: i64,
        what: &str,
    ) -> anyhow::Result<Seen> {
        self.settle_after_move(CLICK_SETTLE_S).await?;
        let (seq, size, grey) = self.snapshot_for_click(http, cam, id, what).await?;
        let (tx, rx) = oneshot::channel();
        *self.clicks.lock_pending() = Some(Pending {
            session: id,
            seq,
            size,
            tx,
        });
        let (at_px, sd_px) = rx.await.map_err(|_| {
            user("the snapshot waiting for a click was withdrawn; run KLIPCAL_BACKLASH_CLICK again")
        })?;
        *self
            .clicks
            .last
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some((id, at_px));
        // The click refined from the pictures (or kept, with the reason).
        let mut reader = self.clicks.take_reader(id);
        let (reader, r) = tokio::task::spawn_blocking(move || {
            let r = reader.read(
                &Gray {
                    width: size[0],
                    height: size[1],
                    data: &grey,
                },
                at_px,
                sd_px,
            );
            (reader, r)
        })
        .await?;
        *self
            .clicks
            .reader
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some((id, reader));
        let kept = r.kept.as_ref().map(|why| {
            format!(
                "{what}: click kept as clicked, ±{:.2} px: it could not be refined from the \
                 pictures: {why}",
                r.sd_px
            )
        });
        if let Some(k) = &kept {
            self.core.console(&format!("{TITLE}: {k}")).await;
        }
        Ok(Seen {
            centre_px: r.at_px,
            uncertainty_px: r.sd_px,
            frames: 1,
            refused: 0,
            refined: r.refined,
            kept,
        })
    }

    /// `_KLIPCAL_BACKLASH_TIP`: the click on the snapshot waiting for it.
    ///
    /// # Errors
    /// No snapshot waiting, another snapshot's number, a point outside the picture.
    pub(super) fn tip(&self, r: &TipRequest) -> anyhow::Result<super::answers::Clicked> {
        let mut g = self.clicks.lock_pending();
        let Some(p) = g.take() else {
            return Err(user(
                "no snapshot is waiting for a click; start with KLIPCAL_BACKLASH_CLICK AXIS=X \
                 (or Y, A, B), then click the nozzle's tip in each snapshot on klipcal's page",
            ));
        };
        if p.tx.is_closed() {
            return Err(user(
                "the measurement that showed this snapshot has ended; start again with \
                 KLIPCAL_BACKLASH_CLICK",
            ));
        }
        let refuse = |g: &mut Option<Pending>, p: Pending, why: String| {
            *g = Some(p);
            Err(user(why))
        };
        if r.frame != p.seq {
            let why = format!(
                "FRAME={}: the snapshot waiting for a click is frame {}; reload the page and \
                 click in it",
                r.frame, p.seq
            );
            return refuse(&mut g, p, why);
        }
        let [w, h] = p.size;
        let [x, y] = r.at_px;
        if !(-0.5..=w as f64 - 0.5).contains(&x) || !(-0.5..=h as f64 - 0.5).contains(&y) {
            let why = format!(
                "X={x} Y={y}: outside the {w}×{h} picture; expected the tip inside it \
                 (X from -0.5 to {}, Y from -0.5 to {})",
                w as f64 - 0.5,
                h as f64 - 0.5
            );
            return refuse(&mut g, p, why);
        }
        let seq = p.seq;
        let _ = p.tx.send((r.at_px, r.sd_px));
        Ok(super::answers::Clicked {
            frame: seq,
            message: format!(
                "tip at ({x:.2}, {y:.2}) px of snapshot {seq} saved; the next snapshot follows"
            ),
        })
    }
}
