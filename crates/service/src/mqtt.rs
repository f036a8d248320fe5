//! MQTT publishing (QoS 1) with store-and-forward through the recorder's database.
//!
//! The control loop's [`MqttObserver`] turns readings, NC jobs and health into JSON
//! messages and queues them with the recorder, which commits them into the
//! `mqtt_outbox` table in the same transaction as the readings. The [`publisher`]
//! task sends the outbox in id order and deletes a message only when the broker has
//! acknowledged it (PUBACK). While the broker is down the outbox grows, up to
//! `outbox_max_messages`; after it is back the backlog goes out first, oldest first.
//! Delivery is at least once: after a broken connection unacknowledged messages are
//! sent again. When the recorder creates its database again (deleted or replaced
//! while running), the publisher follows it to the new file.
//!
//! Topics (`P` = `topic_prefix`, `M` = `machine`):
//!
//! | topic | when | payload |
//! |---|---|---|
//! | `P/M/readings/<device>` | every `publish_interval_s` per device | `{"t_unix_ms", "device", "channels": [{"channel", "value_degc", "unfiltered_degc", "raw", "quality", "reason"}]}` |
//! | `P/M/writes/<axis>` | every NC job | `{"t_unix_ms", "axis", "sd43900_mm", "sd43910", "sd43920_mm", "ok", "job_id", "elapsed_ms", "error", "quality"}` |
//! | `P/M/health` | every `publish_interval_s` | `{"t_unix_ms", "quality", "devices": [{"name", "link", "failed_cycles", "last_error"}], "axes": [{"name", "sd43900_mm", "sd43910", "sd43920_mm", "jobs_ok", "jobs_failed", "warning"}]}` |
//!
//! | `P/M/state` | retained: on each connect, at a clean stop, and by the broker (last will) when the connection is lost | `{"state": "online"}`, `{"state": "offline"}` (stopped), `{"state": "lost"}` (died or cut off, after 1.5 `keep_alive_s`) |
//!
//! `state` goes out directly, not through the outbox: it says what the gateway is now,
//! and a stored one would be stale by the time it was sent.
//!
//! One readings message carries a whole poll cycle of a device (64 channels are one
//! message, not 64). `quality` is `good`, `uncertain` or `bad`: a reading's own quality; `good`/`bad` for
//! a job's result; for health `good` when every link is up and no axis has a warning,
//! else `uncertain`. A device's `link` is its state as `/api/status` says it
//! (`connecting`, `up`, `errors`, `down`).

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rusqlite::Connection;

use rumqttc::{
    AsyncClient, ConnectReturnCode, ConnectionError, Event, LastWill, MqttOptions, Outgoing,
    Packet, QoS,
};
use serde::Serialize;
use serde_json::json;
use tokio::sync::{mpsc, Notify};
use tokio_util::sync::CancellationToken;
use tokio_util::task::AbortOnDropHandle;

use crate::page::device_state;
use crate::record::{
    file_id, now_unix_ms, quality_code, with_suffix, DbFiles, Grid, Record, RecordSender,
};
use crate::ServiceError;
use compgate_core::comp::CompParams;
use compgate_gateway::config::login::Credentials;
use compgate_gateway::config::{secs, MqttConfig};
use compgate_gateway::nc::{JobReport, NcError};
use compgate_gateway::runtime::{GatewayError, Observer, SampleReadings, Status};

fn quality_word(code: u8) -> &'static str {
    match code {
        0 => "good",
        1 => "uncertain",
        _ => "bad",
    }
}

/// A readings message, serialised straight from borrowed values: building a
/// `serde_json::Value` tree first cost six key strings and a map per channel. Fields
/// are in alphabetical order, the order the `json!` maps wrote them in.
#[derive(Serialize)]
struct ReadingsMsg<'a> {
    channels: Vec<ChannelMsg<'a>>,
    device: &'a str,
    t_unix_ms: i64,
}

/// One channel of a [`ReadingsMsg`] (non-finite values are written as `null`).
#[derive(Serialize)]
struct ChannelMsg<'a> {
    channel: &'a str,
    quality: &'static str,
    raw: Option<f64>,
    reason: Option<&'static str>,
    unfiltered_degc: Option<f64>,
    value_degc: Option<f64>,
}

/// Builds the messages in the control loop and queues them with the recorder.
pub struct MqttObserver {
    base: String,
    interval: Duration,
    tx: RecordSender,
    /// Per device index: when its next readings message is due.
    readings_due: HashMap<usize, Grid>,
    health_due: Grid,
}

impl MqttObserver {
    /// An observer for `cfg` that queues through `tx`.
    pub fn new(cfg: &MqttConfig, tx: RecordSender) -> Self {
        MqttObserver {
            base: format!("{}/{}", cfg.topic_prefix, cfg.machine),
            interval: secs(cfg.publish_interval_s),
            tx,
            readings_due: HashMap::new(),
            health_due: Grid::default(),
        }
    }

    /// The write message of `axis`; `result` is `None` for a shadow write, which has
    /// the same topic and fields as a real one, marked: a dashboard shows the would-be
    /// values of a dry run without mistaking them for written ones.
    fn publish_write(
        &mut self,
        axis: &str,
        params: &CompParams,
        result: Option<&Result<JobReport, NcError>>,
    ) {
        let report = result.and_then(|r| r.as_ref().ok());
        let payload = json!({
            "t_unix_ms": now_unix_ms(),
            "axis": axis,
            "sd43900_mm": params.k0_mm,
            "sd43910": params.tan_beta,
            "sd43920_mm": params.p0_mm,
            "ok": report.is_some(),
            "job_id": report.map(|r| r.job_id),
            "elapsed_ms": report.map(|r| r.elapsed.as_secs_f64() * 1e3),
            "error": result.and_then(|r| r.as_ref().err()).map(ToString::to_string),
            "quality": if result.is_some_and(|r| r.is_err()) { "bad" } else { "good" },
            "shadow": result.is_none(),
        });
        self.tx.send(Record::Outbox {
            topic: format!("{}/writes/{axis}", self.base),
            payload: payload.to_string(),
        });
    }
}

impl Observer for MqttObserver {
    fn on_sample(&mut self, readings: &SampleReadings) {
        let due = self.readings_due.entry(readings.device).or_default();
        if !due.due(self.interval, Instant::now()) {
            return;
        }
        let device = &*readings.device_name;
        let channels: Vec<ChannelMsg<'_>> = readings
            .named()
            .map(|(name, c)| {
                let r = &c.reading;
                let (q, reason) = quality_code(&r.quality);
                ChannelMsg {
                    channel: name,
                    quality: quality_word(q),
                    raw: r.raw,
                    reason,
                    unfiltered_degc: r.unfiltered_degc,
                    value_degc: r.value_degc,
                }
            })
            .collect();
        let msg = ReadingsMsg {
            channels,
            device,
            t_unix_ms: now_unix_ms(),
        };
        match serde_json::to_string(&msg) {
            Ok(payload) => self.tx.send(Record::Outbox {
                topic: format!("{}/readings/{device}", self.base),
                payload,
            }),
            Err(e) => tracing::warn!(error = %e, "MQTT: readings message not built"),
        }
    }

    fn on_job(&mut self, axis: &str, params: &CompParams, result: &Result<JobReport, NcError>) {
        self.publish_write(axis, params, Some(result));
    }

    fn on_shadow(&mut self, axis: &str, params: &CompParams) {
        self.publish_write(axis, params, None);
    }

    fn on_status(&mut self, status: &Status) {
        if !self.health_due.due(self.interval, Instant::now()) {
            return;
        }
        let healthy = status.devices.iter().all(|d| device_state(d) == "up")
            && status.axes.iter().all(|a| a.warning.is_none());
        let payload = json!({
            "t_unix_ms": now_unix_ms(),
            "quality": if healthy { "good" } else { "uncertain" },
            "devices": status.devices.iter().map(|d| json!({
                "name": d.name,
                "link": device_state(d),
                "failed_cycles": d.failed_cycles,
                "last_error": d.last_error,
            })).collect::<Vec<_>>(),
            "axes": status.axes.iter().map(|a| json!({
                "name": a.name,
                "sd43900_mm": a.written.map(|p| p.k0_mm),
                "sd43910": a.written.map(|p| p.tan_beta),
                "sd43920_mm": a.written.map(|p| p.p0_mm),
                "jobs_ok": a.jobs_ok,
                "jobs_failed": a.jobs_failed,
                "warning": a.warning,
            })).collect::<Vec<_>>(),
        });
        self.tx.send(Record::Outbox {
            topic: format!("{}/health", self.base),
            payload: payload.to_string(),
        });
    }

    fn on_reload(&mut self, _result: &Result<(), GatewayError>) {
        // Device indices may have moved.
        self.readings_due.clear();
    }
}

/// Messages in flight to the broker at most.
const WINDOW: usize = 64;
/// Work on the outbox (deleting acknowledged rows, reading new ones) waits this long
/// after the first reason for it, so that one database round trip takes what came
/// together.
const BATCH: Duration = Duration::from_millis(100);
/// How often `outbox_max_messages` is enforced in a session (while no session runs,
/// after every commit of the recorder: the outbox only grows then).
const CAP_INTERVAL: Duration = Duration::from_secs(5);

/// Sends the outbox of the database at `db_path` to the broker until `shutdown`.
/// `grown` is notified when the recorder committed new messages.
pub async fn publisher(
    cfg: MqttConfig,
    db_path: PathBuf,
    grown: Arc<Notify>,
    shutdown: CancellationToken,
) {
    let retry = secs(cfg.retry_s);
    let mut outbox = match crate::record::open(&db_path) {
        Ok(conn) => Outbox::new(db_path, conn),
        Err(e) => {
            tracing::error!(error = %e, "MQTT: cannot open the outbox; nothing is published");
            return;
        }
    };
    let mut login = match cfg.login().load() {
        Ok(login) => Login {
            current: login,
            problem: None,
        },
        Err((key, why)) => {
            tracing::error!(key = %format!("mqtt.{key}"), "MQTT: {why}; nothing is published");
            return;
        }
    };
    cfg.login().warn_if_readable_by_others("MQTT");
    let mut link = BrokerLink::default();
    // The outbox may be over the cap from the last run.
    let mut cap_due = true;
    while !shutdown.is_cancelled() {
        let ended = match outbox.reopen_if_replaced() {
            Ok(()) => {
                login.reread(&cfg);
                session(
                    &cfg,
                    login.current.as_ref(),
                    &mut outbox,
                    &grown,
                    &shutdown,
                    &mut link,
                )
                .await
            }
            Err(e) => Err(e),
        };
        match ended {
            // Stopped, or the database was replaced: the next session reads the new one.
            Ok(()) => continue,
            // Logged by the outbox, as its database's error.
            Err(ServiceError::MqttOutbox(_) | ServiceError::Task(_)) => {}
            Err(e) => link.failed(&cfg, &e),
        }
        // No session: the outbox only grows, and the cap holds it after each commit,
        // so that a long outage cannot fill the recorder's database.
        let retry_at = tokio::time::Instant::now() + retry;
        loop {
            if std::mem::take(&mut cap_due) && outbox.reopen_if_replaced().is_ok() {
                let ex = Exchange {
                    acked: Vec::new(),
                    cap: Some(cfg.outbox_max_messages),
                    fetch: None,
                };
                if let Ok((dropped, _)) = outbox.exchange(ex).await {
                    link.dropped(&cfg, dropped);
                }
            }
            tokio::select! {
                _ = shutdown.cancelled() => return,
                () = tokio::time::sleep_until(retry_at) => break,
                () = grown.notified() => cap_due = true,
            }
        }
    }
}

/// The user name and password of the next connection. The credentials file is read
/// again for each: a password changed at the broker and in the file is taken up at
/// the next connection, without a restart.
struct Login {
    current: Option<Credentials>,
    /// Why the file could not be read the last time, so that it is logged once.
    problem: Option<String>,
}

impl Login {
    fn reread(&mut self, cfg: &MqttConfig) {
        match cfg.login().load() {
            Ok(fresh) => {
                if self.problem.take().is_some() {
                    tracing::info!("MQTT: the credentials can be read again");
                }
                if fresh != self.current {
                    let user = fresh.as_ref().map(|c| c.user.clone());
                    tracing::info!(user = ?user, "MQTT: the credentials changed; this connection uses the new ones");
                    self.current = fresh;
                }
            }
            Err((key, why)) => {
                if self.problem.as_ref() != Some(&why) {
                    tracing::warn!(key = %format!("mqtt.{key}"), "MQTT: {why}; the credentials read before are used");
                    self.problem = Some(why);
                }
            }
        }
    }
}

/// What the log says of the broker link and of the cap, so that it is logged once
/// per change (unreachable, refused, reachable again) and once per outage, never
/// once per retry.
#[derive(Debug, Default)]
struct BrokerLink {
    /// Connected, and no connection attempt failed since.
    up: bool,
    down: Option<Outage>,
    /// Messages the cap dropped since the start.
    dropped_total: u64,
}

#[derive(Debug)]
struct Outage {
    since: Instant,
    /// Connection attempts failed.
    attempts: u64,
    /// Why the last attempt failed: the broker's refusal, `None` when it was not
    /// reached.
    refused: Option<&'static str>,
    /// Messages the cap dropped during the outage.
    dropped: u64,
}

impl BrokerLink {
    fn failed(&mut self, cfg: &MqttConfig, e: &ServiceError) {
        let refused = match e {
            ServiceError::MqttRefused(reason) => Some(*reason),
            _ => None,
        };
        self.up = false;
        let changed = match &mut self.down {
            Some(o) => {
                o.attempts += 1;
                std::mem::replace(&mut o.refused, refused) != refused
            }
            None => {
                self.down = Some(Outage {
                    since: Instant::now(),
                    attempts: 1,
                    refused,
                    dropped: 0,
                });
                true
            }
        };
        let attempts = self.down.as_ref().map_or(0, |o| o.attempts);
        match refused {
            _ if !changed => {
                tracing::debug!(broker = %cfg.broker, error = %e, attempts, "MQTT: broker still not connected");
            }
            Some(reason) => {
                tracing::warn!(broker = %cfg.broker, client_id = %client_id(cfg), retry_s = cfg.retry_s, "MQTT: broker refused the connection: {reason}; messages wait in the outbox");
            }
            None => {
                tracing::warn!(broker = %cfg.broker, error = %e, retry_s = cfg.retry_s, "MQTT: broker unreachable; messages wait in the outbox");
            }
        }
    }

    fn connected(&mut self, cfg: &MqttConfig) {
        match self.down.take() {
            Some(o) => tracing::info!(
                broker = %cfg.broker,
                down_s = (o.since.elapsed().as_secs_f64() * 10.0).round() / 10.0,
                failed_attempts = o.attempts,
                dropped = o.dropped,
                "MQTT: broker reachable again; the outbox backlog goes out"
            ),
            None if !self.up => tracing::info!(broker = %cfg.broker, "MQTT connected"),
            None => {}
        }
        self.up = true;
    }

    /// `n` messages dropped by the cap: while the broker is not connected logged at
    /// the first drop, and counted when it is back; else each time (at most every
    /// [`CAP_INTERVAL`]).
    fn dropped(&mut self, cfg: &MqttConfig, n: u64) {
        if n == 0 {
            return;
        }
        self.dropped_total += n;
        let max = cfg.outbox_max_messages;
        match &mut self.down {
            Some(o) => {
                o.dropped += n;
                if o.dropped == n {
                    tracing::warn!(outbox_max_messages = max, dropped = n, dropped_total = self.dropped_total, "MQTT outbox over outbox_max_messages while the broker is not connected: the oldest messages are dropped (counted when it is back)");
                }
            }
            None => {
                tracing::warn!(
                    outbox_max_messages = max,
                    dropped = n,
                    dropped_total = self.dropped_total,
                    "MQTT outbox over outbox_max_messages: oldest messages dropped"
                );
            }
        }
    }
}

/// The CONNACK's refusal in words (MQTT 3.1.1, 3.2.2.3); `anonymous`: the gateway
/// connected without a user name.
fn refusal(code: ConnectReturnCode, anonymous: bool) -> &'static str {
    match code {
        ConnectReturnCode::Success => "accepted",
        ConnectReturnCode::RefusedProtocolVersion => "unacceptable protocol version",
        ConnectReturnCode::BadClientId => "client identifier rejected",
        ConnectReturnCode::ServiceUnavailable => "server unavailable",
        ConnectReturnCode::BadUserNamePassword if anonymous => {
            "bad user name or password (none was given: set mqtt.credentials_file, or mqtt.user_env and mqtt.password_env)"
        }
        ConnectReturnCode::BadUserNamePassword => "bad user name or password",
        ConnectReturnCode::NotAuthorized if anonymous => {
            "not authorized (the gateway connected without user name and password: set mqtt.credentials_file, or mqtt.user_env and mqtt.password_env)"
        }
        ConnectReturnCode::NotAuthorized => {
            "not authorized (a wrong user name or password, or a user the broker does not let connect)"
        }
    }
}

fn client_id(cfg: &MqttConfig) -> String {
    cfg.client_id
        .clone()
        .unwrap_or_else(|| format!("compgate-{}", cfg.machine))
}

type Db = Arc<Mutex<Connection>>;

/// One outbox row: id, topic, payload.
type Row = (i64, String, String);

/// The outbox in the recorder's database at `path`. It is opened again when the
/// recorder's writer created the database anew (deleted or replaced while the
/// gateway runs): the old file no longer gets a message. Its errors are logged as
/// the database's, once per change.
struct Outbox {
    path: PathBuf,
    db: Db,
    /// What `db` has open.
    files: DbFiles,
    /// The last round trip (or opening it again) failed.
    failing: bool,
}

impl Outbox {
    fn new(path: PathBuf, conn: Connection) -> Self {
        Outbox {
            files: DbFiles::at(&path),
            db: Arc::new(Mutex::new(conn)),
            path,
            failing: false,
        }
    }

    /// The path names another database than the one open (the writer's check).
    /// Not while the old -wal or -shm are still at the path: opened with them,
    /// SQLite would replay the old WAL into the new file (the writer removes them
    /// before it creates the new one).
    /// Or the database is the same and its -wal at the path another file than the
    /// one open: the writer found the -wal deleted, checkpointed it and opened the
    /// database again with a new one ([`Self::wal_gone`]).
    fn replaced(&self) -> bool {
        let db = file_id(&self.path);
        if db.is_none() {
            return false;
        }
        if db == self.files.db {
            return self.wal_gone() && file_id(&with_suffix(&self.path, "-wal")).is_some();
        }
        let now = DbFiles::at(&self.path);
        let stale = |old: Option<(u64, u64)>, at_path| old.is_some() && old == at_path;
        !stale(self.files.wal, now.wal) && !stale(self.files.shm, now.shm)
    }

    fn reopen_if_replaced(&mut self) -> Result<(), ServiceError> {
        if !self.replaced() {
            return Ok(());
        }
        let same_file = file_id(&self.path) == self.files.db;
        match crate::record::open(&self.path) {
            Ok(conn) => {
                // The old connection closes here: SQLite sees its file moved and
                // leaves the new -wal and -shm alone (with only the -wal new, the
                // writer's connection keeps them).
                *self = Outbox {
                    failing: self.failing,
                    ..Outbox::new(self.path.clone(), conn)
                };
                if same_file {
                    tracing::info!(path = %self.path.display(), "MQTT: the recorder database was opened again with a new -wal: publishing goes on from its outbox");
                } else {
                    tracing::info!(path = %self.path.display(), "MQTT: the recorder database was created again: publishing goes on from its outbox");
                }
                Ok(())
            }
            Err(e) => {
                let e = outbox_err(e);
                self.note(Some(&e));
                Err(e)
            }
        }
    }

    /// The database file is the one open, its -wal at the path is not (deleted, or
    /// replaced since). This connection still has the old -wal open: once the writer
    /// has checkpointed it and started a new one, every exchange through it fails
    /// with a disk I/O error (SQLite finds the WAL index pointing past the end of the
    /// old file), and before, it writes to a file nobody else can open. Nothing goes
    /// through it until it is opened again.
    fn wal_gone(&self) -> bool {
        self.files.wal.is_some()
            && file_id(&self.path) == self.files.db
            && file_id(&with_suffix(&self.path, "-wal")) != self.files.wal
    }

    /// Runs `ex` on the database; see [`exchange`]. Not while the -wal is gone
    /// ([`Self::wal_gone`]): an error, logged as the database's, until the writer has
    /// opened the database again and [`Self::reopen_if_replaced`] this one too.
    async fn exchange(&mut self, ex: Exchange) -> Result<(u64, Vec<Row>), ServiceError> {
        let result = if self.wal_gone() {
            Err(outbox_err(format!(
                "{}-wal was deleted or replaced: waiting for the recorder to open the database again",
                self.path.display()
            )))
        } else {
            exchange(&self.db, ex).await
        };
        self.note(result.as_ref().err());
        result
    }

    /// Logs the database failing and working again, once per change.
    fn note(&mut self, error: Option<&ServiceError>) {
        let path = self.path.display();
        match (error, self.failing) {
            (Some(e), false) => {
                tracing::warn!(path = %path, error = %e, "MQTT: the outbox database failed; messages wait in it, publishing is tried again every retry_s");
            }
            (Some(e), true) => {
                tracing::debug!(path = %path, error = %e, "MQTT: the outbox database still fails");
            }
            (None, true) => tracing::info!(path = %path, "MQTT: the outbox database works again"),
            (None, false) => {}
        }
        self.failing = error.is_some();
    }
}

/// One round trip to the outbox.
struct Exchange {
    /// Acknowledged rows to delete.
    acked: Vec<i64>,
    /// Enforce the cap: delete the oldest beyond this many messages.
    cap: Option<u64>,
    /// Read up to `.1` rows with an id above `.0`, oldest first.
    fetch: Option<(i64, usize)>,
}

/// An outbox error: the database or its lock.
fn outbox_err(e: impl std::fmt::Display) -> ServiceError {
    ServiceError::MqttOutbox(e.to_string())
}

/// Runs `ex` in one blocking call: deletes first, then reads. Returns the rows
/// dropped by the cap and the rows read.
async fn exchange(db: &Db, ex: Exchange) -> Result<(u64, Vec<Row>), ServiceError> {
    let db = db.clone();
    tokio::task::spawn_blocking(move || {
        let mut conn = db.lock().map_err(outbox_err)?;
        let mut dropped = 0;
        if !ex.acked.is_empty() || ex.cap.is_some() {
            // IMMEDIATE: wait out the recorder's commit at BEGIN (busy timeout).
            let tx = conn
                .transaction_with_behavior(rusqlite::TransactionBehavior::Immediate)
                .map_err(outbox_err)?;
            {
                let mut del = tx
                    .prepare_cached("DELETE FROM mqtt_outbox WHERE id = ?1")
                    .map_err(outbox_err)?;
                for id in &ex.acked {
                    del.execute([id]).map_err(outbox_err)?;
                }
            }
            if let Some(max) = ex.cap {
                dropped = tx
                    .prepare_cached(
                        "DELETE FROM mqtt_outbox WHERE id <= (SELECT max(id) FROM mqtt_outbox) - ?1",
                    )
                    .and_then(|mut s| s.execute([i64::try_from(max).unwrap_or(i64::MAX)]))
                    .map_err(outbox_err)? as u64;
            }
            tx.commit().map_err(outbox_err)?;
        }
        let rows = match ex.fetch {
            Some((after, limit)) => conn
                .prepare_cached(
                    "SELECT id, topic, payload FROM mqtt_outbox WHERE id > ?1 ORDER BY id LIMIT ?2",
                )
                .and_then(|mut s| {
                    s.query_map(rusqlite::params![after, limit as i64], |r| {
                        Ok((r.get(0)?, r.get(1)?, r.get(2)?))
                    })?
                    .collect::<Result<Vec<_>, _>>()
                })
                .map_err(outbox_err)?,
            None => Vec::new(),
        };
        Ok((dropped, rows))
    })
    .await
    .map_err(|e| ServiceError::Task(e.to_string()))?
}

/// One connection to the broker: sends the outbox until `shutdown` or the database
/// replaced (Ok), or an error of the connection or the outbox (Err). A new session
/// starts from the oldest unacknowledged row.
///
/// The outbox is read when the recorder has committed new messages (`grown`), at
/// the start of a connection, and while a backlog is left; acknowledged rows are
/// deleted in batches. An idle session does not wake up at all but for the cap.
async fn session(
    cfg: &MqttConfig,
    login: Option<&Credentials>,
    outbox: &mut Outbox,
    grown: &Notify,
    shutdown: &CancellationToken,
    link: &mut BrokerLink,
) -> Result<(), ServiceError> {
    let (host, port) = cfg
        .broker
        .rsplit_once(':')
        .and_then(|(h, p)| Some((h.to_string(), p.parse::<u16>().ok()?)))
        .ok_or_else(|| ServiceError::MqttBroker(cfg.broker.clone()))?;
    let mut opts = MqttOptions::new(client_id(cfg), host, port);
    opts.set_keep_alive(secs(cfg.keep_alive_s));
    opts.set_clean_session(true);
    opts.set_inflight(WINDOW as u16);
    if let Some(c) = login {
        opts.set_credentials(&c.user, &c.password);
    }
    let state = state_topic(cfg);
    // The broker publishes it when the connection is lost without a clean stop.
    opts.set_last_will(LastWill::new(&state, STATE_LOST, QoS::AtLeastOnce, true));
    let (client, connection) = AsyncClient::new(opts, WINDOW * 2);
    let mut events = Events::drive(connection, login.is_none());

    let mut connected = false;
    let mut queued_upto: i64 = 0;
    let mut window = Window::default();
    // Rows may be waiting that have not been read yet.
    let mut unread = true;
    // When the pending outbox work runs.
    let mut work_at: Option<tokio::time::Instant> = None;
    let mut cap_tick = tokio::time::interval(CAP_INTERVAL);
    cap_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut cap_due = false;
    loop {
        let far = tokio::time::Instant::now() + Duration::from_secs(3600);
        tokio::select! {
            _ = shutdown.cancelled() => {
                if connected {
                    close(&client, &mut events, &mut window, Some(&state)).await;
                }
                let _ = outbox.exchange(Exchange { acked: std::mem::take(&mut window.acked), cap: Some(cfg.outbox_max_messages), fetch: None }).await;
                return Ok(());
            }
            ev = events.next() => {
                match ev? {
                    Event::Incoming(Packet::ConnAck(_)) => {
                        connected = true;
                        link.connected(cfg);
                        // Before any outbox row, so that its packet id is not taken
                        // for a row's.
                        client
                            .try_publish(&state, QoS::AtLeastOnce, true, STATE_ONLINE)
                            .map_err(|e| ServiceError::Mqtt(e.to_string()))?;
                        window.sent.push_back(NOT_A_ROW);
                    }
                    ev => window.track(&ev),
                }
            }
            () = grown.notified() => unread = true,
            _ = cap_tick.tick() => cap_due = true,
            () = tokio::time::sleep_until(work_at.unwrap_or(far)), if work_at.is_some() => {
                work_at = None;
                if outbox.replaced() {
                    if connected {
                        // Without the offline state: the next session says online again.
                        close(&client, &mut events, &mut window, None).await;
                    }
                    return Ok(());
                }
                let room = WINDOW.saturating_sub(window.len());
                let fetch = (connected && unread && room > 0).then_some((queued_upto, room));
                let cap = std::mem::take(&mut cap_due).then_some(cfg.outbox_max_messages);
                let (dropped, rows) = outbox.exchange(Exchange { acked: std::mem::take(&mut window.acked), cap, fetch }).await?;
                link.dropped(cfg, dropped);
                if fetch.is_some() {
                    // A full window may have left more behind.
                    unread = rows.len() == room;
                }
                for (row, topic, payload) in rows {
                    client
                        .try_publish(topic, QoS::AtLeastOnce, false, payload)
                        .map_err(|e| ServiceError::Mqtt(e.to_string()))?;
                    window.sent.push_back(row);
                    queued_upto = row;
                }
            }
        }
        let room = WINDOW > window.len();
        if work_at.is_none()
            && (!window.acked.is_empty() || cap_due || (connected && unread && room))
        {
            work_at = Some(tokio::time::Instant::now() + BATCH);
        }
    }
}

/// The broker connection, polled by a task of its own: its keep-alive and its
/// acknowledgements go on while the session waits on the database (a commit on a
/// slow card, a backup holding the lock), and a connect is never cut off halfway,
/// as dropping rumqttc's `poll` in a `select!` does (the broker then published the
/// last will, "lost", at most starts).
struct Events {
    events: mpsc::UnboundedReceiver<Result<Event, ConnectionError>>,
    /// Connected without a user name: how a refusal is told.
    anonymous: bool,
    _task: AbortOnDropHandle<()>,
}

impl Events {
    /// Ends at the first error (the session starts again), and with the session.
    fn drive(mut connection: rumqttc::EventLoop, anonymous: bool) -> Self {
        // Unbounded, yet short: the window bounds the publishes and acks in flight.
        let (tx, events) = mpsc::unbounded_channel();
        let task = tokio::spawn(async move {
            loop {
                let ev = connection.poll().await;
                let failed = ev.is_err();
                if tx.send(ev).is_err() || failed {
                    return;
                }
            }
        });
        Events {
            events,
            anonymous,
            _task: AbortOnDropHandle::new(task),
        }
    }

    /// The next event, or the connection's error.
    async fn next(&mut self) -> Result<Event, ServiceError> {
        match self.events.recv().await {
            Some(Ok(ev)) => Ok(ev),
            Some(Err(ConnectionError::ConnectionRefused(code))) => {
                Err(ServiceError::MqttRefused(refusal(code, self.anonymous)))
            }
            Some(Err(e)) => Err(ServiceError::Mqtt(e.to_string())),
            None => Err(ServiceError::Mqtt("the connection task ended".into())),
        }
    }
}

/// The outbox rows handed to the client and not yet acknowledged.
#[derive(Default)]
struct Window {
    /// Row ids sent but not yet given a packet id, in send order.
    sent: VecDeque<i64>,
    inflight: BTreeMap<u16, i64>,
    /// Acknowledged, to delete from the outbox.
    acked: Vec<i64>,
}

impl Window {
    fn len(&self) -> usize {
        self.sent.len() + self.inflight.len()
    }

    fn track(&mut self, ev: &Event) {
        match ev {
            Event::Outgoing(Outgoing::Publish(pkid)) => {
                if let Some(row) = self.sent.pop_front() {
                    self.inflight.insert(*pkid, row);
                }
            }
            Event::Incoming(Packet::PubAck(ack)) => {
                if let Some(row) = self.inflight.remove(&ack.pkid).filter(|&r| r != NOT_A_ROW) {
                    self.acked.push(row);
                }
            }
            _ => {}
        }
    }
}

/// The retained `state` payloads.
const STATE_ONLINE: &str = r#"{"state":"online"}"#;
const STATE_OFFLINE: &str = r#"{"state":"offline"}"#;
const STATE_LOST: &str = r#"{"state":"lost"}"#;
/// The row id of a publish that is not from the outbox (the state).
const NOT_A_ROW: i64 = -1;
/// How long a stop waits for the broker to take the offline state.
const CLOSE_WAIT: Duration = Duration::from_secs(3);

fn state_topic(cfg: &MqttConfig) -> String {
    format!("{}/{}/state", cfg.topic_prefix, cfg.machine)
}

/// Ends the session cleanly: at a stop the retained offline state (to `state`)
/// first, then a DISCONNECT, so that the broker drops the last will. For at most
/// [`CLOSE_WAIT`]: a stop does not wait on a slow broker. The publishes handed to
/// the client before go out first; the DISCONNECT follows the last of them (TCP
/// keeps the order). Acknowledgements that come meanwhile are kept in `window`.
async fn close(
    client: &AsyncClient,
    events: &mut Events,
    window: &mut Window,
    state: Option<&str>,
) {
    if let Some(state) = state {
        if client
            .try_publish(state, QoS::AtLeastOnce, true, STATE_OFFLINE)
            .is_err()
        {
            return;
        }
        window.sent.push_back(NOT_A_ROW);
    }
    let _ = tokio::time::timeout(CLOSE_WAIT, async {
        if window.sent.is_empty() && client.try_disconnect().is_err() {
            return;
        }
        loop {
            let Ok(ev) = events.next().await else { return };
            let last =
                matches!(ev, Event::Outgoing(Outgoing::Publish(_))) && window.sent.len() == 1;
            window.track(&ev);
            match ev {
                _ if last && client.try_disconnect().is_err() => return,
                Event::Outgoing(Outgoing::Disconnect) => return,
                _ => {}
            }
        }
    })
    .await;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// How many of `ticks` (seconds after a start) a schedule of `interval_s` takes.
    fn taken(interval_s: f64, ticks: impl IntoIterator<Item = f64>) -> usize {
        let start = Instant::now();
        let mut s = Grid::default();
        let interval = Duration::from_secs_f64(interval_s);
        ticks
            .into_iter()
            .filter(|&t| s.due(interval, start + Duration::from_secs_f64(t)))
            .count()
    }

    #[test]
    fn a_tick_a_little_early_is_not_skipped() {
        // Ticks every second, alternately 30 us early and late: every one is due
        // (measured from the last message every other one was skipped).
        let jitter = |i: u32| if i.is_multiple_of(2) { 30e-6 } else { -30e-6 };
        assert_eq!(taken(1.0, (0..100).map(|i| f64::from(i) + jitter(i))), 100);
    }

    #[test]
    fn the_mean_rate_is_the_interval_whatever_the_tick() {
        // 0.3 s polls for 60 s: one message a second.
        let n = taken(1.0, (0..200).map(|i| f64::from(i) * 0.3));
        assert!((60..=61).contains(&n), "{n}");
        // Ticks slower than the interval: each one.
        assert_eq!(taken(1.0, (0..10).map(|i| f64::from(i) * 2.0)), 10);
        // After a gap, one message and a new grid, no burst to catch up.
        assert_eq!(taken(1.0, [0.0, 1.0, 10.0, 10.1, 10.5, 11.0]), 4);
    }

    #[test]
    fn readings_payload_is_the_documented_json() {
        let msg = ReadingsMsg {
            channels: vec![
                ChannelMsg {
                    channel: "T_bed",
                    quality: "good",
                    raw: Some(1234.0),
                    reason: None,
                    unfiltered_degc: Some(30.02),
                    value_degc: Some(30.0),
                },
                ChannelMsg {
                    channel: "T_col",
                    quality: "bad",
                    raw: None,
                    reason: Some("NE43 low"),
                    unfiltered_degc: Some(f64::NAN),
                    value_degc: None,
                },
            ],
            device: "ain1",
            t_unix_ms: 1_763_800_000_123,
        };
        let expected = json!({
            "t_unix_ms": 1_763_800_000_123_i64,
            "device": "ain1",
            "channels": [
                {"channel": "T_bed", "value_degc": 30.0, "unfiltered_degc": 30.02, "raw": 1234.0, "quality": "good", "reason": null},
                {"channel": "T_col", "value_degc": null, "unfiltered_degc": f64::NAN, "raw": null, "quality": "bad", "reason": "NE43 low"},
            ],
        });
        // Byte for byte what the `json!` maps wrote: same keys, same order.
        assert_eq!(
            serde_json::to_string(&msg).expect("serialises"),
            expected.to_string()
        );
    }

    // The recorder's -wal deleted while the outbox has the database open: nothing goes
    // through the outbox's connection, which still has the deleted -wal open (once the
    // writer has checkpointed it and started a new one, every exchange through it
    // failed with a disk I/O error, and publishing stopped for good); once the writer
    // has opened the database again with a new -wal, the outbox opens it too, and
    // every message is there.
    #[tokio::test]
    async fn the_outbox_waits_out_a_deleted_wal_and_goes_on_with_the_new_one() {
        use crate::record::Recorder;
        use compgate_gateway::config::RecorderConfig;
        use std::sync::atomic::Ordering;
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("r.db");
        let cfg = RecorderConfig {
            path: path.display().to_string(),
            commit_interval_s: 0.05,
            ..RecorderConfig::default()
        };
        let rec = Recorder::start(&cfg).expect("starts");
        let tx = rec.sender();
        let stats = tx.stats().clone();
        let wait = |what: &str, done: &dyn Fn() -> bool| {
            let deadline = Instant::now() + Duration::from_secs(5);
            while !done() {
                assert!(Instant::now() < deadline, "{what}");
                std::thread::sleep(Duration::from_millis(10));
            }
        };
        let message = |payload: &str| Record::Outbox {
            topic: "t".into(),
            payload: payload.into(),
        };
        tx.send(message("before"));
        wait("committed", &|| stats.written.load(Ordering::Relaxed) == 1);
        let mut outbox = Outbox::new(path.clone(), crate::record::open(&path).expect("opens"));
        let fetch = || Exchange {
            acked: Vec::new(),
            cap: None,
            fetch: Some((0, 10)),
        };
        std::fs::remove_file(with_suffix(&path, "-wal")).expect("deleted");
        let e = outbox
            .exchange(fetch())
            .await
            .expect_err("the -wal is gone");
        assert!(e.to_string().contains("r.db-wal"), "{e}");
        tx.send(message("after"));
        wait("reopened", &|| stats.reopened.load(Ordering::Relaxed) == 1);
        wait("committed", &|| stats.written.load(Ordering::Relaxed) == 2);
        assert!(outbox.replaced(), "the writer's new -wal");
        outbox.reopen_if_replaced().expect("opens again");
        assert!(!outbox.replaced());
        let (_, rows) = outbox.exchange(fetch()).await.expect("exchange");
        let payloads: Vec<&str> = rows.iter().map(|(_, _, p)| p.as_str()).collect();
        assert_eq!(payloads, ["before", "after"]);
        drop(tx);
        drop(outbox);
        rec.finish();
    }
}
