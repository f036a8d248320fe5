//! The database layout and its statements.

use std::path::Path;

use rusqlite::{params, Connection, OptionalExtension};

use super::{Record, RecordError};

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS channels (
    id   INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE
);
-- Clustered by time (one b-tree, no separate index): inserts, time-range exports and
-- retention deletes all walk the same key.
CREATE TABLE IF NOT EXISTS readings (
    t_unix_ms       INTEGER NOT NULL,
    channel         INTEGER NOT NULL REFERENCES channels(id),
    raw             REAL,
    unfiltered_degc REAL,
    value_degc      REAL,
    quality         INTEGER NOT NULL, -- 0 good, 1 uncertain, 2 bad
    reason          TEXT,
    PRIMARY KEY (t_unix_ms, channel)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS jobs (
    t_unix_ms  INTEGER NOT NULL,
    axis       TEXT NOT NULL,
    sd43900_mm REAL NOT NULL,
    sd43910    REAL NOT NULL,
    sd43920_mm REAL NOT NULL,
    ok         INTEGER NOT NULL,
    job_id     INTEGER,
    elapsed_ms REAL,
    error      TEXT
);
CREATE INDEX IF NOT EXISTS jobs_t ON jobs(t_unix_ms);
CREATE TABLE IF NOT EXISTS nc (
    t_unix_ms       INTEGER NOT NULL,
    axis            TEXT NOT NULL,
    position_mm     REAL NOT NULL,
    applied_comp_mm REAL NOT NULL,
    sd43900_mm      REAL NOT NULL,
    sd43910         REAL NOT NULL,
    sd43920_mm      REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS nc_t ON nc(t_unix_ms);
CREATE TABLE IF NOT EXISTS mqtt_outbox (
    id      INTEGER PRIMARY KEY AUTOINCREMENT,
    topic   TEXT NOT NULL,
    payload TEXT NOT NULL
);
";

/// Opens the database at `path` (creating it and its tables), in WAL mode.
pub fn open(path: &Path) -> Result<Connection, RecordError> {
    let err = |e: rusqlite::Error| RecordError::Open {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let conn = Connection::open(path).map_err(err)?;
    conn.busy_timeout(std::time::Duration::from_secs(5))
        .map_err(err)?;
    // auto_vacuum only takes effect before the first table exists.
    conn.execute_batch("PRAGMA auto_vacuum = INCREMENTAL;")
        .map_err(err)?;
    let mode: String = conn
        .query_row("PRAGMA journal_mode = WAL", [], |r| r.get(0))
        .map_err(err)?;
    if !mode.eq_ignore_ascii_case("wal") {
        return Err(RecordError::Open {
            path: path.display().to_string(),
            message: format!("cannot switch to WAL mode (journal_mode is {mode})"),
        });
    }
    // In WAL mode NORMAL loses nothing committed when the process dies; only a power
    // loss may take the last commits.
    conn.execute_batch("PRAGMA synchronous = NORMAL; PRAGMA foreign_keys = OFF;")
        .map_err(err)?;
    conn.execute_batch(SCHEMA).map_err(err)?;
    Ok(conn)
}

fn channel_id(conn: &Connection, name: &str) -> rusqlite::Result<i64> {
    if let Some(id) = conn
        .prepare_cached("SELECT id FROM channels WHERE name = ?1")?
        .query_row([name], |r| r.get(0))
        .optional()?
    {
        return Ok(id);
    }
    conn.prepare_cached("INSERT INTO channels(name) VALUES (?1)")?
        .execute([name])?;
    Ok(conn.last_insert_rowid())
}

/// Inserts `batch` in one transaction.
pub fn insert(conn: &mut Connection, batch: &[Record]) -> rusqlite::Result<()> {
    let tx = conn.transaction()?;
    {
        let mut ids: std::collections::HashMap<*const u8, i64> = std::collections::HashMap::new();
        let mut reading = tx.prepare_cached(
            "INSERT OR REPLACE INTO readings(t_unix_ms, channel, raw, unfiltered_degc, value_degc, quality, reason) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
        )?;
        for rec in batch {
            match rec {
                Record::Cycle { t_unix_ms, rows } => {
                    for row in rows {
                        // Names are shared Arcs: look each up once per batch.
                        let key = row.channel.as_ptr();
                        let id = match ids.get(&key) {
                            Some(id) => *id,
                            None => {
                                let id = channel_id(&tx, &row.channel)?;
                                ids.insert(key, id);
                                id
                            }
                        };
                        reading.execute(params![
                            t_unix_ms,
                            id,
                            row.raw,
                            row.unfiltered_degc,
                            row.value_degc,
                            row.quality,
                            row.reason
                        ])?;
                    }
                }
                Record::Job {
                    t_unix_ms,
                    axis,
                    params: p,
                    job_id,
                    elapsed_ms,
                    error,
                } => {
                    tx.prepare_cached("INSERT INTO jobs(t_unix_ms, axis, sd43900_mm, sd43910, sd43920_mm, ok, job_id, elapsed_ms, error) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)")?
                        .execute(params![t_unix_ms, axis, p.k0_mm, p.tan_beta, p.p0_mm, error.is_none(), job_id, elapsed_ms, error])?;
                }
                Record::Nc {
                    t_unix_ms,
                    axis,
                    position_mm,
                    applied_comp_mm,
                    params: p,
                } => {
                    tx.prepare_cached("INSERT INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)")?
                        .execute(params![t_unix_ms, axis, position_mm, applied_comp_mm, p.k0_mm, p.tan_beta, p.p0_mm])?;
                }
                Record::Outbox { topic, payload } => {
                    tx.prepare_cached("INSERT INTO mqtt_outbox(topic, payload) VALUES (?1, ?2)")?
                        .execute(params![topic, payload])?;
                }
            }
        }
    }
    tx.commit()
}

/// Deletes readings, jobs and NC rows older than `cutoff_unix_ms`.
pub fn delete_before(conn: &Connection, cutoff_unix_ms: i64) -> rusqlite::Result<()> {
    for t in ["readings", "jobs", "nc"] {
        conn.execute(
            &format!("DELETE FROM {t} WHERE t_unix_ms < ?1"),
            [cutoff_unix_ms],
        )?;
    }
    Ok(())
}

/// Bytes of pages in use (the file less its free pages).
pub fn data_bytes(conn: &Connection) -> rusqlite::Result<i64> {
    let pages: i64 = conn.query_row("PRAGMA page_count", [], |r| r.get(0))?;
    let free: i64 = conn.query_row("PRAGMA freelist_count", [], |r| r.get(0))?;
    let size: i64 = conn.query_row("PRAGMA page_size", [], |r| r.get(0))?;
    Ok((pages - free) * size)
}

/// First and last reading time, ms since the Unix epoch.
pub fn time_range(conn: &Connection) -> rusqlite::Result<Option<(i64, i64)>> {
    conn.query_row(
        "SELECT min(t_unix_ms), max(t_unix_ms) FROM readings",
        [],
        |r| Ok(r.get::<_, Option<i64>>(0)?.zip(r.get::<_, Option<i64>>(1)?)),
    )
}
