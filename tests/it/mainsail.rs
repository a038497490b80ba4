//! What Mainsail shows after a page reload: its dialog is rebuilt from Moonraker's G-code store
//! (`server.gcode_store`, the console history every client loads). This is a port of
//! `processEvents` and the `showDialog` / `headline` / `activePromptContent` computations in
//! Mainsail's `src/components/dialogs/TheMacroPrompt.vue` (mainsail-crew/mainsail, read at commit
//! 273d7e3): walk the history backwards over `// action:prompt_*` responses, stop at an `end`
//! (nothing shown) or a `begin`; a dialog shows when that `begin` is followed by a `show`.
//! Tests use it to check that a reload (or a second client) shows only the prompt that is true
//! now (issue 9 item 20).

use std::time::Duration;

use klipcal::moonraker::Moonraker;
use serde_json::json;

/// A dialog as Mainsail would draw it.
#[derive(Debug, Clone, PartialEq)]
pub struct Dialog {
    pub title: String,
    pub texts: Vec<String>,
    /// `(label, gcode)` of the body's buttons, then the footer's.
    pub buttons: Vec<(String, String)>,
}

/// The dialog Mainsail shows for this console history (oldest first), if any.
pub fn replay(history: &[(String, String)]) -> Option<Dialog> {
    // (type, message) of the prompt events after the last begin, in order.
    let mut events: Vec<(String, String)> = Vec::new();
    for (kind, message) in history.iter().rev() {
        if kind != "response" || !message.starts_with("// action:prompt_") {
            continue;
        }
        let rest = &message["// action:prompt_".len()..];
        let (ty, msg) = rest.split_once(' ').unwrap_or((rest, ""));
        if ty == "end" {
            return None;
        }
        events.insert(0, (ty.to_string(), msg.trim().to_string()));
        if ty == "begin" {
            break;
        }
    }
    let show = events.iter().rposition(|(t, _)| t == "show")?;
    let begin = events[..show].iter().rposition(|(t, _)| t == "begin")?;
    let active = &events[begin..show];
    let texts: Vec<String> = active
        .iter()
        .filter(|(t, _)| t == "text")
        .map(|(_, m)| m.clone())
        .collect();
    let button = |(_, m): &(String, String)| {
        let mut parts = m.split('|');
        let label = parts.next().unwrap_or("").to_string();
        let gcode = parts.next().unwrap_or(&label).to_string();
        (label, gcode)
    };
    let mut buttons: Vec<(String, String)> = active
        .iter()
        .filter(|(t, _)| t == "button")
        .map(button)
        .collect();
    buttons.extend(
        active
            .iter()
            .filter(|(t, _)| t == "footer_button")
            .map(button),
    );
    // Mainsail hides a dialog with nothing to show.
    if texts.is_empty() && buttons.is_empty() {
        return None;
    }
    Some(Dialog {
        title: events[begin].1.clone(),
        texts,
        buttons,
    })
}

/// The console history as a client loading the page gets it.
pub async fn history(m: &Moonraker) -> Vec<(String, String)> {
    let store = m
        .call("server.gcode_store", json!({"count": 1000}))
        .await
        .unwrap();
    store["gcode_store"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["type"].as_str().unwrap_or("").to_string(),
                e["message"].as_str().unwrap_or("").to_string(),
            )
        })
        .collect()
}

/// The dialog a reload shows now (after the daemon's last script has reached the store).
pub async fn after_reload(m: &Moonraker) -> Option<Dialog> {
    tokio::time::sleep(Duration::from_millis(300)).await;
    replay(&history(m).await)
}

/// What a reload shows once it shows what `want` expects (klipcal sends a dialog after the
/// state it follows is stored, so a loaded machine may show it a moment later), or what it
/// shows after `limit`.
pub async fn after_reload_showing(
    m: &Moonraker,
    limit: Duration,
    want: impl Fn(&Dialog) -> bool,
) -> Option<Dialog> {
    let deadline = std::time::Instant::now() + limit;
    loop {
        let shown = after_reload(m).await;
        if shown.as_ref().is_some_and(&want) || std::time::Instant::now() >= deadline {
            return shown;
        }
    }
}

#[test]
fn the_port_follows_mainsails_reading_of_the_history() {
    let h = |v: &[(&str, &str)]| -> Vec<(String, String)> {
        v.iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect()
    };
    let shown = h(&[
        ("command", "RESPOND TYPE=command MSG=action:prompt_begin x"),
        ("response", "// action:prompt_begin klipcal: Solve?"),
        ("response", "// action:prompt_text all pairs measured"),
        (
            "response",
            "// action:prompt_button Solve|KLIPCAL_AB_SOLVE|primary",
        ),
        (
            "response",
            "// action:prompt_footer_button Close|KLIPCAL_CLOSE|secondary",
        ),
        ("response", "// action:prompt_show"),
        ("response", "// klipcal: something else"),
    ]);
    let d = replay(&shown).unwrap();
    assert_eq!(d.title, "klipcal: Solve?");
    assert_eq!(d.texts, ["all pairs measured"]);
    assert_eq!(d.buttons[0], ("Solve".into(), "KLIPCAL_AB_SOLVE".into()));
    assert_eq!(d.buttons[1].0, "Close");
    let mut ended = shown.clone();
    ended.push(("response".into(), "// action:prompt_end".into()));
    assert_eq!(replay(&ended), None);
    // Begun but not shown yet: nothing.
    assert_eq!(replay(&shown[..4]), None);
    // A newer prompt replaces an older one.
    let mut newer = ended.clone();
    newer.extend(h(&[
        ("response", "// action:prompt_begin klipcal: Apply?"),
        ("response", "// action:prompt_text new values"),
        ("response", "// action:prompt_show"),
    ]));
    assert_eq!(replay(&newer).unwrap().title, "klipcal: Apply?");
}

/// A button's G-code without the question number klipcal adds to it (` ASK=<n>`, issue 40).
pub fn unasked(gcode: &str) -> &str {
    match gcode.rsplit_once(" ASK=") {
        Some((command, n)) if n.chars().all(|c| c.is_ascii_digit()) => command,
        _ => gcode,
    }
}
