//! The live status page on the HTTP listener that serves `/metrics`:
//!
//! - `GET /`: one HTML page (HTML, CSS and JavaScript embedded in the binary, no
//!   internet and no build step needed) that polls `/api/status` once per status
//!   interval and draws devices, channels with a trend, axes, the NC and the last NC
//!   jobs.
//! - `GET /api/status`: the same as JSON ([`to_json`]); `GET /api/status?trend=0`
//!   without the trends (at 384 channels 85 kB instead of 3.66 MB: the page asks for
//!   the trends only every few seconds).
//!
//! Read-only: the router answers GET and HEAD only. The data is the status snapshot
//! the control loop publishes at each status tick; the trend history is kept here, in
//! a task of its own ([`track`]), not in the control loop.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use bytes::Bytes;
use http_body_util::Full;
use hyper::header::{HeaderValue, CACHE_CONTROL, CONTENT_TYPE};
use hyper::{Response, StatusCode};
use serde_json::{json, Value};
use tokio::sync::watch;

use crate::http::Router;
use crate::record::quality_code;
use compgate_core::comp::CompParams;
use compgate_gateway::nc::NcSnapshot;
use compgate_gateway::runtime::{DeviceStatus, Status};

const INDEX_HTML: &str = include_str!("index.html");
const PAGE_CSS: &str = include_str!("page.css");
const PAGE_JS: &str = include_str!("page.js");

/// Points a channel's trend keeps at most: the trend window is sampled this finely.
pub const TREND_POINTS: usize = 300;

/// `degc` in mdegC for a trend point: [`NO_VALUE`] if not finite or beyond the range.
fn to_mdegc(degc: f64) -> i32 {
    let m = (degc * 1000.0).round();
    if m.is_finite() && m > f64::from(NO_VALUE) && m <= f64::from(i32::MAX) {
        m as i32
    } else {
        NO_VALUE
    }
}

/// Trend points kept per channel: [`TREND_POINTS`] apart plus the newest.
const TREND_SLOTS: usize = TREND_POINTS + 1;

/// The quality of a slot a channel has no point in (a channel added by a reload,
/// for the times before it).
const ABSENT: u8 = u8::MAX;

/// A trend point's value in mdegC when it has none.
const NO_VALUE: i32 = i32::MIN;

/// The trends of every channel, by index, on one timeline. Each status gives every
/// channel a point at the same time, so the times are kept once in a ring of
/// [`TREND_POINTS`] + 1, and each channel's points as a value (to 0.001 degC, which a
/// drawn trend does not resolve) and a quality per slot: 5 bytes a point, allocated
/// once. A deque of 32-byte points per channel doubled to 512 points: 16 kB a
/// channel, 164 MB at 10000 channels after five minutes.
#[derive(Debug, Clone, Default)]
pub struct History {
    window: Duration,
    names: Vec<Arc<str>>,
    /// Time of each slot; the kept ones are `len` slots from `head`, oldest first.
    times_ms: Vec<i64>,
    head: usize,
    len: usize,
    /// Channel `c`'s value in slot `s` at `c * TREND_SLOTS + s`, mdegC ([`NO_VALUE`]).
    values_mdegc: Vec<i32>,
    /// Its quality code there (0 good, 1 uncertain, 2 bad; [`ABSENT`]: no point).
    qualities: Vec<u8>,
}

impl History {
    /// History over `window` (the trend's span).
    pub fn new(window: Duration) -> Self {
        History {
            window,
            ..Self::default()
        }
    }

    /// The ring slot of the `k`th kept time, oldest first.
    fn slot(&self, k: usize) -> usize {
        (self.head + k) % TREND_SLOTS
    }

    /// Adds `status` at `t_unix_ms`: one point per channel, kept points at least
    /// window / [`TREND_POINTS`] apart (the newest point is replaced until it is, so
    /// the newest value always shows).
    pub fn push(&mut self, status: &Status, t_unix_ms: i64) {
        // The ring's times, allocated with the first status.
        if self.times_ms.len() != TREND_SLOTS {
            self.times_ms = vec![0; TREND_SLOTS];
        }
        let names_changed = self.names.len() != status.channels.len()
            || self
                .names
                .iter()
                .zip(&status.channels)
                // The same shared name unless a reload changed the channels.
                .any(|(n, c)| !Arc::ptr_eq(n, &c.name) && n != &c.name);
        if names_changed {
            self.rename(status);
        }
        let window_ms = i64::try_from(self.window.as_millis()).unwrap_or(i64::MAX);
        let spacing_ms = window_ms / TREND_POINTS as i64;
        // The wall clock set back: the points after this time are of another
        // timeline, and the newest one would be replaced for the size of the step.
        if self.len > 0 && self.times_ms[self.slot(self.len - 1)] > t_unix_ms {
            self.len = 0;
        }
        // The newest point moves on until it is `spacing_ms` after the one before
        // it; then it stays and the next one starts.
        let n = self.len;
        let replace = n >= 2
            && self.times_ms[self.slot(n - 1)] - self.times_ms[self.slot(n - 2)] < spacing_ms;
        if !replace {
            if self.len == TREND_SLOTS {
                self.head = self.slot(1);
                self.len -= 1;
            }
            self.len += 1;
        }
        let at = self.slot(self.len - 1);
        self.times_ms[at] = t_unix_ms;
        for (c, ch) in status.channels.iter().enumerate() {
            let i = c * TREND_SLOTS + at;
            self.values_mdegc[i] = ch.reading.value_degc.map_or(NO_VALUE, to_mdegc);
            self.qualities[i] = quality_code(&ch.reading.quality).0;
        }
        while self.len > 0 && t_unix_ms - self.times_ms[self.head] > window_ms {
            self.head = self.slot(1);
            self.len -= 1;
        }
    }

    /// A reload with other channels: the trends of the names kept stay, the new
    /// ones start empty.
    fn rename(&mut self, status: &Status) {
        let n = status.channels.len();
        let mut values_mdegc = vec![NO_VALUE; n * TREND_SLOTS];
        let mut qualities = vec![ABSENT; n * TREND_SLOTS];
        for (c, ch) in status.channels.iter().enumerate() {
            if let Some(old) = self.names.iter().position(|o| *o == ch.name) {
                let (from, to) = (old * TREND_SLOTS, c * TREND_SLOTS);
                values_mdegc[to..to + TREND_SLOTS]
                    .copy_from_slice(&self.values_mdegc[from..from + TREND_SLOTS]);
                qualities[to..to + TREND_SLOTS]
                    .copy_from_slice(&self.qualities[from..from + TREND_SLOTS]);
            }
        }
        self.names = status.channels.iter().map(|c| c.name.clone()).collect();
        self.values_mdegc = values_mdegc;
        self.qualities = qualities;
    }

    /// Channel `i`'s points, oldest first: (t_unix_ms, value_degc, quality code).
    fn points(&self, i: usize) -> impl Iterator<Item = (i64, Option<f64>, u8)> + '_ {
        let kept = if i < self.names.len() { self.len } else { 0 };
        (0..kept).filter_map(move |k| {
            let s = self.slot(k);
            let at = i * TREND_SLOTS + s;
            let v = self.values_mdegc[at];
            (self.qualities[at] != ABSENT).then(|| {
                (
                    self.times_ms[s],
                    (v != NO_VALUE).then(|| f64::from(v) / 1000.0),
                    self.qualities[at],
                )
            })
        })
    }

    /// Trend of channel `i`: `[[t_unix_ms, value_degc or null, quality], ...]`.
    fn trend(&self, i: usize) -> Value {
        Value::Array(self.points(i).map(|(t, v, q)| json!([t, v, q])).collect())
    }
}

/// What one snapshot forgets and the page still shows: when each device last answered,
/// and the last NC values each axis read (an unreachable NC leaves the snapshot's
/// empty).
#[derive(Debug, Clone, Default)]
pub struct Seen {
    /// By device: the cycle count last seen and when a cycle last had an answer.
    devices: HashMap<String, (u64, Option<i64>)>,
    /// By axis: the last NC snapshot and when it was seen.
    nc: HashMap<String, (NcSnapshot, i64)>,
}

impl Seen {
    /// Notes `status`, published at `t_unix_ms`.
    pub fn note(&mut self, status: &Status, t_unix_ms: i64) {
        for d in &status.devices {
            let e = self.devices.entry(d.name.clone()).or_insert((0, None));
            // A new cycle that got an answer: a device that hangs in its timeouts
            // keeps link_up from its last cycle but counts no new one.
            if d.link_up && d.cycles != e.0 {
                e.1 = Some(t_unix_ms);
            }
            e.0 = d.cycles;
        }
        for a in &status.axes {
            if let Some(nc) = &a.nc {
                self.nc.insert(a.name.clone(), (*nc, t_unix_ms));
            }
        }
    }
}

fn unix_ms(t: SystemTime) -> i64 {
    t.duration_since(UNIX_EPOCH)
        .ok()
        .and_then(|d| i64::try_from(d.as_millis()).ok())
        .unwrap_or(0)
}

fn params(p: &CompParams) -> Value {
    json!({ "sd43900_mm": p.k0_mm, "sd43910": p.tan_beta, "sd43920_mm": p.p0_mm })
}

/// A JSON number, or null for NaN and infinities (JSON has none).
fn num(v: f64) -> Value {
    if v.is_finite() {
        json!(v)
    } else {
        Value::Null
    }
}

fn nc_json(nc: &NcSnapshot) -> Value {
    json!({
        "sd43900_mm": num(nc.sd43900_mm),
        "sd43910": num(nc.sd43910),
        "sd43920_mm": num(nc.sd43920_mm),
        // null where the target does not report it (OPC UA, ADS).
        "md32750": nc.md32750,
        "position_mm": nc.position_mm.map(num),
        "applied_comp_mm": nc.applied_comp_mm.map(num),
        "target_comp_mm": nc.target_comp_mm.map(num),
        "referenced": nc.referenced,
    })
}

/// A device's state in one word, as `/api/status` and the MQTT health message say it:
/// `connecting`, `up`, `errors` or `down`.
pub(crate) fn device_state(d: &DeviceStatus) -> &'static str {
    match (&d.last_error, d.cycles) {
        // It answers, but a read of it fails: its channels say which.
        (Some(_), _) if d.link_up => "errors",
        (Some(_), _) => "down",
        (None, 0) => "connecting",
        (None, _) => "up",
    }
}

/// `/api/status`: the status at `t_unix_ms`, with the trends if `trends`. Ages
/// (`*_ago_ms`) are relative to `t_unix_ms`: a browser whose clock differs from the
/// gateway's still reads them right.
pub fn to_json(
    s: &Status,
    history: &History,
    seen: &Seen,
    interval_s: f64,
    t_unix_ms: i64,
    trends: bool,
) -> Value {
    let trend_s = history.window.as_secs_f64();
    let devices: Vec<Value> = s
        .devices
        .iter()
        .map(|d| {
            json!({
                "name": d.name,
                "link": d.link,
                "state": device_state(d),
                "cycles": d.cycles,
                "failed_cycles": d.failed_cycles,
                "connects": d.connects,
                "last_cycle_ms": d.last_cycle.as_secs_f64() * 1e3,
                "answered_ago_ms": seen
                    .devices
                    .get(&d.name)
                    .and_then(|e| e.1)
                    .map(|t| t_unix_ms - t),
                "last_error": d.last_error,
                "errors": d.errors,
            })
        })
        .collect();
    let channels: Vec<Value> = s
        .channels
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let r = &c.reading;
            let (code, reason) = quality_code(&r.quality);
            let quality = ["good", "uncertain", "bad"][usize::from(code.min(2))];
            let mut v = json!({
                "name": &*c.name,
                "value_degc": r.value_degc.map(num),
                "unfiltered_degc": r.unfiltered_degc.map(num),
                "current_ma": r.current_ma.map(num),
                "raw": r.raw.map(num),
                "quality": quality,
                "reason": reason,
                "quality_text": r.quality.to_string(),
            });
            if trends {
                v["trend"] = history.trend(i);
            }
            v
        })
        .collect();
    let axes: Vec<Value> = s
        .axes
        .iter()
        .map(|a| {
            json!({
                "name": a.name,
                "shadow": a.shadow,
                "written": a.written.as_ref().map(params),
                "would_write": a.would_write.as_ref().map(params),
                "decision": a.decision,
                "at_limit": a.at_limit,
                "outside_fit": a.outside_fit,
                "jobs_ok": a.jobs_ok,
                "jobs_failed": a.jobs_failed,
                "jobs_shadow": a.jobs_shadow,
                "last_job_error": a.last_job_error,
                "last_failure": a.last_failure.as_ref().map(|(t, error)| {
                    json!({ "t_unix_ms": unix_ms(*t), "error": error })
                }),
                "warning": a.warning,
                "nc": a.nc.as_ref().map(nc_json),
                // The NC's values as last read, also while it does not answer.
                "nc_last": seen.nc.get(&a.name).map(|(nc, t)| {
                    let mut v = nc_json(nc);
                    v["read_ago_ms"] = json!(t_unix_ms - t);
                    v
                }),
            })
        })
        .collect();
    // Newest first: the page lists them so.
    let jobs: Vec<Value> = s
        .jobs
        .iter()
        .rev()
        .map(|j| {
            json!({
                "t_unix_ms": unix_ms(j.at),
                "axis": j.axis,
                "shadow": j.shadow,
                "ok": j.error.is_none() && !j.shadow,
                "job_id": j.job_id,
                "elapsed_ms": j.elapsed.map(|e| e.as_secs_f64() * 1e3),
                "error": j.error,
                "params": params(&j.params),
            })
        })
        .collect();
    json!({
        "t_unix_ms": t_unix_ms,
        "interval_s": interval_s,
        "trend_s": trend_s,
        "samples": s.samples,
        "shadow": s.axes.iter().any(|a| a.shadow),
        "devices": devices,
        "channels": channels,
        "axes": axes,
        "jobs": jobs,
    })
}

/// What the page's routes answer from: the latest status and the trends; the
/// `/api/status` body is built from them when asked for, at most once per status and
/// once per 250 ms, the page's shortest refresh.
#[derive(Debug, Clone, Default)]
pub struct Page {
    inner: Arc<Mutex<Latest>>,
}

#[derive(Debug, Default)]
struct Latest {
    status: Status,
    history: History,
    seen: Seen,
    interval_s: f64,
    t_unix_ms: i64,
    /// Statuses received so far.
    seq: u64,
    /// The bodies last built (with the trends, without).
    body: [Option<Built>; 2],
}

#[derive(Debug)]
struct Built {
    bytes: Bytes,
    /// [`Latest::seq`] of the status it shows.
    seq: u64,
    at: Instant,
}

/// A body is rebuilt for a newer status only when it is older than this, the page's
/// shortest refresh: at a 50 ms status interval, a flood of requests had the listener
/// build half a megabyte of JSON 20 times a second, and `/metrics` went unanswered
/// for 5 s.
const REBUILD_AFTER: Duration = Duration::from_millis(250);

impl Page {
    /// The latest `/api/status` body, with the trends if `trends`.
    pub fn json(&self, trends: bool) -> Bytes {
        let mut l = self.inner.lock().unwrap_or_else(|p| p.into_inner());
        let slot = usize::from(!trends);
        if let Some(b) = &l.body[slot] {
            if b.seq == l.seq || b.at.elapsed() < REBUILD_AFTER {
                return b.bytes.clone();
            }
        }
        let body = Bytes::from(
            to_json(
                &l.status,
                &l.history,
                &l.seen,
                l.interval_s,
                l.t_unix_ms,
                trends,
            )
            .to_string(),
        );
        l.body[slot] = Some(Built {
            bytes: body.clone(),
            seq: l.seq,
            at: Instant::now(),
        });
        body
    }
}

/// `trend=0` in a query string: the answer leaves the trends out.
fn wants_trends(query: Option<&str>) -> bool {
    !query.is_some_and(|q| q.split('&').any(|kv| kv == "trend=0"))
}

/// Keeps `page` up to date from `rx` until the gateway's status sender is gone:
/// the trends are extended here, once per published status, never in the control
/// loop. The JSON is built only when a browser asks: built every tick, with nobody
/// looking, it took the gateway from 0.52 % to 1.16 % of one core at 10k points/s
/// (1000 channels with their trends; scale benchmark).
pub async fn track(
    mut rx: watch::Receiver<Status>,
    page: Page,
    window: Duration,
    interval: Duration,
) {
    {
        let mut l = page.inner.lock().unwrap_or_else(|p| p.into_inner());
        l.history = History::new(window);
        l.interval_s = interval.as_secs_f64();
    }
    // Copied out before the page's lock is taken: a borrow held while a browser's
    // JSON is built under that lock kept the control loop from publishing its next
    // status, and its polls waited.
    let mut s = Status::default();
    loop {
        s.clone_from(&rx.borrow_and_update());
        {
            let now = unix_ms(SystemTime::now());
            let mut l = page.inner.lock().unwrap_or_else(|p| p.into_inner());
            // Before the first sample every channel is "no data": not a trend point.
            if s.samples > 0 {
                l.history.push(&s, now);
            }
            l.seen.note(&s, now);
            std::mem::swap(&mut l.status, &mut s);
            l.t_unix_ms = now;
            l.seq += 1;
        }
        if rx.changed().await.is_err() {
            break;
        }
    }
}

fn with_type(body: impl Into<Bytes>, content_type: &'static str) -> Response<Full<Bytes>> {
    let mut r = Response::new(Full::new(body.into()));
    *r.status_mut() = StatusCode::OK;
    let h = r.headers_mut();
    h.insert(CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(CACHE_CONTROL, HeaderValue::from_static("no-store"));
    r
}

/// `router` with the page's routes: `/`, `/page.css`, `/page.js`, `/api/status`
/// (`?trend=0`: without the trends).
pub fn routes(router: Router, page: Page) -> Router {
    router
        .get("/", || with_type(INDEX_HTML, "text/html; charset=utf-8"))
        .get("/page.css", || {
            with_type(PAGE_CSS, "text/css; charset=utf-8")
        })
        .get("/page.js", || {
            with_type(PAGE_JS, "text/javascript; charset=utf-8")
        })
        .get_with_query("/api/status", move |query| {
            with_type(page.json(wants_trends(query)), "application/json")
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use compgate_core::channel::{Quality, Reading, Reason};
    use compgate_gateway::runtime::{AxisStatus, ChannelStatus, JobStatus};

    fn status(v: f64, q: Quality) -> Status {
        let mut s = Status {
            channels: vec![ChannelStatus {
                name: "T_bed".into(),
                reading: Reading {
                    value_degc: Some(v),
                    quality: q,
                    ..Reading::no_data()
                },
            }],
            axes: vec![AxisStatus {
                name: "X".into(),
                shadow: true,
                would_write: Some(CompParams {
                    k0_mm: 0.02,
                    tan_beta: 1e-5,
                    p0_mm: 0.0,
                }),
                ..AxisStatus::default()
            }],
            ..Status::default()
        };
        s.push_job(JobStatus {
            axis: "X".into(),
            at: UNIX_EPOCH + Duration::from_secs(10),
            params: CompParams::default(),
            shadow: true,
            job_id: None,
            elapsed: None,
            error: None,
        });
        s
    }

    #[test]
    fn the_json_carries_values_quality_trend_shadow_and_jobs() {
        let mut h = History::new(Duration::from_secs(300));
        for k in 0..5 {
            h.push(&status(20.0 + f64::from(k), Quality::Good), 1_000 * k64(k));
        }
        let s = status(25.0, Quality::Bad(Reason::Ne43Low));
        h.push(&s, 5_000);
        let mut seen = Seen::default();
        seen.note(&s, 5_000);
        let j = to_json(&s, &h, &seen, 1.0, 5_000, true);
        let c = &j["channels"][0];
        assert_eq!(c["value_degc"], 25.0);
        assert_eq!(c["quality"], "bad");
        assert_eq!(c["reason"], "NE43 low");
        let trend = c["trend"].as_array().expect("trend");
        assert_eq!(trend.len(), 6);
        assert_eq!(trend[0], json!([0, 20.0, 0]));
        assert_eq!(trend[5], json!([5000, 25.0, 2]));
        assert_eq!(j["shadow"], true);
        assert_eq!(j["axes"][0]["would_write"]["sd43900_mm"], 0.02);
        assert_eq!(j["jobs"][0]["shadow"], true);
        assert_eq!(j["jobs"][0]["ok"], false);
        assert_eq!(j["jobs"][0]["t_unix_ms"], 10_000);
    }

    fn k64(k: u32) -> i64 {
        i64::from(k)
    }

    // The trend spans the window with at most TREND_POINTS + 1 points, however
    // often the status comes, and its newest point is the newest status.
    #[test]
    fn the_trend_is_bounded_by_window_and_points() {
        let mut h = History::new(Duration::from_secs(60));
        for k in 0..10_000u32 {
            h.push(&status(f64::from(k), Quality::Good), i64::from(k) * 50);
        }
        let p: Vec<_> = h.points(0).collect();
        assert!(p.len() <= TREND_POINTS + 1, "{}", p.len());
        assert!(p.len() >= TREND_POINTS / 2, "{}", p.len());
        let last = p.last().expect("points");
        assert_eq!(last.1, Some(9999.0));
        let first = p.first().expect("points");
        assert!(last.0 - first.0 <= 60_000);
        assert!(last.0 - first.0 >= 59_000);
        // The memory is that of the first status: 10000 statuses later nothing grew.
        assert_eq!(h.values_mdegc.capacity(), TREND_SLOTS);
        assert_eq!(h.qualities.capacity(), TREND_SLOTS);
        assert_eq!(h.times_ms.capacity(), TREND_SLOTS);
    }

    #[test]
    fn a_trend_value_keeps_a_thousandth_of_a_degree() {
        for (degc, back) in [(23.4567, Some(23.457)), (-0.0004, Some(0.0)), (1e9, None)] {
            let m = to_mdegc(degc);
            let got = (m != NO_VALUE).then(|| f64::from(m) / 1000.0);
            assert_eq!(got, back, "{degc}");
        }
        assert_eq!(to_mdegc(f64::NAN), NO_VALUE);
        assert_eq!(to_mdegc(f64::NEG_INFINITY), NO_VALUE);
    }

    // A reload keeps the trends of the channels it keeps, wherever they move; a new
    // channel's trend starts with the first status that has it.
    #[test]
    fn a_reload_keeps_the_trends_of_the_channels_kept() {
        let mut h = History::new(Duration::from_secs(60));
        let mut s = status(20.0, Quality::Good);
        let mut t_ms = 0;
        for _ in 0..5 {
            h.push(&s, t_ms);
            t_ms += 1_000;
        }
        let mut new = s.channels[0].clone();
        new.name = "T_new".into();
        new.reading.value_degc = None;
        new.reading.quality = Quality::Bad(Reason::NoData);
        s.channels.insert(0, new);
        h.push(&s, t_ms);
        let kept: Vec<_> = h.points(1).collect();
        assert_eq!(kept.len(), 6, "{kept:?}");
        assert!(kept.iter().all(|p| p.1 == Some(20.0)), "{kept:?}");
        assert_eq!(h.points(0).collect::<Vec<_>>(), vec![(5_000, None, 2)]);
        assert_eq!(h.points(2).count(), 0);
        assert_eq!(h.trend(0), json!([[5_000, null, 2]]));
    }

    // The wall clock set back an hour: the trend starts again at the new time instead
    // of replacing its newest point for an hour.
    #[test]
    fn a_trend_starts_again_when_the_clock_is_set_back() {
        let mut h = History::new(Duration::from_secs(60));
        for k in 0..30u32 {
            h.push(
                &status(f64::from(k), Quality::Good),
                1_000_000 + i64::from(k) * 1_000,
            );
        }
        let back = 1_000_000 - 3_600_000;
        for k in 0..10u32 {
            h.push(
                &status(f64::from(k), Quality::Good),
                back + i64::from(k) * 1_000,
            );
        }
        let p: Vec<_> = h.points(0).collect();
        assert_eq!(p.first().map(|p| p.0), Some(back), "{p:?}");
        assert_eq!(p.last().map(|p| p.0), Some(back + 9_000), "{p:?}");
        assert!(p.len() >= 5, "{p:?}");
    }

    // An NC that stops answering leaves the snapshot without values: the JSON keeps
    // the last ones read with their age; a device's last answer is kept across
    // snapshots; `trend=0` leaves the trends out.
    #[test]
    fn the_last_nc_values_and_device_answers_outlive_a_snapshot() {
        use compgate_gateway::runtime::DeviceStatus;
        let mut s = status(21.0, Quality::Good);
        s.axes[0].nc = Some(NcSnapshot {
            sd43900_mm: 0.03,
            ..NcSnapshot::default()
        });
        s.devices = vec![DeviceStatus {
            name: "ain1".into(),
            cycles: 5,
            link_up: true,
            ..DeviceStatus::default()
        }];
        let mut seen = Seen::default();
        seen.note(&s, 1_000);
        // The device dead since 1 s.
        s.axes[0].nc = None;
        s.devices[0].cycles = 9;
        s.devices[0].link_up = false;
        seen.note(&s, 4_000);
        let j = to_json(&s, &History::default(), &seen, 1.0, 4_000, false);
        let x = &j["axes"][0];
        assert_eq!(x["nc"], Value::Null);
        assert_eq!(x["nc_last"]["sd43900_mm"], 0.03);
        assert_eq!(x["nc_last"]["read_ago_ms"], 3_000);
        assert_eq!(j["devices"][0]["answered_ago_ms"], 3_000);
        assert!(j["channels"][0].get("trend").is_none(), "{j}");
        assert!(wants_trends(None) && wants_trends(Some("a=1")));
        assert!(!wants_trends(Some("a=1&trend=0")));
    }

    #[test]
    fn not_finite_values_are_json_null() {
        let s = status(f64::NAN, Quality::Bad(Reason::NotFinite));
        let j = to_json(&s, &History::default(), &Seen::default(), 1.0, 0, true);
        assert_eq!(j["channels"][0]["value_degc"], Value::Null);
        // serde_json writes NaN as null too; what matters is valid JSON text.
        assert!(serde_json::from_str::<Value>(&j.to_string()).is_ok());
    }

    // A browser's JSON being built (the page's lock held) holds up the trends, never
    // the control loop's next status.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_json_build_does_not_hold_up_the_next_status() {
        let (tx, rx) = watch::channel(Status::default());
        let page = Page::default();
        let tracker = tokio::spawn(track(
            rx,
            page.clone(),
            Duration::from_secs(10),
            Duration::from_secs(1),
        ));
        tokio::time::sleep(Duration::from_millis(100)).await;
        let published = {
            let building = page.inner.lock().expect("page lock");
            tx.send_replace(status(20.0, Quality::Good));
            // The tracker now waits for the lock with that status.
            std::thread::sleep(Duration::from_millis(200));
            let (sent, done) = std::sync::mpsc::channel();
            std::thread::scope(|scope| {
                scope.spawn(|| {
                    tx.send_replace(status(21.0, Quality::Good));
                    let _ = sent.send(());
                });
                let published = done.recv_timeout(Duration::from_secs(2));
                drop(building);
                published
            })
        };
        assert!(published.is_ok(), "the next status waited for the JSON");
        drop(tx);
        tracker.await.expect("tracker");
    }

    // Statuses faster than the page refreshes share one body; a newer status gets its
    // own once the body is REBUILD_AFTER old; a status with no new one since is never
    // built twice.
    #[test]
    fn a_body_is_rebuilt_for_a_newer_status_at_most_every_250_ms() {
        let page = Page::default();
        let publish = |v: f64| {
            let mut l = page.inner.lock().expect("page lock");
            l.status = status(v, Quality::Good);
            l.seq += 1;
        };
        let value = |b: &Bytes| -> f64 {
            let j: Value = serde_json::from_slice(b).expect("json");
            j["channels"][0]["value_degc"].as_f64().expect("value")
        };
        publish(20.0);
        let first = page.json(true);
        assert_eq!(value(&first), 20.0);
        publish(21.0);
        assert_eq!(
            page.json(true).as_ptr(),
            first.as_ptr(),
            "rebuilt before {REBUILD_AFTER:?}"
        );
        // The other body is built for the status of now.
        assert_eq!(value(&page.json(false)), 21.0);
        std::thread::sleep(REBUILD_AFTER);
        let second = page.json(true);
        assert_eq!(value(&second), 21.0);
        std::thread::sleep(REBUILD_AFTER);
        assert_eq!(
            page.json(true).as_ptr(),
            second.as_ptr(),
            "rebuilt without a newer status"
        );
    }
}
