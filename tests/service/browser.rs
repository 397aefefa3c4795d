//! A real headless Chromium driven over the DevTools protocol, for the web
//! page's tests.
//!
//! The protocol goes over a pipe (`--remote-debugging-pipe`: Chromium
//! reads commands from its file descriptor 3 and writes answers and events
//! to 4, each message JSON ended by a NUL byte), not a websocket: no
//! client crate, no port to find, nothing else can connect. The shell that
//! starts it puts the pipes on those descriptors (`3<&0 4>&1`) and then
//! `exec`s Chromium, so no `unsafe` is needed to arrange them here.
//!
//! Chromium is never downloaded: it must be installed (`apt-get install -y
//! chromium`; `.ci/run` does where it is missing). Its console, its log
//! (failed loads among them) and uncaught exceptions are collected, for a
//! test to check that the page ran clean.

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use base64::Engine as _;
use serde_json::{json, Value};
use tempfile::TempDir;

/// How long one protocol command may take.
const COMMAND_TIMEOUT: Duration = Duration::from_secs(30);

/// The Chromium to use: `$PTV_CHROMIUM`, else `chromium`,
/// `chromium-browser` or `google-chrome` on the `PATH`, if it starts
/// (`--version` answers): `None` where there is none that does.
pub fn chromium() -> Option<PathBuf> {
    let candidates: Vec<PathBuf> = match std::env::var_os("PTV_CHROMIUM") {
        Some(path) => vec![PathBuf::from(path)],
        None => {
            let path = std::env::var_os("PATH").unwrap_or_default();
            std::env::split_paths(&path)
                .flat_map(|dir| {
                    ["chromium", "chromium-browser", "google-chrome"].map(|name| dir.join(name))
                })
                .filter(|candidate| candidate.is_file())
                .collect()
        }
    };
    candidates.into_iter().find(|binary| {
        Command::new(binary)
            .arg("--version")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|status| status.success())
    })
}

/// Whether tests that need something from outside Rust (Chromium here;
/// PostgreSQL and S3 are asked for by their own variables) must run
/// rather than skip: under CI (`CI=true`, which CI sets) or
/// `PTV_REQUIRE_ALL=1`.
pub fn everything_required() -> bool {
    let set =
        |name: &str| std::env::var(name).is_ok_and(|v| !v.is_empty() && v != "0" && v != "false");
    set("CI") || set("PTV_REQUIRE_ALL")
}

/// The Chromium for `test`, or `None` after one line on standard error
/// saying that `test` was skipped and how to run it, where there is no
/// Chromium that starts. Under [`everything_required`] a missing Chromium
/// fails the test instead. The line goes to the process's standard error
/// directly, past the test harness's capture, so that `cargo test` shows
/// it for a test that passes.
pub fn chromium_or_skip(test: &str) -> Option<PathBuf> {
    let found = chromium();
    if found.is_none() {
        let how = "install it (`apt-get install -y chromium` on Debian; .ci/run does) or set \
                   PTV_CHROMIUM to a Chromium or Chrome binary";
        assert!(
            !everything_required(),
            "{test} needs Chromium and none starts here (CI=true or PTV_REQUIRE_ALL=1 forbid \
             skipping): {how}"
        );
        use std::io::Write as _;
        let _ = writeln!(
            std::io::stderr(),
            "skipped: {test}: no Chromium starts here; {how} (CI=true or PTV_REQUIRE_ALL=1 \
             make this a failure)"
        );
    }
    found
}

/// Something the page's console or log said, or an uncaught exception.
#[derive(Clone, Debug)]
pub struct LogEntry {
    /// `console`, `log` (with its source, e.g. `log/network`) or `exception`.
    pub origin: String,
    /// `error`, `warning`, `info`, ...
    pub level: String,
    /// The message.
    pub text: String,
    /// The resource it is about, if any.
    pub url: Option<String>,
}

/// A headless Chromium with one tab.
pub struct Browser {
    child: Child,
    input: ChildStdin,
    answers: Receiver<Value>,
    next_id: u64,
    session: String,
    /// What the page logged, in order.
    pub log: Arc<Mutex<Vec<LogEntry>>>,
    _profile: TempDir,
    stderr: PathBuf,
}

impl Browser {
    /// Starts Chromium with a fresh profile and opens one tab of
    /// `width` x `height` CSS pixels.
    pub fn launch(binary: &Path, width: u32, height: u32) -> Browser {
        let profile = tempfile::tempdir().unwrap();
        let stderr = profile.path().join("chromium.stderr");
        let mut child = Command::new("sh")
            .arg("-c")
            .arg(r#"exec "$0" "$@" 3<&0 4>&1 </dev/null >/dev/null"#)
            .arg(binary)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-extensions",
                "--hide-scrollbars",
                "--mute-audio",
                "--remote-debugging-pipe",
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&stderr).unwrap())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", binary.display()));
        let input = child.stdin.take().unwrap();
        let output = child.stdout.take().unwrap();
        let (answers_in, answers) = mpsc::channel();
        let log = Arc::new(Mutex::new(Vec::new()));
        let events_log = log.clone();
        std::thread::spawn(move || {
            let mut reader = BufReader::new(output);
            let mut message = Vec::new();
            loop {
                message.clear();
                match reader.read_until(0, &mut message) {
                    Ok(0) | Err(_) => return,
                    Ok(_) => {}
                }
                if message.last() == Some(&0) {
                    message.pop();
                }
                let Ok(value) = serde_json::from_slice::<Value>(&message) else {
                    continue;
                };
                if value.get("id").is_some() {
                    if answers_in.send(value).is_err() {
                        return;
                    }
                } else if let Some(entry) = log_entry(&value) {
                    events_log.lock().unwrap().push(entry);
                }
            }
        });
        let mut browser = Browser {
            child,
            input,
            answers,
            next_id: 0,
            session: String::new(),
            log,
            _profile: profile,
            stderr,
        };
        let target = browser.call("Target.createTarget", json!({"url": "about:blank"}));
        let target = target["targetId"].as_str().unwrap().to_owned();
        let attached = browser.call(
            "Target.attachToTarget",
            json!({"targetId": target, "flatten": true}),
        );
        browser.session = attached["sessionId"].as_str().unwrap().to_owned();
        for domain in ["Page.enable", "Runtime.enable", "Log.enable"] {
            browser.call(domain, json!({}));
        }
        browser.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
        );
        browser
    }

    /// Sends a command (to the tab, once attached) and waits for its result.
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut message = json!({"id": id, "method": method, "params": params});
        if !self.session.is_empty() {
            message["sessionId"] = json!(self.session);
        }
        let mut bytes = serde_json::to_vec(&message).unwrap();
        bytes.push(0);
        self.input
            .write_all(&bytes)
            .and_then(|()| self.input.flush())
            .unwrap_or_else(|e| panic!("Chromium is gone ({e}); {}", self.stderr_tail()));
        let deadline = Instant::now() + COMMAND_TIMEOUT;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let answer = self
                .answers
                .recv_timeout(left)
                .unwrap_or_else(|e| panic!("no answer to {method} ({e}); {}", self.stderr_tail()));
            if answer["id"] != id {
                continue;
            }
            if let Some(error) = answer.get("error") {
                panic!("{method}: {error}");
            }
            return answer["result"].clone();
        }
    }

    /// Evaluates `expression` in the page (awaiting a promise); its value.
    pub fn eval(&mut self, expression: &str) -> Value {
        let result = self.call(
            "Runtime.evaluate",
            json!({"expression": expression, "returnByValue": true, "awaitPromise": true}),
        );
        if let Some(details) = result.get("exceptionDetails") {
            panic!("`{expression}` threw: {details}");
        }
        result["result"]["value"].clone()
    }

    /// Waits until `expression` is truthy in the page, for at most
    /// `within`; panics with the page's text and log if it never is.
    pub fn wait_for(&mut self, expression: &str, within: Duration) {
        let start = Instant::now();
        loop {
            // False while the page is still loading (no body yet).
            let value = self.eval(&format!(
                "(() => {{ try {{ return Boolean({expression}); }} catch (_) {{ return false; }} }})()"
            ));
            if value == json!(true) {
                return;
            }
            if start.elapsed() > within {
                let text = self.eval("document.body ? document.body.innerText : ''");
                panic!(
                    "`{expression}` still false after {within:?}.\nThe page shows:\n{}\nIts log: {:#?}",
                    text.as_str().unwrap_or(""),
                    self.log.lock().unwrap()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Loads `url` in the tab.
    pub fn open(&mut self, url: &str) {
        let result = self.call("Page.navigate", json!({"url": url}));
        if let Some(error) = result.get("errorText") {
            panic!("cannot open {url}: {error}");
        }
    }

    /// The element's text (`#id`), or null.
    pub fn text(&mut self, id: &str) -> Option<String> {
        self.eval(&format!(
            "(document.getElementById({id:?}) || {{}}).textContent"
        ))
        .as_str()
        .map(str::to_owned)
    }

    /// A left-button drag from one point of the viewport to another, in
    /// `steps` moves.
    pub fn drag(&mut self, from: (f64, f64), to: (f64, f64), steps: u32) {
        let mouse = |kind: &str, (x, y): (f64, f64), buttons: u32| {
            json!({"type": kind, "x": x, "y": y, "button": "left", "buttons": buttons,
                   "clickCount": 1})
        };
        self.call("Input.dispatchMouseEvent", mouse("mousePressed", from, 1));
        for i in 1..=steps {
            let t = f64::from(i) / f64::from(steps);
            let at = (from.0 + t * (to.0 - from.0), from.1 + t * (to.1 - from.1));
            self.call("Input.dispatchMouseEvent", mouse("mouseMoved", at, 1));
        }
        self.call("Input.dispatchMouseEvent", mouse("mouseReleased", to, 0));
    }

    /// A PNG of the whole page, written to `path`.
    pub fn screenshot(&mut self, path: &Path) {
        let shot = self.call(
            "Page.captureScreenshot",
            json!({"format": "png", "captureBeyondViewport": true}),
        );
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(shot["data"].as_str().unwrap())
            .unwrap();
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }

    /// The last lines Chromium wrote to its standard error.
    fn stderr_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.stderr).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        format!(
            "Chromium's stderr ends:\n{}",
            lines[lines.len().saturating_sub(20)..].join("\n")
        )
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // Closes the browser and its helper processes; killed if it does
        // not exit within 5 s.
        let mut bytes = serde_json::to_vec(&json!({"id": 0, "method": "Browser.close"})).unwrap();
        bytes.push(0);
        let _ = self.input.write_all(&bytes);
        let _ = self.input.flush();
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A console message, log entry or uncaught exception from an event.
fn log_entry(event: &Value) -> Option<LogEntry> {
    let params = &event["params"];
    match event["method"].as_str()? {
        "Runtime.consoleAPICalled" => Some(LogEntry {
            origin: "console".into(),
            level: params["type"].as_str().unwrap_or("").into(),
            text: params["args"]
                .as_array()
                .map(|args| {
                    args.iter()
                        .map(|a| {
                            a["value"]
                                .as_str()
                                .map(str::to_owned)
                                .unwrap_or_else(|| a["description"].to_string())
                        })
                        .collect::<Vec<_>>()
                        .join(" ")
                })
                .unwrap_or_default(),
            url: None,
        }),
        "Runtime.exceptionThrown" => Some(LogEntry {
            origin: "exception".into(),
            level: "error".into(),
            text: params["exceptionDetails"].to_string(),
            url: None,
        }),
        "Log.entryAdded" => {
            let entry = &params["entry"];
            Some(LogEntry {
                origin: format!("log/{}", entry["source"].as_str().unwrap_or("")),
                level: entry["level"].as_str().unwrap_or("").into(),
                text: entry["text"].as_str().unwrap_or("").into(),
                url: entry["url"].as_str().map(str::to_owned),
            })
        }
        _ => None,
    }
}
