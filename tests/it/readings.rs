//! Readings typed on the console as Klipper passes them (issue 25, C): every line goes through
//! Moonraker's `printer/gcode/script`, Klipper parses the macro, and klipcal either saves
//! exactly the readings meant or refuses the entry whole, saying why.

use std::time::Duration;

use klipcal::moonraker::Event;
use serde_json::{json, Value};

use crate::bench::{wait_event, Bench};
use crate::session::{measuring_session, session, PLANT};

/// What a console line should lead to.
enum Want<'a> {
    /// klipcal answers with these words and the pair's readings become these.
    Answer(&'a str, &'a [f64]),
    /// Klipper itself refuses the line with these words (klipcal never hears of it).
    Klipper(&'a str),
}

#[tokio::test]
async fn console_readings_are_read_as_typed_or_refused_whole() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    let (d, s) = measuring_session(&bench).await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let pair = s["pairs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["nominal_mm"].as_f64() == Some(10.0))
        .expect("a 10 mm pair")
        .clone();
    let id = pair["id"].as_str().unwrap().to_string();
    let cases: Vec<(String, Want)> = vec![
        // The lines: four numbers, not two readings read as 10 and 10 and 10 and 9.
        (
            format!("KLIPCAL_AB_CHECK PAIR={id} VALUES=10,10,10,09"),
            Want::Answer("use a dot: 10.10", &[]),
        ),
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=10,10,10,09"),
            Want::Answer("nothing saved", &[]),
        ),
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=10"),
            Want::Answer("with its decimals, e.g. 10.10", &[]),
        ),
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=-10.05"),
            Want::Answer("a reading can't be negative", &[]),
        ),
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=1.234,56"),
            Want::Answer("nothing saved, item 1", &[]),
        ),
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=10.123"),
            Want::Answer("3 decimals", &[]),
        ),
        (
            format!("KLIPCAL_AB_CHECK PAIR={id} VALUES=10.10,10.09"),
            Want::Answer("2 reading(s) would be accepted", &[]),
        ),
        // Spaces split a line into parameters: Klipper refuses it.
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=10.10 10.09"),
            Want::Klipper("Malformed command"),
        ),
        // One reading on its own: its comma is the decimal mark.
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUE=10,10"),
            Want::Answer("1 reading(s) saved", &[10.10]),
        ),
        // The documented list: commas between readings, a dot in each, a unit allowed.
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=10.09,10.08mm,"),
            Want::Answer("2 reading(s) saved", &[10.10, 10.09, 10.08]),
        ),
        // `;` starts Klipper's comment: only what comes before it arrives, and the answer
        // says how many were saved (the README says not to use it).
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUES=10.07;10.06"),
            Want::Answer("1 reading(s) saved, 4 of 5", &[10.10, 10.09, 10.08, 10.07]),
        ),
    ];
    send(&bench, &d, &m, &id, &cases).await;
}

/// Runs each console line through Klipper and checks what it led to.
async fn send(
    bench: &Bench,
    d: &crate::bench::Daemon,
    m: &klipcal::moonraker::Moonraker,
    id: &str,
    cases: &[(String, Want<'_>)],
) {
    let readings = |st: &Value| -> Vec<f64> {
        st["readings"][id]
            .as_array()
            .map(|a| a.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default()
    };
    for (line, want) in cases {
        let mut rx = m.events();
        let sent = m.gcode(line).await;
        match want {
            Want::Klipper(words) => {
                let e = sent.expect_err(line).to_string();
                assert!(e.contains(words), "{line}: {e}");
            }
            Want::Answer(words, after) => {
                sent.unwrap_or_else(|e| panic!("{line}: Klipper refused it: {e}"));
                let said = wait_event(
                    &mut rx,
                    Duration::from_secs(15),
                    |ev| matches!(ev, Event::GcodeResponse(l) if l.contains(words)),
                )
                .await;
                assert!(
                    said.is_some(),
                    "{line}: no console line with {words:?}\n{}",
                    d.log_text()
                );
                let got = readings(&session(bench).await);
                assert_eq!(&got, after, "{line}");
            }
        }
    }
}

/// Issue 25 C2: a line sent again would double a pair's readings ("10 of 5 in all"): it is
/// refused, saying how to replace them; more readings than asked for (even one equal to the
/// last) are taken with a word.
#[tokio::test]
async fn a_line_sent_again_is_refused_and_the_answer_says_how_to_replace() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    let (d, s) = measuring_session(&bench).await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let id = s["pairs"][0]["id"].as_str().unwrap().to_string();
    let five = [10.10, 10.09, 10.08, 10.07, 10.06];
    let six = [10.10, 10.09, 10.08, 10.07, 10.06, 10.06];
    let line = format!("KLIPCAL_MEASURE PAIR={id} VALUES=10.10,10.09,10.08,10.07,10.06");
    let cases: Vec<(String, Want)> = vec![
        (
            line.clone(),
            Want::Answer("5 reading(s) saved, 5 of 5", &five),
        ),
        (line.clone(), Want::Answer("already saved", &five)),
        (line.clone(), Want::Answer("CLEAR=1 VALUES=", &five)),
        // A new reading equal to the last one is a reading, not the line sent again.
        (
            format!("KLIPCAL_MEASURE PAIR={id} VALUE=10.06"),
            Want::Answer("more than the 5 asked for", &six),
        ),
        (
            format!("KLIPCAL_MEASURE PAIR={id} CLEAR=1 VALUES=10.10,10.09,10.08,10.07,10.06"),
            Want::Answer("5 of 5 in all", &five),
        ),
    ];
    send(&bench, &d, &m, &id, &cases).await;
}
