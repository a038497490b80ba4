//! KLIPCAL_BACKLASH_CAMERA AXIS=X|Y|A|B [CYCLES=] (issue 27): the seed's backlash procedure done
//! by the daemon, read from the nozzle camera with no tapping.
//!
//! The camera is Moonraker's: `server.webcams.list`, the webcam named in `[backlash] webcam`, or
//! the only one; its snapshot URL (a relative one resolved against Moonraker's host, as
//! Moonraker does). The first frame is checked before anything moves, so a missing camera or a
//! picture with no sure nozzle is refused with the reason at once. Then, in the background:
//! 1. **Scale and rotation**: X, then Y, at −0.5, 0, +0.5 mm about the camera point, every
//!    position approached moving + so the play stays on one side
//!    ([`crate::calib::camera_scale`]).
//! 2. **Cycles**: approach the point from 1 mm below (moving +), read the nozzle; from 1 mm
//!    above (moving −), read it. Backlash = the difference along the axis.
//! 3. Each reading waits `camera_settle_s` after the move, then takes frames until three in a
//!    row agree within their uncertainty (the nozzle has stopped ringing) and reads the
//!    nozzle from the two after the oldest of them ([`settled`]); a frame that
//!    detection refuses is taken again, five in a row end the measurement with the reason.
//!    Every frame looked at is kept for the page with what was found in it
//!    ([`super::snapshot`]).
//! 5. `KLIPCAL_BACKLASH_CLICK` ([`super::click`]) runs the same steps with the person's click
//!    on the nozzle's tip in each snapshot in place of steps 3's detection.
//! 4. The cycles go into the session like the guided flow's, analysed with the camera's noise
//!    floor ([`crate::calib::camera_scale::camera_params`]); KLIPCAL_BACKLASH_APPLY applies
//!    them through the same verified path.

use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::snapshot::SnapshotInfo;
use super::{key_words, next_line, result_key, start_note, Backlash, BacklashCall};
use super::{Session, State};
use super::{JOG_F, KIND, TITLE};
use crate::calib::backlash::BacklashParams;
use crate::calib::backlash_guide::GuideAxis;
use crate::calib::camera_scale::{self, CameraScale, Sighting};
use crate::calib::nozzle::{self, DetectParams, Detection, Gray, Refusal};
use crate::jobs::core::table::{arg, ArgKind, ArgSpec, Args, Op, OpSpec};
use crate::jobs::core::SessionState;
use crate::jobs::user;
use crate::klipper::GcodeCmd;
use crate::moonraker::answers::{WebcamEntry, WebcamList};

/// The camera measurement's operation, declared in the backlash table.
/// AXIS= of the camera and the click measurement (no Z: the camera looks up at the nozzle).
pub(super) const AXIS_ARG: ArgSpec = arg(
    "axis",
    ArgKind::Text,
    "X",
    "X, Y, A or B",
    "",
    "the axis: X, Y, or A/B (CoreXY motors)",
);

pub(super) const OP: Op<BacklashCall> = Op {
    spec: OpSpec::remote(
        "klipcal_backlash_camera",
        "KLIPCAL_BACKLASH_CAMERA",
        "backlash/camera",
        "measure backlash from the nozzle camera, no tapping: AXIS=X or Y (A/B on CoreXY), CYCLES=5, CARRIAGE=0|1 on dual_carriage",
        &[
            AXIS_ARG,
            super::CYCLES_ARG,
            super::CARRIAGE_ARG,
        ],
    ),
    parse: |a| {
        Ok(BacklashCall::Camera(CameraRequest::from_args(
            a,
            "KLIPCAL_BACKLASH_CAMERA",
        )?))
    },
};

/// `KLIPCAL_BACKLASH_CAMERA`, or `KLIPCAL_BACKLASH_CLICK` (`clicks`).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CameraRequest {
    pub axis: GuideAxis,
    pub cycles: Option<usize>,
    pub carriage: Option<i64>,
    /// The person clicks the nozzle's tip in each snapshot ([`super::click`]).
    pub clicks: bool,
}

impl CameraRequest {
    pub(super) fn from_args(a: &Args, macro_name: &str) -> anyhow::Result<Self> {
        let axis_text = a.text("axis").ok_or_else(|| {
            user(format!(
                "{macro_name}: AXIS is required; expected X, Y, A or B"
            ))
        })?;
        let axis = GuideAxis::parse(&axis_text).map_err(|e| user(e.to_string()))?;
        if axis == GuideAxis::Z {
            return Err(user(
                "AXIS=Z: a camera under the nozzle cannot see Z move; measure Z with \
                 KLIPCAL_BACKLASH_START AXIS=Z (guided), or X, Y, A, B here",
            ));
        }
        let cycles = a
            .int("cycles")?
            .map(|c| usize::try_from(c).map_err(|_| user(format!("CYCLES={c}: expected 1..50"))))
            .transpose()?;
        Ok(Self {
            axis,
            cycles,
            carriage: a.int("carriage")?,
            clicks: false,
        })
    }
}

/// The chosen webcam.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Webcam {
    pub name: String,
    /// The absolute snapshot URL.
    pub snapshot_url: String,
}

/// Picks the nozzle camera from `server.webcams.list`'s answer: the one named `wanted`, or the
/// only enabled one. Web pages shown in a webcam panel (service `iframe`, such as klipcal's own
/// page that install registers) are not cameras and are left out. The error says what to do.
pub(crate) fn choose_webcam(
    list: &WebcamList,
    wanted: &str,
    moonraker_base: &str,
) -> Result<Webcam, String> {
    let cams: Vec<&WebcamEntry> = list
        .webcams
        .iter()
        .filter(|c| c.enabled && c.service != "iframe")
        .collect();
    let names: Vec<&str> = cams
        .iter()
        .map(|c| c.name.as_str())
        .filter(|n| !n.is_empty())
        .collect();
    let cam = if wanted.is_empty() {
        match cams.as_slice() {
            [] => {
                return Err(
                    "Moonraker lists no webcam: add the nozzle camera (Mainsail/Fluidd \
                            webcam settings, or [webcam nozzle] in moonraker.conf with its \
                            snapshot_url), or measure with KLIPCAL_BACKLASH_START (guided)"
                        .into(),
                )
            }
            [one] => *one,
            _ => {
                return Err(format!(
                    "Moonraker lists {} webcams ({}); name the nozzle camera in klipcal.toml: \
                     [backlash] webcam = \"…\"",
                    cams.len(),
                    names.join(", ")
                ))
            }
        }
    } else {
        match cams.iter().find(|c| c.name == wanted) {
            Some(c) => *c,
            None => {
                return Err(format!(
                    "no webcam named '{wanted}' in Moonraker's list ({}); set [backlash] webcam \
                     in klipcal.toml to one of them",
                    if names.is_empty() {
                        "it is empty".to_string()
                    } else {
                        names.join(", ")
                    }
                ))
            }
        }
    };
    let name = cam.name.clone();
    let url = cam.snapshot_url.trim();
    if url.is_empty() {
        return Err(format!(
            "webcam '{name}' has no snapshot URL; set one (ustreamer and camera-streamer serve \
             /?action=snapshot or /snapshot)"
        ));
    }
    Ok(Webcam {
        name,
        snapshot_url: resolve_url(url, moonraker_base),
    })
}

/// A snapshot URL as a full one: a relative URL (`/webcam/?action=snapshot`, served through the
/// web server) is on Moonraker's host at the default port, as Moonraker itself resolves it.
pub(crate) fn resolve_url(url: &str, moonraker_base: &str) -> String {
    if url.contains("://") {
        return url.to_string();
    }
    let rest = moonraker_base
        .split_once("://")
        .map_or(moonraker_base, |(_, r)| r);
    let hostport = rest.split('/').next().unwrap_or("");
    let host = if let Some(end) = hostport.strip_prefix('[').and_then(|h| h.find(']')) {
        &hostport[..end + 2]
    } else {
        hostport.split(':').next().unwrap_or(hostport)
    };
    format!("http://{host}/{}", url.trim_start_matches('/'))
}

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
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct Seen {
    pub centre_px: [f64; 2],
    pub uncertainty_px: f64,
    /// Frames taken, and refused by detection.
    pub frames: usize,
    pub refused: usize,
}

/// One camera cycle, as the page and the status show it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct CameraCycle {
    pub plus_px: [f64; 2],
    pub minus_px: [f64; 2],
    /// Where each approach stopped along the axis, mm from the camera point's reading (+:
    /// approached from below, moving +; −: from above).
    #[serde(default)]
    pub plus_mm: f64,
    #[serde(default)]
    pub minus_mm: f64,
    pub backlash_mm: f64,
}

/// How an axis was read through the camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct CameraReport {
    pub webcam: Webcam,
    pub scale: Option<CameraScale>,
    /// The nozzle at the camera point (X approached moving +), px.
    pub reference_px: Option<[f64; 2]>,
    pub cycles: Vec<CameraCycle>,
    /// The largest uncertainty of the cycles' readings, px, and the scale along the axis,
    /// px/mm: the statistics' noise floor.
    pub detection_sd_px: f64,
    pub axis_px_per_mm: f64,
    pub frames: usize,
    pub refused_frames: usize,
    /// The last reading, px (the page marks it).
    pub last_px: Option<[f64; 2]>,
    /// Readings clicked by the person (KLIPCAL_BACKLASH_CLICK) instead of detected: how many.
    #[serde(default)]
    pub clicks: usize,
}

impl CameraReport {
    /// The statistics' settings for these cycles: the camera's noise floor, not a jog's.
    pub(super) fn params(&self, base: &BacklashParams) -> BacklashParams {
        if self.axis_px_per_mm > 0.0 && self.detection_sd_px > 0.0 {
            // The scale's sd along the axis: the larger of X's and Y's relative sd.
            let rel = self.scale.map_or(0.0, |c| c.rel_sd());
            camera_scale::camera_params(
                base,
                self.detection_sd_px,
                self.axis_px_per_mm,
                rel * self.axis_px_per_mm,
                self.clicks == 0,
            )
        } else {
            base.clone()
        }
    }
}

/// What a camera measurement runs.
#[derive(Debug, Clone, Copy)]
struct Run {
    axis: GuideAxis,
    cycles: usize,
    point: [f64; 3],
    carriage: Option<u32>,
    /// Readings by the person's clicks instead of detection.
    clicks: bool,
}

/// Why a frame gave no reading.
enum Look {
    Found(Detection),
    Refused(Refusal),
}

impl Backlash {
    fn http(&self) -> anyhow::Result<reqwest::Client> {
        reqwest::Client::builder()
            .timeout(Duration::from_secs(10))
            .build()
            .context("building the camera's HTTP client")
    }

    /// The nozzle camera from Moonraker's list.
    async fn webcam(&self) -> anyhow::Result<Webcam> {
        let list = self
            .core
            .m()
            .webcams()
            .await
            .context("asking Moonraker for its webcams")?;
        choose_webcam(&list, self.settings.webcam.trim(), self.core.files().base()).map_err(user)
    }

    /// One snapshot's bytes.
    async fn fetch(&self, http: &reqwest::Client, cam: &Webcam) -> anyhow::Result<Vec<u8>> {
        let r = http
            .get(&cam.snapshot_url)
            .send()
            .await
            .map_err(|e| user(format!("webcam '{}' ({}): {e}", cam.name, cam.snapshot_url)))?;
        let status = r.status();
        if !status.is_success() {
            return Err(user(format!(
                "webcam '{}' answered {status} for its snapshot ({}); expected a JPEG",
                cam.name, cam.snapshot_url
            )));
        }
        Ok(r.bytes().await.context("reading the snapshot")?.to_vec())
    }

    /// A snapshot for the person to click in (no detection): kept for the page; its number
    /// and size.
    pub(super) async fn snapshot_for_click(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        id: i64,
        what: &str,
    ) -> anyhow::Result<(u64, [usize; 2])> {
        let bytes = self.fetch(http, cam).await?;
        let name = cam.name.clone();
        let jpeg = bytes.clone();
        let (w, h) = tokio::task::spawn_blocking(move || {
            crate::cmd::camera_render::decode_gray(&bytes)
                .map(|(w, h, _)| (w, h))
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
        Ok((seq, [w, h]))
    }

    /// One frame, fetched and searched; kept for the page as `keep` = (session, what) says.
    async fn look(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        keep: Option<(i64, &str)>,
    ) -> anyhow::Result<Look> {
        let bytes = self.fetch(http, cam).await?;
        let name = cam.name.clone();
        let jpeg = bytes.clone();
        let (w, h, look) = tokio::task::spawn_blocking(move || {
            let (w, h, grey) = crate::cmd::camera_render::decode_gray(&bytes)
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
                    Ok(d) => Look::Found(d),
                    Err(r) => Look::Refused(r),
                },
            ))
        })
        .await??;
        if let Some((session, what)) = keep {
            let (found, refused) = match &look {
                Look::Found(d) => (Some(d), None),
                Look::Refused(r) => (None, Some(r.to_string())),
            };
            self.frames.keep(
                session,
                jpeg,
                SnapshotInfo {
                    seq: 0,
                    width: w,
                    height: h,
                    what: what.to_string(),
                    centre_px: found.map(|d| d.centre_px),
                    radius_px: found.map(|d| d.diagnostics.radius_px),
                    uncertainty_px: found.map(|d| d.uncertainty_px),
                    refused,
                    click: false,
                    hint_px: None,
                    zoom: None,
                },
            );
        }
        Ok(look)
    }

    /// The nozzle once it is still: waits out the move, then frames until three agree
    /// ([`settled`]); a refused frame is taken again (five in a row: the reason).
    async fn sight(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
        id: i64,
        what: &str,
    ) -> anyhow::Result<Seen> {
        self.settle_after_move().await?;
        let (mut frames, mut refused, mut in_a_row) = (0, 0, 0);
        let mut last: Vec<Frame> = Vec::new();
        while frames < 14 {
            frames += 1;
            match self.look(http, cam, Some((id, what))).await? {
                Look::Found(d) => {
                    in_a_row = 0;
                    last.push((d.centre_px, d.uncertainty_px));
                    if last.len() > STILL_FRAMES {
                        last.remove(0);
                    }
                    if let Some((centre_px, uncertainty_px)) = settled(&last) {
                        return Ok(Seen {
                            centre_px,
                            uncertainty_px,
                            frames,
                            refused,
                        });
                    }
                }
                Look::Refused(r) => {
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

    /// Waits until Klipper has finished the moves (M400), then `camera_settle_s` for the
    /// nozzle to stop ringing: before a detected reading and before a snapshot to click in.
    pub(super) async fn settle_after_move(&self) -> anyhow::Result<()> {
        self.core.m().gcode("M400").await?;
        let settle = self.settings.camera_settle_s.clamp(0.0, 10.0);
        tokio::time::sleep(Duration::from_secs_f64(settle)).await;
        Ok(())
    }

    async fn go(&self, p: [f64; 3]) -> anyhow::Result<()> {
        let line = GcodeCmd::new("G1")
            .axis('X', p[0])
            .axis('Y', p[1])
            .axis('Z', p[2])
            .axis('F', JOG_F)
            .build()?;
        self.core.m().gcode(&format!("G90\n{line}")).await?;
        Ok(())
    }

    async fn progress(&self, id: i64, text: String, report: Option<(&str, &CameraReport)>) {
        let _ = self
            .core
            .update::<Session, ()>(id, |s| {
                s.progress = text;
                if let Some((k, r)) = report {
                    s.camera.insert(k.to_string(), r.clone());
                }
                Ok(())
            })
            .await;
    }

    /// `klipcal_backlash_camera`: checks the camera and the printer, then measures in the
    /// background.
    ///
    /// # Errors
    /// Bad arguments, another calibration, a printing or unhomed printer, no camera point, no
    /// or several webcams, a first frame without a sure nozzle (the reason), A/B off CoreXY.
    pub(super) async fn camera(&self, req: &CameraRequest) -> anyhow::Result<Value> {
        let axis = req.axis;
        let cycles = req.cycles.unwrap_or(self.settings.cycles);
        if !(1..=50).contains(&cycles) {
            return Err(user(format!("CYCLES={cycles}: expected 1..50")));
        }
        self.core.refuse_other_kind(KIND)?;
        if let Some(s) = self.active()? {
            if s.state != State::Measured {
                return Err(user(format!(
                    "session {} is {}; finish the axis in progress or KLIPCAL_CANCEL",
                    s.id,
                    s.state.name()
                )));
            }
        }
        self.core.printer_idle().await?;
        self.homed(axis).await?;
        let point = self
            .saved_point()?
            .ok_or_else(|| {
                user("no camera point saved: bring the nozzle over the camera, then KLIPCAL_BACKLASH_SET_POINT")
            })?;
        let cam = self.webcam().await?;
        let http = self.http()?;
        // The picture is checked before anything moves (for clicks: that it comes).
        if req.clicks {
            let b = self.fetch(&http, &cam).await?;
            crate::cmd::camera_render::decode_gray(&b)
                .map_err(|e| user(format!("webcam '{}': {e:#}", cam.name)))?;
        } else if let Look::Refused(r) = self.look(&http, &cam, None).await? {
            return Err(user(format!(
                "webcam '{}' shows no sure nozzle: {r}",
                cam.name
            )));
        }
        let (detection, cf) = self.detect().await?;
        let note = start_note(&detection);
        let kin = cf.settings.printer.kinematics.clone();
        if axis.is_motor() && kin != "corexy" {
            return Err(user(format!(
                "AXIS={} is a CoreXY motor direction; this printer's kinematics is {kin}",
                axis.name().to_uppercase()
            )));
        }
        let max_accel = cf.settings.printer.max_accel;
        let carriage = self
            .carriage_for(&detection, &cf, axis, req.carriage)
            .await?;
        if let Some(n) = carriage {
            self.park_and_select(n).await?;
        }
        let key = result_key(axis, carriage);
        let active_mm = self
            .active_values(&detection, &cf, axis, carriage, &key)
            .await?;
        let progress = format!("camera: measuring {}", key_words(&key));
        let id = self
            .begin_axis(super::guide::AxisStart {
                progress,
                point,
                detection,
                active_mm,
                guide: None,
                carriage,
                kinematics: kin,
                max_accel_mm_s2: max_accel,
            })
            .await?
            .id;
        let clicks = req.clicks;
        let me = Arc::new(self.sibling());
        let fail_me = me.clone();
        let cam2 = cam.clone();
        self.core.spawn_session(
            id,
            TITLE,
            move || {
                let (me, cam) = (me.clone(), cam2.clone());
                async move {
                    let run = Run {
                        axis,
                        cycles,
                        point,
                        carriage,
                        clicks,
                    };
                    me.camera_run(id, run, &cam).await
                }
            },
            move |why| async move {
                let _ = fail_me
                    .finish(
                        id,
                        State::Failed,
                        &format!("camera measurement failed: {why}"),
                    )
                    .await;
                fail_me
                    .core
                    .console_error(&format!("{TITLE}: camera measurement failed: {why}"))
                    .await;
            },
        );
        let msg = if clicks {
            format!(
                "{TITLE} session {id}: {} from webcam '{}', {cycles} cycles: click the nozzle's \
                 tip in each snapshot on klipcal's page{} ({} clicks); the result follows on the \
                 console{}",
                key_words(&key),
                cam.name,
                self.core
                    .page()
                    .map(|p| format!(", {p}"))
                    .unwrap_or_default(),
                6 + 2 * cycles,
                note
            )
        } else {
            format!(
                "{TITLE} session {id}: {} from webcam '{}', {cycles} cycles, no tapping; the \
                 result follows on the console{}",
                key_words(&key),
                cam.name,
                note
            )
        };
        Ok(
            json!({"session": id, "state": "measuring", "axis": axis.name(),
                  "carriage": carriage, "webcam": cam, "message": msg}),
        )
    }

    /// The measurement itself (the runner's steps; run again from the start after an outage).
    async fn camera_run(&self, id: i64, run: Run, cam: &Webcam) -> anyhow::Result<()> {
        let Run {
            axis,
            cycles,
            point,
            carriage,
            clicks,
        } = run;
        let http = self.http()?;
        self.clicks.forget(id);
        let total = 6 + 2 * cycles;
        let mut n = 0;
        let mut read = |what: String| {
            n += 1;
            let http = &http;
            let k = n;
            async move {
                if clicks {
                    let what = format!("click {k} of {total} — {what}");
                    self.progress(
                        id,
                        format!(
                            "click the nozzle's tip in the snapshot on klipcal's page ({what})"
                        ),
                        None,
                    )
                    .await;
                    self.ask_click(http, cam, id, &what).await
                } else {
                    self.sight(http, cam, id, &what).await
                }
            }
        };
        let key = result_key(axis, carriage);
        let approach = self.settings.approach_mm;
        let mut report = CameraReport {
            webcam: cam.clone(),
            scale: None,
            reference_px: None,
            cycles: Vec::new(),
            detection_sd_px: 0.0,
            axis_px_per_mm: 0.0,
            frames: 0,
            refused_frames: 0,
            last_px: None,
            clicks: 0,
        };
        // The cycles' readings set the statistics' noise floor; the scale's readings enter
        // through the scale's uncertainty (a click on the whole-picture zoom of the scale
        // moves is twice as coarse as one on the cycles' zoom).
        let count = |r: &mut CameraReport, s: &Seen, cycle: bool| {
            r.clicks += usize::from(clicks);
            r.frames += s.frames;
            r.refused_frames += s.refused;
            r.last_px = Some(s.centre_px);
            if cycle {
                r.detection_sd_px = r.detection_sd_px.max(s.uncertainty_px);
            }
        };
        // 1. Scale and rotation: each axis at −0.5, 0, +0.5 mm, every one approached moving +.
        let mut sightings: [Vec<Sighting>; 2] = [Vec::new(), Vec::new()];
        for (k, ax) in [GuideAxis::X, GuideAxis::Y].into_iter().enumerate() {
            self.progress(
                id,
                format!(
                    "camera: scale and rotation from {} ±0.5 mm",
                    ax.name().to_uppercase()
                ),
                None,
            )
            .await;
            self.go(ax.point_at(point, -0.5 - approach)).await?;
            for t in [-0.5, 0.0, 0.5] {
                self.go(ax.point_at(point, t)).await?;
                let s = read(format!("scale: {} at {t:+.1} mm", ax.name().to_uppercase())).await?;
                count(&mut report, &s, false);
                sightings[k].push(Sighting {
                    commanded_mm: t,
                    centre_px: s.centre_px,
                    uncertainty_px: s.uncertainty_px.max(0.01),
                });
            }
            self.go(point).await?;
        }
        let scale = CameraScale::from_sightings(&sightings[0], &sightings[1])
            .map_err(|e| user(e.to_string()))?;
        let reference = sightings[0][1].centre_px;
        report.axis_px_per_mm = scale.px_per_mm_along(axis);
        report.scale = Some(scale);
        report.reference_px = Some(reference);
        if clicks {
            self.clicks.point_at(id, reference);
        }
        // 2. The seed's cycles, read from the image.
        let mut got = Vec::new();
        for c in 1..=cycles {
            self.progress(
                id,
                format!("camera: {} cycle {c}/{cycles}", key_words(&key)),
                Some((&key, &report)),
            )
            .await;
            self.go(axis.point_at(point, -approach)).await?;
            self.go(point).await?;
            let words = key_words(&key);
            let plus = read(format!(
                "{words} cycle {c}/{cycles}: approached from below (moving +)"
            ))
            .await?;
            count(&mut report, &plus, true);
            self.go(axis.point_at(point, approach)).await?;
            self.go(point).await?;
            let minus = read(format!(
                "{words} cycle {c}/{cycles}: approached from above (moving −)"
            ))
            .await?;
            count(&mut report, &minus, true);
            let a =
                camera_scale::approaches(&scale, axis, plus.centre_px, minus.centre_px, reference);
            report.cycles.push(CameraCycle {
                plus_px: plus.centre_px,
                minus_px: minus.centre_px,
                plus_mm: a.plus_mm,
                minus_mm: a.minus_mm,
                backlash_mm: a.cycle.backlash_mm(),
            });
            got.push(a.cycle);
        }
        // 3. Into the session, as the guided flow's cycles.
        let again = if clicks {
            "KLIPCAL_BACKLASH_CLICK"
        } else {
            "KLIPCAL_BACKLASH_CAMERA"
        };
        let s = {
            let _g = self.core.lock().await;
            let mut s: Session = self.core.load(id)?;
            if s.state != State::Measuring {
                return Ok(()); // cancelled meanwhile
            }
            s.cycles.insert(key.clone(), got);
            s.camera.insert(key.clone(), report);
            s.carriage = None;
            s.state = State::Measured;
            s.progress = format!(
                "{} measured from the camera{}; {}",
                key_words(&key),
                if clicks { " by your clicks" } else { "" },
                next_line(&s.detection, again)
            );
            self.core.save(id, &s)?;
            s
        };
        let lines = self.result_lines(&s)?;
        self.core
            .console(&format!(
                "{TITLE}: {}\n{}",
                lines.join("\n"),
                next_line(&s.detection, again)
            ))
            .await;
        Ok(())
    }

    /// A camera measurement cut off by a restart: its readings are gone, so it ends, saying
    /// how to run it again (axes measured before are kept).
    pub(super) async fn camera_interrupted(&self, s: &Session) {
        let why = "camera measurement interrupted by a klipcal restart; run \
                   KLIPCAL_BACKLASH_CAMERA (or KLIPCAL_BACKLASH_CLICK) again";
        if s.cycles.is_empty() {
            let _ = self.finish(s.id, State::Failed, why).await;
        } else {
            let _ = self.set_state(s.id, State::Measured, why).await;
        }
        self.core.console(&format!("{TITLE}: {why}")).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn list(v: Value) -> WebcamList {
        WebcamList::parse(v).unwrap()
    }

    #[test]
    fn the_webcam_is_the_named_one_or_the_only_one_and_refusals_say_what_to_do() {
        let base = "http://192.168.1.20:7125";
        let one = list(json!({"webcams": [{"name": "nozzle", "enabled": true,
            "snapshot_url": "/webcam/?action=snapshot"}]}));
        let w = choose_webcam(&one, "", base).unwrap();
        assert_eq!(w.name, "nozzle");
        assert_eq!(
            w.snapshot_url,
            "http://192.168.1.20/webcam/?action=snapshot"
        );
        let two = list(json!({"webcams": [
            {"name": "bed", "snapshot_url": "http://cam:8080/snapshot"},
            {"name": "nozzle", "snapshot_url": "http://10.0.0.5:8081/?action=snapshot"}]}));
        assert_eq!(
            choose_webcam(&two, "nozzle", base).unwrap().snapshot_url,
            "http://10.0.0.5:8081/?action=snapshot"
        );
        let e = choose_webcam(&two, "", base).unwrap_err();
        assert!(
            e.contains("2 webcams (bed, nozzle)") && e.contains("webcam = "),
            "{e}"
        );
        let e = choose_webcam(&two, "tool", base).unwrap_err();
        assert!(e.contains("'tool'") && e.contains("bed, nozzle"), "{e}");
        let e = choose_webcam(&list(json!({"webcams": []})), "", base).unwrap_err();
        assert!(
            e.contains("no webcam") && e.contains("KLIPCAL_BACKLASH_START"),
            "{e}"
        );
        // klipcal's own page, registered by install as an iframe "webcam", is not a camera.
        let with_page = list(json!({"webcams": [
            {"name": "klipcal", "service": "iframe", "snapshot_url": "", "stream_url": "http://h:7150/"},
            {"name": "nozzle", "service": "mjpegstreamer-adaptive",
             "snapshot_url": "/webcam/?action=snapshot"}]}));
        assert_eq!(choose_webcam(&with_page, "", base).unwrap().name, "nozzle");
        let off = list(json!({"webcams": [{"name": "n", "enabled": false, "snapshot_url": "/s"}]}));
        assert!(choose_webcam(&off, "", base).is_err());
        let empty = list(json!({"webcams": [{"name": "n", "snapshot_url": ""}]}));
        assert!(choose_webcam(&empty, "", base)
            .unwrap_err()
            .contains("no snapshot URL"));
        // The bench's real answer: its one camera, by its absolute URL.
        let bench = list(
            serde_json::from_str::<Value>(include_str!(
                "../../../../tests/fixtures/moonraker/webcams-list.json"
            ))
            .unwrap()["result"]
                .clone(),
        );
        let w = choose_webcam(&bench, "", base).unwrap();
        assert_eq!(
            (w.name.as_str(), w.snapshot_url.as_str()),
            ("nozzle", "http://127.0.0.1:54299/?action=snapshot")
        );
        assert_eq!(
            resolve_url("webcam2/?action=snapshot", "http://[fe80::1]:7125"),
            "http://[fe80::1]/webcam2/?action=snapshot"
        );
    }

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
