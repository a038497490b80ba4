//! The page's bed soak: the soak's line (the console's, with the same ETA), how it was worked
//! out, the question of the bed's build with its buttons while it is asked, and — before a
//! print — *Print now* with its cost and *Wait* (issue 38, items 1, 4, 5, 7).

use std::fmt::Write as _;

use serde_json::Value;

use super::{esc, text};

/// One button that calls `op` with `args` (hidden fields of its own form, which the page's
/// script posts as the call's arguments).
fn op_button(h: &mut String, op: &str, args: &[(&str, &str)], label: &str, class: &str) {
    h.push_str("<form class=\"inline\">");
    for (k, v) in args {
        let _ = write!(
            h,
            "<input type=\"hidden\" name=\"{}\" value=\"{}\">",
            esc(k),
            esc(v)
        );
    }
    let _ = write!(
        h,
        "<button class=\"{}\" data-op=\"{}\" data-out=\"soakmsg\">{}</button></form>",
        esc(class),
        esc(op),
        esc(label)
    );
}

/// The soak's section, from the status's `soak` and the session shown (its kind and state say
/// whether a print follows).
pub(super) fn soak_section(h: &mut String, soak: &Value, session: &Value) {
    if soak.is_null() {
        return;
    }
    h.push_str("<section id=\"soaksec\"><h2>Bed soak</h2>");
    if let Some(p) = soak["progress"].as_str() {
        let _ = write!(h, "<p id=\"soakline\">{}</p>", esc(p));
    }
    let q = &soak["question"];
    if !q.is_null() {
        let _ = write!(
            h,
            "<fieldset id=\"soakask\"><legend>{}</legend><p>{}</p><p class=\"row\">",
            text(&q["title"]),
            text(&q["text"])
        );
        for a in q["answers"].as_array().into_iter().flatten() {
            let (arg, value) = (
                a["arg"].as_str().unwrap_or(""),
                a["value"].as_str().unwrap_or(""),
            );
            let class = if value == "unknown" { "quiet" } else { "" };
            op_button(
                h,
                "soak/bed",
                &[(arg, value)],
                a["label"].as_str().unwrap_or(value),
                class,
            );
        }
        h.push_str("</p></fieldset>");
    }
    let prints = session["kind"] == "ab" && session["state"] == "soaking";
    if prints {
        let cost = soak["print_now_c"]
            .as_f64()
            .map(|c| {
                format!(
                    "the surface may still warm by up to {}",
                    crate::calib::soak::cost_words(c)
                )
            })
            .unwrap_or_else(|| {
                "what the surface may still warm is worked out after a few \
                                 minutes"
                    .into()
            });
        let _ = write!(
            h,
            "<p>Print now: {}. Wait: klipcal prints once the bed has settled.</p><p class=\"row\">",
            esc(&cost)
        );
        op_button(h, "ab/soak_choice", &[("choice", "print")], "Print now", "");
        op_button(h, "ab/soak_choice", &[("choice", "wait")], "Wait", "quiet");
        h.push_str("</p>");
    }
    if let Some(d) = soak["derivation"].as_str() {
        let _ = write!(
            h,
            "<details><summary>How this is worked out</summary><p>{}</p></details>",
            esc(d)
        );
    }
    h.push_str("<p id=\"soakmsg\" class=\"msg\"></p></section>");
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    #[test]
    fn the_question_and_the_offer_to_print_are_buttons_with_their_cost() {
        let soak = json!({
            "progress": "bed soaking: 12 % done, about 14 min left",
            "derivation": "waiting until <the surface>",
            "print_now_c": 1.5,
            "question": {"title": "what is on your bed?", "text": "Steel about 17 min",
                "answers": [{"label": "Steel sheet on a magnet", "arg": "surface", "value": "steel"},
                            {"label": "Don't know", "arg": "surface", "value": "unknown"}]}
        });
        let session = json!({"kind": "ab", "state": "soaking"});
        let mut h = String::new();
        super::soak_section(&mut h, &soak, &session);
        assert!(h.contains("name=\"surface\" value=\"steel\""), "{h}");
        assert!(h.contains("data-op=\"soak/bed\""), "{h}");
        assert!(h.contains("name=\"choice\" value=\"print\""), "{h}");
        assert!(h.contains("name=\"choice\" value=\"wait\""), "{h}");
        assert!(h.contains("about 1.5 K, 1.8 µm per 100 mm on steel"), "{h}");
        assert!(h.contains("&lt;the surface&gt;"), "{h}");
        // A mesh capture's soak prints nothing: no offer.
        let mut m = String::new();
        super::soak_section(&mut m, &soak, &json!({"kind": "mesh", "state": "soaking"}));
        assert!(!m.contains("choice"), "{m}");
        assert!(m.contains("soak/bed"), "{m}");
    }
}
