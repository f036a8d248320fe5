//! The service sections `[recorder]`, `[metrics]`, `[mqtt]` (used by
//! `compgate-service`) and their validation.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::login::LoginKeys;
use super::problem::{check_host_port, ConfigProblem};

/// `[recorder]`: every poll cycle's raw and filtered readings with their quality, every
/// NC job with its result, and the NC's position, into an SQLite database (WAL mode).
/// Writes are batched on a thread of their own; the control loop never waits for them.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RecorderConfig {
    /// Database file. A relative path is taken from `$STATE_DIRECTORY` (set by the
    /// unit's `StateDirectory=`, `/var/lib/compgate`), else from the working directory.
    /// Its directory must exist and be writable (`validate` checks it). One gateway
    /// per database: a second one refuses to start (lock file `<path>.lock`).
    /// Default `compgate.db`; at most 4096 characters.
    #[serde(default = "default_recorder_path")]
    #[schemars(length(max = 4096))]
    pub path: String,
    /// Seconds between commits of the batched writes: a crash of the process or a power
    /// loss loses at most this much (each commit is synced to the disk). Each commit is
    /// one fsync: a shorter interval means more of them, and more wear on flash storage.
    /// Default 0.5; 0.001..=1.
    #[serde(default = "default_commit_interval_s")]
    #[schemars(range(min = 0.001, max = 1.0))]
    pub commit_interval_s: f64,
    /// Seconds between the recorded poll cycles of one device: cycles are recorded on
    /// a grid of this period (one up to a tenth of it early counts, so polls at this
    /// period are all kept), so a device polled every 10 ms can be kept once a second
    /// (0 = every cycle). Jobs and NC positions are always recorded. Default 0; 0..=3600.
    #[serde(default)]
    #[schemars(range(min = 0.0, max = 3600.0))]
    pub interval_s: f64,
    /// Poll cycles the queue between the control loop and the writer holds. When it
    /// is full, cycles are dropped, counted and logged; the loop never waits. Default
    /// 4096; 1..=1000000.
    #[serde(default = "default_queue_cycles")]
    #[schemars(range(min = 1, max = 1_000_000))]
    pub queue_cycles: u32,
    /// Days readings, jobs and NC positions are kept. Default 90;
    /// 0.001..=36500.
    #[serde(default = "default_retention_days")]
    #[schemars(range(min = 0.001, max = 36_500.0))]
    pub retention_days: f64,
    /// Largest size of the data in the database, MB; beyond it the oldest unsent MQTT
    /// messages go first, then the oldest records. Default 2048; 0.001..=1000000.
    #[serde(default = "default_max_size_mb")]
    #[schemars(range(min = 0.001, max = 1_000_000.0))]
    pub max_size_mb: f64,
    /// Seconds between retention passes (age and size). Default 60;
    /// 0.001..=86400.
    #[serde(default = "default_retention_interval_s")]
    #[schemars(range(min = 0.001, max = 86_400.0))]
    pub retention_interval_s: f64,
}

impl Default for RecorderConfig {
    fn default() -> Self {
        RecorderConfig {
            path: default_recorder_path(),
            commit_interval_s: default_commit_interval_s(),
            interval_s: 0.0,
            queue_cycles: default_queue_cycles(),
            retention_days: default_retention_days(),
            max_size_mb: default_max_size_mb(),
            retention_interval_s: default_retention_interval_s(),
        }
    }
}

fn default_recorder_path() -> String {
    "compgate.db".into()
}
fn default_commit_interval_s() -> f64 {
    0.5
}
fn default_queue_cycles() -> u32 {
    4096
}
fn default_retention_days() -> f64 {
    90.0
}
fn default_max_size_mb() -> f64 {
    2048.0
}
fn default_retention_interval_s() -> f64 {
    60.0
}

/// `[metrics]`: a Prometheus text endpoint (`GET /metrics`).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MetricsConfig {
    /// `host:port` the HTTP listener (`/metrics` and the status page) listens on.
    /// Default `127.0.0.1:9464`; at most 300 characters (localhost only; expose it
    /// further on purpose, e.g. `0.0.0.0:9464` behind the plant firewall). Port 0
    /// takes a free port, logged at start.
    #[serde(default = "default_metrics_bind")]
    #[schemars(length(max = 300))]
    pub bind: String,
    /// HTTP connections the endpoint holds open at most, 1..=256. Default 64. A new
    /// connection beyond it closes the oldest one that is not being answered (e.g. a
    /// client that sent half a request and waits), or is closed at once when every
    /// held connection is being answered; none is ever queued. Kept far below the
    /// unit's `LimitNOFILE=` so HTTP clients cannot starve the Modbus, CAN and NC links
    /// of descriptors.
    #[serde(default = "default_metrics_max_connections")]
    #[schemars(range(min = 1, max = METRICS_MAX_CONNECTIONS))]
    pub max_connections: u32,
    /// Serve the live status page on the same listener: `GET /` (devices, channels
    /// with trends, axes, NC, last NC jobs; read-only, no internet needed) and
    /// `GET /api/status` (the same as JSON). Default true.
    #[serde(default = "default_status_page")]
    pub status_page: bool,
    /// Seconds of history the status page's channel trends show. Default 300;
    /// 10..=3600.
    #[serde(default = "default_trend_s")]
    #[schemars(range(min = 10.0, max = 3600.0))]
    pub trend_s: f64,
}

impl Default for MetricsConfig {
    fn default() -> Self {
        MetricsConfig {
            bind: default_metrics_bind(),
            max_connections: default_metrics_max_connections(),
            status_page: default_status_page(),
            trend_s: default_trend_s(),
        }
    }
}

fn default_status_page() -> bool {
    true
}

fn default_trend_s() -> f64 {
    300.0
}

/// The largest `metrics.max_connections`.
pub const METRICS_MAX_CONNECTIONS: u32 = 256;

fn default_metrics_max_connections() -> u32 {
    64
}

fn default_metrics_bind() -> String {
    "127.0.0.1:9464".into()
}

/// `[mqtt]`: publishing to an MQTT broker with QoS 1. Topics are
/// `<topic_prefix>/<machine>/...` (see the README). Messages wait in the recorder's
/// database until the broker acknowledges them, so `[recorder]` is required.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MqttConfig {
    /// Broker `host:port`, e.g. `"broker.plant.local:1883"`. Required; at
    /// most 300 characters.
    #[schemars(length(max = 300))]
    pub broker: String,
    /// Machine name in every topic, 1..=64 characters of `A-Z a-z 0-9 _ -`. Required.
    #[schemars(length(max = 64))]
    pub machine: String,
    /// First topic level(s). Default `compgate`; at most 128 characters; no `+`, `#` or leading/trailing `/`.
    #[serde(default = "default_topic_prefix")]
    #[schemars(length(max = 128))]
    pub topic_prefix: String,
    /// MQTT client id. Default `compgate-<machine>`; at most 128 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = 128))]
    pub client_id: Option<String>,
    /// Seconds between the readings messages of one device (each carries the latest
    /// reading of every channel of the device) and between health messages. Default
    /// 1.0; 0.001..=3600.
    #[serde(default = "default_publish_interval_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub publish_interval_s: f64,
    /// MQTT keep-alive, seconds: the broker publishes the gateway's last will
    /// (`state` lost) 1.5 times this after the connection went silent. Default 10;
    /// 1..=65535.
    #[serde(default = "default_keep_alive_s")]
    #[schemars(range(min = 1.0, max = 65_535.0))]
    pub keep_alive_s: f64,
    /// Seconds before a message unacknowledged by a connected broker is sent again,
    /// and between reconnect attempts. Default 2; 0.001..=3600.
    #[serde(default = "default_retry_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub retry_s: f64,
    /// Messages kept for the broker at most (oldest dropped, counted and logged beyond).
    /// Default 1000000; 1..=100000000.
    #[serde(default = "default_outbox_max_messages")]
    #[schemars(range(min = 1, max = 100_000_000))]
    pub outbox_max_messages: u64,
    /// File holding the broker's user name on its first line and the password on its
    /// second (keep it readable by compgate only); a relative path is under
    /// `$STATE_DIRECTORY` when set. Read again for each connection to the broker, so
    /// that a changed password is taken up without a restart. Not with
    /// `user_env`/`password_env`. Default none: anonymous unless the two variables are
    /// named; at most 4096 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = 4096))]
    pub credentials_file: Option<String>,
    /// Name of the environment variable holding the broker's user name; requires
    /// `password_env`. Default none; 1..=128 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = 128))]
    pub user_env: Option<String>,
    /// Name of the environment variable holding the broker's password; requires
    /// `user_env`. Default none; 1..=128 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = 128))]
    pub password_env: Option<String>,
}

impl MqttConfig {
    /// Where the broker's user name and password come from.
    pub fn login(&self) -> LoginKeys<'_> {
        LoginKeys {
            credentials_file: self.credentials_file.as_deref(),
            user_env: self.user_env.as_deref(),
            password_env: self.password_env.as_deref(),
        }
    }
}

fn default_topic_prefix() -> String {
    "compgate".into()
}
fn default_publish_interval_s() -> f64 {
    1.0
}
fn default_keep_alive_s() -> f64 {
    10.0
}
fn default_retry_s() -> f64 {
    2.0
}
fn default_outbox_max_messages() -> u64 {
    1_000_000
}

/// Every problem of the service sections of `cfg`, read from `file`.
pub(super) fn validate_service(
    recorder: Option<&RecorderConfig>,
    metrics: Option<&MetricsConfig>,
    mqtt: Option<&MqttConfig>,
    file: &str,
) -> Vec<ConfigProblem> {
    let mut out = Vec::new();
    let mut problem = |key: &str, msg: String| out.push(ConfigProblem::new(file, key, msg));
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if let Some(r) = recorder {
        if r.path.trim().is_empty() {
            problem("recorder.path", "must not be empty".into());
        }
        if !(positive(r.commit_interval_s) && r.commit_interval_s <= 1.0) {
            problem(
                "recorder.commit_interval_s",
                format!("{} is not within 0 < s <= 1 seconds", r.commit_interval_s),
            );
        }
        if !(r.interval_s.is_finite() && (0.0..=3600.0).contains(&r.interval_s)) {
            problem(
                "recorder.interval_s",
                format!("{} is not within 0..=3600 seconds", r.interval_s),
            );
        }
        if r.queue_cycles == 0 {
            problem("recorder.queue_cycles", "must be at least 1".into());
        }
        for (key, v) in [
            ("recorder.retention_days", r.retention_days),
            ("recorder.max_size_mb", r.max_size_mb),
            ("recorder.retention_interval_s", r.retention_interval_s),
        ] {
            if !positive(v) {
                problem(key, format!("{v} must be a finite number > 0"));
            }
        }
    }
    if let Some(m) = metrics {
        if m.bind.parse::<std::net::SocketAddr>().is_err() {
            problem(
                "metrics.bind",
                format!(
                    "`{}` is not an `ip:port` address, e.g. `127.0.0.1:9464`",
                    m.bind
                ),
            );
        }
        if !(m.trend_s.is_finite() && (10.0..=3600.0).contains(&m.trend_s)) {
            problem(
                "metrics.trend_s",
                format!("{} is not within 10..=3600 seconds", m.trend_s),
            );
        }
        if !(1..=METRICS_MAX_CONNECTIONS).contains(&m.max_connections) {
            problem(
                "metrics.max_connections",
                format!(
                    "{} is not within 1..={METRICS_MAX_CONNECTIONS}",
                    m.max_connections
                ),
            );
        }
    }
    if let Some(m) = mqtt {
        if recorder.is_none() {
            problem(
                "mqtt",
                "needs a [recorder] section: messages wait in its database until the broker has them".into(),
            );
        }
        // The check of every address the gateway connects to; the client resolves the
        // broker the same way (bracketed IPv6 included).
        if let Err(why) = check_host_port(&m.broker) {
            problem(
                "mqtt.broker",
                format!("{why}; for a broker e.g. \"broker.plant.local:1883\""),
            );
        }
        let name_ok = |n: &str| {
            !n.is_empty()
                && n.len() <= 64
                && n.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        };
        if !name_ok(&m.machine) {
            problem(
                "mqtt.machine",
                format!(
                    "`{}` must be 1..=64 characters of A-Z a-z 0-9 _ -",
                    m.machine
                ),
            );
        }
        let p = &m.topic_prefix;
        if p.is_empty() || p.starts_with('/') || p.ends_with('/') || p.contains(['+', '#']) {
            problem(
                "mqtt.topic_prefix",
                format!("`{p}` must be non-empty, without + or #, and not start or end with /"),
            );
        }
        for (key, v) in [
            ("mqtt.publish_interval_s", m.publish_interval_s),
            ("mqtt.retry_s", m.retry_s),
        ] {
            if !positive(v) {
                problem(key, format!("{v} must be a finite number > 0"));
            }
        }
        if !(m.keep_alive_s.is_finite() && m.keep_alive_s >= 1.0) {
            problem(
                "mqtt.keep_alive_s",
                format!("{} must be >= 1 second", m.keep_alive_s),
            );
        }
        if m.outbox_max_messages == 0 {
            problem("mqtt.outbox_max_messages", "must be at least 1".into());
        }
        for (key, why) in m.login().problems() {
            problem(&format!("mqtt.{key}"), why);
        }
    }
    out
}
