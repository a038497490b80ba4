//! The page's backlash section: the results, the camera's last frame (with the detector's
//! mark, or waiting for a click) and each axis's cycles read through the camera.

use std::fmt::Write as _;

use serde_json::Value;

use super::{esc, text};

pub(super) fn backlash_section(h: &mut String, s: &Value) {
    h.push_str("<section id=\"backlash\"><h2>Backlash</h2>");
    if let Some(axis) = s["axis"].as_str() {
        let _ = write!(
            h,
            "<p>measuring {} — cycle {}: jog with the buttons below while watching the nozzle \
             (the same as the dialog's, or _KLIPCAL_BACKLASH_JOG)</p>",
            esc(axis),
            text(&s["cycle"])
        );
        jog_panel(h, s);
    }
    if s["snapshot"].is_object() {
        snapshot_figure(h, s);
    }
    if let Some(reports) = s["camera"].as_object() {
        for (key, rep) in reports {
            camera_cycles(h, key, rep, &s["results"][key.as_str()]);
        }
    }
    if let Some(results) = s["results"].as_object().filter(|r| !r.is_empty()) {
        // Six narrow columns, the ± beside its value and headers that break: the table fits
        // a phone's 366 px (issue 40: seven columns were 462 px wide there).
        h.push_str(
            "<div class=\"scroll\"><table><tr><th>axis</th><th>backlash mm</th>\
             <th>spread mm</th><th>cycles</th><th>compen&shy;sate</th><th>smooth time s</th></tr>",
        );
        for (axis, r) in results {
            let f = |k: &str, d: usize| {
                r[k].as_f64()
                    .map(|v| format!("{v:.d$}"))
                    .unwrap_or_default()
            };
            let _ =
                write!(
                h,
                "<tr><td>{}</td><td>{} ± {}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                esc(axis),
                f("backlash_mm", 3),
                f("uncertainty_mm", 3),
                f("spread_mm", 3),
                text(&r["cycles"]),
                if r["compensate"] == Value::Bool(true) { "yes" } else { "no" },
                f("smooth_time_s", 4)
            );
        }
        h.push_str("</table></div>");
        if s["state"] == "measured" {
            h.push_str(
                "<p class=\"row\"><button data-op=\"backlash/apply\" data-confirm=\"Set the measured \
                 backlash compensation and write it to the config (Klipper restarts)?\">Apply</button></p>",
            );
        }
    }
    h.push_str("</section>");
}

/// The guided measurement's jog buttons beside the camera's live picture (issue 40 item 2: on
/// a phone the dialog is full screen over the camera). Each button posts `backlash/jog` with
/// its press, the operation the dialog's button runs; the page reloads with the next buttons.
fn jog_panel(h: &mut String, s: &Value) {
    let Some(buttons) = s["jog"].as_array().filter(|b| !b.is_empty()) else {
        return;
    };
    h.push_str(
        "<div id=\"jog\"><figure class=\"live\"><img id=\"live\" src=\"/api/backlash/live.jpg\" \
         alt=\"the nozzle camera, live (no picture: [backlash] webcam names none that answers)\">\
         </figure><div class=\"jogs\">",
    );
    for b in buttons {
        let class = match b["style"].as_str() {
            Some("secondary") => " class=\"quiet\"",
            Some("warning") => " class=\"danger\"",
            _ => "",
        };
        let _ = write!(
            h,
            "<form class=\"inline\"><input type=\"hidden\" name=\"press\" value=\"{}\">\
             <button{class} data-op=\"backlash/jog\" data-out=\"jogmsg\">{}</button></form>",
            text(&b["press"]),
            text(&b["label"])
        );
    }
    h.push_str("</div><p id=\"jogmsg\" class=\"msg\"></p></div>");
}

/// A number of px with 2 decimals.
fn px(v: &Value) -> String {
    v.as_f64().map(|x| format!("{x:.2}")).unwrap_or_default()
}

/// The caption of a camera frame: where it was taken, and what detection found (the script
/// builds the same words when a newer frame comes).
fn snapshot_caption(f: &Value) -> String {
    match f["refused"].as_str() {
        Some(why) => format!("{}: no reading, {why}", text(&f["what"])),
        None if f["centre_px"].is_array() => format!(
            "{}: nozzle at ({}, {}) px ± {} px",
            text(&f["what"]),
            px(&f["centre_px"][0]),
            px(&f["centre_px"][1]),
            px(&f["uncertainty_px"])
        ),
        None => text(&f["what"]),
    }
}

/// The newest camera frame (served by klipcal itself, `/api/backlash/snapshot.jpg`) with the
/// nozzle marked where the detector found it, and every cycle's approach positions. Pixel
/// centres are at integers in the detector's frame; the SVG's pixel i spans [i, i + 1], so a
/// mark is drawn at the centre + ½.
fn snapshot_figure(h: &mut String, s: &Value) {
    let f = &s["snapshot"];
    let (w, hh) = (
        f["width"].as_u64().unwrap_or(640),
        f["height"].as_u64().unwrap_or(480),
    );
    let seq = text(&f["seq"]);
    let click = f["click"] == Value::Bool(true);
    let hint = match (f["hint_px"][0].as_f64(), f["hint_px"][1].as_f64()) {
        (Some(x), Some(y)) => format!(
            " data-hint=\"{x:.3},{y:.3}\" data-zoom=\"{}\"",
            f["zoom"].as_f64().unwrap_or(4.0)
        ),
        _ => String::new(),
    };
    if click {
        let _ = write!(
            h,
            "<p class=\"msg ok\" id=\"clickhelp\"><b>Click the nozzle's tip</b> in the picture \
             below{}. <button class=\"quiet\" id=\"wholepic\">Whole picture</button></p>",
            if hint.is_empty() {
                ": a first click zooms in there, a second one marks the tip"
            } else {
                " (zoomed in where you clicked last)"
            }
        );
    }
    let _ = write!(
        h,
        "<figure id=\"snapshot\" data-seq=\"{seq}\" data-click=\"{}\"{hint}><div class=\"snap\">\
         <div class=\"stage\"><img id=\"snapimg\" src=\"/api/backlash/snapshot.jpg?seq={seq}\" \
         width=\"{w}\" height=\"{hh}\" alt=\"the nozzle camera's newest frame\">\
         <svg id=\"snapmarks\" viewBox=\"0 0 {w} {hh}\" preserveAspectRatio=\"none\" aria-hidden=\"true\">",
        u8::from(click)
    );
    let at = |p: &Value| {
        p[0].as_f64()
            .zip(p[1].as_f64())
            .map(|(x, y)| (x + 0.5, y + 0.5))
    };
    for rep in s["camera"].as_object().into_iter().flat_map(|o| o.values()) {
        for c in rep["cycles"].as_array().into_iter().flatten() {
            for (k, class) in [("plus_px", "plus"), ("minus_px", "minus")] {
                if let Some((x, y)) = at(&c[k]) {
                    let _ = write!(
                        h,
                        "<circle class=\"approach {class}\" cx=\"{x:.3}\" cy=\"{y:.3}\" r=\"1.5\"/>"
                    );
                }
            }
        }
    }
    // Waiting for a click, the detector's finding is not shown: the person judges the tip.
    let (found, (x, y)) = match at(&f["centre_px"]).filter(|_| !click) {
        Some(p) => ("", p),
        None => (" style=\"display:none\"", (0.0, 0.0)),
    };
    let r = f["radius_px"].as_f64().unwrap_or(20.0).max(4.0);
    let _ = write!(
        h,
        "<g id=\"found\" transform=\"translate({x:.3} {y:.3})\"{found}><circle r=\"{r:.1}\"/>\
         <line x1=\"-{r:.1}\" x2=\"{r:.1}\" y1=\"0\" y2=\"0\"/><line y1=\"-{r:.1}\" y2=\"{r:.1}\" x1=\"0\" x2=\"0\"/></g>\
         <g id=\"clicked\" style=\"display:none\"><circle r=\"3\"/></g></svg></div></div>\
         <figcaption id=\"snapcap\">{}</figcaption><small>{}blue dots: each cycle's nozzle \
         approached from below (moving +); orange: from above (moving −)</small></figure>",
        snapshot_caption(f),
        if found.is_empty() {
            "red cross: the nozzle as the detector found it; "
        } else {
            ""
        }
    );
}

/// For the click flow: how many clicks were refined from the pictures, and each one kept as
/// clicked with the reason.
fn clicks_refined(rep: &Value) -> String {
    let clicks = rep["clicks"].as_u64().unwrap_or(0);
    if clicks == 0 {
        return String::new();
    }
    let kept: Vec<String> = rep["kept"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_str)
        .map(|k| format!("<li>{}</li>", esc(k)))
        .collect();
    format!(
        "<p class=\"refined\">{} of {clicks} clicks refined from the pictures against the first \
         (the reference); {} kept as clicked</p>{}",
        text(&rep["refined"]),
        kept.len(),
        if kept.is_empty() {
            String::new()
        } else {
            format!("<ul class=\"kept\">{}</ul>", kept.join(""))
        }
    )
}

/// One axis read through the camera: each cycle's approach positions and backlash, then the
/// mean (camera cycles are averaged) and spread the result gives.
fn camera_cycles(h: &mut String, key: &str, rep: &Value, result: &Value) {
    let scale = &rep["scale"];
    let _ = write!(
        h,
        "<div class=\"scroll camera\" data-key=\"{}\"><p><b>{}</b> from webcam '{}': \
         {} px/mm, rotation {}°, {} frames ({} refused and taken again)</p>{}\
         <table><tr><th>cycle</th><th>from below mm</th><th>from above mm</th><th>backlash mm</th></tr>",
        esc(key),
        esc(&key.to_uppercase()),
        text(&rep["webcam"]["name"]),
        scale["x"]["scale_px_per_mm"]
            .as_f64()
            .map(|v| format!("{v:.1}"))
            .unwrap_or_default(),
        scale["rotation_deg"]
            .as_f64()
            .map(|v| format!("{v:.1}"))
            .unwrap_or_default(),
        text(&rep["frames"]),
        text(&rep["refused_frames"]),
        clicks_refined(rep)
    );
    let outliers: Vec<u64> = result["outliers"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_u64)
        .collect();
    let f4 = |v: &Value| v.as_f64().map(|x| format!("{x:.4}")).unwrap_or_default();
    for (i, c) in rep["cycles"].as_array().into_iter().flatten().enumerate() {
        let _ = write!(
            h,
            "<tr class=\"cycle\"><td>{}{}</td><td>{}</td><td>{}</td><td class=\"b\">{}</td></tr>",
            i + 1,
            if outliers.contains(&(i as u64 + 1)) {
                " (outlier, left out)"
            } else {
                ""
            },
            f4(&c["plus_mm"]),
            f4(&c["minus_mm"]),
            f4(&c["backlash_mm"])
        );
    }
    if result.is_object() {
        let _ = write!(
            h,
            "<tr class=\"median\"><th colspan=\"3\">mean ± uncertainty</th><td>{} ± {}</td></tr>\
             <tr class=\"spread\"><th colspan=\"3\">spread (largest − smallest kept)</th><td>{}</td></tr>",
            f4(&result["backlash_mm"]),
            f4(&result["uncertainty_mm"]),
            f4(&result["spread_mm"])
        );
    }
    h.push_str("</table></div>");
}

#[cfg(test)]
mod tests {
    use crate::http::page::render;
    use serde_json::{json, Value};

    #[test]
    fn a_backlash_session_shows_its_results_and_apply() {
        let st = json!({"ok": true, "session": {"kind": "backlash", "id": 9, "state": "measured",
            "progress": "x measured", "axis": null,
            "results": {"x": {"backlash_mm": 0.0812, "uncertainty_mm": 0.0021, "spread_mm": 0.004,
                              "cycles": 5, "compensate": true, "smooth_time_s": 0.005}}},
            "last": {}});
        let page = render(&st, None);
        assert!(
            page.contains("<td>x</td><td>0.081 ± 0.002</td><td>0.004</td>"),
            "{page}"
        );
        assert!(page.contains("data-op=\"backlash/apply\""));
        // No round in a backlash session's header (issue 40: "round measured").
        assert!(page.contains("session 9 <span"), "{page}");
        assert!(!page.contains("· round"), "{page}");
    }

    #[test]
    fn a_guided_axis_shows_the_dialogs_jog_buttons_beside_the_live_camera() {
        let mut st = json!({"ok": true, "session": {"kind": "backlash", "id": 9,
            "state": "measuring", "progress": "measuring x", "axis": "x", "cycle": 2,
            "jog": [{"label": "Coarse X+", "press": "coarse", "style": "secondary"},
                    {"label": "Centred", "press": "centred", "style": "primary"},
                    {"label": "Overshot - start over", "press": "overshot", "style": "warning"}]},
            "last": {}});
        let page = render(&st, None);
        assert!(
            page.contains("<img id=\"live\" src=\"/api/backlash/live.jpg\""),
            "{page}"
        );
        for (press, label) in [("coarse", "Coarse X+"), ("centred", "Centred")] {
            assert!(
                page.contains(&format!(
                    "<input type=\"hidden\" name=\"press\" value=\"{press}\">"
                )) && page.contains(&format!(
                    "data-op=\"backlash/jog\" data-out=\"jogmsg\">{label}<"
                )),
                "{page}"
            );
        }
        assert!(page.contains("<button class=\"danger\" data-op=\"backlash/jog\""));
        // The page reloads when the buttons change (a press made in the dialog).
        assert!(
            page.contains("data-sig=\"9|measuring||{}|0|coarse,centred,overshot|2\""),
            "{page}"
        );
        // No axis being jogged: no panel.
        st["session"]["jog"] = json!([]);
        assert!(!render(&st, None).contains("id=\"live\""));
    }

    #[test]
    fn a_camera_frame_is_shown_with_its_mark_or_as_the_snapshot_to_click_in() {
        let mut st = json!({"ok": true, "session": {"kind": "backlash", "id": 9, "state": "measuring",
            "progress": "camera", "axis": null,
            "snapshot": {"seq": 12, "width": 640, "height": 480, "what": "X cycle 1/5 <b>",
                         "centre_px": [300.25, 200.5], "radius_px": 28.0, "uncertainty_px": 0.05,
                         "refused": null, "click": false, "hint_px": null},
            "camera": {"x": {"webcam": {"name": "nozzle"}, "scale": {"x": {"scale_px_per_mm": 80.0},
                "rotation_deg": 12.0}, "frames": 9, "refused_frames": 1,
                "cycles": [{"plus_px": [300.0, 200.0], "minus_px": [306.0, 200.0],
                            "plus_mm": 0.0012, "minus_mm": 0.0814, "backlash_mm": 0.0802}]}}},
            "last": {}});
        let page = render(&st, None);
        assert!(
            page.contains("src=\"/api/backlash/snapshot.jpg?seq=12\""),
            "{page}"
        );
        // The mark at the detector's centre, + ½ for the SVG's pixel edges.
        assert!(page.contains("<g id=\"found\" transform=\"translate(300.750 201.000)\">"));
        assert!(page.contains("X cycle 1/5 &lt;b&gt;: nozzle at (300.25, 200.50) px ± 0.05 px"));
        assert!(page.contains("<td>0.0012</td><td>0.0814</td><td class=\"b\">0.0802</td>"));
        assert_eq!(page.matches("class=\"approach ").count(), 2);
        assert!(page.contains("data-sig=\"9|measuring||{}|1||\""), "{page}");
        // Waiting for a click: no detector's mark, the help and the zoom's hint.
        st["session"]["snapshot"]["click"] = json!(true);
        st["session"]["snapshot"]["hint_px"] = json!([310.0, 205.5]);
        st["session"]["snapshot"]["zoom"] = json!(8.0);
        let page = render(&st, None);
        assert!(page.contains("data-click=\"1\" data-hint=\"310.000,205.500\" data-zoom=\"8\""));
        assert!(page.contains("id=\"clickhelp\"") && page.contains("Click the nozzle's tip"));
        assert!(page.contains(
            "<g id=\"found\" transform=\"translate(0.000 0.000)\" style=\"display:none\">"
        ));
        // A refused frame says why.
        st["session"]["snapshot"]["click"] = json!(false);
        st["session"]["snapshot"]["centre_px"] = Value::Null;
        st["session"]["snapshot"]["refused"] = json!("two candidates");
        assert!(render(&st, None).contains("X cycle 1/5 &lt;b&gt;: no reading, two candidates"));
        // The click flow: how many clicks the pictures refined, and each one kept with why.
        assert!(!render(&st, None).contains("clicks refined"));
        st["session"]["camera"]["x"]["clicks"] = json!(14);
        st["session"]["camera"]["x"]["refined"] = json!(12);
        st["session"]["camera"]["x"]["kept"] =
            json!(["X cycle 2/4: click kept as clicked, ±1.90 px: <two> places match"]);
        let page = render(&st, None);
        assert!(
            page.contains(
                "12 of 14 clicks refined from the pictures against the first (the \
                           reference); 1 kept as clicked"
            ),
            "{page}"
        );
        assert!(page.contains(
            "<li>X cycle 2/4: click kept as clicked, ±1.90 px: &lt;two&gt; places match</li>"
        ));
    }
}
