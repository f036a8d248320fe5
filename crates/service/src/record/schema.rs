//! The database layout and its statements.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use rusqlite::{params, Connection, OptionalExtension, TransactionBehavior};

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
    raw             REAL,     -- NULL: no value (reason comm, ...) or NaN (reason 'not finite')
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
    job_id     INTEGER, -- the NC handshake's 16-bit id: from 1 at each start, no key
    elapsed_ms REAL,
    error      TEXT,
    shadow     INTEGER NOT NULL DEFAULT 0 -- 1: shadow mode, computed and not sent (ok 0)
);
CREATE INDEX IF NOT EXISTS jobs_t ON jobs(t_unix_ms);
CREATE TABLE IF NOT EXISTS nc (
    t_unix_ms       INTEGER NOT NULL,
    axis            TEXT NOT NULL,
    position_mm     REAL, -- NULL: the target does not report it (OPC UA, ADS)
    applied_comp_mm REAL, -- NULL: likewise
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

/// The layout's version, kept in the database (`PRAGMA user_version`; 0 in databases of
/// the builds before it was set, whose layout is version 1 after `open`'s migrations).
/// Raise it with a change a build of the version before could not write into; a build
/// refuses a database of a later version than its own instead of failing every commit.
pub const LAYOUT_VERSION: i64 = 1;

/// Page cache of one connection, KiB.
pub const PAGE_CACHE_KB: u32 = 1024;
/// Prepared statements kept per connection.
const STATEMENT_CACHE: usize = 32;

/// How long a statement waits for another connection's lock before it fails.
pub const BUSY_TIMEOUT: Duration = Duration::from_secs(5);
/// How long an open waits for another connection's one-time rebuild of a table (about
/// 1.5 s per million rows on the test machine).
const MIGRATION_WAIT: Duration = Duration::from_secs(600);

/// Rebuilds the `nc` table of the layout before NULL positions (`todo` tells whether
/// it still is), telling the log and systemd (a long one must not be taken for a
/// hung start) first. On an error the caller rolls back.
fn rebuild_nc(
    conn: &Connection,
    path: &Path,
    todo: impl Fn(&Connection) -> rusqlite::Result<bool>,
) -> rusqlite::Result<()> {
    conn.busy_timeout(MIGRATION_WAIT)?;
    conn.execute_batch("BEGIN IMMEDIATE")?;
    if todo(conn)? {
        // The highest rowid: the row count without reading the table.
        let rows: i64 =
            conn.query_row("SELECT COALESCE(MAX(rowid), 0) FROM nc", [], |r| r.get(0))?;
        tracing::info!(path = %path.display(), rows, "recorder database: rebuilding the nc table once, so that it takes NC reads without a position (about 1 s per million rows)");
        let wait_us = u32::try_from(MIGRATION_WAIT.as_micros()).unwrap_or(u32::MAX);
        let _ = sd_notify::notify(&[
            sd_notify::NotifyState::ExtendTimeoutUsec(wait_us),
            sd_notify::NotifyState::Status("rebuilding the recorder's nc table once"),
        ]);
        conn.execute_batch(&format!(
            "ALTER TABLE nc RENAME TO nc_not_null;
             DROP INDEX nc_t;
             {SCHEMA}
             INSERT INTO nc SELECT * FROM nc_not_null;
             DROP TABLE nc_not_null;"
        ))?;
    }
    conn.execute_batch("COMMIT")
}

/// Opens the database at `path` (creating it and its tables), in WAL mode. A file
/// that is not a database of the recorder's layout (`check`) is refused before
/// anything is written to it.
pub fn open(path: &Path) -> Result<Connection, RecordError> {
    let err = |e: rusqlite::Error| RecordError::Open {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let conn = Connection::open(path).map_err(err)?;
    conn.busy_timeout(BUSY_TIMEOUT).map_err(err)?;
    check(&conn).map_err(|message| RecordError::Open {
        path: path.display().to_string(),
        message,
    })?;
    // auto_vacuum only takes effect before the first table exists, and setting it
    // takes the write lock: not on a database that has tables, so an open waits only
    // for what it must change (a connection's rebuild below).
    let fresh: bool = conn
        .query_row("SELECT COUNT(*) = 0 FROM sqlite_schema", [], |r| r.get(0))
        .map_err(err)?;
    if fresh {
        conn.execute_batch("PRAGMA auto_vacuum = INCREMENTAL;")
            .map_err(err)?;
    }
    let mode: String = conn
        .query_row("PRAGMA journal_mode = WAL", [], |r| r.get(0))
        .map_err(err)?;
    if !mode.eq_ignore_ascii_case("wal") {
        return Err(RecordError::Open {
            path: path.display().to_string(),
            message: format!("cannot switch to WAL mode (journal_mode is {mode})"),
        });
    }
    // FULL: each commit syncs the WAL, so what a commit returned is on the disk and a
    // power loss takes only the records not committed yet (NORMAL syncs only at
    // checkpoints: a power cut took the last 20 s of readings, and the outbox sent
    // its acknowledged backlog again). The recorder and the MQTT outbox both open
    // their connections here.
    conn.execute_batch("PRAGMA synchronous = FULL; PRAGMA foreign_keys = OFF;")
        .map_err(err)?;
    // The page cache is the part of the memory that grows with use: cap it (in KiB)
    // so RSS levels off. The writer appends at the right edge of each b-tree; a
    // retention pass reads through old pages once.
    conn.execute_batch(&format!("PRAGMA cache_size = -{PAGE_CACHE_KB};"))
        .map_err(err)?;
    // One statement per multi-row insert size in use, the single-row ones and the
    // outbox queries: more than the default 16 would evict each other.
    conn.set_prepared_statement_cache_capacity(STATEMENT_CACHE);
    conn.execute_batch(SCHEMA).map_err(err)?;
    // Databases recorded before shadow mode lack the column: their jobs were all sent.
    let has_shadow: bool = conn
        .query_row(
            "SELECT COUNT(*) > 0 FROM pragma_table_info('jobs') WHERE name = 'shadow'",
            [],
            |r| r.get(0),
        )
        .map_err(err)?;
    if !has_shadow {
        conn.execute_batch("ALTER TABLE jobs ADD COLUMN shadow INTEGER NOT NULL DEFAULT 0;")
            .map_err(err)?;
    }
    // Databases recorded before a target could report no position hold 0 there
    // instead of NULL (their NOT NULL columns refuse it): rebuilt once, in one
    // transaction, rows kept. Another connection opening meanwhile (the MQTT outbox)
    // waits for it as long as it takes, then finds it done. A rebuild that fails (it
    // needs about three times the table's size free) leaves the old layout: the
    // gateway must start all the same, and `insert` skips the rows it refuses.
    let nc_not_null = |conn: &Connection| -> rusqlite::Result<bool> {
        conn.query_row(
            "SELECT COUNT(*) > 0 FROM pragma_table_info('nc') WHERE name = 'position_mm' AND \"notnull\"",
            [],
            |r| r.get(0),
        )
    };
    // Tried once per file and process: the MQTT outbox's open would try again at once.
    static REBUILD_FAILED: std::sync::Mutex<Vec<std::path::PathBuf>> =
        std::sync::Mutex::new(Vec::new());
    let failed_before = || {
        REBUILD_FAILED
            .lock()
            .is_ok_and(|failed| failed.iter().any(|p| p == path))
    };
    if nc_not_null(&conn).map_err(err)? && !failed_before() {
        if let Err(e) = rebuild_nc(&conn, path, nc_not_null) {
            if let Ok(mut failed) = REBUILD_FAILED.lock() {
                failed.push(path.to_path_buf());
            }
            let _ = conn.execute_batch("ROLLBACK");
            tracing::error!(
                path = %path.display(),
                error = %e,
                "recorder database: the nc table could not be rebuilt to take NC reads without a position; it keeps its old layout and its rows, and reads of targets that report no position or no applied compensation (OPC UA, ADS, S7) are not recorded until a start with about three times the table's size free rebuilds it"
            );
        }
        conn.busy_timeout(BUSY_TIMEOUT).map_err(err)?;
    }
    let version: i64 = conn
        .query_row("PRAGMA user_version", [], |r| r.get(0))
        .map_err(err)?;
    if version != LAYOUT_VERSION {
        conn.execute_batch(&format!("PRAGMA user_version = {LAYOUT_VERSION};"))
            .map_err(err)?;
    }
    Ok(conn)
}

/// Each table (but SQLite's own) with its columns, in order.
fn tables(conn: &Connection) -> rusqlite::Result<Vec<(String, Vec<String>)>> {
    let mut stmt = conn.prepare(
        "SELECT m.name, p.name FROM sqlite_schema m, pragma_table_info(m.name) p
         WHERE m.type = 'table' AND m.name NOT LIKE 'sqlite^_%' ESCAPE '^'
         ORDER BY m.name, p.cid",
    )?;
    let mut tables: Vec<(String, Vec<String>)> = Vec::new();
    let rows = stmt.query_map([], |r| Ok((r.get::<_, String>(0)?, r.get(1)?)))?;
    for row in rows {
        let (table, column) = row?;
        match tables.last_mut() {
            Some((t, columns)) if *t == table => columns.push(column),
            _ => tables.push((table, vec![column])),
        }
    }
    Ok(tables)
}

/// Why the database `conn` has open is not one the recorder can write into: not an
/// SQLite database (or its schema unreadable), another program's tables, or a table of
/// the recorder's without one of its columns (a layout older than this recorder, whose
/// every commit would fail). A new, empty database passes; so does a recording that
/// lacks a whole table or `jobs.shadow` (added since: [`open`] adds them). Reads only
/// the schema, not every page: `PRAGMA quick_check` reads the whole file (about 3 s
/// per GB from the page cache, 20 s per GB from the disk of the test machine), too
/// long for each start and each reload's `validate`.
pub fn check(conn: &Connection) -> Result<(), String> {
    let found = tables(conn).map_err(|e| match e.sqlite_error_code() {
        Some(rusqlite::ErrorCode::NotADatabase) => format!("is not an SQLite database ({e})"),
        _ => format!("its tables cannot be read ({e}): the file is damaged; move it away (the recorder then starts a new one at its path; `sqlite3 FILE .recover` reads what is left of it)"),
    })?;
    if found.is_empty() {
        return Ok(());
    }
    let version: i64 = conn
        .query_row("PRAGMA user_version", [], |r| r.get(0))
        .map_err(|e| format!("its layout version cannot be read ({e})"))?;
    if version > LAYOUT_VERSION {
        return Err(format!(
            "was written by a newer compgate (recorder layout {version}; this build knows up to {LAYOUT_VERSION}): run the newer build on it, or give this one another recorder.path"
        ));
    }
    let reference = Connection::open_in_memory()
        .and_then(|mem| mem.execute_batch(SCHEMA).and_then(|()| tables(&mem)))
        .map_err(|e| format!("the recorder's layout: {e}"))?;
    let ours = |t: &str| reference.iter().any(|(r, _)| r == t);
    if !found.iter().any(|(t, _)| ours(t)) {
        let names: Vec<&str> = found.iter().map(|(t, _)| t.as_str()).collect();
        return Err(format!(
            "is an SQLite database without any of the recorder's tables (it holds {}): another program's file",
            names.join(", ")
        ));
    }
    for (table, columns) in &reference {
        let Some((_, have)) = found.iter().find(|(t, _)| t == table) else {
            continue;
        };
        let missing: Vec<&str> = columns
            .iter()
            // `jobs.shadow` came later: `open` adds it.
            .filter(|c| !(have.contains(c) || (table == "jobs" && *c == "shadow")))
            .map(String::as_str)
            .collect();
        if !missing.is_empty() {
            return Err(format!(
                "table {table} has no column {}: another program's or an older layout, which the recorder cannot write into; move the file away (the recorder starts a new one at its path)",
                missing.join(", ")
            ));
        }
    }
    Ok(())
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

/// Readings per INSERT statement at most: a whole poll cycle of a 64-channel module
/// goes in one statement (one bind-step-reset instead of 64, a third less CPU per
/// reading than a statement per row).
const ROWS_PER_INSERT: usize = 64;
/// Columns of a readings row.
const READING_COLUMNS: usize = 7;

/// What the writer keeps between commits: the channels' ids and the texts of the
/// multi-row inserts.
#[derive(Debug, Default)]
pub struct Statements {
    /// The name table the ids belong to (one per configuration).
    names: Option<Arc<[String]>>,
    /// Database id per channel index, once looked up.
    ids: Vec<Option<i64>>,
    /// `INSERT` texts by row count - 1.
    inserts: Vec<String>,
    /// The newest reading's time, once looked up: a cycle after it meets none.
    newest_ms: Option<i64>,
}

/// What [`insert`] did with the readings it was given besides storing them.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Inserted {
    /// Readings not stored: their channel was held at every millisecond tried.
    pub ignored: u64,
    /// Readings stored some milliseconds after their time, which a reading of their
    /// channel held already (the wall clock set back over recorded time).
    pub shifted: u64,
}

/// How many milliseconds past its time a cycle is moved at most to find one free.
const MAX_SHIFT_MS: i64 = 1000;

impl Statements {
    /// Forgets the channel ids (after a rolled-back transaction that may have
    /// created some).
    pub fn forget_channels(&mut self) {
        self.names = None;
        self.ids.clear();
    }

    fn channel(
        &mut self,
        conn: &Connection,
        names: &Arc<[String]>,
        index: u32,
    ) -> rusqlite::Result<i64> {
        if !self.names.as_ref().is_some_and(|n| Arc::ptr_eq(n, names)) {
            self.names = Some(names.clone());
            self.ids = vec![None; names.len()];
        }
        let i = index as usize;
        if let Some(Some(id)) = self.ids.get(i) {
            return Ok(*id);
        }
        let name = names.get(i).ok_or_else(|| {
            rusqlite::Error::InvalidParameterName(format!("channel {i} of {}", names.len()))
        })?;
        let id = channel_id(conn, name)?;
        if let Some(slot) = self.ids.get_mut(i) {
            *slot = Some(id);
        }
        Ok(id)
    }

    /// The first millisecond from `t_ms` on at which the database holds no reading of
    /// `channel`: a cycle is stored whole at one time.
    fn free_ms(&mut self, tx: &Connection, t_ms: i64, channel: i64) -> rusqlite::Result<i64> {
        let newest_ms = match self.newest_ms {
            Some(n) => n,
            None => tx
                .query_row("SELECT max(t_unix_ms) FROM readings", [], |r| {
                    r.get::<_, Option<i64>>(0)
                })?
                .unwrap_or(i64::MIN),
        };
        if t_ms <= newest_ms {
            let mut held =
                tx.prepare_cached("SELECT 1 FROM readings WHERE t_unix_ms = ?1 AND channel = ?2")?;
            for t in t_ms..=t_ms.saturating_add(MAX_SHIFT_MS) {
                if !held.exists(params![t, channel])? {
                    self.newest_ms = Some(newest_ms.max(t));
                    return Ok(t);
                }
            }
            // None free: the insert at its own time stores nothing, and counts it.
        }
        self.newest_ms = Some(newest_ms.max(t_ms));
        Ok(t_ms)
    }

    fn insert_sql(&mut self, rows: usize) -> &str {
        while self.inserts.len() < rows {
            let n = self.inserts.len() + 1;
            let mut sql = String::from(
                "INSERT OR IGNORE INTO readings(t_unix_ms, channel, raw, unfiltered_degc, value_degc, quality, reason) VALUES ",
            );
            for k in 0..n {
                sql.push_str(if k == 0 {
                    "(?,?,?,?,?,?,?)"
                } else {
                    ",(?,?,?,?,?,?,?)"
                });
            }
            self.inserts.push(sql);
        }
        &self.inserts[rows - 1]
    }
}

/// Inserts `batch` in one transaction.
///
/// (time, channel) is the readings' key (one b-tree, no separate index). A cycle
/// whose channel the database holds at its millisecond already (the wall clock set
/// back over recorded time) is stored at the next millisecond free: neither reading
/// is lost, and the one recorded first is never replaced. One that finds none within
/// a second is not stored, and counted.
pub fn insert(
    conn: &mut Connection,
    statements: &mut Statements,
    batch: &[Record],
) -> rusqlite::Result<Inserted> {
    // IMMEDIATE: the write lock is taken at BEGIN, where SQLite waits out the busy
    // timeout. A deferred transaction whose first statement reads (the channel id
    // lookup) gets SQLITE_BUSY at once when another connection (the MQTT outbox)
    // writes, without waiting.
    let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate)?;
    let mut done = Inserted::default();
    let mut ids: Vec<i64> = Vec::with_capacity(ROWS_PER_INSERT);
    for rec in batch {
        match rec {
            Record::Cycle {
                t_unix_ms,
                names,
                rows,
            } => {
                let Some(first) = rows.first() else {
                    continue;
                };
                let probe = statements.channel(&tx, names, first.channel)?;
                let given_ms = *t_unix_ms;
                let t_unix_ms = statements.free_ms(&tx, given_ms, probe)?;
                if t_unix_ms != given_ms {
                    done.shifted += rows.len() as u64;
                }
                for chunk in rows.chunks(ROWS_PER_INSERT) {
                    ids.clear();
                    for row in chunk {
                        ids.push(statements.channel(&tx, names, row.channel)?);
                    }
                    let mut stmt = tx.prepare_cached(statements.insert_sql(chunk.len()))?;
                    for (k, (row, id)) in chunk.iter().zip(&ids).enumerate() {
                        let at = k * READING_COLUMNS;
                        stmt.raw_bind_parameter(at + 1, t_unix_ms)?;
                        stmt.raw_bind_parameter(at + 2, id)?;
                        stmt.raw_bind_parameter(at + 3, row.raw)?;
                        stmt.raw_bind_parameter(at + 4, row.unfiltered_degc)?;
                        stmt.raw_bind_parameter(at + 5, row.value_degc)?;
                        stmt.raw_bind_parameter(at + 6, row.quality)?;
                        stmt.raw_bind_parameter(at + 7, row.reason)?;
                    }
                    let stored = stmt.raw_execute()?;
                    done.ignored += chunk.len().saturating_sub(stored) as u64;
                }
            }
            Record::Job {
                t_unix_ms,
                axis,
                params: p,
                job_id,
                elapsed_ms,
                error,
                shadow,
            } => {
                let ok = error.is_none() && !shadow;
                tx.prepare_cached("INSERT INTO jobs(t_unix_ms, axis, sd43900_mm, sd43910, sd43920_mm, ok, job_id, elapsed_ms, error, shadow) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10)")?
                    .execute(params![t_unix_ms, axis, p.k0_mm, p.tan_beta, p.p0_mm, ok, job_id, elapsed_ms, error, shadow])?;
            }
            Record::Nc {
                t_unix_ms,
                axis,
                position_mm,
                applied_comp_mm,
                params: p,
            } => {
                // OR IGNORE: a table of the layout before that could not be rebuilt
                // (`open`) refuses a NULL position; that row is skipped, not the commit.
                tx.prepare_cached("INSERT OR IGNORE INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)")?
                    .execute(params![t_unix_ms, axis, position_mm, applied_comp_mm, p.k0_mm, p.tan_beta, p.p0_mm])?;
            }
            Record::Outbox { topic, payload } => {
                tx.prepare_cached("INSERT INTO mqtt_outbox(topic, payload) VALUES (?1, ?2)")?
                    .execute(params![topic, payload])?;
            }
        }
    }
    tx.commit()?;
    Ok(done)
}

/// Rows deleted by retention.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Deleted {
    /// Readings.
    pub readings: u64,
    /// NC jobs.
    pub jobs: u64,
    /// NC positions.
    pub nc: u64,
    /// MQTT messages never sent.
    pub outbox: u64,
}

impl Deleted {
    /// Whether nothing was deleted.
    pub fn is_empty(&self) -> bool {
        *self == Deleted::default()
    }
}

impl std::ops::AddAssign for Deleted {
    fn add_assign(&mut self, o: Deleted) {
        self.readings += o.readings;
        self.jobs += o.jobs;
        self.nc += o.nc;
        self.outbox += o.outbox;
    }
}

/// Rows one retention delete takes at most, and free pages one step of giving them
/// back moves: each is its own transaction, with a checkpoint after it, so the WAL
/// holds only a few MB however much a pass deletes. One delete of a month took a WAL
/// as big as the month, and on a nearly full disk no pass could ever succeed.
const DELETE_CHUNK_ROWS: i64 = 10_000;
const VACUUM_CHUNK_PAGES: i64 = 256;

/// Copies the WAL into the database without waiting for anyone, so that the next
/// transaction writes the WAL from its start again instead of growing it.
fn checkpoint_passive(conn: &Connection) -> rusqlite::Result<()> {
    conn.query_row("PRAGMA wal_checkpoint(PASSIVE)", [], |_| Ok(()))
}

/// Deletes readings, jobs and NC rows older than `cutoff_unix_ms`, oldest first, in
/// chunks of about [`DELETE_CHUNK_ROWS`]; after each, only while `go_on`.
pub fn delete_before(
    conn: &Connection,
    cutoff_unix_ms: i64,
    go_on: &dyn Fn() -> bool,
) -> rusqlite::Result<Deleted> {
    let delete = |t: &str| -> rusqlite::Result<u64> {
        let mut total = 0;
        loop {
            // The time of the chunk's last row; rows of one time go together, so a
            // time with more rows than a chunk (every channel's) is taken whole.
            let (first, nth): (Option<i64>, Option<i64>) = conn.query_row(
                &format!(
                    "SELECT (SELECT min(t_unix_ms) FROM {t}), \
                     (SELECT t_unix_ms FROM {t} WHERE t_unix_ms < ?1 ORDER BY t_unix_ms LIMIT 1 OFFSET ?2)"
                ),
                [cutoff_unix_ms, DELETE_CHUNK_ROWS],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )?;
            let cut = match (first, nth) {
                (Some(first), Some(nth)) => nth.max(first + 1),
                _ => cutoff_unix_ms,
            };
            total += conn.execute(&format!("DELETE FROM {t} WHERE t_unix_ms < ?1"), [cut])? as u64;
            if cut >= cutoff_unix_ms || !go_on() {
                return Ok(total);
            }
            checkpoint_passive(conn)?;
        }
    };
    Ok(Deleted {
        readings: delete("readings")?,
        jobs: delete("jobs")?,
        nc: delete("nc")?,
        outbox: 0,
    })
}

/// Free pages are given back to the file system once they are this share of the
/// file or more. Below it they are left for the next commits to fill: giving them
/// back moves as many pages of the newest records into their place, and a pass
/// every minute would copy each minute's records once more on the disk (flash
/// wear), to shrink a file that grows again at once.
const RELEASE_FREE_SHARE: f64 = 0.1;

/// Gives the database's free pages back to the file system, [`VACUUM_CHUNK_PAGES`]
/// at a time, after the first only while `go_on`, when they are at least
/// [`RELEASE_FREE_SHARE`] of the file. Each step of `PRAGMA incremental_vacuum`
/// frees one page: run once (as `execute_batch` does), it gave back 4 KiB a pass.
pub fn release_free_pages(conn: &Connection, go_on: &dyn Fn() -> bool) -> rusqlite::Result<()> {
    let free = || conn.query_row("PRAGMA freelist_count", [], |r| r.get::<_, i64>(0));
    let pages: i64 = conn.query_row("PRAGMA page_count", [], |r| r.get(0))?;
    let mut left = free()?;
    if (left as f64) < RELEASE_FREE_SHARE * pages as f64 {
        return Ok(());
    }
    while left > 0 {
        let mut stmt = conn.prepare(&format!("PRAGMA incremental_vacuum({VACUUM_CHUNK_PAGES})"))?;
        let mut rows = stmt.query([])?;
        while rows.next()?.is_some() {}
        drop(rows);
        drop(stmt);
        checkpoint_passive(conn)?;
        let now = free()?;
        if now >= left || !go_on() {
            break;
        }
        left = now;
    }
    Ok(())
}

/// MQTT messages waiting in the outbox.
pub fn outbox_len(conn: &Connection) -> rusqlite::Result<u64> {
    let n: i64 = conn.query_row("SELECT count(*) FROM mqtt_outbox", [], |r| r.get(0))?;
    Ok(n.unsigned_abs())
}

/// Deletes the `n` oldest MQTT messages of the outbox; returns how many went.
pub fn delete_oldest_outbox(conn: &Connection, n: u64) -> rusqlite::Result<u64> {
    let n = conn.execute(
        "DELETE FROM mqtt_outbox WHERE id IN (SELECT id FROM mqtt_outbox ORDER BY id LIMIT ?1)",
        [i64::try_from(n).unwrap_or(i64::MAX)],
    )?;
    Ok(n as u64)
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
