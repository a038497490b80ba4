//! The page's A/B section: the bed soak, the readings form with the layout diagram, the
//! solution with its Apply button, and the rounds so far.

use std::fmt::Write as _;

use serde_json::Value;

use super::{esc, mm, text};

pub(super) fn ab_sections(h: &mut String, s: &Value, diagram_svg: Option<&str>) {
    let state = s["state"].as_str().unwrap_or("");
    if matches!(state, "heating" | "soaking" | "printing" | "holding") {
        h.push_str(
            "<section><h2>Bed</h2><img id=\"soak\" class=\"plot\" alt=\"bed temperature and power\" \
             src=\"/api/plots/soak.svg\"></section>",
        );
    }
    if matches!(state, "measuring" | "solved") {
        readings_form(h, s, diagram_svg);
    }
    if state == "solved" {
        solution(h, s);
    }
    rounds_table(h, s);
}

fn readings_form(h: &mut String, s: &Value, diagram_svg: Option<&str>) {
    let per_pair = s["readings_per_pair"].as_u64().unwrap_or(5) as usize;
    let on = if s["bed_temp_c"].as_f64().unwrap_or(0.0) > 0.0 {
        "with the part still on the hot bed"
    } else {
        "with the part still on the bed"
    };
    let _ = write!(
        h,
        "<section id=\"readings\"><h2>Readings</h2><p>Measure each pair {on}: {per_pair} readings with \
         calipers from outer face to outer face, just below the top chamfer. One reading per \
         field, as the caliper shows it (10.02 or 10,02); each pair is saved whole or not at \
         all.</p>"
    );
    if let Some(svg) = diagram_svg {
        // The diagram is the generator's own SVG (ids from the layout, no user text).
        let _ = write!(h, "<div class=\"diagram\">{svg}</div>");
    }
    let empty = serde_json::Map::new();
    let readings = s["readings"].as_object().unwrap_or(&empty);
    for p in s["pairs"].as_array().into_iter().flatten() {
        let id = p["id"].as_str().unwrap_or("");
        let have: Vec<f64> = readings
            .get(id)
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default();
        let nominal = p["nominal_mm"].as_f64().unwrap_or(0.0);
        let _ = write!(
            h,
            "<fieldset class=\"pair\" data-pair=\"{}\"><legend>{}: pylon {} → pylon {}, nominal {} mm \
             <span class=\"saved\">({} of {per_pair} saved{})</span></legend>",
            esc(id),
            esc(id),
            text(&p["from"]),
            text(&p["to"]),
            mm(nominal),
            have.len(),
            match have.len().cmp(&per_pair) {
                std::cmp::Ordering::Less => "",
                std::cmp::Ordering::Equal => " ✓",
                std::cmp::Ordering::Greater => ": more than asked; Clear to enter the pair again",
            }
        );
        if !have.is_empty() {
            let list: Vec<String> = have.iter().map(|v| mm(*v)).collect();
            let _ = write!(
                h,
                "<p class=\"saved\">saved: {} <button class=\"clear quiet\">Clear</button></p>",
                esc(&list.join(", "))
            );
        }
        let open = per_pair.saturating_sub(have.len());
        if open > 0 {
            h.push_str("<div class=\"fields\">");
            for k in 0..open {
                let _ = write!(
                    h,
                    "<label class=\"field\"><input class=\"reading\" inputmode=\"decimal\" \
                     autocomplete=\"off\" aria-label=\"{} reading {}\" placeholder=\"{}\">\
                     <span class=\"err\"></span></label>",
                    esc(id),
                    have.len() + k + 1,
                    mm(nominal)
                );
            }
            h.push_str("</div><p class=\"row\"><button class=\"save\">Save ");
            h.push_str(&esc(id));
            h.push_str("</button></p>");
        }
        h.push_str("<p class=\"msg\"></p></fieldset>");
    }
    let missing = s["missing"].as_array().map_or(0, Vec::len);
    if state_is(s, "measuring") {
        let _ = write!(
            h,
            "<p class=\"row\"><button data-op=\"ab/solve\" data-out=\"solvemsg\"{}>Solve</button>\
             <span id=\"solvemsg\" class=\"msg\">{}</span></p>",
            if missing > 0 { " disabled" } else { "" },
            if missing > 0 {
                "enter every pair's readings to solve"
            } else {
                "all pairs measured"
            }
        );
    }
    h.push_str("</section>");
}

fn state_is(s: &Value, name: &str) -> bool {
    s["state"].as_str() == Some(name)
}

fn solution(h: &mut String, s: &Value) {
    let Some(r) = s["rounds"].as_array().and_then(|r| r.last()) else {
        return;
    };
    h.push_str("<section id=\"solution\"><h2>Solution</h2><div class=\"scroll\"><table><tr><th>stepper</th><th>rotation_<wbr>distance now</th><th>new</th><th>scale ± uncertainty</th></tr>");
    for (k, name) in ["stepper_x", "stepper_y"].iter().enumerate() {
        let f = |key: &str| r[key][k].as_f64();
        let _ = write!(
            h,
            "<tr><td>{name}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            f("rotation_distance")
                .map(crate::calib::entry::fmt_rd)
                .unwrap_or_default(),
            f("rotation_distance_new")
                .map(crate::calib::entry::fmt_rd)
                .unwrap_or_default(),
            match (f("scale"), f("uncertainty")) {
                (Some(sc), Some(u)) => format!("{sc:.5} ± {u:.5}"),
                _ => String::new(),
            }
        );
    }
    let _ = write!(
        h,
        "</table></div><p>{}</p><form class=\"row\"><label><input type=\"checkbox\" name=\"force\" style=\"width:auto\"> \
         apply even beyond the change limit (FORCE)</label><button data-op=\"ab/apply\" data-out=\"applymsg\" \
         data-confirm=\"Write the new rotation distances and restart Klipper?\">Apply</button></form>\
         <p id=\"applymsg\" class=\"msg\"></p></section>",
        if r["converged"] == Value::Bool(true) {
            "converged: within the error budget"
        } else {
            "not converged yet: apply, then print another round"
        }
    );
}

fn rounds_table(h: &mut String, s: &Value) {
    let Some(rounds) = s["rounds"].as_array().filter(|r| !r.is_empty()) else {
        return;
    };
    h.push_str("<section id=\"rounds\"><h2>Rounds</h2><div class=\"scroll\"><table><tr><th>round</th><th>job</th><th>error µm/100&nbsp;mm</th><th>converged</th><th>applied</th></tr>");
    let mut solved = false;
    for r in rounds {
        solved |= !r["scale"].is_null();
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            text(&r["n"]),
            text(&r["file"]),
            r["error_um_per_100mm"]
                .as_f64()
                .map(|v| format!("{v:.1}"))
                .unwrap_or_default(),
            match r["converged"].as_bool() {
                Some(true) => "yes",
                Some(false) => "no",
                None => "",
            },
            if r["applied"].is_null() { "" } else { "yes" }
        );
    }
    h.push_str("</table></div>");
    if solved {
        let _ = write!(
            h,
            "<img class=\"plot\" alt=\"convergence\" src=\"/api/sessions/{}/convergence.svg\">",
            text(&s["id"])
        );
    }
    h.push_str("</section>");
}

#[cfg(test)]
mod tests {
    use crate::http::page::render;
    use crate::http::page::tests::measuring;
    use serde_json::json;

    #[test]
    fn the_readings_form_has_a_field_per_missing_reading_and_shows_saved_ones() {
        let page = render(
            &measuring(),
            Some("<svg><g class=\"pair\" data-pair=\"A-D1\"></g></svg>"),
        );
        assert_eq!(page.matches("class=\"reading\"").count(), 3 + 5, "{page}");
        assert!(page.contains("saved: 10.02, 10.03"));
        assert!(page.contains("(2 of 5 saved)"));
        assert!(page.contains("A-D2: pylon A1 → pylon A3, nominal 150 mm"));
        assert!(
            page.contains("data-pair=\"A-D1\"></g>"),
            "the diagram is inline"
        );
        // BED=0: no "hot bed".
        assert!(page.contains("with the part still on the bed") && !page.contains("hot bed"));
        assert!(page.contains("data-op=\"ab/solve\"") && page.contains(" disabled>Solve"));
    }

    #[test]
    fn a_solved_session_shows_the_values_and_the_apply_button() {
        let mut st = measuring();
        st["session"]["state"] = json!("solved");
        st["session"]["missing"] = json!([]);
        st["session"]["rounds"] = json!([{"n": 1, "file": "f", "rotation_distance": [40.0, 40.0],
            "rotation_distance_new": [40.08, 39.96], "scale": [1.002, 0.999], "uncertainty": [0.0001, 0.0001],
            "error_um_per_100mm": 200.0, "converged": false, "applied": null}]);
        let page = render(&st, None);
        assert!(
            // One precision everywhere (issue 9 item 22): as the console and the config say it.
            page.contains("<td>40</td><td>40.08</td>")
                && !page.contains("40.000000")
                && page.contains("1.00200 ± 0.00010"),
            "{page}"
        );
        assert!(page.contains("data-op=\"ab/apply\""));
        assert!(page.contains("/api/sessions/4/convergence.svg"));
    }
}
