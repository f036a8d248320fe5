//! The metrics endpoint as a scraper sees it: one GET over a plain TCP connection.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

/// GET /metrics with every step bounded by `limit`: the body and how long it took;
/// `Err` with what went wrong (an answer other than 200 included).
pub fn scrape(port: u16, limit: Duration) -> Result<(String, Duration), String> {
    let started = Instant::now();
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let mut s = TcpStream::connect_timeout(&addr, limit).map_err(|e| format!("connect: {e}"))?;
    s.set_read_timeout(Some(limit)).map_err(|e| e.to_string())?;
    s.set_write_timeout(Some(limit))
        .map_err(|e| e.to_string())?;
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
        .map_err(|e| format!("request: {e}"))?;
    let mut text = String::new();
    s.read_to_string(&mut text)
        .map_err(|e| format!("response after {:?}: {e}", started.elapsed()))?;
    if !text.starts_with("HTTP/1.1 200") {
        return Err(format!("not 200: {text}"));
    }
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    Ok((body, started.elapsed()))
}

/// The value of `series` (name and labels, as written) in a metrics body.
pub fn value(body: &str, series: &str) -> Option<f64> {
    body.lines()
        .filter_map(|l| l.rsplit_once(' '))
        .find(|(k, _)| *k == series)
        .and_then(|(_, v)| v.parse().ok())
}

/// Whether `promtool` (package prometheus, with the server beside it) is installed;
/// under CI it must be, elsewhere a test without it is skipped.
pub fn have_promtool() -> bool {
    let there = std::process::Command::new("promtool")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !there {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI is set and promtool is missing (./test.sh installs the prometheus package)"
        );
        println!("SKIPPED: promtool not installed (Debian package `prometheus`)");
    }
    there
}
