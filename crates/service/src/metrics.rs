//! Prometheus metrics through the `metrics` facade: the Prometheus exporter's recorder
//! writes the text format, and [`crate::http`] serves it as `GET /metrics` under a
//! connection limit and timeouts. Every metric has help text ([`describe`]).
//!
//! | metric | type | labels | meaning |
//! |---|---|---|---|
//! | `compgate_device_link_up` | gauge | device | 1 when the device answered in its last poll cycle (one of its reads may still have failed) |
//! | `compgate_device_poll_seconds` | histogram | device | duration of a poll cycle: the request round trips |
//! | `compgate_device_errors_total` | counter | device, kind | failed requests by kind, retries included: timeout, deadline, frame, transport, connect, exception; `backoff`: a cycle the reconnect backoff refused |
//! | `compgate_channel_value_degc` | gauge | channel | filtered temperature (NaN without a value, and while the channel is bad), every `gateway.status_interval_s` |
//! | `compgate_channel_quality` | gauge | channel | 0 good, 1 uncertain, 2 bad, every `gateway.status_interval_s` |
//! | `compgate_axis_sd43900_mm`, `compgate_axis_sd43910`, `compgate_axis_sd43920_mm` | gauge | axis | parameters last written and verified (what the NC held at start before the first job) |
//! | `compgate_axis_at_limit` | gauge | axis | 1 while the model's value is beyond `max_abs_k0_mm` or `max_abs_tan_beta` and the NC gets the limit instead |
//! | `compgate_axis_outside_fit` | gauge | axis | 1 while an input reads more than 2 K outside the temperatures the model was fitted over (`fitted_degc`): the model extrapolates |
//! | `compgate_axis_shadow` | gauge | axis | 1 when the axis runs in shadow mode (computes, never writes the NC) |
//! | `compgate_axis_nc_up`, `compgate_axis_md32750_mismatch`, `compgate_axis_unreferenced`, `compgate_axis_jobs_failing` | gauge | axis | the NC answered its last read; it holds another MD32750 than the config; it reports the axis not referenced; the last job failed |
//! | `compgate_axis_shadow_sd43900_mm`, `compgate_axis_shadow_sd43910`, `compgate_axis_shadow_sd43920_mm` | gauge | axis | shadow mode: the parameters the axis would have written last |
//! | `compgate_nc_jobs_total` | counter | axis, result (`ok`/`failed`/`shadow`) | NC job outcomes; `shadow`: computed, not sent |
//! | `compgate_cycle_seconds` | histogram | | control loop: time to process one device sample |
//! | `compgate_recorder_records_total` | counter | outcome (`written`, `dropped_queue`, `dropped_write`) | recorder |
//! | `compgate_recorder_shifted_readings_total` | counter | | readings stored at the next free millisecond: the database held their channel at their time (the wall clock set back over recorded time) |
//! | `compgate_recorder_duplicate_readings_total` | counter | | readings not stored: the database held their channel at every millisecond of a second from their time on |
//! | `compgate_recorder_up` | gauge | | 1 while the recorder's commits succeed, 0 while they fail (database locked by another process, disk full, ...) |
//! | `compgate_recorder_clock_ahead_seconds` | gauge | | how far the wall clock is ahead of the time age retention counts from: a step ahead it does not follow (0: in line) |
//! | `compgate_recorder_outbox_deleted_total` | counter | | MQTT messages the recorder's size limit deleted before they were sent |
//! | `compgate_process_heap_bytes` | gauge | state (`in_use`, `free`) | glibc malloc: bytes allocated (the live heap) and bytes it holds free; RSS growing with `in_use` flat is the allocator, not a leak (glibc only) |
//! | `compgate_http_connections_total` | counter | outcome (`accepted`, `evicted`, `refused`) | connections to this endpoint |
//! | `compgate_http_accept_errors_total` | counter | | failed accepts (e.g. out of descriptors) |

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::sync::{Arc, PoisonError, RwLock};
use std::time::Instant;

use metrics::{counter, gauge, histogram, Counter, Gauge, Histogram};
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder};

use compgate_gateway::config::MetricsConfig;

use crate::record::{quality_code, RecorderStats};
use crate::ServiceError;
use compgate_core::comp::CompParams;
use compgate_gateway::nc::{JobReport, NcError};
use compgate_gateway::runtime::{GatewayError, Observer, SampleReadings, Status};

/// Seconds between the exporter's upkeep passes (histogram buffers drained).
const UPKEEP_S: u64 = 5;

/// Label pairs (`channel="T_bed"`) of channels, devices and axes a reload removed: the
/// exporter cannot forget a series, so `/metrics` leaves theirs out. Their last values
/// stayed in the scrape, and an alert on them (a cut NC, a broken sensor taken out of
/// the config) fired until the next restart.
static RETIRED: RwLock<BTreeSet<String>> = RwLock::new(BTreeSet::new());

/// `text` (the exporter's) without the series of [`RETIRED`] labels.
fn without_retired(text: String) -> String {
    let retired = RETIRED.read().unwrap_or_else(PoisonError::into_inner);
    if retired.is_empty() {
        return text;
    }
    let gone = |line: &str| {
        line.split_once('{')
            .and_then(|(_, rest)| rest.split_once('}'))
            .is_some_and(|(labels, _)| labels.split(',').any(|pair| retired.contains(pair)))
    };
    let mut out = String::with_capacity(text.len());
    for line in text.lines().filter(|l| !gone(l)) {
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// Installs the global recorder with help text for every metric, and serves
/// `GET /metrics` on `cfg.bind` (on a thread of its own; called inside the tokio
/// runtime, which runs the exporter's upkeep), with the status page's routes when
/// `page` is given. Returns the address bound (port 0 takes a free one).
pub fn install(
    cfg: &MetricsConfig,
    page: Option<crate::page::Page>,
) -> Result<SocketAddr, ServiceError> {
    let bind = cfg.bind.as_str();
    let addr: SocketAddr = bind.parse().map_err(|e| bind_err(bind, e))?;
    let buckets = [
        0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0,
    ];
    let recorder = PrometheusBuilder::new()
        .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), &buckets)
        .map_err(|e| ServiceError::Metrics(e.to_string()))?
        .build_recorder();
    let handle = recorder.handle();
    let listener = std::net::TcpListener::bind(addr).map_err(|e| bind_err(bind, e))?;
    listener
        .set_nonblocking(true)
        .map_err(|e| bind_err(bind, e))?;
    metrics::set_global_recorder(recorder).map_err(|e| ServiceError::Metrics(e.to_string()))?;
    describe();
    let upkeep = handle.clone();
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(std::time::Duration::from_secs(UPKEEP_S));
        loop {
            tick.tick().await;
            upkeep.run_upkeep();
        }
    });
    let router = crate::http::Router::new().get("/metrics", move || {
        set_heap_gauges();
        let mut r = crate::http::text(hyper::StatusCode::OK, without_retired(handle.render()));
        r.headers_mut().insert(
            hyper::header::CONTENT_TYPE,
            hyper::header::HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
        );
        r
    });
    let router = match page {
        Some(page) => crate::page::routes(router, page),
        None => router,
    };
    let addr = listener.local_addr().map_err(|e| bind_err(bind, e))?;
    let limits = crate::http::Limits {
        max_connections: cfg.max_connections as usize,
        ..crate::http::Limits::default()
    };
    // A runtime and thread of its own: clients that ask much and read slowly (a
    // scanner, a stuck dashboard) kept the control loop's one worker busy writing
    // answers into their sockets, and the devices missed polls by the second.
    let http = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| ServiceError::Task(format!("HTTP runtime: {e}")))?;
    let listener = {
        let _in = http.enter();
        tokio::net::TcpListener::from_std(listener).map_err(|e| bind_err(bind, e))?
    };
    std::thread::Builder::new()
        .name("http".into())
        .spawn(move || {
            http.block_on(crate::http::serve(
                listener,
                router,
                limits,
                Arc::default(),
                tokio_util::sync::CancellationToken::new(),
            ))
        })
        .map_err(|e| ServiceError::Task(format!("thread http: {e}")))?;
    tracing::info!(bind = %addr, max_connections = cfg.max_connections, "Prometheus metrics on http://{addr}/metrics");
    Ok(addr)
}

/// The heap gauges, read when scraped: `mallinfo2` walks every free chunk under the
/// arena's lock (0.8 ms at 1M points/s, where the allocating threads wait for it), so
/// it runs as often as somebody looks, not on every status tick.
fn set_heap_gauges() {
    if let Some(h) = crate::heap::stats() {
        gauge!("compgate_process_heap_bytes", "state" => "in_use").set(h.in_use_bytes as f64);
        gauge!("compgate_process_heap_bytes", "state" => "free").set(h.free_bytes as f64);
    }
}

/// Help text and units of every metric (Prometheus `# HELP`).
pub fn describe() {
    use metrics::{describe_counter, describe_gauge, describe_histogram, Unit};
    describe_gauge!(
        "compgate_device_link_up",
        Unit::Count,
        "1 when the device answered in its last poll cycle (a read of it may still have failed), else 0"
    );
    describe_histogram!(
        "compgate_device_poll_seconds",
        Unit::Seconds,
        "Duration of a device poll cycle: its request round trips"
    );
    describe_counter!(
        "compgate_device_errors_total",
        Unit::Count,
        "Failed device requests by kind, retries included: timeout, deadline, frame, transport, connect, exception; backoff: a poll cycle the reconnect backoff refused"
    );
    describe_gauge!(
        "compgate_channel_value_degc",
        "Filtered channel temperature in degrees Celsius (NaN without a value and while the channel is bad)"
    );
    describe_gauge!(
        "compgate_channel_quality",
        Unit::Count,
        "Channel quality: 0 good, 1 uncertain, 2 bad"
    );
    describe_gauge!(
        "compgate_axis_sd43900_mm",
        "SD43900 (K0, position-independent offset) in mm, last written and verified"
    );
    describe_gauge!(
        "compgate_axis_sd43910",
        "SD43910 (tan beta, position-dependent slope), last written and verified"
    );
    describe_gauge!(
        "compgate_axis_sd43920_mm",
        "SD43920 (P0, reference position) in mm, last written and verified"
    );
    describe_counter!(
        "compgate_nc_jobs_total",
        Unit::Count,
        "NC jobs by axis and result (ok, failed, shadow: computed in shadow mode, not sent)"
    );
    describe_gauge!(
        "compgate_axis_nc_up",
        Unit::Count,
        "1 while the axis' NC answered its last read (read every status interval, at most once a second), 0 while it does not answer or answers with an error, and before the first read"
    );
    describe_gauge!(
        "compgate_axis_md32750_mismatch",
        Unit::Count,
        "1 while the NC answers with an MD32750 other than the config's: the axis holds and writes nothing"
    );
    describe_gauge!(
        "compgate_axis_unreferenced",
        Unit::Count,
        "1 while the NC answers that the axis is not referenced: it applies no temperature compensation"
    );
    describe_gauge!(
        "compgate_axis_jobs_failing",
        Unit::Count,
        "1 while the axis' last NC job failed (until a job succeeds)"
    );
    describe_gauge!(
        "compgate_axis_at_limit",
        Unit::Count,
        "1 while the model's value is beyond max_abs_k0_mm or max_abs_tan_beta: the NC gets the limit"
    );
    describe_gauge!(
        "compgate_axis_outside_fit",
        Unit::Count,
        "1 while an input reads more than 2 K outside the temperatures the model was fitted over"
    );
    describe_gauge!(
        "compgate_axis_shadow",
        Unit::Count,
        "1 when the axis runs in shadow mode: it computes and records, never writes the NC"
    );
    describe_gauge!(
        "compgate_axis_shadow_sd43900_mm",
        "Shadow mode: SD43900 in mm the axis would have written last"
    );
    describe_gauge!(
        "compgate_axis_shadow_sd43910",
        "Shadow mode: SD43910 the axis would have written last"
    );
    describe_gauge!(
        "compgate_axis_shadow_sd43920_mm",
        "Shadow mode: SD43920 in mm the axis would have written last"
    );
    describe_histogram!(
        "compgate_cycle_seconds",
        Unit::Seconds,
        "Control loop time to process one device sample"
    );
    describe_counter!(
        "compgate_recorder_records_total",
        Unit::Count,
        "Recorder records by outcome: written, dropped_queue, dropped_write"
    );
    describe_counter!(
        "compgate_recorder_duplicate_readings_total",
        Unit::Count,
        "Readings the recorder did not store: the database already held their channel at every millisecond of a second from their time on; the first one is kept"
    );
    describe_counter!(
        "compgate_recorder_shifted_readings_total",
        Unit::Count,
        "Readings stored at the next free millisecond: the database held their channel at their time (the wall clock set back over recorded time)"
    );
    describe_gauge!(
        "compgate_recorder_up",
        Unit::Count,
        "1 while the recorder's commits succeed, 0 while they fail (the database locked by another process, the disk full, ...)"
    );
    describe_gauge!(
        "compgate_recorder_clock_ahead_seconds",
        Unit::Seconds,
        "How far the wall clock is ahead of the time age retention counts from: a step ahead it does not follow (0: in line)"
    );
    describe_counter!(
        "compgate_recorder_outbox_deleted_total",
        Unit::Count,
        "MQTT messages the recorder's size limit (recorder.max_size_mb) deleted before they were sent: they go before the recorded history"
    );
    describe_gauge!(
        "compgate_process_heap_bytes",
        Unit::Bytes,
        "glibc malloc heap: bytes in use (the live heap) and bytes held free"
    );
    describe_counter!(
        "compgate_http_connections_total",
        Unit::Count,
        "Connections to the metrics endpoint by outcome: accepted, evicted (an idle or half-sent one closed for a new one), refused (closed at once)"
    );
    describe_counter!(
        "compgate_http_accept_errors_total",
        Unit::Count,
        "Failed accepts on the metrics endpoint (e.g. out of descriptors)"
    );
}

fn bind_err(bind: &str, e: impl std::fmt::Display) -> ServiceError {
    ServiceError::MetricsBind {
        bind: bind.to_string(),
        message: e.to_string(),
    }
}

struct ChannelHandles {
    value: Gauge,
    quality: Gauge,
    /// Quality code last set: it rarely changes, and setting a gauge is two atomic
    /// writes.
    last_quality: Option<u8>,
}

struct DeviceHandles {
    name: String,
    up: Gauge,
    poll: Histogram,
}

/// The observer that updates the metrics.
#[derive(Default)]
pub struct MetricsObserver {
    channels: Vec<ChannelHandles>,
    devices: Vec<DeviceHandles>,
    cycle: Option<Histogram>,
    recorder: Option<Arc<RecorderStats>>,
    recorder_handles: Option<([Counter; 6], [Gauge; 2])>,
    /// Per axis, the parameters the status carried when the gauges were last set from
    /// it: what the NC held at start counts as written until the first job.
    axis_written: Vec<Option<CompParams>>,
    /// The label pairs of the channels, devices and axes the metrics have series for.
    labels: BTreeSet<String>,
    /// A reload took effect: the next status may name other parts.
    relabel: bool,
}

/// The label pairs `status` exports series for.
fn label_pairs(status: &Status) -> BTreeSet<String> {
    let channels = status
        .channels
        .iter()
        .map(|c| format!("channel=\"{}\"", c.name));
    let devices = status
        .devices
        .iter()
        .map(|d| format!("device=\"{}\"", d.name));
    let axes = status.axes.iter().map(|a| format!("axis=\"{}\"", a.name));
    channels.chain(devices).chain(axes).collect()
}

impl MetricsObserver {
    /// An observer; with `recorder`, its counters are exported too.
    pub fn new(recorder: Option<Arc<RecorderStats>>) -> Self {
        MetricsObserver {
            recorder,
            ..Self::default()
        }
    }
}

fn set_params(axis: &str, p: &CompParams) {
    gauge!("compgate_axis_sd43900_mm", "axis" => axis.to_string()).set(p.k0_mm);
    gauge!("compgate_axis_sd43910", "axis" => axis.to_string()).set(p.tan_beta);
    gauge!("compgate_axis_sd43920_mm", "axis" => axis.to_string()).set(p.p0_mm);
}

impl Observer for MetricsObserver {
    fn on_sample(&mut self, readings: &SampleReadings) {
        let started = Instant::now();
        if let Some(d) = self.devices.get(readings.device) {
            d.up.set(if readings.link_up { 1.0 } else { 0.0 });
            d.poll.record(readings.poll_elapsed.as_secs_f64());
            for kind in &readings.faults {
                counter!("compgate_device_errors_total", "device" => d.name.clone(), "kind" => *kind)
                    .increment(1);
            }
        }
        self.cycle
            .get_or_insert_with(|| histogram!("compgate_cycle_seconds"))
            .record(started.elapsed().as_secs_f64());
    }

    fn on_job(&mut self, axis: &str, params: &CompParams, result: &Result<JobReport, NcError>) {
        let outcome = if result.is_ok() { "ok" } else { "failed" };
        counter!("compgate_nc_jobs_total", "axis" => axis.to_string(), "result" => outcome)
            .increment(1);
        if result.is_ok() {
            set_params(axis, params);
        }
    }

    fn on_shadow(&mut self, axis: &str, params: &CompParams) {
        counter!("compgate_nc_jobs_total", "axis" => axis.to_string(), "result" => "shadow")
            .increment(1);
        gauge!("compgate_axis_shadow_sd43900_mm", "axis" => axis.to_string()).set(params.k0_mm);
        gauge!("compgate_axis_shadow_sd43910", "axis" => axis.to_string()).set(params.tan_beta);
        gauge!("compgate_axis_shadow_sd43920_mm", "axis" => axis.to_string()).set(params.p0_mm);
    }

    fn on_status(&mut self, status: &Status) {
        if self.relabel || self.labels.is_empty() {
            self.relabel = false;
            let now = label_pairs(status);
            let mut retired = RETIRED.write().unwrap_or_else(PoisonError::into_inner);
            retired.extend(self.labels.difference(&now).cloned());
            retired.retain(|pair| !now.contains(pair));
            self.labels = now;
        }
        // The channel gauges once per status interval, from the snapshot: set per
        // sample they were a tenth of the gateway's CPU at 100k points/s (two atomic
        // writes per point), for a value a scrape reads every few seconds.
        if self.channels.len() != status.channels.len() {
            self.channels = status
                .channels
                .iter()
                .map(|c| ChannelHandles {
                    value: gauge!("compgate_channel_value_degc", "channel" => c.name.clone()),
                    quality: gauge!("compgate_channel_quality", "channel" => c.name.clone()),
                    last_quality: None,
                })
                .collect();
        }
        for (h, c) in self.channels.iter_mut().zip(&status.channels) {
            let r = &c.reading;
            // A bad channel's held value is no measurement: NaN leaves a gap in a
            // plot of the value alone, where the held value drew a normal line.
            let value_degc = r.value_degc.filter(|_| r.quality.is_usable());
            h.value.set(value_degc.unwrap_or(f64::NAN));
            let q = quality_code(&r.quality).0;
            if h.last_quality != Some(q) {
                h.quality.set(f64::from(q));
                h.last_quality = Some(q);
            }
        }
        if self.devices.len() != status.devices.len()
            || self
                .devices
                .iter()
                .zip(&status.devices)
                .any(|(h, d)| h.name != d.name)
        {
            self.devices = status
                .devices
                .iter()
                .map(|d| DeviceHandles {
                    name: d.name.clone(),
                    up: gauge!("compgate_device_link_up", "device" => d.name.clone()),
                    poll: histogram!("compgate_device_poll_seconds", "device" => d.name.clone()),
                })
                .collect();
            for a in &status.axes {
                gauge!("compgate_axis_shadow", "axis" => a.name.clone()).set(if a.shadow {
                    1.0
                } else {
                    0.0
                });
            }
        }
        // Whenever the status carries new values, not only when the handles are made:
        // the first status comes before the NC's start read.
        self.axis_written.resize(status.axes.len(), None);
        for (last, a) in self.axis_written.iter_mut().zip(&status.axes) {
            if let Some(p) = a.written.filter(|p| *last != Some(*p)) {
                set_params(&a.name, &p);
                *last = Some(p);
            }
        }
        for a in &status.axes {
            gauge!("compgate_axis_at_limit", "axis" => a.name.clone())
                .set(f64::from(u8::from(a.at_limit)));
            gauge!("compgate_axis_outside_fit", "axis" => a.name.clone())
                .set(f64::from(u8::from(a.outside_fit.is_some())));
            let answers = a.nc.is_some();
            gauge!("compgate_axis_nc_up", "axis" => a.name.clone())
                .set(f64::from(u8::from(answers)));
            gauge!("compgate_axis_md32750_mismatch", "axis" => a.name.clone())
                .set(f64::from(u8::from(answers && a.md32750_wrong)));
            gauge!("compgate_axis_unreferenced", "axis" => a.name.clone())
                .set(f64::from(u8::from(answers && a.unreferenced)));
            gauge!("compgate_axis_jobs_failing", "axis" => a.name.clone())
                .set(f64::from(u8::from(a.last_job_error.is_some())));
        }
        if let Some(stats) = &self.recorder {
            let (c, g) = self.recorder_handles.get_or_insert_with(|| {
                (
                    [
                        counter!("compgate_recorder_records_total", "outcome" => "written"),
                        counter!("compgate_recorder_records_total", "outcome" => "dropped_queue"),
                        counter!("compgate_recorder_records_total", "outcome" => "dropped_write"),
                        counter!("compgate_recorder_duplicate_readings_total"),
                        counter!("compgate_recorder_outbox_deleted_total"),
                        counter!("compgate_recorder_shifted_readings_total"),
                    ],
                    [
                        gauge!("compgate_recorder_up"),
                        gauge!("compgate_recorder_clock_ahead_seconds"),
                    ],
                )
            });
            use std::sync::atomic::Ordering::Relaxed;
            c[0].absolute(stats.written.load(Relaxed));
            c[1].absolute(stats.dropped_queue.load(Relaxed));
            c[2].absolute(stats.dropped_write.load(Relaxed));
            c[3].absolute(stats.duplicate_readings.load(Relaxed));
            c[4].absolute(stats.outbox_deleted.load(Relaxed));
            c[5].absolute(stats.shifted_readings.load(Relaxed));
            g[0].set(if stats.failing.load(Relaxed) {
                0.0
            } else {
                1.0
            });
            g[1].set(stats.clock_ahead_ms.load(Relaxed) as f64 / 1e3);
        }
    }

    fn on_reload(&mut self, _result: &Result<(), GatewayError>) {
        self.channels.clear();
        self.devices.clear();
        self.axis_written.clear();
        self.relabel = true;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_bind_that_is_no_address_is_a_typed_error() {
        let cfg = MetricsConfig {
            bind: "localhost".into(),
            ..MetricsConfig::default()
        };
        assert_eq!(
            install(&cfg, None),
            Err(ServiceError::MetricsBind {
                bind: "localhost".into(),
                message: "invalid socket address syntax".into(),
            })
        );
    }
}
