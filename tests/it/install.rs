//! `klipcal install` / `uninstall` on the bench's printer_data (issue 14): Moonraker restarted
//! with the edited moonraker.conf loads `[update_manager klipcal-<printer>]` without a warning, Klipper
//! restarted with the include runs the macros, a second install changes nothing, a dry run
//! writes nothing, uninstall restores every file byte for byte, and conflicts are refused.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use serde_json::{json, Value};

use crate::bench::{poll, wait_event, Bench, Daemon};

fn klipcal(bench: &Bench, args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_klipcal"))
        .args(["--moonraker", &bench.ws_url()])
        .args(args)
        .env("HOME", bench.dir.path())
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

fn install_args(bench: &Bench, extra: &[&str]) -> Vec<String> {
    let pd = bench.dir.path().display().to_string();
    let mut v: Vec<String> = vec![
        "install".into(),
        "--printer-data".into(),
        pd.clone(),
        "--bin-dir".into(),
        format!("{pd}/klipcal-bin"),
        "--no-systemd".into(),
    ];
    v.extend(extra.iter().map(|s| (*s).to_string()));
    v
}

fn run(bench: &Bench, args: &[String]) -> (bool, String) {
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    klipcal(bench, &refs)
}

/// The files an install may touch — config/ (not its backups or Moonraker's hidden copies),
/// moonraker.asvc, the binary folder — each with its bytes.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    for sub in ["config", "klipcal-bin"] {
        let Ok(rd) = std::fs::read_dir(dir.join(sub)) else {
            continue;
        };
        for e in rd.flatten() {
            let p = e.path();
            let name = p.file_name().unwrap().to_string_lossy().to_string();
            if p.is_file() && !name.starts_with('.') {
                out.push((p.clone(), std::fs::read(&p).unwrap_or_default()));
            }
        }
    }
    let asvc = dir.join("moonraker.asvc");
    out.push((asvc.clone(), std::fs::read(&asvc).unwrap_or_default()));
    out.sort();
    out
}

/// The paths whose bytes differ between two snapshots (for a readable failure).
fn differ(a: &[(PathBuf, Vec<u8>)], b: &[(PathBuf, Vec<u8>)]) -> Vec<String> {
    let mut paths: Vec<&PathBuf> = a.iter().chain(b).map(|(p, _)| p).collect();
    paths.sort();
    paths.dedup();
    paths
        .into_iter()
        .filter(|p| {
            a.iter().find(|x| &x.0 == *p).map(|x| &x.1)
                != b.iter().find(|x| &x.0 == *p).map(|x| &x.1)
        })
        .map(|p| p.display().to_string())
        .collect()
}

async fn wait_ready(bench: &Bench) {
    let files = bench.files();
    let ok = poll(Duration::from_secs(60), || async {
        let v = files.get("/server/info").await.ok()?;
        (v["klippy_state"] == "ready").then_some(())
    })
    .await;
    assert!(ok.is_some(), "Moonraker/Klipper did not come back ready");
}

#[tokio::test]
async fn install_twice_then_uninstall_restores_every_file_byte_for_byte() {
    let bench = Bench::start("corexy");
    let pd = bench.dir.path().to_path_buf();
    let cfg = pd.join("config");
    // A printer as a new user has it: no klipcal include, no macros, no [respond], and
    // Moonraker with its update manager on.
    let printer = std::fs::read_to_string(cfg.join("printer.cfg")).unwrap();
    let printer = printer
        .replace("[include klipcal.cfg]", "")
        .replace("[respond]\n", "");
    std::fs::write(cfg.join("printer.cfg"), &printer).unwrap();
    std::fs::remove_file(cfg.join("klipcal.cfg")).unwrap();
    let mut conf = std::fs::read_to_string(cfg.join("moonraker.conf")).unwrap();
    conf.push_str("\n[update_manager]\nenable_system_updates: False\n");
    std::fs::write(cfg.join("moonraker.conf"), &conf).unwrap();
    let files = bench.files();
    files.post("/server/restart", &json!({})).await.unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
    wait_ready(&bench).await;
    let before = snapshot(&pd);

    // A dry run prints the diffs and writes nothing.
    let (ok, out) = run(&bench, &install_args(&bench, &["--dry-run"]));
    assert!(ok, "{out}");
    assert!(
        out.contains("+[include klipcal.cfg]") && out.contains("+[update_manager klipcal-"),
        "{out}"
    );
    assert!(out.contains("+type: executable"), "{out}");
    assert_eq!(
        differ(&snapshot(&pd), &before),
        Vec::<String>::new(),
        "a dry run wrote something"
    );

    let (ok, out) = run(&bench, &install_args(&bench, &["--yes"]));
    assert!(ok, "{out}");
    let after_install = snapshot(&pd);
    let printer_now = std::fs::read_to_string(cfg.join("printer.cfg")).unwrap();
    assert_eq!(
        printer_now.matches("[include klipcal.cfg]").count(),
        1,
        "{printer_now}"
    );
    // Kalico loads respond without a section: install adds none there.
    assert_eq!(
        printer_now.contains("[respond]"),
        !crate::bench::on_kalico(),
        "{printer_now}"
    );
    // The service of this printer (its folder is not `printer_data`: klipcal-<folder>).
    let service = format!("klipcal-{}", pd.file_name().unwrap().to_string_lossy());
    assert!(std::fs::read_to_string(pd.join("moonraker.asvc"))
        .unwrap()
        .lines()
        .any(|l| l == service));
    let rinfo: Value = serde_json::from_str(
        &std::fs::read_to_string(pd.join("klipcal-bin/release_info.json")).unwrap(),
    )
    .unwrap();
    let asset = rinfo["asset_name"].as_str().unwrap();
    assert!(pd.join("klipcal-bin").join(asset).is_file(), "{rinfo}");

    // Moonraker (restarted by install) loads the section without a warning about klipcal.
    wait_ready(&bench).await;
    let info = files.get("/server/info").await.unwrap();
    let warnings = info["warnings"].to_string();
    assert!(!warnings.to_lowercase().contains("klipcal"), "{warnings}");
    let upd = poll(Duration::from_secs(30), || async {
        let v = files.get("/machine/update/status").await.ok()?;
        let k = v["version_info"][&service].clone();
        (!k.is_null()).then_some(k)
    })
    .await
    .expect("update_manager does not list klipcal");
    assert_eq!(
        upd["version"],
        json!(format!("v{}", env!("CARGO_PKG_VERSION"))),
        "{upd}"
    );
    assert_eq!(upd["configured_type"], "executable", "{upd}");
    assert!(
        upd["warnings"].as_array().is_none_or(|w| w.is_empty()),
        "update_manager warns about klipcal: {upd}"
    );
    // Klipper (restarted by install) runs the macros, and KLIPCAL_STATUS answers.
    let help = files.get("/printer/gcode/help").await.unwrap();
    assert!(help["KLIPCAL_STATUS"].is_string(), "{help}");
    let _d = Daemon::ready(&bench, "").await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let mut rx = m.events();
    m.gcode("KLIPCAL_STATUS").await.unwrap();
    let answer = wait_event(&mut rx, Duration::from_secs(15), |e| {
        matches!(e, klipcal::moonraker::Event::GcodeResponse(t) if t.contains("rotation_distance"))
    })
    .await;
    assert!(answer.is_some(), "KLIPCAL_STATUS did not answer");

    // A second install changes nothing.
    let (ok, out) = run(&bench, &install_args(&bench, &["--yes"]));
    assert!(ok && out.contains("nothing to change"), "{out}");
    assert_eq!(differ(&snapshot(&pd), &after_install), Vec::<String>::new());

    // Uninstall: a dry run writes nothing; then every file is back byte for byte.
    let un = [
        "uninstall".to_string(),
        "--printer-data".into(),
        pd.display().to_string(),
    ];
    let mut dry = un.to_vec();
    dry.push("--dry-run".into());
    let (ok, out) = run(&bench, &dry);
    assert!(ok && out.contains("-[include klipcal.cfg]"), "{out}");
    assert_eq!(differ(&snapshot(&pd), &after_install), Vec::<String>::new());
    let (ok, out) = run(&bench, &un);
    assert!(ok, "{out}");
    assert_eq!(
        differ(&snapshot(&pd), &before),
        Vec::<String>::new(),
        "uninstall left differences"
    );
    wait_ready(&bench).await;
    let info = files.get("/server/info").await.unwrap();
    assert!(
        info["failed_components"].as_array().unwrap().is_empty(),
        "{info}"
    );
}

#[tokio::test]
async fn install_refuses_a_conflict_a_missing_layout_and_keeps_a_users_later_edits() {
    let bench = Bench::start("corexy");
    let pd = bench.dir.path().to_path_buf();
    let cfg = pd.join("config");
    // No printer_data layout.
    let (ok, out) = klipcal(
        &bench,
        &[
            "install",
            "--printer-data",
            "/nonexistent/pd",
            "--no-systemd",
        ],
    );
    assert!(!ok && out.contains("no printer_data layout"), "{out}");
    // A moonraker.conf with someone else's [update_manager klipcal].
    let conf0 = std::fs::read_to_string(cfg.join("moonraker.conf")).unwrap();
    let service = format!("klipcal-{}", pd.file_name().unwrap().to_string_lossy());
    let theirs = format!("{conf0}\n[update_manager {service}]\ntype: git_repo\npath: ~/klipcal\norigin: https://example.org/klipcal.git\n");
    std::fs::write(cfg.join("moonraker.conf"), &theirs).unwrap();
    let before = snapshot(&pd);
    let (ok, out) = run(&bench, &install_args(&bench, &["--yes", "--no-restart"]));
    assert!(!ok && out.contains("did not write"), "{out}");
    assert_eq!(
        differ(&snapshot(&pd), &before),
        Vec::<String>::new(),
        "a refused install wrote something"
    );
    std::fs::write(cfg.join("moonraker.conf"), &conf0).unwrap();
    // An existing include of klipcal.cfg is kept as it is (the bench's printer.cfg has one).
    let printer0 = std::fs::read_to_string(cfg.join("printer.cfg")).unwrap();
    let (ok, out) = run(&bench, &install_args(&bench, &["--yes", "--no-restart"]));
    assert!(ok, "{out}");
    assert_eq!(
        std::fs::read_to_string(cfg.join("printer.cfg")).unwrap(),
        printer0
    );
    // The user edits moonraker.conf after the install: uninstall takes out only klipcal's part.
    let mut conf = std::fs::read_to_string(cfg.join("moonraker.conf")).unwrap();
    conf.push_str("\n[webcam cam]\nservice: mjpegstreamer\n");
    std::fs::write(cfg.join("moonraker.conf"), &conf).unwrap();
    let (ok, out) = klipcal(
        &bench,
        &[
            "uninstall",
            "--printer-data",
            pd.to_str().unwrap(),
            "--no-restart",
        ],
    );
    assert!(ok, "{out}");
    let after = std::fs::read_to_string(cfg.join("moonraker.conf")).unwrap();
    assert!(!after.contains("update_manager klipcal"), "{after}");
    assert!(
        after.contains("[webcam cam]\nservice: mjpegstreamer\n"),
        "{after}"
    );
    assert!(after.starts_with(&conf0), "{after}");
}

/// Every file under `dir` with its bytes' hash, except what the bench's own Klipper, Moonraker
/// and plant keep writing whatever klipcal does (logs/, comms/, database/, tmp/).
fn hashed_tree(dir: &Path) -> Vec<(PathBuf, u64)> {
    use std::hash::{Hash, Hasher};
    fn walk(root: &Path, dir: &Path, out: &mut Vec<(PathBuf, u64)>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            let rel = p.strip_prefix(root).unwrap().to_path_buf();
            if ["logs", "comms", "database", "tmp"]
                .iter()
                .any(|d| rel.starts_with(d))
            {
                continue;
            }
            let t = e.file_type().unwrap();
            if t.is_dir() {
                walk(root, &p, out);
            } else if t.is_file() {
                let mut h = std::collections::hash_map::DefaultHasher::new();
                std::fs::read(&p).unwrap().hash(&mut h);
                out.push((rel, h.finish()));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// How often the bench's Klipper and Moonraker have started (a restart adds one).
fn starts(bench: &Bench) -> (usize, usize) {
    let log = |f: &str| std::fs::read_to_string(bench.dir.path().join("logs").join(f)).unwrap();
    (
        log("klippy.log").matches("Start printer at").count(),
        log("moonraker.log")
            .matches("Starting Moonraker on")
            .count(),
    )
}

/// Runs the klipcal binary with `args` and HOME at `home`: whether it succeeded, and its
/// stdout and stderr.
fn klipcal_cli(home: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_klipcal"))
        .args(args)
        .env("HOME", home)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// The port of the bench's Moonraker.
fn moonraker_port(b: &Bench) -> String {
    b.ws_url()
        .split(':')
        .nth(2)
        .unwrap()
        .split('/')
        .next()
        .unwrap()
        .to_string()
}

/// The daemon install set up for `b`, started as the service would start it.
fn start_installed(b: &Bench, home: &Path) -> Daemon {
    let log = b.dir.path().join("klipcal-installed.log");
    let child = Command::new(env!("CARGO_BIN_EXE_klipcal"))
        .args([
            "--config",
            b.dir.path().join("config/klipcal.toml").to_str().unwrap(),
            "serve",
        ])
        .env("HOME", home)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    Daemon {
        child,
        log,
        url: None,
    }
}

/// The daemon `d` is the one agent of its printer's Moonraker, connected to that printer's
/// port, with its database in that printer's data folder.
async fn talks_only_to_its_printer(b: &Bench, d: &Daemon) {
    let files = b.files();
    let listed = poll(Duration::from_secs(30), || async {
        crate::bench::agent_listed(&files).await.then_some(())
    })
    .await;
    assert!(listed.is_some(), "not connected:\n{}", d.log_text());
    let agents = files.get("/server/extensions/list").await.unwrap();
    assert_eq!(agents["agents"].as_array().unwrap().len(), 1, "{agents}");
    assert!(
        d.log_text().contains(&format!(
            "url=ws://127.0.0.1:{}/websocket",
            moonraker_port(b)
        )),
        "{}",
        d.log_text()
    );
    assert!(b
        .dir
        .path()
        .join("klipcal")
        .join("klipcal.sqlite")
        .is_file());
}

/// Uninstall's output names each folder it leaves in `p2` with what it holds, and a daemon
/// still connected; it says nothing of the other printer (`other_pd`).
fn uninstall_names_what_it_leaves(out: &str, p2: &Path, other_pd: &str) {
    for (dir, words) in [
        (p2.join("klipcal"), "database"),
        (p2.join("config/klipcal"), "pictures"),
        (p2.join("config/klipcal_backups"), "copies of config files"),
        (p2.join("gcodes/klipcal"), "G-code"),
    ] {
        let line = out
            .lines()
            .find(|l| l.contains(&format!("{} (", dir.display())))
            .unwrap_or_else(|| panic!("uninstall does not name {}: {out}", dir.display()));
        assert!(line.contains(words), "{line}");
    }
    assert!(out.contains("600 KB"), "{out}");
    assert!(out.contains("still connected"), "{out}");
    assert!(
        !out.contains(other_pd),
        "uninstall spoke of the other printer: {out}"
    );
}

/// Issue 25 D: two printers on one host (two Moonrakers on their own ports). Install reads
/// each printer's Moonraker from its own moonraker.conf (no --moonraker), checks and restarts
/// only that printer, and writes a klipcal.toml with its URL, its own data folder and page
/// port; each daemon talks only to its printer; uninstalling one names what it leaves and a
/// daemon still connected, and leaves the other printer's files byte for byte.
#[tokio::test]
async fn two_printers_on_one_host_each_get_their_own_klipcal() {
    let b1 = Bench::start("corexy");
    let b2 = Bench::start("corexy");
    let home = tempfile::tempdir().unwrap();
    let klipcal = |args: &[&str]| klipcal_cli(home.path(), args);
    let pd = |b: &Bench| b.dir.path().display().to_string();
    let port = moonraker_port;
    // D2: --moonraker is what the written settings name (a note says it is not the folder's).
    let (ok, out) = klipcal(&[
        "--moonraker",
        "ws://127.0.0.1:1/websocket",
        "install",
        "--printer-data",
        &pd(&b1),
        "--no-systemd",
        "--dry-run",
    ]);
    assert!(ok, "{out}");
    assert!(
        out.contains("+url = \"ws://127.0.0.1:1/websocket\"")
            && out.contains("note: --moonraker ws://127.0.0.1:1/websocket"),
        "{out}"
    );
    let mut http_ports = Vec::new();
    for (b, other) in [(&b1, &b2), (&b2, &b1)] {
        let (other_before, this_before) = (starts(other), starts(b));
        let (ok, out) = klipcal(&["install", "--printer-data", &pd(b), "--no-systemd", "--yes"]);
        assert!(ok, "{out}");
        // D1: this printer's Moonraker, from its moonraker.conf.
        assert!(
            out.contains(&format!(
                "Moonraker at ws://127.0.0.1:{}/websocket",
                port(b)
            )),
            "{out}"
        );
        let restarted = poll(Duration::from_secs(30), || async {
            (starts(b).1 > this_before.1).then_some(())
        })
        .await;
        assert!(
            restarted.is_some(),
            "install did not restart its Moonraker: {out}"
        );
        wait_ready(b).await;
        assert_eq!(
            starts(other),
            other_before,
            "install restarted the other printer: {out}"
        );
        // D2: its settings name its Moonraker, its own data folder and a page port of its own.
        let toml = std::fs::read_to_string(b.dir.path().join("config/klipcal.toml")).unwrap();
        let c = klipcal::config::Config::parse(&toml).unwrap();
        assert_eq!(c.moonraker.url, b.ws_url(), "{toml}");
        assert_eq!(
            klipcal::config::expand_home(&c.daemon.data_dir),
            b.dir.path().join("klipcal")
        );
        let bind: std::net::SocketAddr = c.http.bind.parse().unwrap();
        http_ports.push(bind.port());
    }
    assert_ne!(http_ports[0], http_ports[1], "both pages on one port");

    // Each daemon, started as the service would start it, talks only to its printer.
    let start = |b: &Bench| start_installed(b, home.path());
    let d1 = start(&b1);
    let d2 = start(&b2);
    for (b, d) in [(&b1, &d1), (&b2, &d2)] {
        talks_only_to_its_printer(b, d).await;
    }
    for (d, p) in [(&d1, http_ports[0]), (&d2, http_ports[1])] {
        assert!(
            d.page_url().await.ends_with(&format!(":{p}")),
            "{}",
            d.log_text()
        );
    }

    // What a session leaves: a picture and a print.
    for f in [
        "config/klipcal/ab-s1-r1.png",
        "gcodes/klipcal/ab-s1-r1.gcode",
    ] {
        let p = b2.dir.path().join(f);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(&p, vec![b'x'; 600 * 1024]).unwrap();
    }
    // Moonraker 0.11 cannot be restarted while its start-up shell commands still run (apt's
    // package refresh, the new print's metadata): its close() fails with "Set changed size
    // during iteration" and it does not come back (seen 2 s after the install's restart on a
    // loaded host). A user uninstalls later than that; so does the test.
    tokio::time::sleep(Duration::from_secs(15)).await;
    // D3/D4: uninstall printer 2 while its daemon runs; printer 1 is left byte for byte.
    let mut d1 = d1;
    assert!(d1.terminate(Duration::from_secs(10)).is_some());
    let before = hashed_tree(b1.dir.path());
    let starts_before = starts(&b1);
    let (ok, out) = klipcal(&["uninstall", "--printer-data", &pd(&b2), "--no-systemd"]);
    assert!(ok, "{out}");
    uninstall_names_what_it_leaves(&out, b2.dir.path(), &pd(&b1));
    let restarted = poll(Duration::from_secs(60), || async {
        (starts(&b2).1 > 2).then_some(())
    })
    .await;
    assert!(
        restarted.is_some(),
        "uninstall did not restart its Moonraker: {out}"
    );
    wait_ready(&b2).await;
    wait_ready(&b1).await;
    assert_eq!(
        starts(&b1),
        starts_before,
        "uninstall restarted the other printer"
    );
    assert_eq!(
        hashed_tree(b1.dir.path()),
        before,
        "the other printer's files changed"
    );
    drop(d2);
}

/// The webcams Moonraker lists: (name, service, stream_url), sorted.
async fn webcams(b: &Bench) -> Vec<(String, String, String)> {
    let v = b.files().get("/server/webcams/list").await.unwrap();
    let mut out: Vec<(String, String, String)> = v["webcams"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let s = |k: &str| c[k].as_str().unwrap_or("").to_string();
            (s("name"), s("service"), s("stream_url"))
        })
        .collect();
    out.sort();
    out
}

/// Issue 26 A.6: install offers klipcal's page as an iframe webcam of Moonraker (what Mainsail
/// and Fluidd show in their webcam panels): without a terminal it says how (--webcam) and adds
/// nothing; --webcam adds it with the page's address; a second install changes nothing; a
/// "klipcal" webcam install did not make is left alone; uninstall removes it; the other
/// printer's webcams are untouched throughout.
#[tokio::test]
async fn install_shows_the_page_as_an_iframe_webcam_and_uninstall_removes_it() {
    let b1 = Bench::start("corexy");
    let b2 = Bench::start("corexy");
    let f2 = b2.files();
    f2.post(
        "/server/webcams/item",
        &json!({"name": "Front", "service": "mjpegstreamer", "stream_url": "/webcam/?action=stream"}),
    )
    .await
    .unwrap();
    let other = webcams(&b2).await;
    assert_eq!(other.len(), 1, "{other:?}");
    let ours = |cams: &[(String, String, String)]| {
        cams.iter()
            .filter(|c| c.0 == "klipcal")
            .cloned()
            .collect::<Vec<_>>()
    };

    // No terminal, no flag: offered, not added.
    let (ok, out) = run(&b1, &install_args(&b1, &["--no-restart"]));
    assert!(ok, "{out}");
    assert!(out.contains("run with --webcam"), "{out}");
    assert!(ours(&webcams(&b1).await).is_empty());

    // --webcam: added, with the address klipcal's page answers at.
    let (ok, out) = run(&b1, &install_args(&b1, &["--no-restart", "--webcam"]));
    assert!(ok, "{out}");
    let toml = std::fs::read_to_string(b1.dir.path().join("config/klipcal.toml")).unwrap();
    let bind: std::net::SocketAddr = klipcal::config::Config::parse(&toml)
        .unwrap()
        .http
        .bind
        .parse()
        .unwrap();
    let url = klipcal::http::page_address_here(bind);
    assert!(url.starts_with("http://") && url.ends_with(&format!(":{}/", bind.port())));
    assert!(out.contains("webcam   klipcal added"), "{out}");
    assert_eq!(
        ours(&webcams(&b1).await),
        vec![("klipcal".to_string(), "iframe".to_string(), url.clone())]
    );
    let (ok, out) = run(&b1, &install_args(&b1, &["--no-restart", "--webcam"]));
    assert!(ok && out.contains("nothing to change"), "{out}");
    assert_eq!(ours(&webcams(&b1).await).len(), 1);
    assert_eq!(
        webcams(&b2).await,
        other,
        "the other printer's webcams changed"
    );

    // A "klipcal" webcam the user made on the other printer is theirs: left alone.
    f2.post(
        "/server/webcams/item",
        &json!({"name": "klipcal", "service": "iframe", "stream_url": "http://10.9.9.9:7150/"}),
    )
    .await
    .unwrap();
    let other = webcams(&b2).await;
    let (ok, out) = run(&b2, &install_args(&b2, &["--no-restart", "--webcam"]));
    assert!(ok && out.contains("left as it is"), "{out}");
    assert_eq!(webcams(&b2).await, other);

    // Uninstall removes it; the other printer's are untouched.
    let (ok, out) = run(
        &b1,
        &[
            "uninstall".to_string(),
            "--printer-data".into(),
            b1.dir.path().display().to_string(),
            "--no-restart".into(),
        ],
    );
    assert!(
        ok && out.contains("removed  Moonraker webcam klipcal"),
        "{out}"
    );
    assert!(ours(&webcams(&b1).await).is_empty(), "{out}");
    let (ok, out) = run(
        &b2,
        &[
            "uninstall".to_string(),
            "--printer-data".into(),
            b2.dir.path().display().to_string(),
            "--no-restart".into(),
        ],
    );
    assert!(ok, "{out}");
    assert_eq!(
        webcams(&b2).await,
        other,
        "uninstall removed the user's webcam"
    );
}
