//! `klipcal bench camera`: the bench's nozzle camera (issue 27), an HTTP snapshot server like
//! the ones printers run (ustreamer / camera-streamer: `/?action=snapshot` and `/snapshot`
//! answer a JPEG). Each snapshot draws the nozzle where the bench's simulated mechanics put it
//! (`[klipcal_backlash_sim]`'s state file: klippy's toolhead with the lost motion of its play
//! included) through [`crate::cmd::camera_render`], at the camera's scale, rotation, mirror and
//! offset; lighting, defocus, noise and JPEG quality are drawn once per camera from its seed,
//! the sensor noise afresh for every frame. After each move the nozzle rings for a moment
//! (a damped oscillation along the move), so a reader must wait until the picture is still.
//!
//! With `"photo"` (issue 37, item 5) the frames are a real photograph instead of the renderer's
//! nozzle: one of `tests/fixtures/nozzle`'s hand-labelled photos moved so that its tip is
//! where the simulated nozzle is, through [`crate::cmd::photo_camera`] (the camera's rotation
//! turns it, `zoom` magnifies it, lighting, noise and JPEG 70–90 drawn from the seed), cropped
//! so that its edges never show while the nozzle stays within `reach_mm` of `centre_mm`.
//! Tests and the bench only; not in the printer's build.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use anyhow::Context;
use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde::Deserialize;
use serde_json::Value;

use crate::cmd::camera_render::{self, Family, Scene};
use crate::cmd::photo_camera::{self, Lighting, PhotoCamera, Placement};

/// The camera as the bench configures it (`bench.py start --camera JSON`).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub(crate) struct CameraSpec {
    /// ring (the default), dark_tip, or a picture detection must refuse: empty, two_nozzles,
    /// saturated, flat. Not with `photo`.
    pub look: Option<String>,
    /// A real photo instead of the renderer: a picture of tests/fixtures/nozzle/manifest.json
    /// (`ktamv-frame`) or a source file (`tamv-nozzle.jpg`), with a hand-labelled tip.
    pub photo: Option<String>,
    /// The photo's magnification (0: the least that keeps its edges out of the frame).
    pub zoom: f64,
    /// How far the nozzle may go from `centre_mm` in X and Y with the photo's edges still out
    /// of the frame, mm.
    pub reach_mm: f64,
    /// Snapshot size, px.
    pub width: usize,
    pub height: usize,
    /// Scale, px per mm.
    pub px_per_mm: f64,
    /// The machine X axis's angle in the image (y down), degrees.
    pub rotation_deg: f64,
    /// Mirrored (a camera looking up at the nozzle).
    pub mirror: bool,
    /// The machine X, Y (mm) seen at the image centre plus `offset_px`.
    pub centre_mm: [f64; 2],
    /// Where `centre_mm` falls from the image centre, px.
    pub offset_px: [f64; 2],
    /// Nozzle radius, px (0: 0.35 mm at the scale).
    pub radius_px: f64,
    /// Seed of the lighting, defocus, noise and JPEG quality.
    pub seed: u64,
    /// Ringing after a move: initial amplitude along the move, mm.
    pub ring_mm: f64,
    /// … its decay time, s.
    pub ring_tau_s: f64,
    /// Every n-th snapshot is a dropped, blank frame (0: none), as a camera hiccups.
    pub drop_every: u64,
}

impl Default for CameraSpec {
    fn default() -> Self {
        CameraSpec {
            look: None,
            photo: None,
            zoom: 0.0,
            reach_mm: 0.75,
            width: 640,
            height: 480,
            px_per_mm: 80.0,
            rotation_deg: 0.0,
            mirror: true,
            centre_mm: [100.0, 100.0],
            offset_px: [0.0, 0.0],
            radius_px: 0.0,
            seed: 1,
            ring_mm: 0.01,
            ring_tau_s: 0.12,
            drop_every: 0,
        }
    }
}

impl CameraSpec {
    /// Reads and checks the bench's JSON.
    ///
    /// # Errors
    /// Not a JSON object of the fields above, an unknown look, or numbers out of range.
    pub(crate) fn parse(text: &str) -> anyhow::Result<CameraSpec> {
        let s: CameraSpec = serde_json::from_str(text)
            .with_context(|| format!("--spec {text:?}: expected a JSON object of camera fields"))?;
        s.family()?;
        anyhow::ensure!(
            (64..=4096).contains(&s.width) && (64..=4096).contains(&s.height),
            "width/height {}×{}: expected 64..4096 px",
            s.width,
            s.height
        );
        anyhow::ensure!(
            s.px_per_mm.is_finite() && (5.0..=1000.0).contains(&s.px_per_mm),
            "px_per_mm {}: expected 5..1000",
            s.px_per_mm
        );
        if let Some(p) = &s.photo {
            anyhow::ensure!(
                s.look.is_none() && s.radius_px == 0.0,
                "photo {p:?}: look and radius_px draw the renderer's nozzle; leave them out with \
                 a photo"
            );
        }
        anyhow::ensure!(
            s.zoom == 0.0 || (s.zoom.is_finite() && (1.0..=16.0).contains(&s.zoom)),
            "zoom {}: expected 1..16 (0: the least that hides the photo's edges)",
            s.zoom
        );
        anyhow::ensure!(
            s.reach_mm.is_finite() && (0.0..=20.0).contains(&s.reach_mm),
            "reach_mm {}: expected 0..20",
            s.reach_mm
        );
        anyhow::ensure!(
            [s.rotation_deg, s.ring_mm, s.ring_tau_s, s.radius_px]
                .iter()
                .chain(s.centre_mm.iter())
                .chain(s.offset_px.iter())
                .all(|v| v.is_finite())
                && s.ring_mm >= 0.0
                && s.ring_tau_s > 0.0
                && s.radius_px >= 0.0,
            "camera numbers must be finite (ring_mm, radius_px ≥ 0, ring_tau_s > 0)"
        );
        Ok(s)
    }

    fn family(&self) -> anyhow::Result<Family> {
        Ok(match self.look.as_deref().unwrap_or("ring") {
            "ring" => Family::Ring,
            "dark_tip" => Family::DarkTip,
            "empty" => Family::Empty,
            "two_nozzles" => Family::TwoNozzles,
            "saturated" => Family::Saturated,
            "flat" => Family::Flat,
            other => anyhow::bail!(
                "look {other:?}: expected ring, dark_tip, empty, two_nozzles, saturated or flat"
            ),
        })
    }

    /// image ← machine displacement, px: columns X and Y.
    fn matrix(&self) -> [[f64; 2]; 2] {
        let (s, th) = (self.px_per_mm, self.rotation_deg.to_radians());
        let m = if self.mirror { -1.0 } else { 1.0 };
        let (c, si) = (th.cos(), th.sin());
        [[s * c, s * si], [-m * s * si, m * s * c]]
    }

    pub(crate) fn origin_px(&self) -> [f64; 2] {
        [
            self.width as f64 / 2.0 + self.offset_px[0],
            self.height as f64 / 2.0 + self.offset_px[1],
        ]
    }

    /// Where the nozzle at machine (x, y) mm is drawn, px.
    pub(crate) fn to_px(&self, xy: [f64; 2]) -> [f64; 2] {
        let a = self.matrix();
        let o = self.origin_px();
        let (dx, dy) = (xy[0] - self.centre_mm[0], xy[1] - self.centre_mm[1]);
        [
            o[0] + a[0][0] * dx + a[1][0] * dy,
            o[1] + a[0][1] * dx + a[1][1] * dy,
        ]
    }
}

/// The simulated nozzle as the state file tells it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Truth {
    xy: [f64; 2],
    moves: u64,
    /// When the simulation wrote it (after a move).
    written: SystemTime,
}

fn read_truth(path: &std::path::Path) -> anyhow::Result<Truth> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the simulated nozzle from {}", path.display()))?;
    let written = std::fs::metadata(path)
        .and_then(|m| m.modified())
        .unwrap_or_else(|_| SystemTime::now());
    let v: Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let n = &v["nozzle"];
    let xy = [n[0].as_f64(), n[1].as_f64()];
    let [Some(x), Some(y)] = xy else {
        anyhow::bail!("{}: no nozzle [x, y, z] in {v}", path.display());
    };
    Ok(Truth {
        xy: [x, y],
        moves: v["moves"].as_u64().unwrap_or(0),
        written,
    })
}

/// What the camera shows: the renderer's nozzle, or a real photo.
enum Content {
    Render(Scene),
    Photo(PhotoCamera),
}

/// The camera on the spec's photo, laid as the spec says; None without one.
///
/// # Errors
/// An unknown or unlabelled photo, or a zoom that would show its edges.
pub(crate) fn photo_camera(
    spec: &CameraSpec,
    rng: &mut fastrand::Rng,
) -> anyhow::Result<Option<PhotoCamera>> {
    let Some(name) = &spec.photo else {
        return Ok(None);
    };
    let photo = photo_camera::photo(&crate::cmd::nozzle_fixture, name)?;
    let at = Placement {
        width: spec.width,
        height: spec.height,
        rotation_deg: spec.rotation_deg,
        home_px: spec.origin_px(),
        reach_px: spec.reach_mm * spec.px_per_mm,
        zoom: (spec.zoom > 0.0).then_some(spec.zoom),
    };
    Ok(Some(PhotoCamera::new(&photo, &at, Lighting::draw(rng))?))
}

struct Cam {
    spec: CameraSpec,
    state_file: PathBuf,
    content: Content,
    rng: fastrand::Rng,
    last: Option<Truth>,
    /// The last move: when it was made, and its unit direction in mm.
    ring: Option<(SystemTime, [f64; 2])>,
    frames: u64,
}

impl Cam {
    fn new(spec: CameraSpec, state_file: PathBuf) -> anyhow::Result<Cam> {
        let mut rng = fastrand::Rng::with_seed(spec.seed);
        let content = match photo_camera(&spec, &mut rng)? {
            Some(p) => Content::Photo(p),
            None => {
                let radius = if spec.radius_px > 0.0 {
                    spec.radius_px
                } else {
                    0.35 * spec.px_per_mm
                };
                Content::Render(camera_render::varied_scene(
                    spec.family()?,
                    spec.width,
                    spec.height,
                    spec.origin_px(),
                    radius,
                    &mut rng,
                ))
            }
        };
        Ok(Cam {
            spec,
            state_file,
            content,
            rng,
            last: None,
            ring: None,
            frames: 0,
        })
    }

    /// One snapshot, JPEG.
    fn snapshot(&mut self) -> anyhow::Result<Vec<u8>> {
        let t = read_truth(&self.state_file)?;
        let now = SystemTime::now();
        if let Some(last) = self.last {
            if last.moves != t.moves {
                let d = [t.xy[0] - last.xy[0], t.xy[1] - last.xy[1]];
                let n = d[0].hypot(d[1]);
                let dir = if n > 0.0 {
                    [d[0] / n, d[1] / n]
                } else {
                    [1.0, 0.0]
                };
                // It rings from the moment the move was made, not when a frame is asked for.
                self.ring = Some((t.written, dir));
            }
        }
        self.last = Some(t);
        let mut xy = t.xy;
        if let Some((t0, dir)) = self.ring {
            let dt = now.duration_since(t0).unwrap_or_default().as_secs_f64();
            let a = self.spec.ring_mm
                * (-dt / self.spec.ring_tau_s).exp()
                * (std::f64::consts::TAU * 15.0 * dt).cos();
            xy = [xy[0] + a * dir[0], xy[1] + a * dir[1]];
        }
        self.frames += 1;
        let dropped = self.spec.drop_every > 0 && self.frames % self.spec.drop_every == 0;
        let mut scene = match &self.content {
            Content::Photo(p) if dropped => return Ok(p.blank(&mut self.rng)?.1),
            Content::Photo(p) => return Ok(p.frame(self.spec.to_px(xy), &mut self.rng)?.1),
            Content::Render(s) => s.clone(),
        };
        if dropped {
            scene.nozzles_px.clear();
            scene.gradient = [0.0, 0.0];
            scene.vignette = 0.0;
        } else if !scene.nozzles_px.is_empty() {
            // The nozzle (the first one; a second nozzle keeps its distance from it).
            let p = self.spec.to_px(xy);
            let d = [p[0] - scene.nozzles_px[0][0], p[1] - scene.nozzles_px[0][1]];
            for c in &mut scene.nozzles_px {
                c[0] += d[0];
                c[1] += d[1];
            }
        }
        let (grey, jpeg) = scene.render(&mut self.rng)?;
        match jpeg {
            Some(j) => Ok(j),
            None => camera_render::encode_jpeg(&grey, scene.width, scene.height, 90),
        }
    }
}

type Shared = Arc<Mutex<Cam>>;

#[derive(Deserialize)]
struct ActionQuery {
    action: Option<String>,
}

async fn root(State(cam): State<Shared>, Query(q): Query<ActionQuery>) -> Response {
    match q.action.as_deref() {
        Some("snapshot") => snapshot(State(cam)).await,
        other => (
            StatusCode::NOT_FOUND,
            format!("action {other:?}: this bench camera serves ?action=snapshot only"),
        )
            .into_response(),
    }
}

async fn snapshot(State(cam): State<Shared>) -> Response {
    let got = tokio::task::spawn_blocking(move || {
        let mut c = cam
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        c.snapshot()
    })
    .await;
    match got {
        Ok(Ok(jpeg)) => ([(header::CONTENT_TYPE, "image/jpeg")], jpeg).into_response(),
        Ok(Err(e)) => (StatusCode::SERVICE_UNAVAILABLE, format!("{e:#}")).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// Serves the camera until killed.
///
/// # Errors
/// A bad spec, or the port cannot be bound.
pub(crate) async fn serve(
    args: &crate::cli::BenchCameraArgs,
) -> anyhow::Result<std::process::ExitCode> {
    let spec = CameraSpec::parse(&args.spec)?;
    let cam = Cam::new(spec, args.state_file.clone())?;
    let shared: Shared = Arc::new(Mutex::new(cam));
    let app = axum::Router::new()
        .route("/", get(root))
        .route("/snapshot", get(snapshot))
        .with_state(shared);
    let addr = SocketAddr::from(([127, 0, 0, 1], args.port));
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("binding the bench camera to {addr}"))?;
    eprintln!("bench camera on http://{addr}/?action=snapshot");
    axum::serve(listener, app).await?;
    Ok(std::process::ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::nozzle::{detect, DetectParams, Gray};

    #[test]
    fn a_snapshot_shows_the_simulated_nozzle_where_the_camera_maps_it() {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("nozzle_true.json");
        std::fs::write(&state, r#"{"nozzle": [100.2, 99.9, 5.0], "moves": 3}"#).unwrap();
        let spec = CameraSpec::parse(
            r#"{"look": "dark_tip", "rotation_deg": 30, "px_per_mm": 80, "seed": 4}"#,
        )
        .unwrap();
        let want = spec.to_px([100.2, 99.9]);
        let mut cam = Cam::new(spec, state.clone()).unwrap();
        let jpeg = cam.snapshot().unwrap();
        let (w, h, g) = camera_render::decode_gray(&jpeg).unwrap();
        let d = detect(
            &Gray {
                width: w,
                height: h,
                data: &g,
            },
            &DetectParams::default(),
        )
        .unwrap();
        assert!(
            (d.centre_px[0] - want[0]).hypot(d.centre_px[1] - want[1]) < 0.3,
            "{:?} vs {want:?}",
            d.centre_px
        );
        // +0.2 mm X at 30°: (+13.86, +8.00) px; −0.1 mm Y, mirrored (Y at 30° − 90°):
        // (−4.00, +6.93) px.
        assert!(
            (want[0] - 320.0 - 9.856).abs() < 0.01 && (want[1] - 240.0 - 14.928).abs() < 0.01,
            "{want:?}"
        );
        // A move rings: the next frame is displaced along the move, then settles.
        std::fs::write(&state, r#"{"nozzle": [100.3, 99.9, 5.0], "moves": 4}"#).unwrap();
        let _ = cam.snapshot().unwrap();
        assert!(cam.ring.is_some());
    }

    #[test]
    fn bad_specs_are_refused_by_name() {
        for (text, want) in [
            (r#"{"look": "square"}"#, "square"),
            (r#"{"px_per_mm": 0}"#, "px_per_mm"),
            (r#"{"zoom": 0.5}"#, "zoom"),
            (r#"{"magnify": 2}"#, "magnify"),
            (
                r#"{"photo": "tamv-nozzle", "look": "ring"}"#,
                "leave them out",
            ),
            (r#"{"reach_mm": -1}"#, "reach_mm"),
            ("[1]", "JSON object"),
        ] {
            let e = format!("{:#}", CameraSpec::parse(text).unwrap_err());
            assert!(e.contains(want), "{text}: {e}");
        }
        let dir = tempfile::tempdir().unwrap();
        for (text, want) in [
            (r#"{"photo": "nozzle.png"}"#, "ktamv-frame"),
            (r#"{"photo": "tamv-test-card"}"#, "hand-labelled"),
            (r#"{"photo": "ktamv-frame", "zoom": 1}"#, "is needed"),
        ] {
            let spec = CameraSpec::parse(text).unwrap();
            let e = Cam::new(spec, dir.path().join("s.json")).err().unwrap();
            assert!(format!("{e:#}").contains(want), "{text}: {e:#}");
        }
    }

    /// With a photo, a snapshot is that photo moved to where the camera maps the simulated
    /// nozzle (lit, noisy, JPEG), not the renderer's nozzle, and a move moves it.
    #[test]
    fn a_photo_snapshot_is_the_photo_moved_to_the_simulated_nozzle() {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("nozzle_true.json");
        std::fs::write(&state, r#"{"nozzle": [100.3, 99.8, 5.0], "moves": 3}"#).unwrap();
        let text = r#"{"photo": "tamv-nozzle.jpg", "width": 400, "height": 300,
            "rotation_deg": 10, "px_per_mm": 80, "seed": 3}"#;
        let spec = CameraSpec::parse(text).unwrap();
        let want = spec.to_px([100.3, 99.8]);
        let home = spec.to_px([100.0, 100.0]);
        let mut cam = Cam::new(spec.clone(), state.clone()).unwrap();
        let (w, h, g) = camera_render::decode_gray(&cam.snapshot().unwrap()).unwrap();
        assert_eq!((w, h), (400, 300));
        let pc = photo_camera(&spec, &mut fastrand::Rng::with_seed(3))
            .unwrap()
            .unwrap();
        let there = klipcal_core::photo_camera::ncc(&pc.clean(want), &g);
        let at_home = klipcal_core::photo_camera::ncc(&pc.clean(home), &g);
        assert!(there > 0.97 && at_home < 0.9, "{there} {at_home}");
    }
}
