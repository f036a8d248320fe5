//! MQTT publishing (QoS 1) with store-and-forward through the recorder's database.
//!
//! The control loop's [`MqttObserver`] turns readings, NC jobs and health into JSON
//! messages and queues them with the recorder, which commits them into the
//! `mqtt_outbox` table in the same transaction as the readings. The [`publisher`]
//! task sends the outbox in id order and deletes a message only when the broker has
//! acknowledged it (PUBACK). While the broker is down the outbox grows; after it is
//! back the backlog goes out first, oldest first. Delivery is at least once: after a
//! broken connection unacknowledged messages are sent again.
//!
//! Topics (`P` = `topic_prefix`, `M` = `machine`):
//!
//! | topic | when | payload |
//! |---|---|---|
//! | `P/M/readings/<device>` | every `publish_interval_s` per device | `{"t_unix_ms", "device", "channels": [{"channel", "value_degc", "unfiltered_degc", "raw", "quality", "reason"}]}` |
//! | `P/M/writes/<axis>` | every NC job | `{"t_unix_ms", "axis", "sd43900_mm", "sd43910", "sd43920_mm", "ok", "job_id", "elapsed_ms", "error", "quality"}` |
//! | `P/M/health` | every `publish_interval_s` | `{"t_unix_ms", "quality", "devices": [{"name", "link", "failed_cycles", "last_error"}], "axes": [{"name", "sd43900_mm", "sd43910", "sd43920_mm", "jobs_ok", "jobs_failed", "warning"}]}` |
//!
//! One readings message carries a whole poll cycle of a device (64 channels are one
//! message, not 64). `quality` is `good`, `uncertain` or `bad`: a reading's own quality; `good`/`bad` for
//! a job's result; for health `good` when every link is up and no axis has a warning,
//! else `uncertain`.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rusqlite::Connection;

use rumqttc::{AsyncClient, Event, MqttOptions, Outgoing, Packet, QoS};
use serde_json::json;
use tokio_util::sync::CancellationToken;

use crate::comp::CompParams;
use crate::config::{secs, MqttConfig};
use crate::gateway::{Observer, Pipeline, Status};
use crate::nc::{JobReport, NcError};
use crate::record::{now_unix_ms, quality_code, Record, RecordSender};
use crate::source::DeviceSample;

fn quality_word(code: u8) -> &'static str {
    match code {
        0 => "good",
        1 => "uncertain",
        _ => "bad",
    }
}

/// Builds the messages in the control loop and queues them with the recorder.
pub struct MqttObserver {
    base: String,
    interval: Duration,
    tx: RecordSender,
    /// Per device index: last readings message.
    last_reading: HashMap<usize, Instant>,
    last_health: Option<Instant>,
    /// Device names by index, from the status.
    devices: Vec<String>,
}

impl MqttObserver {
    /// An observer for `cfg` that queues through `tx`.
    pub fn new(cfg: &MqttConfig, tx: RecordSender) -> Self {
        MqttObserver {
            base: format!("{}/{}", cfg.topic_prefix, cfg.machine),
            interval: secs(cfg.publish_interval_s),
            tx,
            last_reading: HashMap::new(),
            last_health: None,
            devices: Vec::new(),
        }
    }

    fn due(last: Option<&Instant>, interval: Duration, now: Instant) -> bool {
        last.is_none_or(|t| now.saturating_duration_since(*t) >= interval)
    }
}

impl Observer for MqttObserver {
    fn on_sample(&mut self, sample: &DeviceSample, pipeline: &Pipeline) {
        let now = Instant::now();
        if !Self::due(self.last_reading.get(&sample.device), self.interval, now) {
            return;
        }
        self.last_reading.insert(sample.device, now);
        let device = self
            .devices
            .get(sample.device)
            .cloned()
            .unwrap_or_else(|| format!("device{}", sample.device));
        let channels: Vec<serde_json::Value> = sample
            .values
            .iter()
            .filter_map(|(ch, _)| {
                let name = pipeline.channel_names.get(*ch)?;
                let r = pipeline.processors.get(*ch)?.last();
                let (q, reason) = quality_code(&r.quality);
                Some(json!({
                    "channel": name,
                    "value_degc": r.value_degc,
                    "unfiltered_degc": r.unfiltered_degc,
                    "raw": r.raw,
                    "quality": quality_word(q),
                    "reason": reason,
                }))
            })
            .collect();
        let payload = json!({
            "t_unix_ms": now_unix_ms(),
            "device": device,
            "channels": channels,
        });
        self.tx.send(Record::Outbox {
            topic: format!("{}/readings/{device}", self.base),
            payload: payload.to_string(),
        });
    }

    fn on_job(&mut self, axis: &str, params: &CompParams, result: &Result<JobReport, NcError>) {
        let payload = json!({
            "t_unix_ms": now_unix_ms(),
            "axis": axis,
            "sd43900_mm": params.k0_mm,
            "sd43910": params.tan_beta,
            "sd43920_mm": params.p0_mm,
            "ok": result.is_ok(),
            "job_id": result.as_ref().ok().map(|r| r.job_id),
            "elapsed_ms": result.as_ref().ok().map(|r| r.elapsed.as_secs_f64() * 1e3),
            "error": result.as_ref().err().map(ToString::to_string),
            "quality": if result.is_ok() { "good" } else { "bad" },
        });
        self.tx.send(Record::Outbox {
            topic: format!("{}/writes/{axis}", self.base),
            payload: payload.to_string(),
        });
    }

    fn on_status(&mut self, status: &Status) {
        if self.devices.len() != status.devices.len() {
            self.devices = status.devices.iter().map(|d| d.name.clone()).collect();
        }
        let now = Instant::now();
        if !Self::due(self.last_health.as_ref(), self.interval, now) {
            return;
        }
        self.last_health = Some(now);
        let healthy = status
            .devices
            .iter()
            .all(|d| d.cycles > 0 && d.last_error.is_none())
            && status.axes.iter().all(|a| a.warning.is_none());
        let payload = json!({
            "t_unix_ms": now_unix_ms(),
            "quality": if healthy { "good" } else { "uncertain" },
            "devices": status.devices.iter().map(|d| json!({
                "name": d.name,
                "link": if d.cycles > 0 && d.last_error.is_none() { "up" } else { "down" },
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

    fn on_reload(&mut self, _result: &Result<(), String>) {
        // Device indices may have moved.
        self.last_reading.clear();
        self.devices.clear();
    }
}

/// Messages in flight to the broker at most.
const WINDOW: usize = 64;

/// Sends the outbox of the database at `db` to the broker until `shutdown`.
pub async fn publisher(cfg: MqttConfig, db_path: PathBuf, shutdown: CancellationToken) {
    let retry = secs(cfg.retry_s);
    let mut dropped_total: u64 = 0;
    let db = match crate::record::open(&db_path) {
        Ok(c) => Arc::new(Mutex::new(c)),
        Err(e) => {
            tracing::error!(error = %e, "MQTT: cannot open the outbox; nothing is published");
            return;
        }
    };
    while !shutdown.is_cancelled() {
        match session(&cfg, &db, &shutdown, &mut dropped_total).await {
            Ok(()) => break,
            Err(e) => {
                tracing::warn!(broker = %cfg.broker, error = %e, retry_s = cfg.retry_s, "MQTT: broker unreachable; messages wait in the outbox");
            }
        }
        tokio::select! {
            _ = shutdown.cancelled() => break,
            _ = tokio::time::sleep(retry) => {}
        }
    }
}

type Db = Arc<Mutex<Connection>>;

/// Outbox rows with an id above `after`, oldest first.
async fn fetch(db: &Db, after: i64, limit: usize) -> Result<Vec<(i64, String, String)>, String> {
    let db = db.clone();
    tokio::task::spawn_blocking(move || {
        let conn = db.lock().map_err(|e| e.to_string())?;
        let mut s = conn
            .prepare_cached(
                "SELECT id, topic, payload FROM mqtt_outbox WHERE id > ?1 ORDER BY id LIMIT ?2",
            )
            .map_err(|e| e.to_string())?;
        let rows = s
            .query_map(rusqlite::params![after, limit as i64], |r| {
                Ok((r.get(0)?, r.get(1)?, r.get(2)?))
            })
            .and_then(|rows| rows.collect::<Result<Vec<_>, _>>())
            .map_err(|e| e.to_string())?;
        Ok(rows)
    })
    .await
    .map_err(|e| e.to_string())?
}

/// Deletes acknowledged rows, and the oldest beyond `max` (counted as dropped).
async fn delete(db: &Db, ids: Vec<i64>, max: u64) -> Result<u64, String> {
    let db = db.clone();
    tokio::task::spawn_blocking(move || {
        let mut conn = db.lock().map_err(|e| e.to_string())?;
        let tx = conn.transaction().map_err(|e| e.to_string())?;
        for id in ids {
            tx.execute("DELETE FROM mqtt_outbox WHERE id = ?1", [id])
                .map_err(|e| e.to_string())?;
        }
        let dropped = tx
            .execute(
                "DELETE FROM mqtt_outbox WHERE id <= (SELECT max(id) FROM mqtt_outbox) - ?1",
                [i64::try_from(max).unwrap_or(i64::MAX)],
            )
            .map_err(|e| e.to_string())?;
        tx.commit().map_err(|e| e.to_string())?;
        Ok(dropped as u64)
    })
    .await
    .map_err(|e| e.to_string())?
}

/// One connection to the broker: sends the outbox until `shutdown` (Ok) or a
/// connection error (Err). A new session starts from the oldest unacknowledged row.
async fn session(
    cfg: &MqttConfig,
    db: &Db,
    shutdown: &CancellationToken,
    dropped_total: &mut u64,
) -> Result<(), String> {
    let (host, port) = cfg
        .broker
        .rsplit_once(':')
        .and_then(|(h, p)| Some((h.to_string(), p.parse::<u16>().ok()?)))
        .ok_or_else(|| format!("mqtt.broker `{}` is not host:port", cfg.broker))?;
    let id = cfg
        .client_id
        .clone()
        .unwrap_or_else(|| format!("compgate-{}", cfg.machine));
    let mut opts = MqttOptions::new(id, host, port);
    opts.set_keep_alive(secs(cfg.keep_alive_s));
    opts.set_clean_session(true);
    opts.set_inflight(WINDOW as u16);
    let (client, mut events) = AsyncClient::new(opts, WINDOW * 2);

    let mut connected = false;
    let mut queued_upto: i64 = 0;
    // Row ids sent but not yet given a packet id, in send order.
    let mut sent: VecDeque<i64> = VecDeque::new();
    let mut inflight: BTreeMap<u16, i64> = BTreeMap::new();
    let mut acked: Vec<i64> = Vec::new();
    let mut ticks: u64 = 0;
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => {
                let _ = delete(db, std::mem::take(&mut acked), cfg.outbox_max_messages).await;
                let _ = client.try_disconnect();
                return Ok(());
            }
            ev = events.poll() => {
                match ev.map_err(|e| e.to_string())? {
                    Event::Incoming(Packet::ConnAck(_)) => {
                        connected = true;
                        tracing::info!(broker = %cfg.broker, "MQTT connected");
                    }
                    Event::Outgoing(Outgoing::Publish(pkid)) => {
                        if let Some(row) = sent.pop_front() {
                            inflight.insert(pkid, row);
                        }
                    }
                    Event::Incoming(Packet::PubAck(ack)) => {
                        if let Some(row) = inflight.remove(&ack.pkid) {
                            acked.push(row);
                        }
                    }
                    _ => {}
                }
            }
            _ = tick.tick() => {
                ticks += 1;
                // The cap is enforced every 5 s; acknowledged rows go every tick.
                if !acked.is_empty() || ticks.is_multiple_of(50) {
                    let dropped = delete(db, std::mem::take(&mut acked), cfg.outbox_max_messages).await?;
                    if dropped > 0 {
                        *dropped_total += dropped;
                        tracing::warn!(dropped, dropped_total = *dropped_total, "MQTT outbox over outbox_max_messages: oldest messages dropped");
                    }
                }
                if !connected {
                    continue;
                }
                let room = WINDOW.saturating_sub(sent.len() + inflight.len());
                if room == 0 {
                    continue;
                }
                for (row, topic, payload) in fetch(db, queued_upto, room).await? {
                    client
                        .try_publish(topic, QoS::AtLeastOnce, false, payload)
                        .map_err(|e| e.to_string())?;
                    sent.push_back(row);
                    queued_upto = row;
                }
            }
        }
    }
}
