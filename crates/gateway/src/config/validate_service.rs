//! Validation of the service sections: `[recorder]`, `[metrics]`, `[mqtt]`.

use super::{Config, ConfigProblem};

/// Every problem of the service sections of `cfg`, read from `file`.
pub(super) fn validate(cfg: &Config, file: &str) -> Vec<ConfigProblem> {
    let mut out = Vec::new();
    let mut problem = |key: &str, msg: String| out.push(ConfigProblem::new(file, key, msg));
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if let Some(r) = &cfg.recorder {
        if r.path.trim().is_empty() {
            problem("recorder.path", "must not be empty".into());
        }
        if !(positive(r.commit_interval_s) && r.commit_interval_s <= 1.0) {
            problem(
                "recorder.commit_interval_s",
                format!("{} is not within 0 < s <= 1 seconds", r.commit_interval_s),
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
    if let Some(m) = &cfg.metrics {
        if m.bind.parse::<std::net::SocketAddr>().is_err() {
            problem(
                "metrics.bind",
                format!(
                    "`{}` is not an `ip:port` address, e.g. `127.0.0.1:9464`",
                    m.bind
                ),
            );
        }
    }
    if let Some(m) = &cfg.mqtt {
        if cfg.recorder.is_none() {
            problem(
                "mqtt",
                "needs a [recorder] section: messages wait in its database until the broker has them".into(),
            );
        }
        match m.broker.rsplit_once(':') {
            Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok_and(|p| p > 0) => {}
            _ => problem(
                "mqtt.broker",
                format!(
                    "`{}` is not `host:port`, e.g. `broker.plant.local:1883`",
                    m.broker
                ),
            ),
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
    }
    out
}
