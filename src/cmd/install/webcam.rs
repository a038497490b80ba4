//! klipcal's page as an iframe "webcam" of Moonraker (`server.webcams.*`), so Mainsail ("HTML
//! Iframe") and Fluidd ("HTTP page") show it in their webcam panels — on a phone the
//! way to the readings form, where Mainsail's dashboard has no console. [`decide`] is pure;
//! [`list`], [`register`] and [`remove`] talk to Moonraker's HTTP API.

use serde_json::json;

use crate::moonraker::answers::WebcamList;
use crate::moonraker::Files;

/// The webcam's name in Moonraker, Mainsail and Fluidd.
pub(crate) const NAME: &str = "klipcal";
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
