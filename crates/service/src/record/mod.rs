//! Durable recording: every poll cycle's raw and filtered readings with their quality,
//! every NC job with its result and the NC's position, into SQLite in WAL mode.
//!
//! The control loop hands records to a bounded queue ([`RecordSender`]) and never
//! waits: when the queue is full the record is dropped and counted. A writer thread
//! commits the queue in one transaction every `commit_interval_s` (a crash loses at
//! most that much; `synchronous = NORMAL` in WAL mode survives a killed process) and
//! applies retention by age and by size. A failed commit (disk full) drops its batch,
//! is counted and logged, and the writer carries on. A database file deleted or
//! replaced while open (its path no longer names the file the writer has open) is
//! logged and created again at its path at the next commit; what was committed to
//! the deleted file is gone, what comes after is not.
//!
//! The same database holds the MQTT outbox, written in the same transaction as the
//! readings, so what was recorded is also what will be published.

pub mod export;
mod schema;

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, SyncSender, TryRecvError, TrySendError};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use rusqlite::{params, Connection};

use compgate_core::channel::Quality;
use compgate_core::comp::CompParams;
use compgate_gateway::config::RecorderConfig;
use compgate_gateway::nc::{JobReport, NcError};
use compgate_gateway::runtime::{Observer, SampleReadings, Status};

pub use schema::open;

/// Errors of the recorder.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The database could not be opened or prepared.
    #[error("recorder database {path}: {message}")]
    Open {
        /// The database file.
        path: String,
        /// What failed.
        message: String,
    },
    /// `recorder.path` names a database the gateway cannot create or write.
    #[error("recorder.path: {path}: {message}")]
    Path {
        /// The database file.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// Another process records into the database.
    #[error("recorder database {path}: another gateway records into it (it holds {lock}); give each gateway its own recorder.path")]
    InUse {
        /// The database file.
        path: String,
        /// The lock file the other process holds.
        lock: String,
    },
    /// A query failed.
    #[error("recorder database: {0}")]
    Sqlite(#[from] rusqlite::Error),
}

/// Milliseconds since the Unix epoch, now.
pub fn now_unix_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// Quality as stored: 0 good, 1 uncertain, 2 bad, with the reason apart.
pub fn quality_code(q: &Quality) -> (u8, Option<&'static str>) {
    match q {
        Quality::Good => (0, None),
        Quality::Uncertain(r) => (1, Some(r.as_str())),
        Quality::Bad(r) => (2, Some(r.as_str())),
    }
}

/// One channel's reading of one poll cycle.
#[derive(Debug, Clone)]
pub struct Row {
    /// Channel: index into the cycle's `names`.
    pub channel: u32,
    /// Raw register value. SQLite stores a NaN as NULL, like `None`: the reason
    /// (`not finite` against `comm` and the like) tells them apart.
    pub raw: Option<f64>,
    /// Temperature before filtering, degC.
    pub unfiltered_degc: Option<f64>,
    /// Filtered temperature, degC.
    pub value_degc: Option<f64>,
    /// 0 good, 1 uncertain, 2 bad.
    pub quality: u8,
    /// Why not good.
    pub reason: Option<&'static str>,
}

/// What the writer stores.
#[derive(Debug, Clone)]
pub enum Record {
    /// One device poll cycle.
    Cycle {
        /// Time, ms since the Unix epoch.
        t_unix_ms: i64,
        /// Every channel name of the configuration, by index; one shared table per
        /// configuration, so a cycle costs one reference count, not one per channel.
        names: Arc<[String]>,
        /// Its channels' readings.
        rows: Vec<Row>,
    },
    /// One NC job and its result.
    Job {
        /// Time the result arrived, ms since the Unix epoch.
        t_unix_ms: i64,
        /// Axis name.
        axis: String,
        /// Parameters sent.
        params: CompParams,
        /// Job id, when the job got that far.
        job_id: Option<u16>,
        /// Duration of the job, ms.
        elapsed_ms: Option<f64>,
        /// `None` when the NC accepted and the read-back matched.
        error: Option<String>,
        /// Shadow mode: computed, not sent to the NC (`job_id`, `elapsed_ms` and
        /// `error` are `None`).
        shadow: bool,
    },
    /// The NC's state of one axis.
    Nc {
        /// Time, ms since the Unix epoch.
        t_unix_ms: i64,
        /// Axis name.
        axis: String,
        /// Actual position, mm.
        position_mm: f64,
        /// Compensation applied, mm.
        applied_comp_mm: f64,
        /// Parameters the NC holds.
        params: CompParams,
    },
    /// An MQTT message waiting for the broker.
    Outbox {
        /// Topic.
        topic: String,
        /// JSON payload.
        payload: String,
    },
}

/// Counters of the recorder, shared with metrics.
#[derive(Debug, Default)]
pub struct RecorderStats {
    /// Records dropped because the queue was full.
    pub dropped_queue: AtomicU64,
    /// Records lost because a commit failed (disk full, I/O error).
    pub dropped_write: AtomicU64,
    /// Records committed.
    pub written: AtomicU64,
    /// Commits that failed.
    pub failed_commits: AtomicU64,
    /// Times the database file was found deleted or replaced under the writer and
    /// opened again at its path.
    pub reopened: AtomicU64,
    /// Readings not stored because the database already held one of the same
    /// channel at the same millisecond (the wall clock set back); the one recorded
    /// first is kept.
    pub duplicate_readings: AtomicU64,
}

/// What the queue's ends share besides the queue: how full it is and who to wake.
#[derive(Debug)]
struct QueueShared {
    /// Records queued and not yet taken by the writer.
    pending: AtomicUsize,
    /// At this many pending records the writer is woken before its commit is due.
    wake_at: usize,
    /// The writer thread, set once it runs.
    writer: OnceLock<std::thread::Thread>,
}

/// The control loop's end of the queue. Cloneable; never blocks.
#[derive(Debug, Clone)]
pub struct RecordSender {
    tx: SyncSender<Record>,
    stats: Arc<RecorderStats>,
    shared: Arc<QueueShared>,
}

impl RecordSender {
    /// Queues `record`; drops and counts it when the queue is full.
    pub fn send(&self, record: Record) {
        // Counted before it is queued, so the writer never takes more than counted.
        let n = self.shared.pending.fetch_add(1, Ordering::Relaxed) + 1;
        match self.tx.try_send(record) {
            Ok(()) => {
                // The writer sleeps until its commit is due (waking it for every
                // record cost as much CPU as the inserts); only a queue filling up
                // wakes it early.
                if n == self.shared.wake_at {
                    if let Some(t) = self.shared.writer.get() {
                        t.unpark();
                    }
                }
            }
            Err(TrySendError::Full(_)) => {
                self.shared.pending.fetch_sub(1, Ordering::Relaxed);
                let n = self.stats.dropped_queue.fetch_add(1, Ordering::Relaxed) + 1;
                // Log the first drop and then every 1000th, not every one.
                if n == 1 || n.is_multiple_of(1000) {
                    tracing::warn!(dropped = n, "recorder queue full: records dropped");
                }
            }
            Err(TrySendError::Disconnected(_)) => {
                self.shared.pending.fetch_sub(1, Ordering::Relaxed);
                self.stats.dropped_write.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// The counters.
    pub fn stats(&self) -> &Arc<RecorderStats> {
        &self.stats
    }
}

/// The database path: `path` as configured, relative ones under `$STATE_DIRECTORY`
/// (systemd's `StateDirectory=`) when set.
pub fn resolve_path(path: &str) -> PathBuf {
    let p = Path::new(path);
    if p.is_absolute() {
        return p.to_path_buf();
    }
    match state_directory() {
        Some(dir) => dir.join(p),
        None => p.to_path_buf(),
    }
}

/// `$STATE_DIRECTORY`: systemd may pass several, separated by ':'; the first is ours.
fn state_directory() -> Option<PathBuf> {
    let dirs = std::env::var_os("STATE_DIRECTORY")?;
    let dirs = dirs.to_string_lossy();
    Some(PathBuf::from(dirs.split(':').next().unwrap_or("")))
}

/// Why the database at `path` (as [`resolve_path`] gives it) will not work as meant
/// under the unit: outside `$STATE_DIRECTORY` (when set), where `ProtectSystem=strict`,
/// `ProtectHome=yes` and `PrivateTmp=yes` make every place read-only, hidden or
/// private to the service (a database in /tmp would be lost at every stop). A
/// warning, not an error: a drop-in may grant the place with `ReadWritePaths=`.
pub fn outside_state_directory(path: &Path) -> Option<String> {
    let state = state_directory()?;
    let inside = path.starts_with(&state)
        && !path
            .components()
            .any(|c| c == std::path::Component::ParentDir);
    (!inside).then(|| {
        format!(
            "the database {} is outside the state directory {} ($STATE_DIRECTORY): under the unit (ProtectSystem=strict, ProtectHome=yes, PrivateTmp=yes) it is read-only, hidden or private to the service; give a path relative to the state directory, e.g. path = \"compgate.db\"",
            path.display(),
            state.display()
        )
    })
}

/// The running recorder: the writer thread and the queue's sending end.
#[derive(Debug)]
pub struct Recorder {
    sender: RecordSender,
    thread: Option<std::thread::JoinHandle<()>>,
    path: PathBuf,
    outbox: Arc<tokio::sync::Notify>,
    /// The database's lock, held while the recorder lives: its file is removed and
    /// the lock dropped after `Drop::drop` joined the writer, so after its last commit.
    lock: Option<(std::fs::File, PathBuf)>,
}

/// Checks, creating nothing, that the recorder can create or write its database at
/// `path` (as [`resolve_path`] gives it): its directory exists and is writable
/// (SQLite creates the `-wal` and `-shm` files there, the recorder its lock file),
/// and the database, if it exists, is a writable file. `validate` runs it, so a
/// config that `run` would refuse does not pass. A problem names the environment
/// variable that set `recorder.path`, if one did.
pub fn check_path(path: &Path) -> Result<(), RecordError> {
    let problem = |message: String| RecordError::Path {
        path: path.display().to_string(),
        message: message + &compgate_gateway::config::env_note("recorder.path"),
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    match std::fs::metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(problem(format!(
                "the directory {} does not exist (the recorder creates the database file, not its directory)",
                dir.display()
            )))
        }
        Err(e) => return Err(problem(format!("the directory {}: {e}", dir.display()))),
        Ok(m) if !m.is_dir() => {
            return Err(problem(format!("{} is not a directory", dir.display())))
        }
        Ok(_) => {}
    }
    if let Ok(m) = std::fs::metadata(path) {
        if m.is_dir() {
            return Err(problem("is a directory, not a database file".into()));
        }
        writable(path).map_err(|e| problem(format!("the database is not writable: {e}")))?;
    }
    writable(dir).map_err(|e| {
        problem(format!(
            "the directory {} is not writable (the database, its -wal and -shm files are created there): {e}",
            dir.display()
        ))
    })
}

/// Whether this process may write `path` (permissions, ACLs, a read-only mount),
/// asked without opening it.
fn writable(path: &Path) -> std::io::Result<()> {
    use rustix::fs::{accessat, Access, AtFlags, CWD};
    accessat(CWD, path, Access::WRITE_OK, AtFlags::EACCESS).map_err(std::io::Error::from)
}

/// Takes the lock that makes this process the database's only recorder: an
/// advisory lock on `<db>.lock`, which the kernel releases when the process ends,
/// however it ends. Two gateways recording into one database would mix their rows
/// with nothing to tell them apart. Readers (`export`) do not take it.
fn lock(path: &Path) -> Result<(std::fs::File, PathBuf), RecordError> {
    let lock_path = with_suffix(path, ".lock");
    let err = |e: std::io::Error| RecordError::Open {
        path: path.display().to_string(),
        message: format!("lock file {}: {e}", lock_path.display()),
    };
    loop {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&lock_path)
            .map_err(err)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                return Err(RecordError::InUse {
                    path: path.display().to_string(),
                    lock: lock_path.display().to_string(),
                })
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(err(e)),
        }
        // A recorder that finished removes its lock file: if it did so between our
        // open and our lock, we hold a file nobody else finds. Lock the one there now.
        let held = file.metadata().map_err(err)?;
        if file_id(&lock_path) == Some((held.dev(), held.ino())) {
            return Ok((file, lock_path));
        }
    }
}

impl Recorder {
    /// Checks the path, takes the database's lock, opens (creating if needed) the
    /// database and starts the writer thread.
    pub fn start(cfg: &RecorderConfig) -> Result<Self, RecordError> {
        let path = resolve_path(&cfg.path);
        check_path(&path)?;
        let lock = lock(&path)?;
        let conn = open(&path)?;
        let queue = usize::try_from(cfg.queue_cycles).unwrap_or(usize::MAX);
        let (tx, rx) = mpsc::sync_channel(queue);
        let stats = Arc::new(RecorderStats::default());
        let shared = Arc::new(QueueShared {
            pending: AtomicUsize::new(0),
            // Half full: the other half takes what arrives while the writer wakes.
            wake_at: (queue / 2).max(1),
            writer: OnceLock::new(),
        });
        let outbox = Arc::new(tokio::sync::Notify::new());
        let writer = Writer {
            files: DbFiles::at(&path),
            conn: Some(conn),
            path: path.clone(),
            commit_interval: compgate_gateway::config::secs(cfg.commit_interval_s),
            retention_interval: compgate_gateway::config::secs(cfg.retention_interval_s),
            retention_ms: (cfg.retention_days * 86_400_000.0) as i64,
            max_bytes: (cfg.max_size_mb * 1024.0 * 1024.0) as i64,
            stats: stats.clone(),
            shared: shared.clone(),
            outbox: outbox.clone(),
            statements: schema::Statements::default(),
        };
        let thread = std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || writer.run(rx))
            .map_err(|e| RecordError::Open {
                path: path.display().to_string(),
                message: format!("cannot start the writer thread: {e}"),
            })?;
        let _ = shared.writer.set(thread.thread().clone());
        tracing::info!(path = %path.display(), "recording into SQLite (WAL)");
        Ok(Recorder {
            sender: RecordSender { tx, stats, shared },
            thread: Some(thread),
            path,
            outbox,
            lock: Some(lock),
        })
    }

    /// A sending end of the queue.
    pub fn sender(&self) -> RecordSender {
        self.sender.clone()
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Notified after every commit that added MQTT outbox messages, so the publisher
    /// reads the outbox when there is something new instead of polling it.
    pub fn outbox_notify(&self) -> Arc<tokio::sync::Notify> {
        self.outbox.clone()
    }

    /// The observer that records what the control loop sees.
    pub fn observer(&self) -> RecordObserver {
        RecordObserver {
            tx: self.sender(),
            clock: None,
            interval: Duration::ZERO,
            next_due: Vec::new(),
            nc_reads: Vec::new(),
        }
    }

    /// The observer with its own clock (ms since the Unix epoch): a simulation that
    /// runs hours in seconds stamps its records with the simulated instant.
    pub fn observer_with_clock(&self, clock: Clock) -> RecordObserver {
        RecordObserver {
            tx: self.sender(),
            clock: Some(clock),
            interval: Duration::ZERO,
            next_due: Vec::new(),
            nc_reads: Vec::new(),
        }
    }

    /// Closes the queue and waits for the writer's last commit.
    pub fn finish(mut self) {
        self.join();
    }

    fn join(&mut self) {
        // Replace our sender so the writer sees the queue close once every other
        // sender (observers) is gone too.
        let (dead, _) = mpsc::sync_channel(0);
        self.sender.tx = dead;
        if let Some(t) = self.thread.take() {
            // It sleeps until its next commit: wake it to see the queue closed.
            t.thread().unpark();
            let _ = t.join();
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.join();
        // Still locked while removed, so no other recorder can take the file in between.
        if let Some((_file, path)) = self.lock.take() {
            let _ = std::fs::remove_file(path);
        }
    }
}

/// When a periodic record or message is due: on a grid of the interval from the
/// first one, so the mean rate is the interval's. The ticks that offer it (polls,
/// status ticks) jitter by microseconds; measured from the last one taken, a tick a
/// little early waited a whole further tick (1 s, 2 s, 1 s, ... with ticks at the
/// interval), so a tick up to a tenth of the interval early counts. After a gap of a
/// whole interval (a device away) the next tick starts a new grid, with no burst to
/// catch up.
#[derive(Debug, Clone, Copy, Default)]
pub struct Grid {
    next: Option<Instant>,
}

impl Grid {
    /// Whether the tick at `now` is due; if so, schedules the next one.
    pub fn due(&mut self, interval: Duration, now: Instant) -> bool {
        match self.next {
            Some(next) if now + interval / 10 < next => false,
            Some(next) => {
                let following = next + interval;
                self.next = Some(if following <= now {
                    now + interval
                } else {
                    following
                });
                true
            }
            None => {
                self.next = Some(now + interval);
                true
            }
        }
    }
}

/// A clock of the recorder: ms since the Unix epoch.
pub type Clock = Arc<dyn Fn() -> i64 + Send + Sync>;

/// Records cycles, jobs and the NC's position from the control loop.
pub struct RecordObserver {
    tx: RecordSender,
    /// `None`: the wall clock.
    clock: Option<Clock>,
    /// Least time between two recorded cycles of a device.
    interval: Duration,
    /// Per device index: when its next cycle is due to be recorded.
    next_due: Vec<Grid>,
    /// Per axis: the count of NC reads last recorded.
    nc_reads: Vec<u64>,
}

impl std::fmt::Debug for RecordObserver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecordObserver")
            .field("tx", &self.tx)
            .field("clock", &self.clock.as_ref().map(|_| "simulated"))
            .field("interval", &self.interval)
            .finish()
    }
}

impl RecordObserver {
    fn now_unix_ms(&self) -> i64 {
        self.clock.as_ref().map_or_else(now_unix_ms, |c| c())
    }

    /// Records a device's cycle at most every `interval` (zero, the default: every
    /// cycle).
    pub fn with_interval(mut self, interval: Duration) -> Self {
        self.interval = interval;
        self
    }

    /// Whether the cycle of `device` at `now` is one to record.
    fn due(&mut self, device: usize, now: Instant) -> bool {
        if self.interval.is_zero() {
            return true;
        }
        if self.next_due.len() <= device {
            self.next_due.resize(device + 1, Grid::default());
        }
        self.next_due[device].due(self.interval, now)
    }
}

impl Observer for RecordObserver {
    fn on_sample(&mut self, readings: &SampleReadings) {
        if !self.due(readings.device, Instant::now()) {
            return;
        }
        let t_unix_ms = self.now_unix_ms();
        let mut rows = Vec::with_capacity(readings.channels.len());
        rows.extend(readings.channels.iter().filter_map(|c| {
            let r = &c.reading;
            let (quality, reason) = quality_code(&r.quality);
            Some(Row {
                channel: u32::try_from(c.channel).ok()?,
                raw: r.raw,
                unfiltered_degc: r.unfiltered_degc,
                value_degc: r.value_degc,
                quality,
                reason,
            })
        }));
        self.tx.send(Record::Cycle {
            t_unix_ms,
            names: readings.channel_names.clone(),
            rows,
        });
    }

    fn on_job(&mut self, axis: &str, params: &CompParams, result: &Result<JobReport, NcError>) {
        let (job_id, elapsed_ms, error) = match result {
            Ok(r) => (Some(r.job_id), Some(r.elapsed.as_secs_f64() * 1e3), None),
            Err(e) => (None, None, Some(e.to_string())),
        };
        self.tx.send(Record::Job {
            t_unix_ms: self.now_unix_ms(),
            axis: axis.to_string(),
            params: *params,
            job_id,
            elapsed_ms,
            error,
            shadow: false,
        });
    }

    fn on_shadow(&mut self, axis: &str, params: &CompParams) {
        self.tx.send(Record::Job {
            t_unix_ms: now_unix_ms(),
            axis: axis.to_string(),
            params: *params,
            job_id: None,
            elapsed_ms: None,
            error: None,
            shadow: true,
        });
    }

    fn on_status(&mut self, status: &Status) {
        let t_unix_ms = self.now_unix_ms();
        // One row per read of the NC, not per status update.
        self.nc_reads.resize(status.axes.len(), 0);
        for (a, recorded) in status.axes.iter().zip(&mut self.nc_reads) {
            if a.nc_reads == *recorded {
                continue;
            }
            *recorded = a.nc_reads;
            if let Some(nc) = &a.nc {
                self.tx.send(Record::Nc {
                    t_unix_ms,
                    axis: a.name.clone(),
                    position_mm: nc.position_mm,
                    applied_comp_mm: nc.applied_comp_mm,
                    params: nc.thermal(),
                });
            }
        }
    }
}

/// (device, inode) of the file at `path`; `None` when there is none.
pub(crate) fn file_id(path: &Path) -> Option<(u64, u64)> {
    std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
}

/// `path` with `suffix` appended to its file name, as SQLite names its `-wal` and
/// `-shm` files.
fn with_suffix(path: &Path, suffix: &str) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(suffix);
    PathBuf::from(name)
}

/// Which files the writer's connection has open, taken when it opened them: the
/// path naming another file (or none) means the database was deleted or replaced
/// under it, and every later commit would go to a file nobody can open again.
#[derive(Debug, Clone, Copy)]
pub(crate) struct DbFiles {
    pub(crate) db: Option<(u64, u64)>,
    pub(crate) wal: Option<(u64, u64)>,
    pub(crate) shm: Option<(u64, u64)>,
}

impl DbFiles {
    pub(crate) fn at(path: &Path) -> Self {
        DbFiles {
            db: file_id(path),
            wal: file_id(&with_suffix(path, "-wal")),
            shm: file_id(&with_suffix(path, "-shm")),
        }
    }
}

struct Writer {
    /// `None` while the database cannot be opened again after it vanished.
    conn: Option<Connection>,
    /// The database file.
    path: PathBuf,
    /// What `conn` has open.
    files: DbFiles,
    commit_interval: Duration,
    retention_interval: Duration,
    retention_ms: i64,
    max_bytes: i64,
    stats: Arc<RecorderStats>,
    shared: Arc<QueueShared>,
    outbox: Arc<tokio::sync::Notify>,
    statements: schema::Statements,
}

impl Writer {
    fn run(mut self, rx: mpsc::Receiver<Record>) {
        let mut batch: Vec<Record> = Vec::new();
        let mut next_commit = Instant::now() + self.commit_interval;
        let mut next_retention = Instant::now();
        loop {
            // Sleep until the commit is due; a filling queue or the recorder's end
            // unparks earlier, and the commit comes early then (as it does after a
            // rare spurious wake-up: one more commit, nothing lost).
            let wait = next_commit.saturating_duration_since(Instant::now());
            if !wait.is_zero() {
                std::thread::park_timeout(wait);
            }
            let mut closed = false;
            let mut taken = 0;
            loop {
                match rx.try_recv() {
                    Ok(r) => {
                        batch.push(r);
                        taken += 1;
                    }
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Disconnected) => {
                        closed = true;
                        break;
                    }
                }
            }
            self.shared.pending.fetch_sub(taken, Ordering::Relaxed);
            let now = Instant::now();
            // After taking the batch: a record sent after the file was deleted is
            // never committed to the deleted file.
            self.reopen_if_gone();
            self.commit(&mut batch);
            next_commit = now + self.commit_interval;
            if now >= next_retention || closed {
                if let Err(e) = self.retention() {
                    tracing::warn!(error = %e, "recorder retention pass failed");
                }
                next_retention = now + self.retention_interval;
            }
            if closed {
                break;
            }
        }
        // A clean stop leaves no WAL behind.
        if let Some(conn) = &self.conn {
            let _ = conn.query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |_| Ok(()));
        }
        tracing::info!("recorder stopped");
    }

    /// Opens the database again when its file was deleted or replaced (one `stat` a
    /// commit), or when opening it again failed before.
    fn reopen_if_gone(&mut self) {
        if self.conn.is_some() && file_id(&self.path) == self.files.db {
            return;
        }
        let first = self.conn.is_some();
        if let Some(conn) = self.conn.take() {
            let n = self.stats.reopened.fetch_add(1, Ordering::Relaxed) + 1;
            tracing::error!(path = %self.path.display(), reopened = n, "recorder database deleted or replaced while the gateway runs: what was committed to it is lost; creating it again at its path");
            // Closed before the new one opens: SQLite's last connection to a database
            // removes its -wal and -shm files by name, which would be the new ones.
            drop(conn);
            // Another connection (the MQTT outbox) may still hold the old database,
            // and then its -wal and -shm stay at the path: opened with the new file,
            // SQLite would replay the old WAL into it.
            for (suffix, id) in [("-wal", self.files.wal), ("-shm", self.files.shm)] {
                let stale = with_suffix(&self.path, suffix);
                if id.is_some() && file_id(&stale) == id {
                    let _ = std::fs::remove_file(&stale);
                }
            }
            // Channel ids of the old database.
            self.statements.forget_channels();
        }
        match open(&self.path) {
            Ok(conn) => {
                self.files = DbFiles::at(&self.path);
                self.conn = Some(conn);
                tracing::info!(path = %self.path.display(), "recording into SQLite (WAL) again");
            }
            // Tried again every commit; the dropped batches are counted and logged.
            Err(e) if first => {
                tracing::error!(error = %e, "recorder database cannot be created again: records are dropped until it can")
            }
            Err(_) => {}
        }
    }

    fn commit(&mut self, batch: &mut Vec<Record>) {
        if batch.is_empty() {
            return;
        }
        let n = batch.len() as u64;
        let outbox = batch.iter().any(|r| matches!(r, Record::Outbox { .. }));
        let result = match self.conn.as_mut() {
            Some(conn) => {
                schema::insert(conn, &mut self.statements, batch).map_err(RecordError::from)
            }
            None => Err(RecordError::Open {
                path: self.path.display().to_string(),
                message: "deleted while open and not created again".into(),
            }),
        };
        match result {
            Ok(ignored) => {
                self.stats.written.fetch_add(n, Ordering::Relaxed);
                if ignored > 0 {
                    let before = self
                        .stats
                        .duplicate_readings
                        .fetch_add(ignored, Ordering::Relaxed);
                    // The first and then one line per 1000 more, not one per commit.
                    if before == 0 || before / 1000 != (before + ignored) / 1000 {
                        tracing::warn!(duplicates = before + ignored, "recorder: readings not stored, the database already holds their channel at the same millisecond (the wall clock set back?); the ones recorded first are kept");
                    }
                }
                if outbox {
                    self.outbox.notify_one();
                }
            }
            Err(e) => {
                // Channel ids looked up in the rolled-back transaction are gone.
                self.statements.forget_channels();
                self.stats.dropped_write.fetch_add(n, Ordering::Relaxed);
                let failed = self.stats.failed_commits.fetch_add(1, Ordering::Relaxed) + 1;
                if failed == 1 || failed.is_multiple_of(100) {
                    tracing::error!(error = %e, records = n, failed_commits = failed, "recorder commit failed: batch dropped, the gateway carries on");
                }
            }
        }
        batch.clear();
    }

    fn retention(&mut self) -> Result<(), RecordError> {
        let Some(conn) = &self.conn else {
            return Ok(());
        };
        let cutoff = now_unix_ms() - self.retention_ms;
        schema::delete_before(conn, cutoff)?;
        // Oldest tenth of the time range at a time until the data fits.
        for _ in 0..10 {
            let used = schema::data_bytes(conn)?;
            if used <= self.max_bytes {
                break;
            }
            let Some((first, last)) = schema::time_range(conn)? else {
                break;
            };
            // Never the newest records: a limit below the schema's own pages would
            // otherwise empty the database pass after pass.
            if last <= first {
                break;
            }
            let cut = first + ((last - first) / 10).max(1);
            tracing::info!(
                used_bytes = used,
                max_bytes = self.max_bytes,
                "recorder over its size: deleting the oldest records"
            );
            schema::delete_before(conn, cut)?;
        }
        conn.execute_batch("PRAGMA incremental_vacuum;")?;
        let _ = conn.query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |_| Ok(()));
        Ok(())
    }
}

/// Readings, jobs and NC rows, counted (for tests and `export`).
pub fn counts(conn: &Connection) -> Result<(i64, i64, i64), RecordError> {
    let c = |t: &str| -> Result<i64, RecordError> {
        Ok(
            conn.query_row(&format!("SELECT count(*) FROM {t}"), params![], |r| {
                r.get(0)
            })?,
        )
    };
    Ok((c("readings")?, c("jobs")?, c("nc")?))
}

#[cfg(test)]
mod tests;
