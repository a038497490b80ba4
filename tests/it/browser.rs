//! A real browser for the page's tests: Debian's headless Chromium (installed by the bench's
//! setup), driven over the DevTools protocol on a websocket — navigate, evaluate JavaScript in
//! the page as a user's clicks and typing would, take screenshots. Killed on drop.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use serde_json::{json, Value};
use tokio_tungstenite::tungstenite::Message;

type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// How long Chromium may take to print its DevTools address and open its socket.
const START_LIMIT: Duration = Duration::from_secs(60);
/// How long one DevTools command may take: a page's script or a screenshot on a machine at
/// load 13 took over the 30 s this once was.
const ANSWER_LIMIT: Duration = Duration::from_secs(90);

pub struct Browser {
    child: Child,
    ws: Socket,
    session: String,
    next_id: u64,
    /// The tab's size in CSS pixels, and whether it is a phone's (touch, mobile layout).
    viewport: (u32, u32, bool),
    _profile: tempfile::TempDir,
}

impl Browser {
    /// Starts headless Chromium with an empty profile and opens one tab. Under load (a CI run
    /// beside other builds) Chromium can be slow to print its DevTools address or to answer
    /// the first commands ("DevTools never answered" once at load 13): the start waits longer
    /// and is tried again from scratch, up to three times, before the test fails.
    pub async fn start() -> Browser {
        let mut why = Vec::new();
        for attempt in 1..=3 {
            match Self::try_start().await {
                Ok(b) => return b,
                Err(e) => {
                    eprintln!("chromium start {attempt}/3 failed: {e}");
                    why.push(e);
                }
            }
        }
        panic!("chromium never started: {why:?}");
    }

    async fn try_start() -> Result<Browser, String> {
        let profile = tempfile::tempdir().unwrap();
        let mut child = Command::new("chromium")
            .args([
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--window-size=430,900",
                "--remote-debugging-port=0",
                &format!("--user-data-dir={}", profile.path().display()),
                "about:blank",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("chromium (tests/bench/setup.sh installs it with apt-get)");
        let stderr = child.stderr.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(url) = line.split("DevTools listening on ").nth(1) {
                    let _ = tx.send(url.trim().to_string());
                }
            }
        });
        let fail = |mut child: Child, e: String| -> Result<Browser, String> {
            let _ = child.kill();
            let _ = child.wait();
            Err(e)
        };
        let url = match rx.recv_timeout(START_LIMIT) {
            Ok(url) => url,
            Err(_) => return fail(child, "chromium never printed its DevTools address".into()),
        };
        let ws =
            match tokio::time::timeout(START_LIMIT, tokio_tungstenite::connect_async(url.as_str()))
                .await
            {
                Ok(Ok((ws, _))) => ws,
                Ok(Err(e)) => return fail(child, format!("DevTools websocket: {e}")),
                Err(_) => return fail(child, "DevTools websocket: no answer".into()),
            };
        let mut b = Browser {
            child,
            ws,
            session: String::new(),
            next_id: 0,
            viewport: (430, 900, true),
            _profile: profile,
        };
        // The handshake: its errors and silences are the start's, tried again (the Browser's
        // drop kills this Chromium).
        let target = b
            .try_send(None, "Target.createTarget", json!({"url": "about:blank"}))
            .await?;
        let attached = b
            .try_send(
                None,
                "Target.attachToTarget",
                json!({"targetId": target["targetId"], "flatten": true}),
            )
            .await?;
        b.session = attached["sessionId"]
            .as_str()
            .ok_or_else(|| format!("no session in {attached}"))?
            .to_string();
        let s = b.session.clone();
        b.try_send(Some(&s), "Page.enable", json!({})).await?;
        b.try_send(Some(&s), "Runtime.enable", json!({})).await?;
        // A phone-sized window.
        b.set_viewport(430, 900, true).await;
        Ok(b)
    }

    /// Resizes the tab: `mobile` emulates a phone (its layout and touch).
    pub async fn set_viewport(&mut self, width: u32, height: u32, mobile: bool) {
        self.viewport = (width, height, mobile);
        self.apply_viewport(height).await;
    }

    async fn apply_viewport(&mut self, height: u32) {
        let (width, _, mobile) = self.viewport;
        self.cmd(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": mobile}),
        )
        .await;
    }

    /// Types `text` into the focused field, as a keyboard would.
    pub async fn type_text(&mut self, text: &str) {
        self.cmd("Input.insertText", json!({ "text": text })).await;
    }

    /// Presses and releases Enter.
    pub async fn press_enter(&mut self) {
        for (ty, text) in [("keyDown", "\r"), ("keyUp", "")] {
            self.cmd(
                "Input.dispatchKeyEvent",
                json!({"type": ty, "key": "Enter", "code": "Enter",
                       "windowsVirtualKeyCode": 13, "text": text}),
            )
            .await;
        }
    }

    /// A click (a tap) at a point of the window, as the mouse gives it.
    pub async fn tap(&mut self, x: f64, y: f64) {
        for ty in ["mousePressed", "mouseReleased"] {
            self.cmd(
                "Input.dispatchMouseEvent",
                json!({"type": ty, "x": x, "y": y, "button": "left", "clickCount": 1}),
            )
            .await;
        }
    }

    async fn send(&mut self, session: Option<&str>, method: &str, params: Value) -> Value {
        match self.try_send(session, method, params).await {
            Ok(v) => v,
            Err(e) => panic!("DevTools {method}: {e}"),
        }
    }

    async fn try_send(
        &mut self,
        session: Option<&str>,
        method: &str,
        params: Value,
    ) -> Result<Value, String> {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = session {
            msg["sessionId"] = json!(s);
        }
        self.ws
            .send(Message::Text(msg.to_string().into()))
            .await
            .map_err(|e| format!("DevTools {method} not sent: {e}"))?;
        let deadline = tokio::time::Instant::now() + ANSWER_LIMIT;
        loop {
            let frame = tokio::time::timeout_at(deadline, self.ws.next())
                .await
                .map_err(|_| format!("DevTools never answered {method} within {ANSWER_LIMIT:?}"))?
                .ok_or_else(|| format!("DevTools closed before answering {method}"))?
                .map_err(|e| format!("DevTools {method}: {e}"))?;
            let Message::Text(text) = frame else { continue };
            let v: Value = serde_json::from_str(&text).unwrap();
            if v["id"] == json!(id) {
                if let Some(e) = v.get("error") {
                    return Err(e.to_string());
                }
                return Ok(v["result"].clone());
            }
        }
    }

    /// A command in the tab.
    pub async fn cmd(&mut self, method: &str, params: Value) -> Value {
        let s = self.session.clone();
        self.send(Some(&s), method, params).await
    }

    /// Evaluates `js` in the page (awaiting a promise) and returns its value.
    pub async fn eval(&mut self, js: &str) -> Value {
        let r = self
            .cmd(
                "Runtime.evaluate",
                json!({"expression": js, "awaitPromise": true, "returnByValue": true}),
            )
            .await;
        if let Some(e) = r.get("exceptionDetails") {
            panic!("page script failed: {e}\n{js}");
        }
        r["result"]["value"].clone()
    }

    /// Evaluates `js` inside the frame whose address starts with `url` (an iframe of the page,
    /// e.g. klipcal's page as Mainsail's webcam), in a world of its own that sees the frame's
    /// document; `None` while no such frame is there.
    pub async fn eval_in_frame(&mut self, url: &str, js: &str) -> Option<Value> {
        fn find(tree: &Value, url: &str) -> Option<String> {
            if tree["frame"]["url"].as_str()?.starts_with(url)
                && tree["frame"]["parentId"].is_string()
            {
                return tree["frame"]["id"].as_str().map(str::to_string);
            }
            tree["childFrames"]
                .as_array()?
                .iter()
                .find_map(|c| find(c, url))
        }
        let tree = self.cmd("Page.getFrameTree", json!({})).await;
        let frame = find(&tree["frameTree"], url)?;
        let s = self.session.clone();
        let world = self
            .try_send(
                Some(&s),
                "Page.createIsolatedWorld",
                json!({"frameId": frame, "worldName": "klipcal-test"}),
            )
            .await
            .ok()?;
        let r = self
            .try_send(
                Some(&s),
                "Runtime.evaluate",
                json!({"expression": js, "contextId": world["executionContextId"],
                       "awaitPromise": true, "returnByValue": true}),
            )
            .await
            .ok()?;
        if r.get("exceptionDetails").is_some() {
            return None;
        }
        Some(r["result"]["value"].clone())
    }

    /// Opens `url` and waits until the document has loaded.
    pub async fn open(&mut self, url: &str) {
        self.cmd("Page.navigate", json!({"url": url})).await;
        self.wait_for(
            "document.readyState === 'complete' && location.href !== 'about:blank'",
            Duration::from_secs(20),
        )
        .await;
    }

    /// Polls `js` until it is true (e.g. after a reload), at most `limit`.
    pub async fn wait_for(&mut self, js: &str, limit: Duration) -> bool {
        let deadline = tokio::time::Instant::now() + limit;
        let probe =
            format!("(() => {{ try {{ return !!({js}); }} catch (e) {{ return false; }} }})()");
        while tokio::time::Instant::now() < deadline {
            // While the page reloads the evaluation may fail: that is "not yet".
            let s = self.session.clone();
            let r = self
                .try_send(
                    Some(&s),
                    "Runtime.evaluate",
                    json!({"expression": probe, "returnByValue": true}),
                )
                .await;
            if r.is_ok_and(|r| r["result"]["value"] == json!(true)) {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(150)).await;
        }
        false
    }

    /// Saves a PNG screenshot of the page to `path`.
    pub async fn screenshot(&mut self, path: &std::path::Path) {
        // The whole page: the window grows to the document's height for the shot.
        let height = self
            .eval("Math.ceil(document.documentElement.scrollHeight)")
            .await
            .as_u64()
            .unwrap_or(900)
            .clamp(300, 8000);
        self.apply_viewport(u32::try_from(height).unwrap_or(900))
            .await;
        let r = self
            .cmd("Page.captureScreenshot", json!({"format": "png"}))
            .await;
        self.apply_viewport(self.viewport.1).await;
        self.save_png(&r, path);
    }

    /// Saves a PNG screenshot of what the window shows now (its size, not the whole page:
    /// an app such as Mainsail or Fluidd that scrolls inside its own panels).
    pub async fn screenshot_window(&mut self, path: &std::path::Path) {
        let r = self
            .cmd("Page.captureScreenshot", json!({"format": "png"}))
            .await;
        self.save_png(&r, path);
    }

    fn save_png(&self, r: &Value, path: &std::path::Path) {
        let data = r["data"].as_str().unwrap();
        let png = data_encoding::BASE64.decode(data.as_bytes()).unwrap();
        assert!(png.starts_with(b"\x89PNG"), "not a PNG");
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).unwrap();
        }
        std::fs::write(path, png).unwrap();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Where tests keep what a person would look at (screenshots): `target/test-artifacts/`.
pub fn artifact(name: &str) -> std::path::PathBuf {
    crate::bench::repo()
        .join("target/test-artifacts")
        .join(name)
}

/// The largest picture in docs/images, bytes (tests/it/docs.rs checks the same).
const DOC_IMAGE_BYTES_MAX: usize = 150 * 1024;

/// With `KLIPCAL_DOC_IMAGES=1` (scripts/doc-images.sh), keeps the screenshot `shot` as the
/// documentation's picture `docs/images/<name>`: scaled down to at most `width` px wide (and
/// further, a tenth at a time, until it fits the docs' size limit), without alpha, at PNG's best
/// compression. Without the variable it does nothing, so the tests run as before.
pub fn doc_image(shot: &std::path::Path, name: &str, width: u32) {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    if std::env::var("KLIPCAL_DOC_IMAGES").map_or(true, |v| v != "1") {
        return;
    }
    let img = image::open(shot).unwrap().to_rgb8();
    let mut w = width.min(img.width());
    loop {
        let h = (u64::from(img.height()) * u64::from(w) / u64::from(img.width())).max(1);
        let small = image::imageops::resize(
            &img,
            w,
            u32::try_from(h).unwrap(),
            image::imageops::FilterType::Lanczos3,
        );
        let mut png = Vec::new();
        PngEncoder::new_with_quality(&mut png, CompressionType::Best, FilterType::Adaptive)
            .write_image(
                small.as_raw(),
                small.width(),
                small.height(),
                image::ExtendedColorType::Rgb8,
            )
            .unwrap();
        if png.len() <= DOC_IMAGE_BYTES_MAX || w < 200 {
            let path = crate::bench::repo().join("docs/images").join(name);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, &png).unwrap();
            println!(
                "doc image {} ({w} px wide, {} bytes)",
                path.display(),
                png.len()
            );
            return;
        }
        w = w * 9 / 10;
    }
}

impl Browser {
    /// Saves a PNG screenshot of one element of the page (found by a CSS selector, scrolled
    /// into view), with `margin` CSS px around it.
    pub async fn screenshot_element(
        &mut self,
        selector: &str,
        margin: f64,
        path: &std::path::Path,
    ) {
        let r = self
            .eval(&format!(
                "(() => {{ const e = document.querySelector({sel}); if (!e) return null;
                   e.scrollIntoView({{block: 'start'}}); const r = e.getBoundingClientRect();
                   return JSON.stringify({{x: r.left + window.scrollX, y: r.top + window.scrollY,
                                           w: r.width, h: r.height}}); }})()",
                sel = serde_json::to_string(selector).unwrap()
            ))
            .await;
        let r: Value =
            serde_json::from_str(r.as_str().unwrap_or_else(|| panic!("no {selector}"))).unwrap();
        let at = |k: &str| r[k].as_f64().unwrap();
        let clip = json!({
            "x": (at("x") - margin).max(0.0), "y": (at("y") - margin).max(0.0),
            "width": at("w") + 2.0 * margin, "height": at("h") + 2.0 * margin, "scale": 1,
        });
        let shot = self
            .cmd(
                "Page.captureScreenshot",
                json!({"format": "png", "clip": clip, "captureBeyondViewport": true}),
            )
            .await;
        self.save_png(&shot, path);
    }
}
