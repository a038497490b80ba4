//! Test helpers: start and stop a bench run (tests/bench/bench.py) and the klipcal daemon,
//! and small waits on Moonraker. Nothing here asserts; tests do.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use klipcal::moonraker::{ClientOptions, Event, Files, Moonraker};
use serde_json::{json, Map, Value};
use tokio_util::sync::CancellationToken;

pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Runs the `klipcal` binary as `cmd` sets it up and asserts that it succeeded (its stderr in
/// the failure message); its output.
pub fn klipcal_ok(cmd: &mut Command) -> std::process::Output {
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The daemon binary for `klipcal bench …`, which execs `klipcal-bench` beside it: fails with
/// what to do when that binary was not built (`cargo test --workspace` builds it through the
/// bench crate's own tests; `cargo test -p klipcal` alone does not).
pub fn klipcal_with_bench() -> &'static str {
    let klipcal = env!("CARGO_BIN_EXE_klipcal");
    let bench = std::path::Path::new(klipcal).with_file_name("klipcal-bench");
    assert!(
        bench.exists(),
        "{} is missing: `klipcal bench …` runs it; build it first with \
         `cargo build -p klipcal-bench` (tests/run-all.sh does)",
        bench.display()
    );
    klipcal
}

fn bench_py(args: &[&str]) -> Result<String, String> {
    let out = Command::new("python3")
        .arg(repo().join("tests/bench/bench.py"))
        .args(args)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("cannot run python3: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "bench.py {args:?} failed: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The Klipper host the benches of this test run use: `kalico` when `KLIPCAL_KLIPPY=kalico`
/// (tests/run-all.sh's second pass), else Klipper's `klippy` (bench.py reads the same variable).
pub fn host() -> String {
    std::env::var("KLIPCAL_KLIPPY").unwrap_or_else(|_| "klippy".into())
}

/// True when the benches run Kalico's klippy.
pub fn on_kalico() -> bool {
    host() == "kalico"
}

/// One bench run; stopped on drop.
pub struct Bench {
    pub dir: tempfile::TempDir,
    pub info: Value,
}

impl Bench {
    /// Starts klippy, Moonraker and the thermal plant. Panics (fails the test) when the bench
    /// cannot start: tests never skip silently.
    pub fn start(kinematics: &str) -> Bench {
        Self::start_with(kinematics, None)
    }

    pub fn start_with(kinematics: &str, plant_json: Option<&str>) -> Bench {
        let extra: Vec<&str> = match plant_json {
            Some(p) => vec!["--plant-json", p],
            None => vec![],
        };
        Self::start_args(kinematics, &extra)
    }

    /// Starts a bench with extra `bench.py start` arguments (e.g. `--backlash-module seed`).
    pub fn start_args(kinematics: &str, extra: &[&str]) -> Bench {
        let dir = tempfile::Builder::new()
            .prefix("kc-")
            .tempdir_in(std::env::temp_dir())
            .expect("temp dir");
        let run_dir = dir.path().to_string_lossy().into_owned();
        let owner = std::process::id().to_string();
        let mut args = vec![
            "start",
            "--run-dir",
            &run_dir,
            "--kinematics",
            kinematics,
            "--owner-pid",
            &owner,
        ];
        args.extend_from_slice(extra);
        let out = bench_py(&args).unwrap_or_else(|e| panic!("bench did not start: {e}"));
        let line = out.lines().rev().find(|l| l.starts_with('{')).unwrap_or("");
        let info: Value =
            serde_json::from_str(line).unwrap_or_else(|e| panic!("bench output {out:?}: {e}"));
        Bench { dir, info }
    }

    pub fn ws_url(&self) -> String {
        self.info["ws_url"].as_str().unwrap().to_string()
    }

    pub fn http_url(&self) -> String {
        self.info["http_url"].as_str().unwrap().to_string()
    }

    pub fn run_dir(&self) -> String {
        self.dir.path().to_string_lossy().into_owned()
    }

    pub fn stop_one(&self, name: &str) {
        bench_py(&["stop-one", name, "--run-dir", &self.run_dir()]).unwrap();
    }

    pub fn start_one(&self, name: &str) {
        bench_py(&["start-one", name, "--run-dir", &self.run_dir()]).unwrap();
    }

    /// Restarts klippy (its config re-read from disk) and waits until Moonraker reports it
    /// ready; panics after 60 s.
    pub async fn restart_klippy(&self) {
        self.stop_one("klippy");
        self.start_one("klippy");
        let files = self.files();
        let ready = poll(Duration::from_secs(60), || async {
            let v = files.get("/server/info").await.ok()?;
            (v["klippy_state"] == "ready").then_some(())
        })
        .await;
        assert!(ready.is_some(), "klippy did not come back ready");
    }

    pub fn files(&self) -> Files {
        Files::new(&self.http_url(), None, Duration::from_secs(30)).unwrap()
    }

    /// A test's own Moonraker client (not an agent's methods).
    pub fn client(&self, subscriptions: Value) -> (Moonraker, CancellationToken) {
        let cancel = CancellationToken::new();
        let subs = match subscriptions {
            Value::Object(m) => m,
            _ => Map::new(),
        };
        let (m, _calls) = Moonraker::spawn(
            ClientOptions {
                url: self.ws_url(),
                api_key: None,
                client_name: "klipcal-test".into(),
                agent: false,
                request_timeout: Duration::from_secs(20),
                reconnect_min: Duration::from_millis(200),
                reconnect_max: Duration::from_secs(1),
                remote_methods: vec![],
                subscriptions: subs,
            },
            cancel.clone(),
        );
        (m, cancel)
    }
}

impl Drop for Bench {
    fn drop(&mut self) {
        let _ = bench_py(&["stop", "--run-dir", &self.run_dir()]);
        if std::thread::panicking() {
            // Keep the logs of a failed test for a look.
            let kept = self.dir.path().to_path_buf();
            eprintln!("bench logs kept in {}", kept.display());
            std::mem::forget(std::mem::replace(
                &mut self.dir,
                tempfile::tempdir().expect("temp dir"),
            ));
        }
    }
}

/// The klipcal daemon as a child process; killed on drop.
pub struct Daemon {
    pub child: Child,
    pub log: PathBuf,
    /// The page's base URL (`http://127.0.0.1:PORT`) the helper gave it, when it set `[http]`.
    pub url: Option<String>,
}

/// A loopback port free at the time of asking (the daemon binds it a moment later).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

impl Daemon {
    /// Starts the daemon with extra TOML appended to its settings (e.g. `[ab]`, `[soak]`).
    pub fn start_with(bench: &Bench, extra_toml: &str) -> Daemon {
        let dir = bench.dir.path();
        let cfg = dir.join("klipcal.toml");
        // Tests run side by side: each daemon's page on its own free loopback port, whose
        // address the helper knows (no scraping of the log).
        let port = (!extra_toml.contains("[http]")).then(free_port);
        std::fs::write(
            &cfg,
            format!(
                "[moonraker]\nurl = \"{}\"\nreconnect_min_s = 0.2\nreconnect_max_s = 1.0\n\
                 [daemon]\ndata_dir = \"{}\"\n{}{extra_toml}\n",
                bench.ws_url(),
                dir.join("klipcal-data").display(),
                port.map(|p| format!("[http]\nbind = \"127.0.0.1:{p}\"\n"))
                    .unwrap_or_default()
            ),
        )
        .unwrap();
        let log = dir.join("klipcal.log");
        let child = Command::new(env!("CARGO_BIN_EXE_klipcal"))
            .args(["--config", cfg.to_str().unwrap(), "serve"])
            .env("RUST_LOG", "klipcal=debug")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("klipcal binary");
        Daemon {
            child,
            log,
            url: port.map(|p| format!("http://127.0.0.1:{p}")),
        }
    }

    /// Starts the daemon and waits until Moonraker lists it as an agent and it says it is
    /// connected (its remote methods registered with Klipper: a macro run before that gets
    /// "Remote method … not registered").
    pub async fn ready(bench: &Bench, extra_toml: &str) -> Daemon {
        let d = Self::start_with(bench, extra_toml);
        let files = bench.files();
        let listed = poll(Duration::from_secs(30), || async {
            if !agent_listed(&files).await {
                return None;
            }
            let st = extension_request(&files, "klipcal_status", json!({}))
                .await
                .ok()?;
            (st["connection"]["moonraker"] == "connected").then_some(())
        })
        .await;
        assert!(
            listed.is_some(),
            "klipcal never registered as an agent with its methods:\n{}",
            d.log_text()
        );
        d
    }

    /// The page's base URL (`http://127.0.0.1:PORT`): the address the helper gave the daemon,
    /// or, when a test set its own `[http]`, the one the daemon's log names.
    pub async fn page_url(&self) -> String {
        if let Some(url) = &self.url {
            let up = poll(Duration::from_secs(15), || async {
                reqwest::get(format!("{url}/api/status"))
                    .await
                    .ok()
                    .map(|_| ())
            })
            .await;
            assert!(
                up.is_some(),
                "the daemon's page never answered at {url}:\n{}",
                self.log_text()
            );
            return url.clone();
        }
        let url = poll(Duration::from_secs(15), || async {
            let log = self.log_text();
            let rest = log.split("page and API on ").nth(1)?;
            let url: String = rest.chars().take_while(|c| !c.is_whitespace()).collect();
            Some(url.trim_end_matches('/').to_string())
        })
        .await;
        url.unwrap_or_else(|| {
            panic!(
                "the daemon never said where its page is:\n{}",
                self.log_text()
            )
        })
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Sends SIGTERM and waits at most `limit` for the exit; returns the exit status.
    pub fn terminate(&mut self, limit: Duration) -> Option<std::process::ExitStatus> {
        let pid = self.child.id().to_string();
        Command::new("kill").args(["-TERM", &pid]).status().unwrap();
        let start = Instant::now();
        while start.elapsed() < limit {
            if let Some(st) = self.child.try_wait().unwrap() {
                return Some(st);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Waits for an event matching `pred`, at most `limit`.
pub async fn wait_event(
    rx: &mut tokio::sync::broadcast::Receiver<Event>,
    limit: Duration,
    mut pred: impl FnMut(&Event) -> bool,
) -> Option<Event> {
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, rx.recv()).await {
            Ok(Ok(e)) if pred(&e) => return Some(e),
            Ok(Ok(_)) | Ok(Err(tokio::sync::broadcast::error::RecvError::Lagged(_))) => {}
            _ => return None,
        }
    }
}

/// Polls `f` until it returns Some, at most `limit`.
pub async fn poll<T, F, Fut>(limit: Duration, mut f: F) -> Option<T>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if let Some(v) = f().await {
            return Some(v);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    None
}

/// Whether Moonraker lists klipcal among its connected agents.
pub async fn agent_listed(files: &Files) -> bool {
    match files.get("/server/extensions/list").await {
        Ok(v) => v["agents"]
            .as_array()
            .is_some_and(|a| a.iter().any(|x| x["name"] == "klipcal")),
        Err(_) => false,
    }
}

/// Calls one of klipcal's methods through Moonraker's HTTP extensions endpoint.
pub async fn extension_request(
    files: &Files,
    method: &str,
    arguments: Value,
) -> Result<Value, String> {
    let v = files
        .post(
            "/server/extensions/request",
            &json!({"agent": "klipcal", "method": method, "arguments": arguments}),
        )
        .await
        .map_err(|e| e.to_string())?;
    if v["ok"] == json!(false) {
        return Err(v["error"]["message"].as_str().unwrap_or("").to_string());
    }
    Ok(v)
}

/// One bad call: the operation (`/api/<group>/<op>`, remote method `klipcal_<group>_<op>`), its
/// arguments, what the refusal must name, and the same call typed as a macro (or `None`).
pub type BadCall<'a> = (&'a str, Value, &'a str, Option<&'a str>);

/// Every bad call is refused by name the same way on each road in: through Moonraker as an
/// HTTP caller of the remote method, by the daemon's own API (400, the same message), and typed
/// as a macro (the console says it; a console line has ',' for ';').
pub async fn assert_refused_everywhere(
    bench: &Bench,
    d: &Daemon,
    m: &Moonraker,
    group: &str,
    cases: &[BadCall<'_>],
) {
    let files = bench.files();
    let base = d.page_url().await;
    let http = reqwest::Client::new();
    for (op, args, want, mac) in cases {
        let method = format!("klipcal_{group}_{op}");
        let e = extension_request(&files, &method, args.clone())
            .await
            .expect_err(&format!("{method} {args} was accepted"));
        assert!(e.contains(want), "{method} {args}: {e}");
        assert!(!e.contains("panicked"), "{e}");
        let r = http
            .post(format!("{base}/api/{group}/{op}"))
            .header("content-type", "application/json")
            .body(args.to_string())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 400, "{op} {args}");
        let v: Value = r.json().await.unwrap();
        assert_eq!(v["error"]["message"], json!(e), "{op} {args}");
        if let Some(line) = mac {
            let said_want = want.replace(';', ",");
            let mut rx = m.events();
            m.gcode(line).await.unwrap();
            let said = wait_event(
                &mut rx,
                Duration::from_secs(15),
                |ev| matches!(ev, Event::GcodeResponse(l) if l.contains(&said_want)),
            )
            .await;
            assert!(
                said.is_some(),
                "{line}: no console line with {said_want:?}\n{}",
                d.log_text()
            );
            // Sent as an error (RESPOND TYPE=error), which Mainsail and Fluidd colour
            // (issue 9 item 21): Klipper writes it as "!! …".
            assert!(
                said.as_ref().is_some_and(
                    |ev| matches!(ev, Event::GcodeResponse(l) if l.starts_with("!! "))
                ),
                "{line}: the refusal is not an error line: {said:?}"
            );
        }
    }
}
