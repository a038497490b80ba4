//! The daemon's own page and API (issue 13) on the bench: the API gives what the remote methods
//! give, with the same messages; the guard refuses untrusted addresses, cross-site posts,
//! non-JSON and huge bodies; malformed input never takes the server down; and in a real
//! headless Chromium a user enters readings through the form, sees a bad one refused next to
//! its field with nothing saved, and solves.

use std::path::Path;
use std::time::Duration;

use serde_json::{json, Value};

use crate::bench::{extension_request, Bench, Daemon};
use crate::browser::{artifact, Browser};
use crate::session::{measuring_session, session, simulated_readings, wait_state, PLANT};

pub fn client_from(local: &str) -> reqwest::Client {
    reqwest::Client::builder()
        .local_address(Some(local.parse().unwrap()))
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap()
}

async fn post(c: &reqwest::Client, url: &str, body: &str) -> (u16, Value) {
    let r = c
        .post(url)
        .header("content-type", "application/json")
        .body(body.to_string())
        .send()
        .await
        .unwrap();
    let code = r.status().as_u16();
    (code, r.json().await.unwrap_or(Value::Null))
}

/// Malformed input gets a clear JSON error, never a crash: bad JSON, an unknown path or
/// session, a huge body (413, naming the limit), a method the path does not take (405 saying
/// what it takes).
async fn malformed_requests_get_clear_json_errors(me: &reqwest::Client, base: &str) {
    for (body, want) in [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "JSON object"),
        ("\"A-D1\"", "JSON object"),
        ("{\"pair\": {\"x\": [1]}, \"values\": null}", ""),
    ] {
        let (code, v) = post(me, &format!("{base}/api/ab/measure"), body).await;
        assert_eq!(code, 400, "{body}: {v}");
        assert!(
            v["error"]["message"].as_str().unwrap().contains(want),
            "{body}: {v}"
        );
    }
    let (code, v) = post(me, &format!("{base}/api/ab/nonsense"), "{}").await;
    assert_eq!(code, 404);
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("ab/measure"),
        "{v}"
    );
    for (path, want) in [
        ("/api/sessions/abc", 400),
        ("/api/sessions/999", 404),
        ("/nowhere", 404),
    ] {
        let r = me.get(format!("{base}{path}")).send().await.unwrap();
        assert_eq!(r.status().as_u16(), want, "{path}");
    }
    // A huge body: 413 before anything reads it (on its own connection: the server closes it
    // without reading the rest).
    let huge = format!("{{\"pair\": \"{}\"}}", "x".repeat(200_000));
    let (code, v) = post(
        &client_from("127.0.0.1"),
        &format!("{base}/api/ab/measure"),
        &huge,
    )
    .await;
    assert_eq!(code, 413);
    // Issue 26 B.7: the refusal names the limit.
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap_or("")
            .contains("limit of 64 KiB"),
        "{v}"
    );
    // A method the path does not take: a JSON error saying what it takes, not an empty 405.
    for (method, path, want) in [
        ("POST", "/api/sessions", "read with GET"),
        ("GET", "/api/ab/start", "POST it with a JSON body"),
    ] {
        let r = me
            .request(method.parse().unwrap(), format!("{base}{path}"))
            .header("content-type", "application/json")
            .body("{}")
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 405, "{method} {path}");
        let v: Value = r.json().await.unwrap_or(Value::Null);
        let msg = v["error"]["message"].as_str().unwrap_or("");
        assert!(
            msg.contains(want) && msg.contains(path),
            "{method} {path}: {v}"
        );
    }
}

/// Not JSON (what a cross-site form sends) and a cross-origin POST are refused; another
/// loopback address is outside trusted_clients (403, the page too) unless it brings the key.
async fn the_guard_refuses_cross_site_and_untrusted_clients(me: &reqwest::Client, base: &str) {
    // Not JSON (what a cross-site form sends) and a cross-origin POST: refused.
    let r = me
        .post(format!("{base}/api/cancel"))
        .header("content-type", "application/x-www-form-urlencoded")
        .body("reason=x")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 415);
    let r = me
        .post(format!("{base}/api/cancel"))
        .header("content-type", "application/json")
        .header("origin", "http://evil.example")
        .body("{}")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 403);
    let v: Value = r.json().await.unwrap();
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("cross-site"),
        "{v}"
    );

    // Another loopback address is outside trusted_clients: 403, unless it brings the key.
    let other = client_from("127.0.0.2");
    let r = other
        .get(format!("{base}/api/status"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 403);
    let v: Value = r.json().await.unwrap();
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("127.0.0.2"),
        "{v}"
    );
    let r = other.get(format!("{base}/")).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 403, "the page is guarded too");
    let r = other
        .get(format!("{base}/api/status"))
        .header("x-api-key", "k3y")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let r = other
        .get(format!("{base}/api/status"))
        .header("x-api-key", "wrong")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 403);
}

#[tokio::test]
async fn the_api_answers_like_the_remote_methods_and_its_guard_holds() {
    let bench = Bench::start("corexy");
    let d = Daemon::ready(
        &bench,
        "[http]\nbind = \"127.0.0.1:0\"\ntrusted_clients = [\"127.0.0.1/32\"]\napi_key = \"k3y\"\n",
    )
    .await;
    let base = d.page_url().await;
    let me = client_from("127.0.0.1");

    // Status: the same document the remote method answers.
    let st: Value = me
        .get(format!("{base}/api/status"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(st["ok"], json!(true), "{st}");
    let via_moonraker = extension_request(&bench.files(), "klipcal_status", json!({}))
        .await
        .unwrap();
    assert_eq!(
        st["printer"]["kinematics"],
        via_moonraker["printer"]["kinematics"]
    );
    assert_eq!(st["printer"]["kinematics"], "corexy");

    // A user's mistake carries the console's message, as a JSON error with 400.
    let (code, v) = post(
        &me,
        &format!("{base}/api/ab/measure"),
        r#"{"pair": "A-D1", "values": [10.02]}"#,
    )
    .await;
    let console = extension_request(
        &bench.files(),
        "klipcal_measure",
        json!({"pair": "A-D1", "values": [10.02]}),
    )
    .await
    .unwrap_err();
    assert_eq!(code, 400, "{v}");
    assert_eq!(v["ok"], json!(false));
    assert_eq!(v["error"]["message"].as_str().unwrap(), console);
    // An unknown argument is refused by name, as from a macro.
    let (code, v) = post(&me, &format!("{base}/api/ab/start"), r#"{"bde": 60}"#).await;
    assert_eq!(code, 400);
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("unknown argument BDE"),
        "{v}"
    );

    malformed_requests_get_clear_json_errors(&me, &base).await;

    the_guard_refuses_cross_site_and_untrusted_clients(&me, &base).await;

    // The bed plot from Moonraker's temperature store, with the detector replayed over it.
    let r = me
        .get(format!("{base}/api/plots/soak.svg"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let svg = r.text().await.unwrap();
    assert!(
        svg.contains("<svg") && svg.contains("bed °C") && svg.contains("power %"),
        "{svg}"
    );
    // The page itself renders, with nothing external.
    let r = me.get(format!("{base}/")).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let html = r.text().await.unwrap();
    assert!(html.contains("Start an A/B calibration"), "{html}");
    assert!(
        !html.contains("http://") && !html.contains("https://"),
        "no external resources"
    );
    // The daemon is still up after all that.
    let st: Value = me
        .get(format!("{base}/api/status"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(st["ok"], json!(true));
    assert!(!d.log_text().contains("panicked"), "{}", d.log_text());
}

/// The JS that types `values` into the empty fields of `pair`'s fieldset, as a user would.
fn type_into(pair: &str, values: &[String]) -> String {
    format!(
        "(() => {{ const fs = document.querySelector('fieldset.pair[data-pair=\"{pair}\"]');
            const inputs = [...fs.querySelectorAll('input.reading')];
            const vals = {};
            vals.forEach((v, k) => {{ inputs[k].focus(); inputs[k].value = v;
                inputs[k].dispatchEvent(new Event('input', {{bubbles: true}})); }});
            return inputs.length; }})()",
        serde_json::to_string(values).unwrap()
    )
}

fn click_save(pair: &str) -> String {
    format!("document.querySelector('fieldset.pair[data-pair=\"{pair}\"] button.save').click()")
}

/// A field holds one reading: the comma in the second is its decimal mark. A reading without
/// its decimals in the third is refused beside that field, and the pair's message does not
/// say "nothing saved" before Save is pressed (issue 25, C1 and C3); after Save, nothing is
/// saved and what the user typed stays to correct.
async fn a_bad_field_is_refused_beside_it(
    b: &mut Browser,
    bench: &Bench,
    first: &str,
    pair: &Value,
) {
    let good: Vec<String> = simulated_readings(pair)
        .iter()
        .map(|v| format!("{v:.2}"))
        .collect();
    let mut bad = good.clone();
    bad[1] = good[1].replace('.', ",");
    bad[2] = good[2].split('.').next().unwrap().to_string();
    b.eval(&type_into(first, &bad)).await;
    let field = |k: usize| {
        format!("document.querySelectorAll('fieldset.pair[data-pair=\"{first}\"] .field')[{k}]")
    };
    let field3 = field(2);
    assert!(
        b.wait_for(&format!("{field3}.querySelector('input').getAttribute('aria-invalid') === 'true' && {field3}.querySelector('.err').textContent.includes('with its decimals')"), Duration::from_secs(10)).await,
        "no error next to the bad field: {}",
        b.eval(&format!("{field3}.outerHTML")).await
    );
    for k in [0, 1] {
        assert_eq!(
            b.eval(&format!(
                "{}.querySelector('input').getAttribute('aria-invalid')",
                field(k)
            ))
            .await,
            json!("false"),
            "field {}",
            k + 1
        );
    }
    let msg = format!("document.querySelector('fieldset.pair[data-pair=\"{first}\"] .msg')");
    let before_save = b.eval(&format!("{msg}.textContent")).await;
    let before_save = before_save.as_str().unwrap_or("");
    assert!(
        before_save.contains("field 3") && !before_save.contains("nothing saved"),
        "{before_save}"
    );
    b.eval(&click_save(first)).await;
    assert!(
        b.wait_for(
            &format!(
                "{msg}.classList.contains('error') && {msg}.textContent.includes('nothing saved; field 3')"
            ),
            Duration::from_secs(10)
        )
        .await,
        "the refusal is not shown: {}",
        b.eval(&format!("{msg}.outerHTML")).await
    );
    assert!(
        session(bench).await["readings"][&first].is_null(),
        "a refused entry was saved"
    );
    // What the user typed is still there to correct.
    assert_eq!(
        b.eval(&format!("document.querySelectorAll('fieldset.pair[data-pair=\"{first}\"] input.reading')[0].value")).await,
        json!(good[0])
    );
    b.screenshot(&artifact("page-refused.png")).await;
}

/// Every pair entered through the form (the second reading with a decimal comma, as typed in
/// Europe): saved, and the page shows each as complete.
async fn every_pair_is_entered_through_the_form(
    b: &mut Browser,
    bench: &Bench,
    pairs: &[Value],
    per_pair: usize,
) {
    for p in pairs {
        let id = p["id"].as_str().unwrap();
        // As typed in Europe: the second reading with a decimal comma.
        let mut values: Vec<String> = simulated_readings(p)
            .iter()
            .map(|v| format!("{v:.2}"))
            .collect();
        values[1] = values[1].replace('.', ",");
        assert!(
            b.wait_for(
                &format!(
                    "document.querySelector('fieldset.pair[data-pair=\"{id}\"] input.reading')"
                ),
                Duration::from_secs(15)
            )
            .await
        );
        b.eval(&format!(
            "document.querySelectorAll('fieldset.pair[data-pair=\"{id}\"] input.reading').forEach(i => i.value = '')"
        ))
        .await;
        b.eval(&type_into(id, &values)).await;
        b.eval(&click_save(id)).await;
        assert!(
            b.wait_for(&format!("document.querySelector('fieldset.pair[data-pair=\"{id}\"] legend').textContent.includes('{per_pair} of {per_pair} saved')"), Duration::from_secs(15)).await,
            "{id} not shown as saved"
        );
        let saved = session(bench).await["readings"][id].clone();
        assert_eq!(saved, json!(simulated_readings(p)), "{id}");
    }
}

/// Issue 26 B.6: on a phone (390×844) the rounds and solution tables fit, or scroll inside
/// their own box: nothing of them lies outside the window, no cell is cut, and the page itself
/// does not scroll sideways. The documentation's phone picture and convergence plot are made
/// here.
async fn the_tables_fit_on_a_phone(b: &mut Browser, bench: &Bench, base: &str) {
    b.set_viewport(390, 844, true).await;
    b.open(&format!("{base}/")).await;
    assert!(
        b.wait_for(
            "document.querySelector('#rounds table') && document.querySelector('#solution table')",
            Duration::from_secs(15)
        )
        .await,
        "no rounds or solution table on the phone"
    );
    b.screenshot(&artifact("page-solved-phone.png")).await;
    // The documentation's pictures (KLIPCAL_DOC_IMAGES=1): the page as a phone shows it, from
    // the solution down, and the convergence plot the daemon saved beside the config.
    b.eval("document.querySelector('#solution').scrollIntoView({block: 'start'})")
        .await;
    b.screenshot_window(&artifact("page-solved-phone-window.png"))
        .await;
    crate::browser::doc_image(
        &artifact("page-solved-phone-window.png"),
        "page-phone.png",
        600,
    );
    let config = Path::new(bench.info["printer_cfg"].as_str().unwrap())
        .parent()
        .unwrap()
        .to_path_buf();
    let plot = std::fs::read_dir(config.join("klipcal"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.to_string_lossy().ends_with("-convergence.png"))
        .expect("the daemon saved no convergence plot beside the config");
    crate::browser::doc_image(&plot, "convergence.png", 720);
    let fit = b.eval(TABLES_ON_A_PHONE).await;
    let fit: Value = serde_json::from_str(fit.as_str().unwrap()).unwrap();
    println!("tables on a phone: {fit}");
    let w = fit["width"].as_f64().unwrap();
    assert!(
        fit["page"].as_f64().unwrap() <= w + 1.0,
        "the page scrolls sideways on a phone: {fit}"
    );
    for id in ["rounds", "solution"] {
        let t = &fit[id];
        let (left, right) = (t["box"][0].as_f64().unwrap(), t["box"][1].as_f64().unwrap());
        assert!(
            left >= -1.0 && right <= w + 1.0,
            "#{id}'s box lies outside the window: {fit}"
        );
        // A wider table (more rounds, longer numbers) scrolls inside its box; a round's table
        // fits whole (before the phone CSS its last column hid beyond the box's edge: 402 and
        // 448 px tables in a 342 px box).
        assert!(
            matches!(t["overflow"].as_str(), Some("auto" | "scroll")),
            "#{id}'s box does not scroll: {fit}"
        );
        assert!(
            t["table"].as_f64().unwrap() <= t["client"].as_f64().unwrap() + 1.0,
            "#{id}'s table is wider than its box on a phone: {fit}"
        );
        assert_eq!(t["cut"], json!([]), "#{id}: cells cut on a phone: {fit}");
    }
    b.set_viewport(1280, 800, false).await;
}

#[tokio::test]
async fn in_a_real_browser_readings_are_entered_refused_next_to_the_field_and_solved() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    let (d, s) = measuring_session(&bench).await;
    let base = d.page_url().await;
    let mut b = Browser::start().await;
    b.open(&format!("{base}/")).await;
    assert!(
        b.wait_for(
            "document.querySelectorAll('fieldset.pair').length > 0",
            Duration::from_secs(10)
        )
        .await
    );
    b.screenshot(&artifact("page-measuring.png")).await;
    let pairs = s["pairs"].as_array().unwrap().clone();
    assert_eq!(
        b.eval("document.querySelectorAll('fieldset.pair').length")
            .await,
        json!(pairs.len())
    );
    // The pylon diagram is inline, and focusing a field highlights its pair.
    let first = pairs[0]["id"].as_str().unwrap().to_string();
    let per_pair = s["readings_per_pair"].as_u64().unwrap() as usize;
    assert_eq!(b.eval(&type_into(&first, &[])).await, json!(per_pair));
    b.eval(&format!(
        "document.querySelector('fieldset.pair[data-pair=\"{first}\"] input.reading').focus()"
    ))
    .await;
    assert!(
        b.wait_for(
            &format!("document.querySelector('.diagram .pair.hl').dataset.pair === '{first}'"),
            Duration::from_secs(5)
        )
        .await,
        "the diagram does not highlight the pair"
    );

    a_bad_field_is_refused_beside_it(&mut b, &bench, &first, &pairs[0]).await;

    every_pair_is_entered_through_the_form(&mut b, &bench, &pairs, per_pair).await;
    // Solve from the page: the state changes and the page shows the solution with Apply.
    assert!(
        b.wait_for(
            "!document.querySelector('button[data-op=\"ab/solve\"]').disabled",
            Duration::from_secs(10)
        )
        .await
    );
    b.eval("document.querySelector('button[data-op=\"ab/solve\"]').click()")
        .await;
    wait_state(&bench, "solved", Duration::from_secs(30)).await;
    assert!(
        b.wait_for(
            "document.querySelector('#solution button[data-op=\"ab/apply\"]')",
            Duration::from_secs(15)
        )
        .await,
        "the page does not show the solution"
    );
    let table = b
        .eval("document.querySelector('#solution table').textContent")
        .await;
    assert!(table.as_str().unwrap().contains("stepper_x"), "{table}");
    b.screenshot(&artifact("page-solved.png")).await;
    the_tables_fit_on_a_phone(&mut b, &bench, &base).await;
    // Solving saved the rounds' plot under the config root and named it.
    let id = s["id"].as_i64().unwrap();
    let plot = bench
        .dir
        .path()
        .join(format!("config/klipcal/ab-s{id}-convergence.svg"));
    assert!(
        std::fs::read_to_string(&plot)
            .unwrap_or_default()
            .contains("<svg"),
        "{}",
        plot.display()
    );
    assert!(b
        .eval("document.body.textContent")
        .await
        .as_str()
        .unwrap_or("")
        .contains("stepper_x"));
    // The convergence plot and the diagram are served as SVG.
    let me = client_from("127.0.0.1");
    for path in [
        format!("/api/sessions/{id}/convergence.svg"),
        format!("/api/sessions/{id}/diagram.svg"),
    ] {
        let r = me.get(format!("{base}{path}")).send().await.unwrap();
        assert_eq!(r.status().as_u16(), 200, "{path}");
        assert!(r.text().await.unwrap().contains("<svg"), "{path}");
    }
    drop(d);
}

/// Issue 26 B.7: klipcal's port taken by another program. The daemon runs on (the macros work)
/// and says so where a user looks: on stderr at start, on the console once connected, and in
/// KLIPCAL_STATUS (and the status answer's `page.off`).
#[tokio::test]
async fn a_taken_page_port_is_said_on_the_console_and_in_the_status() {
    let bench = Bench::start("corexy");
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let d = Daemon::ready(&bench, &format!("[http]\nbind = \"127.0.0.1:{port}\"\n")).await;
    let words = format!("another program listens on 127.0.0.1:{port}");
    let st = extension_request(&bench.files(), "klipcal_status", json!({}))
        .await
        .unwrap();
    assert!(
        st["page"]["off"].as_str().unwrap_or("").contains(&words),
        "{st}"
    );
    assert!(d
        .log_text()
        .contains(&format!("klipcal: its page and API are off: {words}")));
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let console = |m: klipcal::moonraker::Moonraker| async move {
        let store = m
            .call("server.gcode_store", json!({"count": 100}))
            .await
            .unwrap();
        store["gcode_store"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|e| e["message"].as_str().map(str::to_string))
            .collect::<Vec<_>>()
            .join("\n")
    };
    let said = crate::bench::poll(Duration::from_secs(15), || {
        let m = m.clone();
        let words = words.clone();
        async move {
            let text = console(m).await;
            text.contains(&format!("klipcal's page is off: {words}"))
                .then_some(())
        }
    })
    .await;
    assert!(
        said.is_some(),
        "no console line at start:\n{}",
        console(m.clone()).await
    );
    m.gcode("KLIPCAL_STATUS").await.unwrap();
    let status = crate::bench::poll(Duration::from_secs(15), || {
        let m = m.clone();
        let words = words.clone();
        async move {
            let text = console(m).await;
            (text
                .matches(&format!("klipcal's page is off: {words}"))
                .count()
                >= 2)
                .then_some(())
        }
    })
    .await;
    assert!(
        status.is_some(),
        "KLIPCAL_STATUS does not say it:\n{}",
        console(m.clone()).await
    );
    drop(taken);
}

/// Issue 26 B.7: a cancel from klipcal's page leaves a console line (a macro's cancel is
/// answered there by the agent; the page's was not).
#[tokio::test]
async fn a_cancel_from_the_page_is_said_on_the_console() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    let (d, _s) = measuring_session(&bench).await;
    let base = d.page_url().await;
    let (code, v) = post(
        &client_from("127.0.0.1"),
        &format!("{base}/api/cancel"),
        "{}",
    )
    .await;
    assert_eq!(code, 200, "{v}");
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let said = crate::bench::poll(Duration::from_secs(15), || {
        let m = m.clone();
        async move {
            crate::mainsail::history(&m)
                .await
                .into_iter()
                .any(|(_, msg)| msg.contains("cancelled from klipcal's page"))
                .then_some(())
        }
    })
    .await;
    assert!(
        said.is_some(),
        "no console line for the page's cancel: {:#?}",
        crate::mainsail::history(&m).await
    );
}

/// The page's tables on the window as it is: the page's width against the window's, and for
/// `#rounds` and `#solution` their scroll box's left and right, the table's width against the
/// box's, the box's overflow, and the cells whose text is cut.
const TABLES_ON_A_PHONE: &str = r#"(() => {
  const out = {width: window.innerWidth, page: document.documentElement.scrollWidth};
  for (const id of ['rounds', 'solution']) {
    const s = document.getElementById(id); if (!s) { out[id] = null; continue; }
    const box = s.querySelector('.scroll') || s; const t = s.querySelector('table');
    const r = box.getBoundingClientRect();
    const cut = [...t.querySelectorAll('td, th')]
      .filter(c => c.scrollWidth > c.clientWidth + 1).map(c => c.textContent);
    out[id] = {box: [r.left, r.right], table: t.scrollWidth, client: box.clientWidth,
               overflow: getComputedStyle(box).overflowX, cut};
  }
  return JSON.stringify(out);
})()"#;
