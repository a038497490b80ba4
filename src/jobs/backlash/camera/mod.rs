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
//!    nozzle from the two after the oldest of them (`frames`); a frame that
//!    detection refuses is taken again, five in a row end the measurement with the reason.
//!    Every frame looked at is kept for the page with what was found in it
//!    ([`super::snapshot`]).
//! 5. `KLIPCAL_BACKLASH_CLICK` ([`super::click`]) runs the same steps with the person's click
//!    on the nozzle's tip in each snapshot in place of steps 3's detection.
//! 4. The cycles go into the session like the guided flow's, analysed with the camera's noise
//!    floor ([`crate::calib::camera_scale::camera_params`]); KLIPCAL_BACKLASH_APPLY applies
//!    them through the same verified path.
//!
//! This file holds the operation and the measurement's steps; the webcam and its snapshots are
//! in `webcam`, reading the nozzle in the frames in `frames`.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::{key_words, next_line, result_key, start_note, Backlash, BacklashCall};
use super::{Session, State};
use super::{KIND, TITLE};
use crate::calib::backlash::BacklashParams;
use crate::calib::backlash_guide::GuideAxis;
use crate::calib::camera_scale::{self, CameraScale, Sighting};
use crate::jobs::core::table::{arg, ArgKind, ArgSpec, Args, Op, OpSpec};
use crate::jobs::core::SessionState;
use crate::jobs::user;

pub(crate) use frames::Seen;
pub(crate) use webcam::Webcam;

mod frames;
pub mod meter;
mod webcam;

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
    parse: |a| Ok(BacklashCall::Camera(CameraRequest::from_args(a)?)),
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
    /// Reads the call's arguments (KLIPCAL_BACKLASH_CAMERA's or KLIPCAL_BACKLASH_CLICK's).
    ///
    /// # Errors
    /// No or a bad axis (Z), bad cycles or carriage.
    pub(super) fn from_args(a: &Args) -> anyhow::Result<Self> {
        let axis =
            GuideAxis::parse(&a.required_text(&AXIS_ARG)?).map_err(|e| user(e.to_string()))?;
        if axis == GuideAxis::Z {
            return Err(user(
                "AXIS=Z: a camera under the nozzle cannot see Z move; measure Z with \
                 KLIPCAL_BACKLASH_START AXIS=Z (guided), or X, Y, A, B here",
            ));
        }
        Ok(Self {
            axis,
            cycles: a.count(&super::CYCLES_ARG)?,
            carriage: a.int(&super::CARRIAGE_ARG)?,
            clicks: false,
        })
    }
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
    /// Of those, refined from the pictures against the first one (the reference) …
    #[serde(default)]
    pub refined: usize,
    /// … and kept as clicked: which and why.
    #[serde(default)]
    pub kept: Vec<String>,
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
                // The detector's and the registration's sub-pixel errors repeat at the same
                // nozzle positions; clicks as clicked slip afresh.
                self.clicks == 0 || self.refined > 0,
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

impl Backlash {
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
    pub(super) async fn camera(
        &self,
        req: &CameraRequest,
    ) -> anyhow::Result<super::answers::AxisStarted> {
        let axis = req.axis;
        let cycles = req.cycles.unwrap_or(self.settings.guide.cycles);
        super::cycles_allowed(cycles)?;
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
            crate::calib::nozzle::decode_gray(&b)
                .map_err(|e| user(format!("webcam '{}': {e:#}", cam.name)))?;
        } else if let Err(r) = self.look(&http, &cam, None, None).await?.found {
            return Err(user(format!(
                "webcam '{}' shows no sure nozzle: {r}",
                cam.name
            )));
        }
        let printer = self.axis_printer(axis, req.carriage).await?;
        let note = start_note(&printer.detection);
        let (carriage, key) = (printer.carriage, printer.key.clone());
        let progress = format!("camera: measuring {}", key_words(&key));
        let id = self
            .begin_axis(super::guide::AxisStart {
                progress,
                point,
                guide: None,
                printer,
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
        Ok(super::answers::AxisStarted {
            session: id,
            state: State::Measuring.name(),
            axis: axis.name(),
            carriage,
            webcam: Some(cam),
            message: msg,
        })
    }

    /// The measurement itself (the runner's steps; run again from the start after an outage).
    async fn camera_run(&self, id: i64, run: Run, cam: &Webcam) -> anyhow::Result<()> {
        let http = self.http()?;
        self.clicks.forget(id);
        let mut m = Measure::new(id, &run, cam, http, self.settings.guide.approach_mm);
        let (scale, reference) = self.camera_scale(&mut m).await?;
        let got = self.camera_cycles(&mut m, &scale, reference).await?;
        self.camera_record(m, got).await
    }

    /// One reading of the measurement `m` at the commanded position `at` (about the camera
    /// point): the camera's sighting, or the person's click.
    async fn camera_read(
        &self,
        m: &mut Measure<'_>,
        at: [f64; 3],
        what: String,
    ) -> anyhow::Result<Seen> {
        let seen = self.camera_read_inner(m, at, what).await?;
        let mm = [at[0] - m.point[0], at[1] - m.point[1]];
        m.track.add(mm, seen.centre_px);
        Ok(seen)
    }

    async fn camera_read_inner(
        &self,
        m: &mut Measure<'_>,
        at: [f64; 3],
        what: String,
    ) -> anyhow::Result<Seen> {
        m.n += 1;
        let (k, total) = (m.n, m.total);
        if m.clicks {
            let what = format!("click {k} of {total} — {what}");
            self.progress(
                m.id,
                format!("click the nozzle's tip in the snapshot on klipcal's page ({what})"),
                None,
            )
            .await;
            self.ask_click(&m.http, m.cam, m.id, &what).await
        } else {
            let expect = m.track.expect([at[0] - m.point[0], at[1] - m.point[1]]);
            self.sight(&m.http, m.cam, (m.id, &what), &m.reg, expect)
                .await
        }
    }

    /// Step 1, scale and rotation: each axis at −0.5, 0, +0.5 mm, every one approached moving +;
    /// returns the scale and the reference (X at 0).
    async fn camera_scale(&self, m: &mut Measure<'_>) -> anyhow::Result<(CameraScale, [f64; 2])> {
        let (id, point, approach) = (m.id, m.point, m.approach);
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
                let at = ax.point_at(point, t);
                self.go(at).await?;
                let s = self
                    .camera_read(
                        m,
                        at,
                        format!("scale: {} at {t:+.1} mm", ax.name().to_uppercase()),
                    )
                    .await?;
                m.count(&s, false);
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
        m.report.axis_px_per_mm = scale.px_per_mm_along(m.axis);
        m.report.scale = Some(scale);
        m.report.reference_px = Some(reference);
        if m.clicks {
            self.clicks.point_at(id, reference);
        }
        Ok((scale, reference))
    }

    /// Step 2, the seed's cycles, read from the image.
    async fn camera_cycles(
        &self,
        m: &mut Measure<'_>,
        scale: &CameraScale,
        reference: [f64; 2],
    ) -> anyhow::Result<Vec<crate::calib::backlash::Cycle>> {
        let (id, axis, point, approach, cycles) = (m.id, m.axis, m.point, m.approach, m.cycles);
        let key = m.key.clone();
        let mut got = Vec::new();
        for c in 1..=cycles {
            self.progress(
                id,
                format!("camera: {} cycle {c}/{cycles}", key_words(&key)),
                Some((&key, &m.report)),
            )
            .await;
            self.go(axis.point_at(point, -approach)).await?;
            self.go(point).await?;
            let words = key_words(&key);
            let plus = self
                .camera_read(
                    m,
                    point,
                    format!("{words} cycle {c}/{cycles}: approached from below (moving +)"),
                )
                .await?;
            m.count(&plus, true);
            self.go(axis.point_at(point, approach)).await?;
            self.go(point).await?;
            let minus = self
                .camera_read(
                    m,
                    point,
                    format!("{words} cycle {c}/{cycles}: approached from above (moving −)"),
                )
                .await?;
            m.count(&minus, true);
            let a =
                camera_scale::approaches(scale, axis, plus.centre_px, minus.centre_px, reference);
            m.report.cycles.push(CameraCycle {
                plus_px: plus.centre_px,
                minus_px: minus.centre_px,
                plus_mm: a.plus_mm,
                minus_mm: a.minus_mm,
                backlash_mm: a.cycle.backlash_mm(),
            });
            got.push(a.cycle);
        }
        Ok(got)
    }

    /// Step 3, into the session as the guided flow's cycles, and the result on the console.
    async fn camera_record(
        &self,
        m: Measure<'_>,
        got: Vec<crate::calib::backlash::Cycle>,
    ) -> anyhow::Result<()> {
        // 3. Into the session, as the guided flow's cycles.
        let again = if m.clicks {
            "KLIPCAL_BACKLASH_CLICK"
        } else {
            "KLIPCAL_BACKLASH_CAMERA"
        };
        let s = {
            let _g = self.core.lock().await;
            let mut s: Session = self.core.load(m.id)?;
            if s.state != State::Measuring {
                return Ok(()); // cancelled meanwhile
            }
            s.cycles.insert(m.key.clone(), got);
            s.camera.insert(m.key.clone(), m.report);
            s.carriage = None;
            s.state = State::Measured;
            s.progress = format!(
                "{} measured from the camera{}; {}",
                key_words(&m.key),
                if m.clicks { " by your clicks" } else { "" },
                next_line(&s.detection, again)
            );
            self.core.save(m.id, &s)?;
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

/// One camera measurement under way: where and what it reads, how many readings it has taken
/// of how many, and its report.
struct Measure<'a> {
    id: i64,
    axis: GuideAxis,
    cycles: usize,
    point: [f64; 3],
    approach: f64,
    clicks: bool,
    key: String,
    cam: &'a Webcam,
    http: reqwest::Client,
    /// Every frame of this measurement read against its first.
    reg: frames::Registration,
    /// The readings so far at their commanded positions: where the next one is expected.
    track: meter::Track,
    n: usize,
    total: usize,
    report: CameraReport,
}

impl<'a> Measure<'a> {
    fn new(id: i64, run: &Run, cam: &'a Webcam, http: reqwest::Client, approach: f64) -> Self {
        Measure {
            id,
            axis: run.axis,
            cycles: run.cycles,
            point: run.point,
            approach,
            clicks: run.clicks,
            key: result_key(run.axis, run.carriage),
            cam,
            http,
            reg: Default::default(),
            track: meter::Track::default(),
            n: 0,
            total: 6 + 2 * run.cycles,
            report: CameraReport {
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
                refined: 0,
                kept: Vec::new(),
            },
        }
    }

    /// A reading counted in the report. The cycles' readings set the statistics' noise floor;
    /// the scale's readings enter through the scale's uncertainty (a click on the
    /// whole-picture zoom of the scale moves is twice as coarse as one on the cycles' zoom).
    fn count(&mut self, s: &Seen, cycle: bool) {
        let r = &mut self.report;
        r.clicks += usize::from(self.clicks);
        r.refined += usize::from(s.refined);
        r.kept.extend(s.kept.clone());
        r.frames += s.frames;
        r.refused_frames += s.refused;
        r.last_px = Some(s.centre_px);
        if cycle {
            r.detection_sd_px = r.detection_sd_px.max(s.uncertainty_px);
        }
    }
}
