//! The shop-floor service around the gateway: systemd notification, journald logging,
//! SIGHUP reload, and the observers (recorder, metrics, MQTT) behind the control loop.
//! Each observer receives every device sample's readings once from the core loop
//! (`compgate_gateway::runtime::Observer`); none looks a channel up again.
//!
//! - [`notify`]: READY, STATUS and the watchdog for systemd.
//! - [`record`]: durable recording into SQLite (WAL) off the control loop, retention,
//!   and `compgate export` to the measurement CSV.
//! - [`metrics`] and [`http`]: the Prometheus metrics and the listener that serves
//!   them, with a connection limit and timeouts.
//! - [`mqtt`]: readings, NC writes and health to an MQTT broker, through an outbox
//!   that loses nothing across a broker outage.
//! - [`page`]: the live status page (`GET /`) and `GET /api/status` on the metrics
//!   listener.
//! - [`status`]: the live status table on a terminal, plain lines in the journal.
//! - [`heap`]: glibc malloc's figures and the service's one-arena setting.

pub mod heap;
pub mod http;
pub mod metrics;
pub mod mqtt;
pub mod notify;
pub mod page;
pub mod record;
pub mod status;

use std::io::IsTerminal;
use std::path::{Path, PathBuf};

use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use crate::record::{RecordError, Recorder};
use compgate_gateway::config::{self, Config};
use compgate_gateway::runtime::{self, GatewayError, Hooks, Observer, Observers};

/// Errors of the service layer. Errors of other crates are kept as their messages,
/// so the enum stays `Clone + Eq` for tests to compare.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ServiceError {
    /// The recorder could not start (its [`RecordError`], as a message).
    #[error("{0}")]
    Recorder(String),
    /// The metrics exporter cannot listen on `metrics.bind`.
    #[error("metrics.bind `{bind}`: {message}")]
    MetricsBind {
        /// The configured address.
        bind: String,
        /// Why not.
        message: String,
    },
    /// The metrics recorder could not be set up or installed.
    #[error("metrics: {0}")]
    Metrics(String),
    /// `mqtt.broker` is not `host:port`.
    #[error("mqtt.broker `{0}` is not host:port")]
    MqttBroker(String),
    /// The MQTT client or its connection to the broker failed.
    #[error("{0}")]
    Mqtt(String),
    /// The broker refused the connection: its CONNACK's return code, in words.
    #[error("broker refused the connection: {0}")]
    MqttRefused(&'static str),
    /// The MQTT outbox in the recorder's database failed.
    #[error("{0}")]
    MqttOutbox(String),
    /// The gateway could not run.
    #[error(transparent)]
    Gateway(#[from] GatewayError),
    /// A task of the service panicked or was cancelled.
    #[error("{0}")]
    Task(String),
}

impl From<RecordError> for ServiceError {
    fn from(e: RecordError) -> Self {
        Self::Recorder(e.to_string())
    }
}

fn task_err(e: tokio::task::JoinError) -> ServiceError {
    ServiceError::Task(e.to_string())
}

/// Directives the default log filter adds to its level; `--log` and `RUST_LOG` are
/// taken as given. tokio-modbus' RTU codec logs a multi-line WARN per bad frame that
/// names no device, and an ERROR ("Failed to decode response PDU", "Giving up to
/// decode frame") for a garbled reply: the gateway reports the same fault itself, per
/// device, as a `bad reply on <path>` WARN, so the codec logs nothing. The OPC UA client
/// logs "Transport disconnected: Good" at WARN whenever a session closes cleanly
/// (every `nc read` and `nc write`). Other errors of both libraries stay.
const QUIET_LIBRARIES: &str =
    "tokio_modbus=error,tokio_modbus::codec::rtu=off,opcua_client::session::event_loop=error";

/// The log filter when neither `--log` nor `RUST_LOG` gives one: `level` (e.g.
/// `info`), with tokio-modbus and the OPC UA client's session loop at `error` only and
/// tokio-modbus' RTU codec off.
pub fn default_log_filter(level: &str) -> String {
    format!("{level},{QUIET_LIBRARIES}")
}

/// Logs to stderr, as lines the journal takes at their level when stderr is the
/// journal stream systemd connected (`JOURNAL_STREAM` names stderr's device and
/// inode): see `JournalStream`. `JOURNAL_STREAM` alone is not enough: a terminal of
/// a systemd user session inherits it with stderr on the terminal. The filter is
/// `filter` (`--log`), else `RUST_LOG`, else [`default_log_filter`] of
/// `default_level`.
pub fn init_tracing(filter: Option<&str>, default_level: &str) {
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    let filter = filter
        .map(str::to_string)
        .or_else(|| std::env::var("RUST_LOG").ok())
        .unwrap_or_else(|| default_log_filter(default_level));
    let registry = tracing_subscriber::registry().with(tracing_subscriber::EnvFilter::new(filter));
    let fmt = tracing_subscriber::fmt::layer();
    if crate::status::stderr_is_journal() {
        // The journal stamps each line itself.
        registry
            .with(
                fmt.without_time()
                    .with_ansi(false)
                    .with_writer(JournalStream),
            )
            .init();
    } else {
        registry
            .with(
                fmt.with_writer(std::io::stderr)
                    // Colour codes only for a person at a terminal.
                    .with_ansi(std::io::stderr().is_terminal()),
            )
            .init();
    }
}

/// stderr as the journal's stream: every line of an event starts with its syslog
/// priority (`<4>` for a WARN, sd-daemon(3)), which journald takes as the line's level,
/// so `journalctl -p warning` and the colours work. An event stays one line with its
/// fields (`device=ain1 error=...`): journald's native protocol would keep the fields
/// apart from the message, where `journalctl -u compgate` does not show them.
struct JournalStream;

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for JournalStream {
    type Writer = PrioritizedStderr;

    fn make_writer(&'a self) -> Self::Writer {
        PrioritizedStderr(b"<6>")
    }

    fn make_writer_for(&'a self, meta: &tracing::Metadata<'_>) -> Self::Writer {
        PrioritizedStderr(match *meta.level() {
            tracing::Level::ERROR => b"<3>",
            tracing::Level::WARN => b"<4>",
            tracing::Level::INFO => b"<6>",
            _ => b"<7>",
        })
    }
}

/// stderr with each line prefixed by a syslog priority.
struct PrioritizedStderr(&'static [u8; 3]);

impl std::io::Write for PrioritizedStderr {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        // One write per event (the fmt layer hands over whole events), so the lines
        // of two threads' events do not interleave.
        let mut out = Vec::with_capacity(buf.len() + 8);
        for line in buf.split_inclusive(|&b| b == b'\n') {
            out.extend_from_slice(self.0);
            out.extend_from_slice(line);
        }
        std::io::stderr().lock().write_all(&out)?;
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// What Ctrl-C and SIGTERM ask for.
struct StopRequests {
    /// The first: stop (NC reads are abandoned, a job in flight gets its grace).
    shutdown: CancellationToken,
    /// The second: wait for nothing but the recorder's final commit. A third exits
    /// at once.
    force: CancellationToken,
}

/// Watches Ctrl-C and SIGTERM (see [`StopRequests`]); sends the reloaded config on
/// SIGHUP. A config that does not load is logged, told to systemd
/// ([`notify::reload_refused`]) and not sent: the old one stays.
fn signals(path: PathBuf, reload: mpsc::Sender<Config>, opts: RunOptions) -> StopRequests {
    use tokio::signal::unix::{signal, SignalKind};
    let requests = StopRequests {
        shutdown: CancellationToken::new(),
        force: CancellationToken::new(),
    };
    let (shutdown, force) = (requests.shutdown.clone(), requests.force.clone());
    tokio::spawn(async move {
        let (mut term, mut hup) = match (
            signal(SignalKind::terminate()),
            signal(SignalKind::hangup()),
        ) {
            (Ok(term), Ok(hup)) => (term, hup),
            (Err(e), _) | (_, Err(e)) => {
                tracing::error!(error = %e, "cannot watch SIGTERM/SIGHUP");
                let _ = tokio::signal::ctrl_c().await;
                shutdown.cancel();
                return;
            }
        };
        let mut stops = 0;
        loop {
            let why = tokio::select! {
                _ = tokio::signal::ctrl_c() => "Ctrl-C",
                _ = term.recv() => "SIGTERM",
                _ = hup.recv() => {
                    tracing::info!(file = %path.display(), "SIGHUP: reloading the configuration");
                    match config::load(&path) {
                        Ok(mut cfg) => {
                            opts.apply(&mut cfg);
                            let _ = reload.send(cfg).await;
                        }
                        Err(e) => {
                            tracing::error!(error = %e, "reload refused: the running configuration stays");
                            notify::reload_refused(&e);
                        }
                    }
                    continue;
                }
            };
            stops += 1;
            match stops {
                1 => {
                    tracing::info!("{why}: stopping");
                    shutdown.cancel();
                }
                2 => {
                    tracing::warn!("{why} again: stopping now; an NC job in flight is abandoned (whether it landed is unknown); the recorder commits what it holds, a third signal exits at once");
                    force.cancel();
                }
                _ => {
                    // Committed transactions are in the database file or its WAL:
                    // SQLite keeps them across an exit at any moment.
                    tracing::error!(
                        "{why} a third time: exiting at once; what the recorder committed is kept"
                    );
                    std::process::exit(1);
                }
            }
        }
    });
    requests
}

/// Starts the HTTP listener of `[metrics]`: `/metrics`, and the status page fed by
/// `status` unless `metrics.status_page = false`. Returns the address bound.
pub async fn http_listener(
    m: &config::MetricsConfig,
    status: &watch::Receiver<runtime::Status>,
    status_interval: std::time::Duration,
) -> Result<std::net::SocketAddr, ServiceError> {
    let page = m.status_page.then(page::Page::default);
    let addr = metrics::install(m, page.clone())?;
    if let Some(page) = page {
        // Detached: it ends when the gateway drops the status' sender.
        drop(status_reader(
            "status-page",
            page::track(
                status.clone(),
                page,
                std::time::Duration::from_secs_f64(m.trend_s),
                status_interval,
            ),
        )?);
        tracing::info!(bind = %addr, "status page on http://{addr}/");
    }
    Ok(addr)
}

/// Runs `reader` of the status on a thread of its own, not on the runtime's worker:
/// the page's trends and the printed line walk every channel once per status
/// interval, which at 10000 channels held every poll up for 1.4 ms each second.
fn status_reader(
    name: &str,
    reader: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<std::thread::JoinHandle<()>, ServiceError> {
    let runtime = tokio::runtime::Handle::current();
    std::thread::Builder::new()
        .name(name.to_string())
        .spawn(move || runtime.block_on(reader))
        .map_err(|e| ServiceError::Task(format!("thread {name}: {e}")))
}

/// What the command line sets over the config file, for the run and every reload.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RunOptions {
    /// `--shadow`: every axis in shadow mode (as `gateway.shadow = true`).
    pub shadow: bool,
}

impl RunOptions {
    /// Sets what the options force in `cfg`.
    pub fn apply(&self, cfg: &mut Config) {
        cfg.gateway.shadow |= self.shadow;
    }
}

/// `compgate run`: the gateway on `cfg` (loaded from `path`) as a service, until
/// SIGTERM or Ctrl-C; a second one stops at once, after the recorder's last commit.
pub async fn run(path: &Path, mut cfg: Config, opts: RunOptions) -> Result<(), ServiceError> {
    opts.apply(&mut cfg);
    let (reload_tx, reload_rx) = mpsc::channel(1);
    let stop = signals(path.to_path_buf(), reload_tx, opts);
    let shutdown = stop.shutdown.clone();
    let recorder = match &cfg.recorder {
        Some(r) => Some(Recorder::start(r)?),
        None => None,
    };
    // Declared after the recorder, so dropped before it: on an early return (the
    // metrics port in use) the recorder's drop waits for its writer, which waits for
    // the observers' senders to go.
    let mut observers: Vec<Box<dyn Observer>> = vec![Box::new(notify::Notifier::new())];
    if let (Some(r), Some(c)) = (&recorder, &cfg.recorder) {
        observers.push(Box::new(
            r.observer().with_interval(config::secs(c.interval_s)),
        ));
    }
    let mut publisher = None;
    if let (Some(m), Some(r)) = (&cfg.mqtt, &recorder) {
        observers.push(Box::new(mqtt::MqttObserver::new(m, r.sender())));
        publisher = Some(tokio::spawn(mqtt::publisher(
            m.clone(),
            r.path().to_path_buf(),
            r.outbox_notify(),
            shutdown.clone(),
        )));
    }
    let (tx, rx) = watch::channel(runtime::Status::default());
    if let Some(m) = &cfg.metrics {
        http_listener(m, &rx, cfg.gateway.status_interval()).await?;
        let stats = recorder.as_ref().map(|r| r.sender().stats().clone());
        observers.push(Box::new(metrics::MetricsObserver::new(stats)));
    }
    for (name, a) in &cfg.axes {
        if a.shadow || cfg.gateway.shadow {
            tracing::warn!(axis = %name, "shadow mode: the axis computes and records what it would write; its NC is never written");
        }
    }
    let printer = if crate::status::stdout_is_journal() {
        tracing::info!("stdout is the journal: no status line per update (systemctl status, the status page and /metrics show the status)");
        None
    } else if crate::status::stdout_is_null() {
        tracing::info!("stdout is /dev/null: no status line per update");
        None
    } else {
        Some(status_reader(
            "status-line",
            crate::status::print_loop(rx, std::io::stdout().is_terminal(), shutdown.clone()),
        )?)
    };
    let hooks = Hooks {
        observer: Box::new(Observers(observers)),
        reload: Some(reload_rx),
        watchdog_interval: notify::watchdog_interval(),
    };
    // On a runtime worker, where the device tasks run: a sample then wakes the
    // control loop on the same thread, not `block_on`'s thread through a futex, once
    // per poll cycle.
    let gateway_cfg = cfg.clone();
    let gateway_shutdown = shutdown.clone();
    // The configuration's parse is over: its peak goes back to the system.
    heap::release_free();
    let mut gateway =
        tokio::spawn(
            async move { runtime::run_with(&gateway_cfg, gateway_shutdown, tx, hooks).await },
        );
    let result = tokio::select! {
        r = &mut gateway => r.map_err(task_err),
        () = stop.force.cancelled() => {
            // Its observers go with it: the recorder's writer commits what they queued.
            gateway.abort();
            let _ = gateway.await;
            Ok(Ok(()))
        }
    };
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    shutdown.cancel();
    if let Some(mut p) = publisher {
        tokio::select! {
            _ = &mut p => {}
            () = stop.force.cancelled() => p.abort(),
        }
    }
    if let Some(r) = recorder {
        // The observers are gone with the gateway: the writer commits what is queued.
        tokio::task::spawn_blocking(move || r.finish())
            .await
            .map_err(task_err)?;
    }
    shutdown.cancel();
    if let Some(p) = printer {
        let _ = tokio::task::spawn_blocking(move || p.join()).await;
    }
    Ok(result??)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};
    use tracing_subscriber::layer::SubscriberExt;

    /// The level and target of every event the filter before it let through.
    #[derive(Clone, Default)]
    struct Seen(Arc<Mutex<Vec<String>>>);

    impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for Seen {
        fn on_event(
            &self,
            event: &tracing::Event<'_>,
            _: tracing_subscriber::layer::Context<'_, S>,
        ) {
            let m = event.metadata();
            self.0
                .lock()
                .unwrap()
                .push(format!("{} {}", m.level(), m.target()));
        }
    }

    #[test]
    fn the_default_filter_quiets_two_libraries_warnings_and_keeps_their_errors() {
        // tokio-modbus' RTU codec logged "ERROR tokio_modbus::codec::rtu: Failed to
        // decode response PDU" for a garbled reply, naming no device: off, the gateway
        // WARNs "bad reply on <path>" itself. tokio-modbus' other errors stay.
        let seen = Seen::default();
        let subscriber = tracing_subscriber::registry()
            .with(tracing_subscriber::EnvFilter::new(default_log_filter(
                "info",
            )))
            .with(seen.clone());
        tracing::subscriber::with_default(subscriber, || {
            tracing::warn!(target: "tokio_modbus::codec::rtu", "Failed to decode response frame");
            tracing::error!(target: "tokio_modbus::codec::rtu", "Failed to decode response PDU: Invalid data");
            tracing::error!(target: "tokio_modbus::service::rtu", "an error");
            tracing::warn!(target: "opcua_client::session::event_loop", "Transport disconnected: Good");
            tracing::error!(target: "opcua_client::session::event_loop", "Session activity loop ended unexpectedly");
            tracing::warn!(target: "opcua_client::session::connect", "another OPC UA warning");
            tracing::info!(target: "compgate_gateway::runtime", "device link up again");
            tracing::debug!(target: "compgate_gateway::runtime", "a debug line");
        });
        assert_eq!(
            *seen.0.lock().unwrap(),
            [
                "ERROR tokio_modbus::service::rtu",
                "ERROR opcua_client::session::event_loop",
                "WARN opcua_client::session::connect",
                "INFO compgate_gateway::runtime",
            ]
        );
        assert_eq!(
            default_log_filter("warn"),
            "warn,tokio_modbus=error,tokio_modbus::codec::rtu=off,\
             opcua_client::session::event_loop=error"
        );
    }
}
