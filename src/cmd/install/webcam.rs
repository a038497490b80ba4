//! klipcal's page as an iframe "webcam" of Moonraker (`server.webcams.*`), so Mainsail ("HTML
//! Iframe") and Fluidd ("HTTP page") show it in their webcam panels — on a phone the
//! way to the readings form, where Mainsail's dashboard has no console. [`decide`] is pure;
//! [`list`], [`register`] and [`remove`] talk to Moonraker's HTTP API;
//! [`webcam_plan`] decides, asking on a terminal, what install does about it.

use std::io::IsTerminal;

use serde_json::json;

use super::host::ask;
use super::manifest::Manifest;
use super::InstallArgs;
use crate::config::Config;
use crate::moonraker::answers::WebcamList;
use crate::moonraker::Files;

/// The webcam's name in Moonraker, Mainsail and Fluidd.
pub(crate) const NAME: &str = crate::jobs::core::session::PAGE_WEBCAM;
/// Moonraker's service for a web page in a frame.
pub(crate) const SERVICE: &str = "iframe";
/// Portrait: the page is a form and plots, read on a phone.
pub(crate) const ASPECT_RATIO: &str = "3:4";

/// What install does about the webcam.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Decision {
    /// klipcal's webcam is there with this URL.
    Nothing { uid: String },
    /// No webcam of that name: add one.
    Add,
    /// klipcal's own webcam (by the uid install recorded) names another address: update it.
    Update { uid: String, from: String },
    /// A webcam of that name that install did not make (the user's, or from moonraker.conf):
    /// left alone.
    Foreign { url: String },
}

/// Decides from Moonraker's `server.webcams.list` answer, the uid the last install recorded
/// and the page's URL.
pub(crate) fn decide(list: &WebcamList, ours: Option<&str>, url: &str) -> Decision {
    let cams = &list.webcams;
    if let Some(c) = ours.and_then(|u| cams.iter().find(|c| c.uid == u)) {
        if c.stream_url == url && c.service == SERVICE {
            return Decision::Nothing { uid: c.uid.clone() };
        }
        return Decision::Update {
            uid: c.uid.clone(),
            from: c.stream_url.clone(),
        };
    }
    match cams.iter().find(|c| c.name == NAME) {
        Some(c) => Decision::Foreign {
            url: c.stream_url.clone(),
        },
        None => Decision::Add,
    }
}

/// Moonraker's webcams.
///
/// # Errors
/// Moonraker did not answer or refused, or its answer is malformed (the message names what).
pub(crate) async fn list(files: &Files) -> anyhow::Result<WebcamList> {
    Ok(WebcamList::parse(files.get("/server/webcams/list").await?)?)
}

/// Adds klipcal's webcam (or updates the one with `uid`) with the page's `url`; returns its uid.
///
/// # Errors
/// Moonraker refused (the message says why).
pub(crate) async fn register(
    files: &Files,
    uid: Option<&str>,
    url: &str,
) -> anyhow::Result<String> {
    let mut body = json!({
        "name": NAME,
        "service": SERVICE,
        "stream_url": url,
        "snapshot_url": "",
        "aspect_ratio": ASPECT_RATIO,
        "icon": "mdiWebBox",
        "location": "printer",
        "enabled": true,
    });
    if let Some(u) = uid {
        body["uid"] = json!(u);
    }
    let answer = files.post("/server/webcams/item", &body).await?;
    answer["webcam"]["uid"]
        .as_str()
        .map(str::to_string)
        .ok_or_else(|| anyhow::anyhow!("Moonraker's answer names no webcam uid: {answer}"))
}

/// Removes the webcam with `uid`; `Ok(false)` when it is gone already.
///
/// # Errors
/// Moonraker did not answer or refused.
pub(crate) async fn remove(files: &Files, uid: &str) -> anyhow::Result<bool> {
    let cams = list(files).await?;
    let present = cams.webcams.iter().any(|c| c.uid == uid);
    if !present {
        return Ok(false);
    }
    files
        .delete_api(&format!("/server/webcams/item?uid={uid}"))
        .await?;
    Ok(true)
}

/// A webcam install adds or updates.
pub(super) struct WebcamChange {
    /// The webcam to update (klipcal's own, from an earlier install); `None` adds one.
    pub(super) uid: Option<String>,
    pub(super) url: String,
    /// The address it had.
    pub(super) from: Option<String>,
}

impl WebcamChange {
    pub(super) fn describe(&self) -> String {
        match &self.from {
            None => format!(
                "add Moonraker webcam {} (service {}): {}",
                NAME, SERVICE, self.url
            ),
            Some(from) => format!("update Moonraker webcam {}: {from} -> {}", NAME, self.url),
        }
    }

    pub(super) fn done(&self) -> String {
        format!(
            "webcam   {} {} in Moonraker: klipcal's page {} shows in Mainsail (\"HTML Iframe\") \
             and Fluidd's webcam panels",
            NAME,
            if self.from.is_some() {
                "updated"
            } else {
                "added"
            },
            self.url
        )
    }
}

/// Whether install adds (or updates) klipcal's page as an iframe webcam: asked on a terminal,
/// `--webcam`/`--yes` add it, `--no-webcam` skips it; needs Moonraker and the page on.
pub(super) async fn webcam_plan(
    a: &InstallArgs,
    moonraker: Option<&crate::moonraker::Files>,
    manifest: &Manifest,
    settings: Option<&str>,
) -> Option<WebcamChange> {
    if a.no_webcam {
        return None;
    }
    let files = moonraker?;
    let Some(c) = settings.and_then(|t| Config::parse(t).ok()) else {
        println!("note: klipcal.toml does not read; no webcam for klipcal's page");
        return None;
    };
    if !c.http.enabled {
        println!("note: klipcal's page is off ([http] enabled = false); no webcam for it");
        return None;
    }
    let Ok(bind) = c.http.bind.parse::<std::net::SocketAddr>() else {
        return None;
    };
    let url = crate::http::page_address_here(bind);
    if !url.starts_with("http://") || url.contains(' ') {
        println!(
            "note: klipcal's page is at {url}, which a browser elsewhere cannot open; no webcam \
             for it"
        );
        return None;
    }
    let list = match list(files).await {
        Ok(l) => l,
        Err(e) => {
            println!("note: Moonraker's webcam list did not answer ({e:#}); no webcam added");
            return None;
        }
    };
    match decide(&list, manifest.webcam.as_deref(), &url) {
        Decision::Nothing { .. } => None,
        Decision::Foreign { url: theirs } => {
            println!(
                "note: Moonraker has a webcam named {} already ({theirs}) that klipcal did not \
                 add: left as it is",
                NAME
            );
            None
        }
        Decision::Update { uid, from } => Some(WebcamChange {
            uid: Some(uid),
            url,
            from: Some(from),
        }),
        Decision::Add => {
            let add = if a.webcam || a.yes || a.dry_run {
                true
            } else if std::io::stdin().is_terminal() {
                ask(&format!(
                    "Show klipcal's page ({url}) inside Mainsail and Fluidd, as the iframe webcam \
                     \"{}\"?",
                    NAME
                ))
            } else {
                println!(
                    "note: klipcal's page ({url}) can show inside Mainsail and Fluidd as an \
                     iframe webcam: run with --webcam to add it"
                );
                false
            };
            add.then_some(WebcamChange {
                uid: None,
                url,
                from: None,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::Value;

    fn cams(list: &[(&str, &str, &str, &str)]) -> WebcamList {
        parse(
            json!({"webcams": list.iter().map(|(name, uid, service, url)| json!({
            "name": name, "uid": uid, "service": service, "stream_url": url,
        })).collect::<Vec<_>>()}),
        )
    }

    fn parse(v: Value) -> WebcamList {
        WebcamList::parse(v).unwrap()
    }

    #[test]
    fn install_adds_updates_or_leaves_a_webcam_it_did_not_make() {
        let url = "http://192.168.1.23:7150/";
        assert_eq!(
            decide(&parse(json!({"webcams": []})), None, url),
            Decision::Add
        );
        assert_eq!(
            decide(
                &cams(&[("Front", "u1", "mjpegstreamer", "/webcam/")]),
                None,
                url
            ),
            Decision::Add
        );
        let ours = cams(&[("klipcal", "u2", "iframe", url)]);
        assert_eq!(
            decide(&ours, Some("u2"), url),
            Decision::Nothing { uid: "u2".into() }
        );
        assert_eq!(
            decide(&ours, Some("u2"), "http://10.0.0.5:7150/"),
            Decision::Update {
                uid: "u2".into(),
                from: url.into()
            }
        );
        // A "klipcal" webcam install did not make (no uid recorded, or another one) is the
        // user's: never overwritten.
        assert_eq!(
            decide(&ours, None, url),
            Decision::Foreign { url: url.into() }
        );
        assert_eq!(
            decide(&ours, Some("gone"), url),
            Decision::Foreign { url: url.into() }
        );
        // Ours deleted by the user since: offered again.
        assert_eq!(
            decide(&parse(json!({"webcams": []})), Some("u2"), url),
            Decision::Add
        );
        // Moonraker's answer without a list: nothing to find.
        assert_eq!(decide(&parse(json!({})), Some("u2"), url), Decision::Add);
    }
}
