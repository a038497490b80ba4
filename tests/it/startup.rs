//! The daemon when Moonraker is not there, or not its own: one clear warning while Moonraker
//! cannot be reached (again only when the reason changes), a plain-text log when stderr is not
//! a terminal, and a second daemon on the same Moonraker exiting with Moonraker's reason.

use std::io::{Read, Write};
use std::net::TcpListener;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::bench::{agent_listed, Bench, Daemon};

/// The daemon pointed at `url`, logging at its default level to a file.
struct Lone {
    child: Child,
    log: std::path::PathBuf,
    _dir: tempfile::TempDir,
}

impl Lone {
    fn start(url: &str, reconnect_max_s: f64) -> Lone {
        let dir = tempfile::tempdir().unwrap();
        let cfg = dir.path().join("klipcal.toml");
        std::fs::write(
            &cfg,
            format!(
                "[moonraker]\nurl = \"{url}\"\nreconnect_min_s = 0.2\nreconnect_max_s = \
                 {reconnect_max_s}\n[daemon]\ndata_dir = \"{}\"\n[http]\nbind = \"127.0.0.1:0\"\n",
                dir.path().join("data").display()
            ),
        )
        .unwrap();
        let log = dir.path().join("klipcal.log");
        let child = Command::new(env!("CARGO_BIN_EXE_klipcal"))
            .args(["--config", cfg.to_str().unwrap(), "serve"])
            .env_remove("RUST_LOG")
            .env_remove("JOURNAL_STREAM")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("klipcal binary");
        Lone {
            child,
            log,
            _dir: dir,
        }
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Waits until the log holds `n` lines containing `needle`; returns the log.
    fn wait_lines(&self, needle: &str, n: usize, limit: Duration) -> String {
        let start = Instant::now();
        loop {
            let text = self.log_text();
            if text.lines().filter(|l| l.contains(needle)).count() >= n || start.elapsed() > limit {
                return text;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Lone {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn warnings(log: &str) -> Vec<&str> {
    log.lines()
        .filter(|l| l.contains("cannot reach Moonraker"))
        .collect()
}

#[test]
fn unreachable_moonraker_is_warned_once_per_reason_at_the_default_level() {
    let port = free_port();
    let url = format!("ws://127.0.0.1:{port}/websocket");
    let d = Lone::start(&url, 1.0);
    let log = d.wait_lines("cannot reach Moonraker", 1, Duration::from_secs(10));
    let w = warnings(&log);
    assert_eq!(w.len(), 1, "one warning within 10 s:\n{log}");
    assert!(w[0].contains("WARN"), "{log}");
    assert!(
        w[0].contains(&format!(
            "cannot reach Moonraker at {url}: connection refused; retrying every 1 s at most"
        )),
        "{log}"
    );
    // Several retries later (1 s apart at most) still one warning.
    std::thread::sleep(Duration::from_secs(4));
    assert_eq!(warnings(&d.log_text()).len(), 1, "{}", d.log_text());

    // The reason changes: something answers on the port, but not as Moonraker does.
    let listener = TcpListener::bind(("127.0.0.1", port)).unwrap();
    listener.set_nonblocking(true).unwrap();
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(6) {
        match listener.accept() {
            Ok((mut s, _)) => {
                s.set_nonblocking(false).unwrap();
                s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
                let mut buf = [0u8; 2048];
                let _ = s.read(&mut buf);
                let _ = s.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n");
            }
            Err(_) => std::thread::sleep(Duration::from_millis(20)),
        }
    }
    drop(listener);
    let log = d.wait_lines("cannot reach Moonraker", 3, Duration::from_secs(10));
    let w = warnings(&log);
    assert_eq!(w.len(), 3, "refused, then 404, then refused again:\n{log}");
    assert!(w[1].contains("HTTP 404"), "{log}");
    assert!(w[2].contains("connection refused"), "{log}");
}

#[test]
fn the_log_has_no_colour_codes_when_stderr_is_not_a_terminal() {
    let url = format!("ws://127.0.0.1:{}/websocket", free_port());
    let d = Lone::start(&url, 1.0);
    let log = d.wait_lines("cannot reach Moonraker", 1, Duration::from_secs(10));
    assert!(log.contains("klipcal starting"), "{log}");
    assert!(
        !log.contains('\u{1b}'),
        "ANSI escape codes in a log file:\n{log:?}"
    );
}

#[tokio::test]
async fn a_second_daemon_on_the_same_moonraker_exits_with_moonrakers_reason() {
    let bench = Bench::start("corexy");
    let _first = Daemon::ready(&bench, "").await;
    let mut second = Daemon::start_with(&bench, "");
    let start = Instant::now();
    let status = loop {
        if let Some(st) = second.child.try_wait().unwrap() {
            break Some(st);
        }
        if start.elapsed() > Duration::from_secs(30) {
            break None;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let log = second.log_text();
    let status = status.unwrap_or_else(|| panic!("the second daemon stayed up:\n{log}"));
    assert!(!status.success(), "{log}");
    assert!(log.contains("already registered"), "{log}");
    assert!(log.contains("another klipcal is already serving"), "{log}");
    // The first one keeps serving.
    assert!(agent_listed(&bench.files()).await);
}
