//! The shipped Prometheus alerting rules (`deploy/prometheus/compgate-alerts.yml`):
//! their promtool unit tests, and a real Prometheus server scraping the real gateway,
//! whose alerts go pending for a field device and an NC that stop answering.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::io::{Read, Write};
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::metrics::{have_promtool, scrape};
use common::process::Gateway;
use common::proxy::Proxy;
use compgate::plant::{Bind, Plant};
use compgate_plc::field::CommFault;

const RULES: &str = "deploy/prometheus/compgate-alerts.yml";

fn said(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr)
}

// The rules load, and each alert fires when its unit tests say (and not for a fault
// shorter than its `for:`).
#[test]
fn the_shipped_alert_rules_pass_promtool() {
    if !have_promtool() {
        return;
    }
    let out = Command::new("promtool")
        .args(["check", "rules", RULES])
        .output()
        .unwrap();
    assert!(out.status.success(), "promtool check rules: {}", said(&out));
    let out = Command::new("promtool")
        .args(["test", "rules", "tests/prometheus/compgate-alerts.test.yml"])
        .output()
        .unwrap();
    assert!(out.status.success(), "promtool test rules: {}", said(&out));
}

/// A GET of `path` on the Prometheus at `port`: the body.
fn get(port: u16, path: &str) -> Result<String, String> {
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let limit = Duration::from_secs(2);
    let mut s =
        std::net::TcpStream::connect_timeout(&addr, limit).map_err(|e| format!("connect: {e}"))?;
    s.set_read_timeout(Some(limit)).map_err(|e| e.to_string())?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n"
    )
    .map_err(|e| e.to_string())?;
    let mut text = String::new();
    s.read_to_string(&mut text).map_err(|e| e.to_string())?;
    let (head, body) = text.split_once("\r\n\r\n").ok_or("no body")?;
    if !head.starts_with("HTTP/1.1 200") {
        return Err(format!("{head}\n{body}"));
    }
    // Chunked or not, the JSON is the part between the outer braces.
    match (body.find('{'), body.rfind('}')) {
        (Some(a), Some(b)) => Ok(body[a..=b].to_string()),
        _ => Err(format!("no JSON: {body}")),
    }
}

/// A Prometheus server scraping the gateway's metrics at `target` every second with
/// the shipped rules, evaluated every second.
struct Prometheus {
    child: Child,
    port: u16,
}

impl Prometheus {
    fn start(dir: &Path, target: u16) -> Self {
        let rules = std::env::current_dir().unwrap().join(RULES);
        let conf = dir.join("prometheus.yml");
        std::fs::write(
            &conf,
            format!(
                "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n\
                 rule_files: [{rules:?}]\n\
                 scrape_configs:\n  - job_name: compgate\n    static_configs:\n      \
                 - targets: [\"127.0.0.1:{target}\"]\n        labels: {{instance: \"DMU 65 no. 3\"}}\n"
            ),
        )
        .unwrap();
        let port = common::free_port();
        let child = Command::new("prometheus")
            .arg(format!("--config.file={}", conf.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.join("tsdb").display()
            ))
            .arg(format!("--web.listen-address=127.0.0.1:{port}"))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("prometheus.log")).unwrap())
            .spawn()
            .expect("prometheus starts");
        let mut p = Prometheus { child, port };
        common::process::wait_listening(&mut p.child, port, 20.0, "prometheus");
        p
    }

    /// The alerts pending or firing, as JSON.
    fn alerts(&self) -> String {
        get(self.port, "/api/v1/alerts").unwrap_or_default()
    }
}

impl Drop for Prometheus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Every `compgate_...` metric name the rules use.
fn rule_metrics() -> Vec<String> {
    let text = std::fs::read_to_string(RULES).unwrap();
    let mut names: Vec<String> = text
        .lines()
        .filter_map(|l| l.trim().strip_prefix("expr:"))
        .flat_map(|e| {
            e.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                .filter(|w| w.starts_with("compgate_"))
                .map(str::to_string)
                .collect::<Vec<_>>()
        })
        .collect();
    names.sort();
    names.dedup();
    names
}

// The shipped rules against what the gateway exports: every metric they use is in a
// real scrape, and a real Prometheus evaluating them sees a field device and an NC
// that stop answering (the alerts pending: their `for:` is minutes), and nothing
// about the gateway or its recorder; parts a reload removes take their alerts along.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_prometheus_raises_the_alerts_for_a_silent_device_and_nc() {
    if !have_promtool() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let toml = common::config("hold", "", "");
    let plant = Plant::start(
        &compgate_gateway::config::load_str(&toml, "t.toml").unwrap(),
        Bind::Ephemeral,
    )
    .await
    .unwrap();
    let proxy = Proxy::start(plant.config.nc_modules["nc_x"].address.clone()).await;
    let mut cfg = plant.config.clone();
    cfg.nc_modules.get_mut("nc_x").unwrap().address = proxy.addr.to_string();
    let path = dir.path().join("compgate.toml");
    let extra = format!(
        "\n[metrics]\nbind = \"127.0.0.1:0\"\n\n[recorder]\npath = {:?}\n",
        dir.path().join("rec.db").display().to_string()
    );
    std::fs::write(&path, toml::to_string(&cfg).unwrap() + &extra).unwrap();
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    let port = tokio::task::block_in_place(|| gw.metrics_port(10.0));
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "first job", |m| m.contains("jobs 1 ok")));

    let (body, _) =
        tokio::task::block_in_place(|| scrape(port, Duration::from_secs(2))).expect("scrape");
    let names = rule_metrics();
    assert!(names.len() >= 9, "{names:?}");
    for name in &names {
        assert!(
            body.contains(&format!("# HELP {name} ")) && body.contains(&format!("\n{name}")),
            "the rules use {name}, which the gateway does not export:\n{body}"
        );
    }

    let prom = tokio::task::block_in_place(|| Prometheus::start(dir.path(), port));
    let deadline = Instant::now() + Duration::from_secs(30);
    while !get(
        prom.port,
        "/api/v1/query?query=up%7Bjob%3D%22compgate%22%7D%3D%3D1",
    )
    .is_ok_and(|r| r.contains("\"result\":[{"))
    {
        assert!(
            Instant::now() < deadline,
            "prometheus never scraped the gateway"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }

    plant.field["ain1"].set_comm_fault(CommFault::Silent);
    proxy.cut();
    let wanted = [
        r#""alertname":"CompgateDeviceDown","device":"ain1""#,
        r#""alertname":"CompgateChannelBad","channel":"T_bed""#,
        r#""alertname":"CompgateNcUnreachable","axis":"X""#,
    ];
    let deadline = Instant::now() + Duration::from_secs(30);
    let alerts = loop {
        let alerts = tokio::task::block_in_place(|| prom.alerts());
        if wanted.iter().all(|w| alerts.contains(w)) {
            break alerts;
        }
        assert!(
            Instant::now() < deadline,
            "after 30 s the alerts are: {alerts}\n{}",
            std::fs::read_to_string(dir.path().join("prometheus.log")).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    // The scrape names the machine (as the rules file's head shows): so do the alerts.
    assert!(alerts.contains(r#""instance":"DMU 65 no. 3""#), "{alerts}");
    for quiet in [
        "CompgateDown",
        "CompgateRecorderFailing",
        "CompgateRecordsDropped",
    ] {
        assert!(!alerts.contains(quiet), "{quiet}: {alerts}");
    }

    // The engineer takes the broken sensor and the cut NC out of the config: their
    // series leave the scrape at the reload, and their alerts go (they stayed until
    // the next restart).
    cfg.axes.remove("X");
    cfg.nc_modules.remove("nc_x");
    cfg.channels.remove("T_bed");
    cfg.sim = None;
    std::fs::write(&path, toml::to_string(&cfg).unwrap() + &extra).unwrap();
    gw.signal("HUP");
    tokio::task::block_in_place(|| gw.wait_log(10.0, "configuration reloaded"));
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let alerts = tokio::task::block_in_place(|| prom.alerts());
        let (body, _) =
            tokio::task::block_in_place(|| scrape(port, Duration::from_secs(2))).expect("scrape");
        let gone = !body.contains("axis=\"X\"") && !body.contains("channel=\"T_bed\"");
        if gone && !alerts.contains(wanted[1]) && !alerts.contains(wanted[2]) {
            assert!(body.contains("channel=\"T_screw\""), "{body}");
            assert!(alerts.contains(wanted[0]), "{alerts}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "30 s after the reload, the alerts: {alerts}\nthe scrape: {body}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    drop(prom);
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

// An NC that answers and applies no compensation raised no alert: its MD32750 is not
// the config's (the axis holds), or the axis is not referenced. Each has a gauge of
// its own, which the rules `CompgateMd32750Mismatch` and `CompgateAxisNotReferenced`
// watch (their timing: tests/prometheus/compgate-alerts.test.yml).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_nc_that_applies_no_compensation_is_in_the_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let toml = common::config("hold", "", "").replace(
        "referenced = true\nmd32750 = 3",
        "referenced = false\nmd32750 = 2",
    );
    let (plant, path) =
        common::plant_and_file(dir.path(), &toml, "\n[metrics]\nbind = \"127.0.0.1:0\"\n").await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let port = tokio::task::block_in_place(|| gw.metrics_port(10.0));
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (body, _) =
            tokio::task::block_in_place(|| scrape(port, Duration::from_secs(2))).expect("scrape");
        let of = |series: &str| common::metrics::value(&body, series);
        if of("compgate_axis_md32750_mismatch{axis=\"X\"}") == Some(1.0)
            && of("compgate_axis_unreferenced{axis=\"X\"}") == Some(1.0)
        {
            assert_eq!(of("compgate_axis_nc_up{axis=\"X\"}"), Some(1.0), "{body}");
            break;
        }
        assert!(Instant::now() < deadline, "after 10 s: {body}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}
