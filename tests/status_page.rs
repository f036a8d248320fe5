//! The live status page of the real binary against the simulated plant of the demo
//! config, looked at by a real headless Chromium: it loads with no console message,
//! its values change between two looks, and a channel in NE43 fault shows as bad.
//! Also `/api/status` and shadow mode as the page, the metrics and the record show it.
//! A Chromium that keeps running ([`Browser`]) watches the page turn stale when the
//! gateway hangs and live again when it goes on, the summary line, the bad channels
//! first, the HOLD badge, a shadow banner naming its axes, times with their zone, and
//! the last failed job kept on its axis.
//!
//! Chromium is Debian's `chromium` (test.sh installs it). Without it the browser test
//! skips with a message, or fails when `CI` is set.

mod common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::time::{Duration, Instant};

use common::process::Gateway;
use compgate::plant::Plant;
use compgate_ncproto::JobStatus;
use compgate_plc::field::SensorFault;
use compgate_plc::nc::JobFault;
use serde_json::Value;

/// The demo's own configuration: sines of a few degC, one axis.
const DEMO: &str = include_str!("../config/demo.toml");

/// GET `path` on 127.0.0.1:`port`: status line and body.
fn get(port: u16, path: &str) -> Result<(String, String), String> {
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2))
        .map_err(|e| format!("connect: {e}"))?;
    s.set_read_timeout(Some(Duration::from_secs(5)))
        .map_err(|e| e.to_string())?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n"
    )
    .map_err(|e| format!("request: {e}"))?;
    let mut text = String::new();
    s.read_to_string(&mut text)
        .map_err(|e| format!("response: {e}"))?;
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    Ok((head.to_string(), body.to_string()))
}

fn api_status(port: u16) -> Option<Value> {
    let (head, body) = get(port, "/api/status").ok()?;
    if !head.starts_with("HTTP/1.1 200") {
        return None;
    }
    serde_json::from_str(&body).ok()
}

/// Polls `/api/status` until `pred` holds; panics with the last answer and the
/// gateway's log after `secs`.
fn wait_api(
    gateway: &Gateway,
    port: u16,
    secs: f64,
    what: &str,
    pred: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    let mut last = None;
    while Instant::now() < deadline {
        if let Some(v) = api_status(port) {
            if pred(&v) {
                return v;
            }
            last = Some(v);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    panic!(
        "timed out after {secs} s waiting for {what}; last /api/status: {last:#?}\ngateway log:\n{}",
        gateway.stderr_text()
    );
}

fn channel<'a>(status: &'a Value, name: &str) -> &'a Value {
    status["channels"]
        .as_array()
        .and_then(|c| c.iter().find(|c| c["name"] == name))
        .unwrap_or_else(|| panic!("no channel {name} in {status}"))
}

/// The plant of `toml` and a config file for it with `[metrics]` on port 0
/// ([`Gateway::metrics_port`] tells which one it got).
async fn plant(dir: &Path, toml: &str, extra: &str) -> (Plant, PathBuf) {
    common::plant_and_file(
        dir,
        toml,
        &format!("\n[metrics]\nbind = \"127.0.0.1:0\"\n{extra}"),
    )
    .await
}

/// Debian's chromium, or why not.
fn chromium() -> Option<PathBuf> {
    ["chromium", "chromium-browser"].iter().find_map(|name| {
        std::env::var_os("PATH").and_then(|paths| {
            std::env::split_paths(&paths)
                .map(|d| d.join(name))
                .find(|p| p.is_file())
        })
    })
}

/// What one headless Chromium run saw: the DOM after the page's scripts ran, and
/// every console message (errors, warnings and logs alike).
struct Look {
    dom: String,
    console: Vec<String>,
}

/// Headless Chromium as root on a machine without network: without the
/// background-networking flags it keeps trying the hosts it phones.
const HEADLESS: [&str; 9] = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
];

/// Loads `url` in a fresh headless Chromium, lets the page run for `budget_ms` of
/// virtual time (the page's fetches complete first) and returns what it showed.
fn look(chromium: &Path, url: &str, budget_ms: u32) -> Look {
    let profile = tempfile::tempdir().expect("profile dir");
    let mut cmd = Command::new(chromium);
    cmd.args(HEADLESS)
        .args(["--enable-logging=stderr", "--v=0"])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg(format!("--virtual-time-budget={budget_ms}"))
        .arg("--dump-dom");
    let child = cmd
        .arg(url)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("chromium starts");
    // A browser that hangs must fail the test, not stall it.
    let pid = child.id();
    let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
    std::thread::spawn(move || {
        if let Err(std::sync::mpsc::RecvTimeoutError::Timeout) =
            done_rx.recv_timeout(Duration::from_secs(120))
        {
            let _ = Command::new("kill")
                .args(["-KILL", &pid.to_string()])
                .status();
        }
    });
    let out = child.wait_with_output().expect("chromium output");
    let _ = done_tx.send(());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "chromium failed ({}):\n{stderr}",
        out.status
    );
    Look {
        dom: String::from_utf8_lossy(&out.stdout).to_string(),
        console: stderr
            .lines()
            .filter(|l| l.contains(":CONSOLE"))
            .map(str::to_string)
            .collect(),
    }
}

/// The attribute `attr` of the element with `data-channel="name"` in `dom`.
fn row_attr<'a>(dom: &'a str, key: &str, name: &str, attr: &str) -> Option<&'a str> {
    let at = dom.find(&format!("{key}=\"{name}\""))?;
    let tag_start = dom[..at].rfind('<')?;
    let tag = &dom[tag_start..at + dom[at..].find('>')?];
    let a = tag.find(&format!("{attr}=\""))? + attr.len() + 2;
    Some(&tag[a..a + tag[a..].find('"')?])
}

/// The value cell of channel `name`'s row.
fn shown_value<'a>(dom: &'a str, name: &str) -> Option<&'a str> {
    let at = dom.find(&format!("data-channel=\"{name}\""))?;
    let cell = dom[at..].find("class=\"num value\">")? + at + "class=\"num value\">".len();
    Some(&dom[cell..cell + dom[cell..].find('<')?])
}

/// A headless Chromium that keeps running, driven over its DevTools pipe
/// (`--remote-debugging-pipe`: JSON messages ended by NUL, read on its fd 3 and
/// written on its fd 4; a shell maps them onto the child's stdin and stdout).
struct Browser {
    child: Child,
    to: ChildStdin,
    from: std::sync::mpsc::Receiver<Value>,
    next_id: u64,
    session: Option<String>,
    _profile: tempfile::TempDir,
}

impl Browser {
    fn start(chromium: &Path) -> Self {
        let profile = tempfile::tempdir().expect("profile dir");
        let mut child = Command::new("sh")
            .args([
                "-c",
                "exec \"$0\" \"$@\" 3<&0 4>&1 </dev/null >/dev/null",
                &chromium.display().to_string(),
            ])
            .args(HEADLESS)
            .args([
                "--disable-background-timer-throttling",
                "--disable-renderer-backgrounding",
                "--remote-debugging-pipe",
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromium starts");
        let to = child.stdin.take().expect("stdin");
        let mut out = std::io::BufReader::new(child.stdout.take().expect("stdout"));
        let (tx, from) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut msg = Vec::new();
            while std::io::BufRead::read_until(&mut out, 0, &mut msg).is_ok_and(|n| n > 0) {
                msg.pop_if(|b| *b == 0);
                if let Ok(v) = serde_json::from_slice::<Value>(&msg) {
                    if tx.send(v).is_err() {
                        break;
                    }
                }
                msg.clear();
            }
        });
        Browser {
            child,
            to,
            from,
            next_id: 0,
            session: None,
            _profile: profile,
        }
    }

    /// Calls `method` (on the page once [`open`](Self::open) attached to one) and
    /// returns its result; events in between are dropped.
    fn call(&mut self, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = serde_json::json!({ "id": id, "method": method, "params": params });
        if let Some(s) = &self.session {
            msg["sessionId"] = Value::from(s.as_str());
        }
        let mut bytes = msg.to_string().into_bytes();
        bytes.push(0);
        self.to.write_all(&bytes).expect("write to chromium");
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let v = self
                .from
                .recv_timeout(left)
                .unwrap_or_else(|e| panic!("no answer from chromium to {method}: {e}"));
            if v["id"] == id {
                assert!(v["error"].is_null(), "{method}: {v}");
                return v["result"].clone();
            }
        }
    }

    /// Opens `url` in a new page in time zone `zone`, `script` run first in it.
    fn open(&mut self, url: &str, zone: &str, script: &str) {
        let target = self.call(
            "Target.createTarget",
            serde_json::json!({ "url": "about:blank" }),
        );
        let attached = self.call(
            "Target.attachToTarget",
            serde_json::json!({ "targetId": target["targetId"], "flatten": true }),
        );
        self.session = attached["sessionId"].as_str().map(str::to_string);
        self.call("Page.enable", serde_json::json!({}));
        self.call(
            "Emulation.setTimezoneOverride",
            serde_json::json!({ "timezoneId": zone }),
        );
        if !script.is_empty() {
            self.call(
                "Page.addScriptToEvaluateOnNewDocument",
                serde_json::json!({ "source": script }),
            );
        }
        self.call("Page.navigate", serde_json::json!({ "url": url }));
    }

    /// The value of the JavaScript expression `expr` in the page.
    fn eval(&mut self, expr: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            serde_json::json!({ "expression": expr, "returnByValue": true }),
        );
        r["result"]["value"].clone()
    }

    /// Polls until `expr` is true in the page; panics after `secs` with [`STATE`].
    fn wait(&mut self, secs: f64, what: &str, expr: &str) -> Value {
        let deadline = Instant::now() + Duration::from_secs_f64(secs);
        while Instant::now() < deadline {
            if self.eval(expr) == Value::Bool(true) {
                return self.eval(STATE);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        panic!(
            "timed out after {secs} s waiting for {what}; the page: {:#}",
            self.eval(STATE)
        );
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// What the tests read of the page: header, banners, summary, channel order, axes.
const STATE: &str = r##"(() => {
  const text = (id) => { const e = document.getElementById(id); return e && !e.hidden ? e.textContent.trim() : null; };
  return {
    live: document.getElementById("live").dataset.state,
    live_text: text("live-text"),
    body_stale: document.body.classList.contains("stale"),
    main_opacity: Number(getComputedStyle(document.querySelector("main")).opacity),
    stale_banner: text("stale-banner"),
    shadow_banner: text("shadow-banner"),
    summary: text("summary"),
    channels: [...document.querySelectorAll("#channels tbody tr")].map((r) => r.dataset.channel),
    axes: Object.fromEntries([...document.querySelectorAll(".axis")].map((a) =>
      [a.dataset.axis, { heading: a.querySelector("h3").textContent.replace(/\s+/g, " ").trim(),
                         held: a.dataset.held, text: a.textContent.replace(/\s+/g, " ") }])),
    job_times: [...document.querySelectorAll("#jobs tbody tr td:first-child")].map((t) => t.textContent),
  };
})()"##;

/// `YYYY-MM-DD` of the UTC day of `t` (days to civil date, H. Hinnant's algorithm).
fn utc_date(t: std::time::SystemTime) -> String {
    let secs = t
        .duration_since(std::time::UNIX_EPOCH)
        .expect("after 1970")
        .as_secs();
    let z = i64::try_from(secs / 86_400).expect("days") + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02}")
}

/// Chromium, or `None` after saying why the test skips (fails under `CI`).
fn chromium_or_skip() -> Option<PathBuf> {
    let found = chromium();
    if found.is_none() {
        assert!(
            std::env::var_os("CI").is_none(),
            "chromium is missing (test.sh installs Debian's chromium)"
        );
        eprintln!("SKIPPED: chromium is not installed (test.sh installs it)");
    }
    found
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_in_chromium_loads_clean_updates_and_shows_a_ne43_fault_as_bad() {
    let Some(chromium) = chromium() else {
        assert!(
            std::env::var_os("CI").is_none(),
            "chromium is missing (test.sh installs Debian's chromium)"
        );
        eprintln!("SKIPPED: chromium is not installed (test.sh installs it)");
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let (plant, path) = plant(dir.path(), DEMO, "").await;
    let gateway = Gateway::start(dir.path(), &path, &[]);
    let port = gateway.metrics_port(20.0);
    wait_api(
        &gateway,
        port,
        20.0,
        "every channel good with a trend",
        |s| {
            s["channels"].as_array().is_some_and(|c| {
                !c.is_empty()
                    && c.iter().all(|c| {
                        c["quality"] == "good"
                            && c["trend"].as_array().is_some_and(|t| t.len() >= 3)
                    })
            })
        },
    );
    let url = format!("http://127.0.0.1:{port}/");

    // The page loads, draws every channel from /api/status and logs nothing.
    let first = look(&chromium, &url, 3000);
    assert!(first.console.is_empty(), "console: {:#?}", first.console);
    let names = ["T_bed", "T_column", "T_screw", "T_ambient"];
    for name in names {
        assert_eq!(
            row_attr(&first.dom, "data-channel", name, "data-quality"),
            Some("good"),
            "{name} in\n{}",
            first.dom
        );
        assert!(shown_value(&first.dom, name).is_some_and(|v| v.ends_with("°C")));
    }
    assert_eq!(
        row_attr(&first.dom, "data-device", "ain1", "data-state"),
        Some("up")
    );
    assert!(first.dom.contains("data-axis=\"X\""), "{}", first.dom);
    assert!(first.dom.contains("<polyline"), "no trend drawn");

    // A second look some status intervals later shows other values.
    std::thread::sleep(Duration::from_secs(3));
    let second = look(&chromium, &url, 3000);
    assert!(second.console.is_empty(), "console: {:#?}", second.console);
    let values = |l: &Look| -> Vec<String> {
        names
            .iter()
            .map(|n| shown_value(&l.dom, n).unwrap_or_default().to_string())
            .collect()
    };
    assert_ne!(values(&first), values(&second), "values did not change");
    let samples = |l: &Look| -> u64 {
        let at = l.dom.find("data-samples=\"").expect("samples") + "data-samples=\"".len();
        l.dom[at..at + l.dom[at..].find('"').expect("quote")]
            .parse()
            .expect("number")
    };
    assert!(samples(&second) > samples(&first));

    // T_bed's transmitter: broken wire, 3.5 mA (NE43 downscale).
    let t_bed = plant.transmitter["T_bed"];
    plant.field["ain1"]
        .set_sensor_fault(t_bed, SensorFault::Open)
        .expect("fault set");
    wait_api(&gateway, port, 10.0, "T_bed bad", |s| {
        channel(s, "T_bed")["quality"] == "bad"
    });
    let faulted = look(&chromium, &url, 3000);
    assert!(
        faulted.console.is_empty(),
        "console: {:#?}",
        faulted.console
    );
    assert_eq!(
        row_attr(&faulted.dom, "data-channel", "T_bed", "data-quality"),
        Some("bad"),
        "{}",
        faulted.dom
    );
    assert!(faulted.dom.contains("bad (NE43 low)"), "{}", faulted.dom);
    // Its value cell shows no temperature, though the API still holds the last good one.
    let held = api_status(port).expect("status");
    assert!(channel(&held, "T_bed")["value_degc"].is_f64(), "{held}");
    assert_eq!(
        shown_value(&faulted.dom, "T_bed"),
        Some("-"),
        "{}",
        faulted.dom
    );
    assert_eq!(
        row_attr(&faulted.dom, "data-channel", "T_column", "data-quality"),
        Some("good")
    );

    drop(gateway);
}

// `/api/status` is JSON with every part the page draws; the page and its assets are
// embedded; anything but GET/HEAD is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_api_answers_json_and_the_listener_is_read_only() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (_plant, path) = plant(dir.path(), DEMO, "").await;
    let gateway = Gateway::start(dir.path(), &path, &[]);
    let port = gateway.metrics_port(20.0);
    let s = wait_api(&gateway, port, 20.0, "a job done", |s| {
        s["jobs"].as_array().is_some_and(|j| !j.is_empty())
    });
    for key in ["devices", "channels", "axes", "jobs"] {
        assert!(s[key].is_array(), "{key} in {s}");
    }
    assert_eq!(s["devices"][0]["state"], "up");
    assert!(channel(&s, "T_bed")["value_degc"].is_f64());
    assert!(channel(&s, "T_bed")["trend"]
        .as_array()
        .is_some_and(|t| !t.is_empty()));
    let x = &s["axes"][0];
    assert_eq!(x["name"], "X");
    assert!(x["nc"]["applied_comp_mm"].is_f64(), "{x}");
    assert!(x["written"]["sd43900_mm"].is_f64(), "{x}");
    assert_eq!(s["jobs"][0]["ok"], true);
    assert_eq!(s["jobs"][0]["shadow"], false);

    let (head, body) = get(port, "/").expect("page");
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    assert!(head.to_ascii_lowercase().contains("text/html"), "{head}");
    assert!(body.contains("page.js"));
    for asset in ["/page.js", "/page.css"] {
        let (head, _) = get(port, asset).expect("asset");
        assert!(head.starts_with("HTTP/1.1 200"), "{asset}: {head}");
    }
    // Read-only.
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let mut c = TcpStream::connect(addr).expect("connect");
    c.write_all(
        b"POST /api/status HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
    )
    .expect("write");
    let mut answer = String::new();
    let _ = c.read_to_string(&mut answer);
    assert!(answer.starts_with("HTTP/1.1 405"), "{answer}");
}

// `compgate run --shadow`: the would-be values are computed, shown, published and
// recorded as shadow jobs, and the NC module's parameters never change.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shadow_mode_records_and_shows_what_it_would_write_and_leaves_the_nc_alone() {
    let dir = tempfile::tempdir().expect("tempdir");
    let db = dir.path().join("rec.sqlite");
    let (plant, path) = plant(
        dir.path(),
        &common::config("hold", "", ""),
        // A broker that is not there: MQTT messages stay in the outbox to be read.
        &format!(
            "\n[recorder]\npath = \"{}\"\n\n[mqtt]\nbroker = \"127.0.0.1:{}\"\nmachine = \"m1\"\n",
            db.display(),
            common::free_port()
        ),
    )
    .await;
    let nc_before = plant.nc["nc_x"].state();
    let mut gateway = Gateway::start_with_args(dir.path(), &path, &["--shadow"]);
    let port = gateway.metrics_port(20.0);
    // T_bed 30 degC, coeff 0.004 mm/degC from 20 degC: K0 0.04 mm would be written.
    let s = wait_api(&gateway, port, 20.0, "a shadow write of K0 0.04 mm", |s| {
        s["axes"][0]["would_write"]["sd43900_mm"]
            .as_f64()
            .is_some_and(|k0| (k0 - 0.04).abs() < 0.001)
    });
    let x = &s["axes"][0];
    assert_eq!(x["shadow"], true);
    assert_eq!(s["shadow"], true);
    assert_eq!(x["jobs_ok"], 0, "{x}");
    let job = &s["jobs"][0];
    assert_eq!(job["shadow"], true, "{job}");
    assert_eq!(job["ok"], false);
    // The NC still holds what it held; it applies what it held.
    assert_eq!(
        x["nc"]["sd43900_mm"].as_f64(),
        Some(nc_before.sd43900_mm),
        "{x}"
    );
    let (_, metrics) = get(port, "/metrics").expect("metrics");
    assert!(
        metrics
            .lines()
            .any(|l| l.starts_with("compgate_axis_shadow{axis=\"X\"} 1")),
        "{metrics}"
    );
    assert!(
        metrics
            .lines()
            .any(|l| l.starts_with("compgate_nc_jobs_total{axis=\"X\",result=\"shadow\"}")),
        "{metrics}"
    );
    // systemd's STATUS= line says so.
    gateway.wait_notify(10.0, "STATUS= with SHADOW", |m| {
        m.contains("STATUS=") && m.contains("X SHADOW (NC not written): would write SD43900=")
    });
    // The page says so too (where a browser is at hand; the first test requires it).
    if let Some(chromium) = chromium() {
        let page = look(&chromium, &format!("http://127.0.0.1:{port}/"), 3000);
        assert!(page.console.is_empty(), "console: {:#?}", page.console);
        assert!(page.dom.contains("data-shadow=\"true\""), "{}", page.dom);
        assert!(page.dom.contains("would write"), "{}", page.dom);
        assert!(
            !page
                .dom
                .contains("id=\"shadow-banner\" class=\"banner\" hidden"),
            "{}",
            page.dom
        );
    }
    std::thread::sleep(Duration::from_millis(500));
    let nc = plant.nc["nc_x"].state();
    assert_eq!(
        (nc.sd43900_mm, nc.sd43910, nc.sd43920_mm),
        (
            nc_before.sd43900_mm,
            nc_before.sd43910,
            nc_before.sd43920_mm
        )
    );
    assert_eq!(plant.nc["nc_x"].jobs_executed(), 0);

    gateway.signal("TERM");
    let _ = gateway.child.wait();
    let conn = rusqlite::Connection::open(&db).expect("db");
    let (shadow, sent, k0): (i64, i64, f64) = conn
        .query_row(
            "SELECT SUM(shadow), SUM(ok), MAX(sd43900_mm) FROM jobs WHERE axis = 'X'",
            [],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
        )
        .expect("jobs");
    assert!(shadow >= 1, "no shadow job recorded");
    assert_eq!(sent, 0, "a job recorded as sent");
    assert!((k0 - 0.04).abs() < 0.001, "recorded K0 {k0}");
    let payload: String = conn
        .query_row(
            "SELECT payload FROM mqtt_outbox WHERE topic = 'compgate/m1/writes/X' LIMIT 1",
            [],
            |r| r.get(0),
        )
        .expect("a writes message");
    let msg: Value = serde_json::from_str(&payload).expect("json");
    assert_eq!(msg["shadow"], true, "{msg}");
    assert_eq!(msg["ok"], false, "{msg}");
    assert!(msg["sd43900_mm"]
        .as_f64()
        .is_some_and(|k0| (k0 - 0.04).abs() < 0.001));
}

// `[axes.X] shadow = true` alone, in the library: the status carries the would-be
// values and the shadow jobs, the NC is never written. The would-be values step to the
// model's 0.04 mm as a real run would (0.01 mm per update), and stay there: the NC,
// still holding 0, is no reason to start again from 0 at each snapshot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_axis_in_shadow_mode_shows_would_be_values_and_writes_nothing() {
    let toml = common::config("hold", "", "")
        .replace(
            "[axes.X]\nnc_module = \"nc_x\"",
            "[axes.X]\nshadow = true\nnc_module = \"nc_x\"",
        )
        .replace("max_step_k0_mm = 0.5", "max_step_k0_mm = 0.01");
    assert!(toml.contains("shadow = true") && toml.contains("max_step_k0_mm = 0.01"));
    let mut rig = common::start(&toml).await;
    let before = rig.plant.nc["nc_x"].state();
    let s = rig
        .wait_for(20.0, "a shadow write", |s| {
            s.axes[0]
                .would_write
                .is_some_and(|p| (p.k0_mm - 0.04).abs() < 0.001)
        })
        .await;
    // At least 2.5 s more (50 polls of 50 ms): two snapshots of the NC or more.
    let samples = s.samples;
    let s = rig
        .wait_for(20.0, "50 more samples", |s| s.samples >= samples + 50)
        .await;
    let k0: Vec<f64> = s.jobs.iter().map(|j| j.params.k0_mm).collect();
    assert!(
        k0.windows(2).all(|w| (w[1] - w[0]).abs() <= 0.01 + 1e-9),
        "a would-be step over 0.01 mm: {k0:?}"
    );
    let reached = k0.iter().position(|&k| k > 0.039).expect("0.04 mm reached");
    assert!(reached >= 3, "not stepped up: {k0:?}");
    assert!(
        k0[reached..].iter().all(|&k| k > 0.039),
        "would-be K0 started again from what the NC holds: {k0:?}"
    );
    assert!(s.axes[0].shadow);
    assert_eq!(s.axes[0].jobs_ok + s.axes[0].jobs_failed, 0);
    assert!(s.jobs.iter().all(|j| j.shadow && j.axis == "X"));
    assert!(!s.jobs.is_empty());
    // Counted by the gateway, all of them: the job list keeps the last ones only.
    assert!(
        s.axes[0].jobs_shadow as usize >= s.jobs.len(),
        "{}",
        s.axes[0].jobs_shadow
    );
    assert_eq!(rig.plant.nc["nc_x"].jobs_executed(), 0);
    let nc = rig.plant.nc["nc_x"].state();
    assert_eq!(nc.sd43900_mm, before.sd43900_mm);
    let text = compgate_service::status::render(&s);
    let k0 = s.axes[0].would_write.map(|p| p.k0_mm).unwrap_or_default();
    let want = format!("SHADOW would_write SD43900={k0:.4}mm");
    assert!(text.contains(&want), "{text}");
    rig.stop().await;
}

// A hung gateway (SIGSTOP) answers nothing and closes nothing: the page, loaded in a
// Chromium that keeps running, gives its fetch up, says since when nothing came and
// greys the old data out within about 4 status intervals (1 s in the demo), and is
// live again by itself when the gateway goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hung_gateway_turns_the_page_stale_and_it_recovers_by_itself() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let (_plant, path) = plant(dir.path(), DEMO, "").await;
    let gateway = Gateway::start(dir.path(), &path, &[]);
    let port = gateway.metrics_port(20.0);
    wait_api(&gateway, port, 20.0, "a channel read", |s| {
        s["samples"].as_u64().is_some_and(|n| n > 0)
    });
    let mut browser = Browser::start(&chromium);
    browser.open(&format!("http://127.0.0.1:{port}/"), "UTC", "");
    let live = browser.wait(
        10.0,
        "the page live",
        r#"document.getElementById("live").dataset.state === "live""#,
    );
    assert!(!live["body_stale"].as_bool().unwrap_or(true), "{live:#}");
    assert_eq!(live["main_opacity"], 1.0, "{live:#}");

    gateway.signal("STOP");
    let stopped = Instant::now();
    let stale = browser.wait(
        6.0,
        "the page stale",
        r#"document.getElementById("live").dataset.state === "stale""#,
    );
    let took = stopped.elapsed();
    // Let it stay stopped about 4 status intervals in all; still stale then.
    std::thread::sleep(Duration::from_secs(4).saturating_sub(took));
    let stale_later = browser.eval(STATE);
    gateway.signal("CONT");
    assert!(
        took >= Duration::from_secs(2),
        "stale after {took:?}: {stale:#}"
    );
    let text = stale["live_text"].as_str().unwrap_or_default();
    assert!(text.starts_with("no answer since "), "{stale:#}");
    assert_eq!(stale["body_stale"], true, "{stale:#}");
    assert!(
        stale["main_opacity"].as_f64().is_some_and(|o| o < 0.6),
        "{stale:#}"
    );
    assert!(
        stale["stale_banner"]
            .as_str()
            .is_some_and(|b| b.starts_with("Data of ") && b.contains("not live")),
        "{stale:#}"
    );
    assert_eq!(stale_later["body_stale"], true, "{stale_later:#}");

    let back = browser.wait(
        10.0,
        "the page live again",
        r#"document.getElementById("live").dataset.state === "live""#,
    );
    assert_eq!(back["body_stale"], false, "{back:#}");
    assert_eq!(back["stale_banner"], Value::Null, "{back:#}");
    drop(browser);
    drop(gateway);
}

/// [`common::config`] (policy `hold`) with a second NC module and axis Z in shadow
/// mode, its model on T_screw only.
fn two_axes_z_shadow() -> String {
    let toml = common::config("hold", "", "");
    let z = r#"
[nc_modules.nc_z]
address = "127.0.0.1:0"
unit_id = 1
timeout_s = 0.5
job_timeout_s = 0.5

[axes.Z]
shadow = true
nc_module = "nc_z"
md32750 = 3
p0_mm = 0.0
update_interval_s = 0.1
deadband_k0_mm = 0.00001
deadband_tan_beta = 0.0000000001
max_abs_k0_mm = 0.5
max_abs_tan_beta = 0.01
max_step_k0_mm = 0.5
max_step_tan_beta = 0.01
on_bad_input = "hold"
k0 = { offset_mm = 0.0, terms = [{ channel = "T_screw", ref_degc = 20.0, coeff_mm_per_degc = 0.002 }] }
tan_beta = { offset = 0.0, terms = [] }
fitted_degc = { T_screw = [18.0, 22.0] }

[sim.nc_modules.nc_z]
referenced = true
md32750 = 3
motion_min_mm = 0.0
motion_max_mm = 0.0
motion_speed_mm_per_s = 0.0
"#;
    // The axes before [sim]: a table appended after [sim.*] would land in it.
    let at = toml.find("\n[sim]").expect("a [sim] table");
    format!("{}{z}{}", &toml[..at], &toml[at..])
}

// One axis of two in shadow mode: the banner names it and does not say the NC is
// not written. A summary line on top counts the bad channels, the devices up and says
// each axis' state; bad channels are listed first; an axis that holds for a bad input
// has a HOLD badge; the shadow axis counts its shadow jobs, and its T_screw (25 degC)
// is 3 K above the temperatures its model was fitted over: OUTSIDE FIT, with the why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_summary_orders_channels_and_badges_say_hold_and_which_axis_is_shadow() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let (plant, path) = plant(dir.path(), &two_axes_z_shadow(), "").await;
    let gateway = Gateway::start(dir.path(), &path, &[]);
    let port = gateway.metrics_port(20.0);
    wait_api(&gateway, port, 20.0, "X written, Z shadow jobs", |s| {
        s["axes"][0]["jobs_ok"].as_u64().is_some_and(|n| n > 0)
            && s["axes"][1]["jobs_shadow"].as_u64().is_some_and(|n| n > 0)
    });
    // T_col (third, in no model) broken: listed first, and no axis holds for it.
    let field = &plant.field["ain1"];
    field
        .set_sensor_fault(plant.transmitter["T_col"], SensorFault::Open)
        .expect("fault set");
    wait_api(&gateway, port, 10.0, "T_col bad", |s| {
        channel(s, "T_col")["quality"] == "bad"
    });
    let mut browser = Browser::start(&chromium);
    browser.open(&format!("http://127.0.0.1:{port}/"), "UTC", "");
    let one_bad = browser.wait(
        10.0,
        "one bad channel in the summary",
        r#"document.getElementById("summary").dataset.bad === "1""#,
    );
    assert_eq!(
        one_bad["channels"],
        serde_json::json!(["T_col", "T_bed", "T_screw"]),
        "{one_bad:#}"
    );
    let summary = one_bad["summary"].as_str().unwrap_or_default();
    for want in [
        "3 channels: 1 bad",
        "devices: 1 of 1 up",
        "axis X ok, Z shadow, outside its fit",
    ] {
        assert!(summary.contains(want), "{want:?} in {one_bad:#}");
    }
    let banner = one_bad["shadow_banner"].as_str().unwrap_or_default();
    assert!(banner.starts_with("SHADOW MODE on axis Z:"), "{one_bad:#}");
    assert!(!banner.contains("the NC is not written"), "{one_bad:#}");
    let z = &one_bad["axes"]["Z"];
    assert!(
        z["heading"]
            .as_str()
            .is_some_and(|h| h.contains("SHADOW") && h.contains("OUTSIDE FIT")),
        "{z:#}"
    );
    assert!(
        z["text"].as_str().is_some_and(|t| t.contains(
            "model: T_screw reads 25.0 degC, 3.0 K above the 18.0..22.0 degC the model was fitted over"
        )),
        "{z:#}"
    );
    assert!(
        z["text"]
            .as_str()
            .is_some_and(|t| t.contains(" shadow") && !t.contains("jobs 0 ok")),
        "{z:#}"
    );
    assert_eq!(one_bad["axes"]["X"]["heading"], "Axis X", "{one_bad:#}");

    // T_bed (in X's model) broken too: X holds, with a badge; both bad ones first,
    // in config order.
    field
        .set_sensor_fault(plant.transmitter["T_bed"], SensorFault::Open)
        .expect("fault set");
    let held = browser.wait(
        10.0,
        "X held",
        r#"document.querySelector('.axis[data-axis="X"]')?.dataset.held === "true""#,
    );
    assert_eq!(held["axes"]["X"]["heading"], "Axis X HOLD", "{held:#}");
    assert_eq!(
        held["channels"],
        serde_json::json!(["T_bed", "T_col", "T_screw"]),
        "{held:#}"
    );
    let summary = held["summary"].as_str().unwrap_or_default();
    for want in [
        "3 channels: 2 bad",
        "axis X held, Z shadow, outside its fit",
    ] {
        assert!(summary.contains(want), "{want:?} in {held:#}");
    }
    drop(browser);
    drop(gateway);
}

// A failed job stays on its axis' card after jobs succeed again: with several axes
// writing, it scrolls out of the job list within seconds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_last_failed_job_stays_on_its_axis_after_jobs_succeed_again() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let (plant, path) = plant(dir.path(), &common::config("hold", "", ""), "").await;
    let nc = plant.nc["nc_x"].clone();
    nc.set_job_fault(JobFault::Refuse(JobStatus::AccessDenied));
    let gateway = Gateway::start(dir.path(), &path, &[]);
    let port = gateway.metrics_port(20.0);
    wait_api(&gateway, port, 20.0, "a refused job", |s| {
        s["axes"][0]["jobs_failed"].as_u64().is_some_and(|n| n > 0)
    });
    nc.set_job_fault(JobFault::None);
    // A new temperature calls for a new job.
    plant.field["ain1"]
        .set_temperature_override(0, Some(35.0))
        .expect("override set");
    wait_api(&gateway, port, 20.0, "a job that succeeds", |s| {
        s["axes"][0]["jobs_ok"].as_u64().is_some_and(|n| n > 0)
            && s["axes"][0]["last_job_error"].is_null()
    });
    let mut browser = Browser::start(&chromium);
    browser.open(&format!("http://127.0.0.1:{port}/"), "UTC", "");
    let shown = browser.wait(
        10.0,
        "the axis card drawn",
        r#"!!document.querySelector('.axis[data-axis="X"]')"#,
    );
    let x = shown["axes"]["X"]["text"].as_str().unwrap_or_default();
    assert!(
        x.contains("last failed job") && x.contains("access denied"),
        "{shown:#}"
    );
    assert!(!x.contains("last job:"), "{shown:#}");
    drop(browser);
    drop(gateway);
}

// Times name their zone, and carry a date when not of today: a browser whose clock
// is a day ahead of the gateway's shows the gateway's data with its date, and is live
// all the same (its staleness is measured on its own clock, never against the
// gateway's). A browser on today shows the time and zone only.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn times_show_their_zone_and_a_date_when_not_today() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let (_plant, path) = plant(dir.path(), &common::config("hold", "", ""), "").await;
    let gateway = Gateway::start(dir.path(), &path, &[]);
    let port = gateway.metrics_port(20.0);
    wait_api(&gateway, port, 20.0, "a job done", |s| {
        s["jobs"].as_array().is_some_and(|j| !j.is_empty())
    });
    let url = format!("http://127.0.0.1:{port}/");
    let is_live = r#"document.getElementById("live").dataset.state === "live""#;
    let mut today = Browser::start(&chromium);
    today.open(&url, "UTC", "");
    let now = today.wait(10.0, "the page live", is_live);
    let time_utc = |s: &str| {
        let b = s.as_bytes();
        s.len() == 12
            && s.ends_with(" UTC")
            && [2, 5].iter().all(|&i| b[i] == b':')
            && [0, 1, 3, 4, 6, 7].iter().all(|&i| b[i].is_ascii_digit())
    };
    let text = now["live_text"].as_str().unwrap_or_default();
    assert!(
        text.strip_prefix("live, data of ").is_some_and(time_utc),
        "{now:#}"
    );
    assert!(
        now["job_times"]
            .as_array()
            .is_some_and(|t| !t.is_empty() && t.iter().all(|t| t.as_str().is_some_and(time_utc))),
        "{now:#}"
    );
    drop(today);

    let day = utc_date(std::time::SystemTime::now());
    // The page's clock a day ahead: every date it makes without a time given.
    let ahead = "{ const D = Date; const DAY = 86400000; \
        globalThis.Date = class extends D { \
          constructor(...a) { if (a.length) { super(...a); } else { super(D.now() + DAY); } } \
          static now() { return D.now() + DAY; } }; }";
    let mut tomorrow = Browser::start(&chromium);
    tomorrow.open(&url, "UTC", ahead);
    let later = tomorrow.wait(10.0, "the page live", is_live);
    let text = later["live_text"].as_str().unwrap_or_default();
    assert!(
        text.strip_prefix("live, data of ")
            .and_then(|t| t.strip_prefix(&format!("{day} ")))
            .is_some_and(time_utc),
        "{day} in {later:#}"
    );
    assert!(
        later["job_times"].as_array().is_some_and(|t| !t.is_empty()
            && t.iter().all(|t| t
                .as_str()
                .and_then(|t| t.strip_prefix(&format!("{day} ")))
                .is_some_and(time_utc))),
        "{later:#}"
    );
    // Still live some status intervals on: no comparison with the gateway's clock.
    std::thread::sleep(Duration::from_secs(4));
    let still = tomorrow.eval(STATE);
    assert_eq!(still["live"], "live", "{still:#}");
    drop(tomorrow);
    drop(gateway);
}
