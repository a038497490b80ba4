//! The soak question (issue 38, item 1) as a user meets it: a klipcal.toml that names neither
//! the bed nor the frame, an A/B start typed as Klipper runs it (`printer/gcode/script`), the
//! dialog's buttons pressed as the macros they are, a dialog closed by mistake and brought
//! back, the frame answered over klipcal's API; klipcal.toml rewritten with a backup and its
//! comments kept, the running soak using the answer at once, a broken file refused whole; and
//! the soak's Wait and Print now (item 5).

use std::time::Duration;

use klipcal::moonraker::{Event, Moonraker};
use serde_json::{json, Value};

use crate::bench::{wait_event, Bench, Daemon};
use crate::session::{session, wait_state, PLANT};

/// Settings a user might have: their own comment in `[soak]`, neither bed nor frame named; a
/// soak that stays open while the test answers (min_soak_s), on the bench's fast plant.
const TOML: &str = "[ab]\nbed_temp_c = 60.0\ncooldown_s = 0.0\nhold_max_s = 600.0\n\
                    soak_max_s = 600.0\n\
                    [soak]\n# my own note: the bed is the stock one\nsettle_s = 1.0\nbin_s = 0.5\n\
                    min_soak_s = 3000.0\ntau_max_s = 30.0\n";

/// Types `line` as Klipper runs it and waits for a console response containing `words`.
async fn typed(m: &Moonraker, line: &str, words: &str) -> String {
    let mut rx = m.events();
    m.gcode(line)
        .await
        .unwrap_or_else(|e| panic!("{line}: Klipper refused it: {e}"));
    match wait_event(
        &mut rx,
        Duration::from_secs(30),
        |ev| matches!(ev, Event::GcodeResponse(l) if l.contains(words)),
    )
    .await
    {
        Some(Event::GcodeResponse(l)) => l,
        _ => panic!(
            "{line}: no console line with {words:?}; the console said:\n{}",
            crate::mainsail::history(m)
                .await
                .iter()
                .rev()
                .take(20)
                .map(|(_, l)| l.as_str())
                .collect::<Vec<_>>()
                .join("\n")
        ),
    }
}

/// The dialog Mainsail shows now, once its title contains `title`.
async fn dialog(m: &Moonraker, title: &str) -> crate::mainsail::Dialog {
    let got = crate::bench::poll(Duration::from_secs(30), || async {
        crate::mainsail::after_reload(m)
            .await
            .filter(|d| d.title.contains(title))
    })
    .await;
    match got {
        Some(d) => d,
        None => panic!(
            "no dialog {title:?}; Mainsail shows {:?}",
            crate::mainsail::after_reload(m).await
        ),
    }
}

async fn api(d: &Daemon, path: &str, body: Value) -> Value {
    let base = d.page_url().await;
    reqwest::Client::new()
        .post(format!("{base}/api/{path}"))
        .json(&body)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap()
}

#[tokio::test]
async fn the_first_soak_asks_the_build_writes_the_answer_and_uses_it_at_once() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    let d = Daemon::ready(&bench, TOML).await;
    let cfg = bench.dir.path().join("klipcal.toml");
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();

    // Started as a user types it: the soak asks what is on the bed.
    typed(&m, "KLIPCAL_AB_START BED=60", "session").await;
    let q = dialog(&m, "what is on your bed?").await;
    // (Each button also carries the question's number, ASK=n, issue 40.)
    let gcodes: Vec<&str> = q
        .buttons
        .iter()
        .map(|(_, g)| g.split(" ASK=").next().unwrap_or(g))
        .collect();
    assert_eq!(
        gcodes,
        [
            "KLIPCAL_SOAK_BED SURFACE=steel",
            "KLIPCAL_SOAK_BED SURFACE=glass",
            "KLIPCAL_SOAK_BED SURFACE=bare",
            "KLIPCAL_SOAK_BED SURFACE=unknown"
        ],
        "{q:?}"
    );
    assert!(q.texts.iter().any(|t| t.contains("min")), "{q:?}");

    // The button, as Klipper runs it: the next step.
    typed(
        &m,
        "KLIPCAL_SOAK_BED SURFACE=steel",
        "next: where is the bed's thermistor?",
    )
    .await;
    dialog(&m, "where is the bed's thermistor?").await;
    // Closed by mistake (Mainsail's ✕ sends prompt_end): not lost.
    let said = typed(
        &m,
        "RESPOND TYPE=command MSG=action:prompt_end",
        "still waiting for your answer",
    )
    .await;
    assert!(said.contains("KLIPCAL_SOAK_BED SENSOR=pad"), "{said}");
    let status = typed(&m, "KLIPCAL_STATUS", "klipcal asks").await;
    assert!(status.contains("KLIPCAL_SOAK_BED SENSOR=plate"), "{status}");
    typed(&m, "_KLIPCAL_PROMPT_BACK", "prompt_show").await;
    dialog(&m, "where is the bed's thermistor?").await;

    // Answered: written to klipcal.toml with a backup, the user's comment kept.
    let before = std::fs::read_to_string(&cfg).unwrap();
    typed(
        &m,
        "KLIPCAL_SOAK_BED SENSOR=pad",
        "soak.bed = 'steel-pad' written",
    )
    .await;
    let after = std::fs::read_to_string(&cfg).unwrap();
    assert!(
        after.contains("# my own note: the bed is the stock one"),
        "{after}"
    );
    assert!(after.contains("bed = \"steel-pad\""), "{after}");
    let backups = bench.dir.path().join("klipcal_backups");
    let backup = std::fs::read_dir(&backups)
        .unwrap()
        .flatten()
        .map(|e| e.path().join("klipcal.toml"))
        .find(|p| p.exists())
        .expect("a backup of klipcal.toml");
    assert_eq!(std::fs::read_to_string(backup).unwrap(), before);
    dialog(&m, "is the printer enclosed?").await;

    // The frame over klipcal's API: the running soak uses both at once.
    let mut rx = m.events();
    let r = api(&d, "soak/bed", json!({"frame": "open"})).await;
    assert_eq!(r["ok"], true, "{r}");
    assert!(
        r["message"]
            .as_str()
            .unwrap_or("")
            .contains("the soak under way uses it now"),
        "{r}"
    );
    let used = wait_event(&mut rx, Duration::from_secs(30), |ev| {
        matches!(ev, Event::GcodeResponse(l)
            if l.contains("this soak now uses soak.bed = 'steel-pad' and soak.frame = 'open'"))
    })
    .await;
    assert!(used.is_some(), "the running soak did not take the answer");
    let cfg_now: String = std::fs::read_to_string(&cfg).unwrap();
    assert!(cfg_now.contains("frame = \"open\""), "{cfg_now}");
    assert!(crate::mainsail::after_reload(&m)
        .await
        .map_or(true, |d| !d.title.contains("enclosed")));

    // Item 5: from the band on, Print now and Wait are buttons; Wait (the macro's default)
    // is an answer, not "nothing to choose".
    wait_state(&bench, "soaking", Duration::from_secs(120)).await;
    let offer = dialog(&m, "the bed is soaking").await;
    let labels: Vec<&str> = offer.buttons.iter().map(|(l, _)| l.as_str()).collect();
    assert_eq!(
        labels,
        ["Print now", "Wait", "Cancel session…"],
        "{offer:?}"
    );
    typed(
        &m,
        "KLIPCAL_SOAK_CHOICE",
        "waiting until the bed has settled",
    )
    .await;
    assert_eq!(session(&bench).await["state"], "soaking");

    // A broken file is refused whole: nothing written.
    let broken = "[soak]\nbin_s = 0\nbed = \"\"\n";
    std::fs::write(&cfg, broken).unwrap();
    let r = api(
        &d,
        "soak/bed",
        json!({"surface": "glass", "sensor": "plate"}),
    )
    .await;
    assert_eq!(r["ok"], false, "{r}");
    let msg = r["error"]["message"].as_str().unwrap_or("");
    assert!(
        msg.contains("nothing written") && msg.contains("bin_s"),
        "{msg}"
    );
    assert_eq!(std::fs::read_to_string(&cfg).unwrap(), broken);
    std::fs::write(&cfg, cfg_now).unwrap();

    typed(&m, "KLIPCAL_CANCEL", "cancel").await;
    drop(d);
}

/// The bench's plant with an enclosure's air that warms steadily (0.02 K per real second at
/// 20 simulated seconds per second) for 300 real seconds, then stays flat, read by the
/// chamber variant's `[temperature_sensor chamber]`.
const CHAMBER_PLANT: &str = r#"{"accel": 20, "bed": {"tau_plate_s": 100.0, "tau_heater_s": 20.0},
    "chamber": {"initial_c": 30.0, "warm_c_per_s": 0.001, "warm_until_s": 6000.0}}"#;

/// Whether the plant's chamber still warms (its own state file).
fn chamber_warming(bench: &Bench) -> Option<bool> {
    let text = std::fs::read_to_string(bench.dir.path().join("comms/plant_state.json")).ok()?;
    let v: Value = serde_json::from_str(&text).ok()?;
    v["chamber"]["warming"].as_bool()
}

/// Issue 38: a chamber thermometer that keeps warming holds the soak (the bed alone settles
/// within a minute or two on this plant), and once it is flat the soak ends. The build and
/// frame are named (no question), the chamber's window is a test's minute
/// (`soak.chamber_window_s`), the A/B start is typed as Klipper runs it and STATUS says what
/// the chamber shows.
#[tokio::test]
async fn a_chamber_that_keeps_warming_holds_the_soak_and_a_flat_one_lets_it_end() {
    let bench = Bench::start_args(
        "corexy",
        &["--plant-json", CHAMBER_PLANT, "--variant", "chamber"],
    );
    let toml = "[ab]\nbed_temp_c = 60.0\ncooldown_s = 0.0\nhold_max_s = 600.0\n\
                soak_max_s = 900.0\n\
                [soak]\nsettle_s = 1.0\nbin_s = 0.5\nmin_soak_s = 3.0\ntau_max_s = 30.0\n\
                surface_budget_c = 0.1\nbed = \"bare-plate\"\nframe = \"enclosed\"\n\
                chamber_window_s = 60.0\n";
    let d = Daemon::ready(&bench, toml).await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    typed(&m, "KLIPCAL_AB_START BED=60", "session").await;
    wait_state(&bench, "soaking", Duration::from_secs(120)).await;
    let soaking_since = std::time::Instant::now();
    // While the air warms the soak holds, and STATUS says why.
    let mut said_warming = None;
    while chamber_warming(&bench) != Some(false) {
        let s = session(&bench).await;
        assert_eq!(
            s["state"],
            "soaking",
            "the soak ended while the chamber still warmed ({:.0} s into it): {s}",
            soaking_since.elapsed().as_secs_f64()
        );
        if said_warming.is_none() && soaking_since.elapsed() > Duration::from_secs(90) {
            let status = typed(&m, "KLIPCAL_STATUS", "bed soak:").await;
            if status.contains("chamber sensor temperature_sensor chamber: still warming") {
                said_warming = Some(status);
            }
        }
        tokio::time::sleep(Duration::from_secs(2)).await;
    }
    let held = soaking_since.elapsed();
    assert!(
        said_warming.is_some(),
        "STATUS never said the chamber still warmed:\n{}",
        d.log_text()
    );
    assert!(
        held > Duration::from_secs(120),
        "the chamber stopped warming {held:?} into the soak: too soon to show it held"
    );
    // Flat: the soak ends once the window has seen it so (a minute), with the sensor named.
    let s = wait_state(&bench, "printing", Duration::from_secs(240)).await;
    let said = s["progress"].as_str().unwrap_or("");
    assert!(
        said.contains("bed stable")
            && said.contains("chamber sensor temperature_sensor chamber: flat"),
        "the declaration did not say the chamber was flat: {said}"
    );
    typed(&m, "KLIPCAL_CANCEL", "cancel").await;
    drop(d);
}
