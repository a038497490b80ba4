//! The nozzle camera: which of Moonraker's webcams, its snapshot URL, and one snapshot's bytes.

use std::time::Duration;

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::super::Backlash;
use crate::jobs::user;
use crate::moonraker::answers::{WebcamEntry, WebcamList};

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

impl Backlash {
    pub(in crate::jobs::backlash) fn http(&self) -> anyhow::Result<reqwest::Client> {
        reqwest::Client::builder()
            .timeout(Duration::from_secs(10))
            .build()
            .context("building the camera's HTTP client")
    }

    /// The nozzle camera from Moonraker's list.
    pub(in crate::jobs::backlash) async fn webcam(&self) -> anyhow::Result<Webcam> {
        let list = self
            .core
            .m()
            .webcams()
            .await
            .context("asking Moonraker for its webcams")?;
        choose_webcam(&list, self.settings.webcam.trim(), self.core.files().base()).map_err(user)
    }

    /// One snapshot's bytes.
    pub(in crate::jobs::backlash) async fn fetch(
        &self,
        http: &reqwest::Client,
        cam: &Webcam,
    ) -> anyhow::Result<Vec<u8>> {
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::{json, Value};

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
}
