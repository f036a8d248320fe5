//! Durable recording: every poll cycle's raw and filtered readings with their quality,
//! every NC job with its result and the NC's position, into SQLite in WAL mode.
//!
//! The control loop hands records to a bounded queue ([`RecordSender`]) and never
//! waits: when the queue is full the record is dropped and counted. A writer thread
//! commits the queue in one transaction every `commit_interval_s` (a crash or a power
//! loss loses at most that much: `synchronous = FULL` syncs every commit) and
//! applies retention by age and by size. A commit that fails because the database
//! is locked by another process or the disk is full keeps its records for the next
//! commit (at most `queue_cycles` of them; beyond it the oldest are dropped, NC jobs
//! last); one that fails otherwise drops its batch. Failures are counted and logged
//! once when they start and once when commits succeed again; the writer carries on.
//! A database file moved, deleted or replaced while open (its path no longer names
//! the file the writer has open) is checkpointed through the open connection, so a
//! moved file keeps every committed record, and created again at its path. A `-wal`
//! deleted or replaced while open is checkpointed the same way into the database
//! file, which keeps every committed record, and the database is opened again with
//! a new `-wal`.
//!
//! The same database holds the MQTT outbox, written in the same transaction as the
//! readings, so what was recorded is also what will be published. Over the size
//! limit, unsent messages go before the recorded history.

mod clock;
pub mod export;
mod schema;

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
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
        /// Actual position, mm; `None` where the target does not report it.
        position_mm: Option<f64>,
        /// Compensation applied, mm; `None` where the target does not report it.
        applied_comp_mm: Option<f64>,
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
    /// Records lost because a commit failed: a batch dropped on an error other than a
    /// lock or a full disk, or records beyond `queue_cycles` waiting for a commit.
    pub dropped_write: AtomicU64,
    /// Records committed.
    pub written: AtomicU64,
    /// Commits that failed.
    pub failed_commits: AtomicU64,
    /// Times the database file, or its `-wal`, was found deleted or replaced under
    /// the writer and the database opened again at its path.
    pub reopened: AtomicU64,
    /// Readings not stored because the database already held one of the same
    /// channel at every millisecond of the second from their time on; the one
    /// recorded first is kept.
    pub duplicate_readings: AtomicU64,
    /// How far the wall clock is ahead of the time age retention counts from, ms.
    pub clock_ahead_ms: AtomicU64,
    /// Readings stored at the next millisecond free because the database held one of
    /// the same channel at their time (the wall clock set back over recorded time).
    pub shifted_readings: AtomicU64,
    /// MQTT messages the size limit deleted before they were sent: the outbox goes
    /// before the recorded history.
    pub outbox_deleted: AtomicU64,
    /// Whether commits fail now (the database locked by another process, the disk
    /// full, ...).
    pub failing: AtomicBool,
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
    /// The recorder is stopping: a retention pass ends after its current chunk.
    stopping: AtomicBool,
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
                // The writer logs when drops start and when they stop: the control
                // loop does not log.
                self.stats.dropped_queue.fetch_add(1, Ordering::Relaxed);
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
/// and the database, if it exists, is a writable regular file holding an SQLite
/// database of the recorder's layout (`schema::check`: not a device such as
/// `/dev/null`, not the config file, not an older layout). `validate` runs it, and
/// `run` before it creates anything, so a config that `run` would refuse does not
/// pass. A problem names the environment variable that set `recorder.path`, if one
/// did.
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
    let existing = std::fs::metadata(path).ok();
    if let Some(m) = &existing {
        if m.is_dir() {
            return Err(problem("is a directory, not a database file".into()));
        }
        if !m.is_file() {
            return Err(problem(
                "is not a regular file (a device, a fifo or a socket): the recorder needs a database file of its own".into(),
            ));
        }
        writable(path).map_err(|e| problem(format!("the database is not writable: {e}")))?;
        // A -wal or -shm copied along with the database (as root, say) that this user
        // cannot write: SQLite opens the database and fails at the first write.
        for suffix in ["-wal", "-shm"] {
            let side = with_suffix(path, suffix);
            if std::fs::symlink_metadata(&side).is_ok() {
                writable(&side).map_err(|e| {
                    problem(format!(
                        "its {} is not writable: {e} (give it the database's owner)",
                        side.display()
                    ))
                })?;
            }
        }
    }
    writable(dir).map_err(|e| {
        problem(format!(
            "the directory {} is not writable (the database, its -wal and -shm files are created there): {e}",
            dir.display()
        ))
    })?;
    // An empty file is a new database to SQLite.
    if existing.is_some_and(|m| m.len() > 0) {
        // Read-write, not read-only: a read-only connection to a WAL database leaves
        // its -wal and -shm files behind, the last read-write one removes them.
        let flags =
            rusqlite::OpenFlags::SQLITE_OPEN_READ_WRITE | rusqlite::OpenFlags::SQLITE_OPEN_NO_MUTEX;
        let conn = Connection::open_with_flags(path, flags)
            .map_err(|e| problem(format!("the database cannot be opened: {e}")))?;
        conn.busy_timeout(schema::BUSY_TIMEOUT)
            .map_err(|e| problem(e.to_string()))?;
        schema::check(&conn).map_err(problem)?;
    }
    Ok(())
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
            stopping: AtomicBool::new(false),
        });
        let outbox = Arc::new(tokio::sync::Notify::new());
        let writer = Writer::new(
            cfg,
            &path,
            conn,
            stats.clone(),
            shared.clone(),
            outbox.clone(),
        );
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
            last_cycle: Vec::new(),
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
            last_cycle: Vec::new(),
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
        self.sender.shared.stopping.store(true, Ordering::Relaxed);
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
    /// Per device index: the clock's reading (ms) at its last recorded cycle and the
    /// time that cycle was recorded at; see [`Self::cycle_time_ms`].
    last_cycle: Vec<Option<(i64, i64)>>,
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

    /// The time a cycle of `device` is recorded at, the clock reading `now_ms`. Its
    /// readings' key is their channel and millisecond, and two cycles of one device
    /// can end in one millisecond: a cycle whose connect the cycle deadline cut ends
    /// after the poll interval, so the next one starts at once, and the reconnect
    /// backoff that failed connect started refuses it within microseconds. The later
    /// cycle is recorded 1 ms after the earlier one then, as long as the clock has not
    /// gone back since: a clock set back keeps its own time, and the writer stores
    /// the readings that meet recorded ones at the next free millisecond.
    fn cycle_time_ms(&mut self, device: usize, now_ms: i64) -> i64 {
        if self.last_cycle.len() <= device {
            self.last_cycle.resize(device + 1, None);
        }
        let t = match self.last_cycle[device] {
            Some((clock, recorded)) if clock <= now_ms && now_ms <= recorded => recorded + 1,
            _ => now_ms,
        };
        self.last_cycle[device] = Some((now_ms, t));
        t
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
        let t_unix_ms = self.cycle_time_ms(readings.device, self.now_unix_ms());
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
                // Stamped when it was read, not when the status came out (up to a
                // status interval later: export's pos_mm lagged the axis by that).
                let age_ms = a.nc_read_at.map_or(0, |at| {
                    i64::try_from(at.elapsed().as_millis()).unwrap_or(i64::MAX)
                });
                self.tx.send(Record::Nc {
                    t_unix_ms: t_unix_ms.saturating_sub(age_ms),
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
pub(crate) fn with_suffix(path: &Path, suffix: &str) -> PathBuf {
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
    /// Records waiting for a commit at most (the queue's size).
    max_held: usize,
    stats: Arc<RecorderStats>,
    shared: Arc<QueueShared>,
    outbox: Arc<tokio::sync::Notify>,
    statements: schema::Statements,
    /// The commits failing now, if they do.
    outage: Option<Outage>,
    /// `dropped_queue` when last looked at, and when the queue's overflow began.
    queue_seen: u64,
    queue_full_from: Option<u64>,
    /// Whether the last retention pass deleted unsent MQTT messages.
    deleting_outbox: bool,
    /// The time age retention counts from.
    clock: clock::RetentionClock,
    /// Whether the last commit stored readings after their time.
    shifting: bool,
}

/// Commits failing since `since`: logged when it begins and when commits succeed again.
#[derive(Debug)]
struct Outage {
    since: Instant,
    failed_commits: u64,
    dropped_records: u64,
    dropped_readings: u64,
    /// Whether the records beyond `queue_cycles` were told of.
    shed_told: bool,
    /// The file is damaged: commits that touch the damaged pages fail, the others
    /// succeed, and neither ends the outage (nothing heals the file).
    damaged: bool,
}

/// Readings in `r`.
fn readings_in(r: &Record) -> u64 {
    match r {
        Record::Cycle { rows, .. } => rows.len() as u64,
        _ => 0,
    }
}

/// Whether `e` says the database file is damaged.
fn damaged(e: &RecordError) -> bool {
    use rusqlite::ErrorCode::{DatabaseCorrupt, NotADatabase};
    matches!(e, RecordError::Sqlite(e) if matches!(e.sqlite_error_code(), Some(DatabaseCorrupt | NotADatabase)))
}

/// Whether a commit that failed with `e` may succeed later with the same records:
/// another process holds the database's lock longer than the busy timeout, or the
/// disk is full. Any other error (a damaged file, a record it cannot take) would
/// fail them again.
fn transient(e: &RecordError) -> bool {
    use rusqlite::ErrorCode::{DatabaseBusy, DatabaseLocked, DiskFull};
    matches!(e, RecordError::Sqlite(e) if matches!(e.sqlite_error_code(), Some(DatabaseBusy | DatabaseLocked | DiskFull)))
}

/// Whether the file system holding the database at `path` refuses writes as read-only
/// now. ext4 mounted `errors=remount-ro` turns read-only after a disk error, under the
/// open database; SQLite reports the EROFS of its next write as a "disk I/O error".
/// The mount's flags may still say `rw` (ext4 only aborts its journal), so this asks
/// with a write: an empty file created beside the database and removed.
fn read_only_fs(path: &Path) -> bool {
    let erofs =
        |e: std::io::Error| e.raw_os_error() == Some(rustix::io::Errno::ROFS.raw_os_error());
    let probe = with_suffix(path, ".probe");
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => std::fs::remove_file(&probe).is_err_and(erofs),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            std::fs::remove_file(&probe).is_err_and(erofs)
        }
        Err(e) => erofs(e),
    }
}

/// A failed commit's error `e` as logged, with the cause SQLite's text hides: a write
/// to a file system gone read-only (`read_only`, from [`read_only_fs`]) is only a
/// "disk I/O error" to SQLite.
fn commit_error(e: &RecordError, read_only: bool) -> String {
    if read_only {
        format!("{e}: the file system is read-only (EROFS, errno 30; ext4 turns read-only after a disk error): every commit fails until it is writable again; check the disk (dmesg), then reboot or remount it read-write")
    } else {
        e.to_string()
    }
}

/// Drops the oldest records of `batch` beyond `max`, NC jobs last: they are what the
/// NC was sent. Returns the records and readings dropped.
fn shed(batch: &mut Vec<Record>, max: usize) -> (u64, u64) {
    let mut excess = batch.len().saturating_sub(max);
    let (mut records, mut readings) = (0, 0);
    let mut count = |r: &Record| {
        records += 1;
        readings += readings_in(r);
    };
    batch.retain(|r| {
        if excess == 0 || matches!(r, Record::Job { .. }) {
            return true;
        }
        excess -= 1;
        count(r);
        false
    });
    batch.drain(..excess).for_each(|r| count(&r));
    (records, readings)
}

/// Checkpoints the WAL into the database file `conn` has open and empties it;
/// whether that was done (another connection reading the WAL prevents it).
fn checkpoint(conn: &Connection) -> bool {
    conn.query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |r| {
        r.get::<_, i64>(0)
    })
    .is_ok_and(|busy| busy == 0)
}

/// Where this process has the file `id` open now, by name (Linux: `/proc/self/fd`):
/// where a database moved while open went.
fn open_path_of(id: (u64, u64)) -> Option<PathBuf> {
    std::fs::read_dir("/proc/self/fd")
        .ok()?
        .flatten()
        .map(|fd| fd.path())
        .find(|fd| file_id(fd) == Some(id))
        .and_then(|fd| std::fs::read_link(fd).ok())
        // A deleted file's link reads "<path> (deleted)": only a file still there counts.
        .filter(|p| file_id(p) == Some(id))
}

impl Writer {
    fn new(
        cfg: &RecorderConfig,
        path: &Path,
        conn: Connection,
        stats: Arc<RecorderStats>,
        shared: Arc<QueueShared>,
        outbox: Arc<tokio::sync::Notify>,
    ) -> Self {
        Writer {
            files: DbFiles::at(path),
            conn: Some(conn),
            path: path.to_path_buf(),
            commit_interval: compgate_gateway::config::secs(cfg.commit_interval_s),
            retention_interval: compgate_gateway::config::secs(cfg.retention_interval_s),
            retention_ms: (cfg.retention_days * 86_400_000.0) as i64,
            max_bytes: (cfg.max_size_mb * 1024.0 * 1024.0) as i64,
            max_held: usize::try_from(cfg.queue_cycles).unwrap_or(usize::MAX),
            stats,
            shared,
            outbox,
            statements: schema::Statements::default(),
            outage: None,
            queue_seen: 0,
            queue_full_from: None,
            deleting_outbox: false,
            clock: clock::RetentionClock::default(),
            shifting: false,
        }
    }

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
            if self.reopen_if_gone() {
                // Before the commit: a message it adds to the outbox gets a commit
                // interval to reach the broker before retention may delete it.
                if now >= next_retention || closed {
                    if let Err(e) = self.retention() {
                        tracing::warn!(error = %e, "recorder retention pass failed");
                    }
                    next_retention = now + self.retention_interval;
                }
                self.commit(&mut batch);
            }
            self.hold(&mut batch);
            self.report_queue();
            next_commit = now + self.commit_interval;
            if closed {
                break;
            }
        }
        if !batch.is_empty() {
            let n = batch.len() as u64;
            self.stats.dropped_write.fetch_add(n, Ordering::Relaxed);
            tracing::error!(
                records = n,
                "recorder stopped with records it could not commit: they are lost"
            );
        }
        // A clean stop leaves no WAL behind.
        if let Some(conn) = &self.conn {
            checkpoint(conn);
        }
        tracing::info!("recorder stopped");
    }

    /// Opens the database again when its file was moved, deleted or replaced (one
    /// `stat` a commit), or when opening it again failed before. False while the
    /// old file's WAL cannot be emptied into it: the records wait for the next commit.
    fn reopen_if_gone(&mut self) -> bool {
        if self.conn.is_some() && file_id(&self.path) == self.files.db {
            return self.reopen_if_wal_gone();
        }
        let first = self.conn.is_some();
        if let Some(conn) = &self.conn {
            // Its committed transactions may be in the WAL alone, which SQLite names
            // by the path: checkpointed into the file the connection has open,
            // wherever that is now (SQLite skips this at close when the file moved).
            // A WAL still holding anything is never removed nor paired with the new
            // file.
            let wal = with_suffix(&self.path, "-wal");
            let ours = self.files.wal.is_some() && file_id(&wal) == self.files.wal;
            let emptied =
                checkpoint(conn) && (!ours || std::fs::metadata(&wal).is_ok_and(|m| m.len() == 0));
            if !emptied {
                tracing::debug!(path = %self.path.display(), "recorder database gone: its WAL is not checkpointed yet, tried again at the next commit");
                return false;
            }
            let n = self.stats.reopened.fetch_add(1, Ordering::Relaxed) + 1;
            match self.files.db.and_then(open_path_of) {
                Some(to) => {
                    tracing::warn!(path = %self.path.display(), moved_to = %to.display(), reopened = n, "recorder database moved while the gateway runs: every record committed to it is in {}; recording into a new database at its path", to.display())
                }
                None => {
                    tracing::error!(path = %self.path.display(), reopened = n, "recorder database deleted or replaced while the gateway runs: what was committed to it went with it; recording into a new database at its path")
                }
            }
            // Closed before the new one opens: SQLite's last connection to a database
            // removes its -wal and -shm files by name, which would be the new ones.
            self.conn = None;
            // Another connection (the MQTT outbox) may still hold the old database,
            // and then its -wal and -shm stay at the path: opened with the new file,
            // SQLite would take them for its own.
            for (suffix, id) in [("-wal", self.files.wal), ("-shm", self.files.shm)] {
                let stale = with_suffix(&self.path, suffix);
                if id.is_some() && file_id(&stale) == id {
                    let _ = std::fs::remove_file(&stale);
                }
            }
            // Channel ids of the old database.
            self.statements.forget_channels();
            // Whatever was damaged stays with the old file.
            if let Some(o) = &mut self.outage {
                o.damaged = false;
            }
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
        true
    }

    /// Opens the database again when its `-wal` file was deleted or replaced (one
    /// `stat` a commit, with the database file's): SQLite goes on appending to the
    /// unlinked WAL, which no other connection reads (`compgate export` fails with a
    /// disk I/O error) and which a crash takes with every commit since. Its frames are
    /// checkpointed through the connection into the database file first, so the
    /// committed records are kept; the connection opened again creates a new `-wal`.
    /// False while the checkpoint cannot complete (a reader of the WAL): the records
    /// wait for the next commit, and are not committed to the unlinked WAL meanwhile.
    fn reopen_if_wal_gone(&mut self) -> bool {
        let wal = with_suffix(&self.path, "-wal");
        let at_path = file_id(&wal);
        // SQLite creates the -wal when the connection first reads, before the writer
        // takes `files`; should it not have, the first one seen is the connection's.
        if self.files.wal.is_none() {
            self.files.wal = at_path;
            return true;
        }
        if at_path == self.files.wal {
            return true;
        }
        let Some(conn) = &self.conn else {
            return true;
        };
        if !checkpoint(conn) {
            tracing::debug!(path = %wal.display(), "recorder WAL gone: not checkpointed yet, tried again at the next commit");
            return false;
        }
        let n = self.stats.reopened.fetch_add(1, Ordering::Relaxed) + 1;
        let what = if at_path.is_some() {
            "replaced"
        } else {
            "deleted"
        };
        tracing::error!(path = %wal.display(), reopened = n, "recorder WAL file {what} while the gateway runs: every record committed to it was checkpointed into the database and is kept; the database is opened again with a new WAL");
        // The database file stays: its -shm stays too (another connection of this
        // process, the MQTT outbox, shares it). A -wal left at the path is empty for
        // SQLite: the checkpoint reset the WAL index.
        self.conn = None;
        self.statements.forget_channels();
        match open(&self.path) {
            Ok(conn) => {
                self.files = DbFiles::at(&self.path);
                self.conn = Some(conn);
                tracing::info!(path = %self.path.display(), "recording into SQLite (WAL) again");
            }
            // Tried again every commit (the database's own check finds no connection).
            Err(e) => {
                tracing::error!(error = %e, "recorder database cannot be opened again: records are dropped until it can")
            }
        }
        true
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
                message: "moved, deleted or replaced while open, and not opened again at its path (the error before says why)".into(),
            }),
        };
        match result {
            Ok(schema::Inserted { ignored, shifted }) => {
                batch.clear();
                self.stats.written.fetch_add(n, Ordering::Relaxed);
                // Told when it begins: every cycle of the period the clock repeats.
                if shifted > 0 && !self.shifting {
                    tracing::warn!(shifted_total = self.stats.shifted_readings.load(Ordering::Relaxed) + shifted, "recorder: the wall clock set back over recorded time: readings are stored at the next free millisecond after the ones recorded there, which are kept; the two periods interleave in time");
                }
                self.shifting = shifted > 0;
                self.stats
                    .shifted_readings
                    .fetch_add(shifted, Ordering::Relaxed);
                if ignored > 0 {
                    let before = self
                        .stats
                        .duplicate_readings
                        .fetch_add(ignored, Ordering::Relaxed);
                    // The first and then one line per 1000 more, not one per commit.
                    if before == 0 || before / 1000 != (before + ignored) / 1000 {
                        tracing::warn!(duplicates = before + ignored, "recorder: readings not stored, the database already holds their channel at every millisecond of a second from their time on; the ones recorded first are kept");
                    }
                }
                if outbox {
                    self.outbox.notify_one();
                }
                if let Some(o) = self.outage.take_if(|o| !o.damaged) {
                    self.stats.failing.store(false, Ordering::Relaxed);
                    tracing::info!(
                        failed_commits = o.failed_commits,
                        dropped_records = o.dropped_records,
                        dropped_readings = o.dropped_readings,
                        failing_s = o.since.elapsed().as_secs_f64(),
                        "recorder commits succeed again"
                    );
                }
            }
            Err(e) => {
                // Channel ids looked up in the rolled-back transaction are gone.
                self.statements.forget_channels();
                self.stats.failed_commits.fetch_add(1, Ordering::Relaxed);
                let kept = transient(&e);
                let begins = self.outage.is_none();
                let outage = self.outage.get_or_insert_with(|| Outage {
                    since: Instant::now(),
                    failed_commits: 0,
                    dropped_records: 0,
                    dropped_readings: 0,
                    shed_told: false,
                    damaged: false,
                });
                outage.failed_commits += 1;
                self.stats.failing.store(true, Ordering::Relaxed);
                if damaged(&e) && !outage.damaged {
                    outage.damaged = true;
                    tracing::error!(error = %e, path = %self.path.display(), records = n, "recorder commit failed: the database is damaged; commits that touch its damaged pages fail and their records are dropped until the gateway records into another file: stop it and move the file away (the recorder starts a new one at its path; `sqlite3 FILE .recover` reads what is left of it)");
                } else if begins {
                    let what = if kept {
                        "the records wait for the next commit (at most recorder.queue_cycles of them)"
                    } else {
                        "batch dropped"
                    };
                    let e = commit_error(&e, read_only_fs(&self.path));
                    tracing::error!(error = %e, path = %self.path.display(), records = n, "recorder commit failed: {what}; the gateway carries on (logged again when commits succeed)");
                }
                if !kept {
                    let readings: u64 = batch.iter().map(readings_in).sum();
                    outage.dropped_records += n;
                    outage.dropped_readings += readings;
                    self.stats.dropped_write.fetch_add(n, Ordering::Relaxed);
                    batch.clear();
                }
            }
        }
    }

    /// Keeps what a failed commit left at most `queue_cycles` records long; the
    /// oldest beyond are dropped, counted and logged (once per outage).
    fn hold(&mut self, batch: &mut Vec<Record>) {
        let (records, readings) = shed(batch, self.max_held);
        if records == 0 {
            return;
        }
        self.stats
            .dropped_write
            .fetch_add(records, Ordering::Relaxed);
        let told = match &mut self.outage {
            Some(o) => {
                o.dropped_records += records;
                o.dropped_readings += readings;
                std::mem::replace(&mut o.shed_told, true)
            }
            None => false,
        };
        if !told {
            tracing::warn!(
                records,
                readings,
                queue_cycles = self.max_held,
                "recorder: more records wait for a commit than recorder.queue_cycles: the oldest are dropped, NC jobs last"
            );
        }
    }

    /// Logs when the queue begins to drop records and when it stops.
    fn report_queue(&mut self) {
        let dropped = self.stats.dropped_queue.load(Ordering::Relaxed);
        match self.queue_full_from {
            None if dropped > self.queue_seen => {
                tracing::warn!(
                    queue_cycles = self.max_held,
                    "recorder queue full: records dropped (the writer is behind or waits for the database)"
                );
                self.queue_full_from = Some(self.queue_seen);
            }
            Some(from) if dropped == self.queue_seen => {
                tracing::info!(dropped = dropped - from, "recorder queue no longer full");
                self.queue_full_from = None;
            }
            _ => {}
        }
        self.queue_seen = dropped;
    }

    fn retention(&mut self) -> Result<(), RecordError> {
        let Some(conn) = &self.conn else {
            return Ok(());
        };
        let (now_ms, event) = if self.clock.started() {
            self.clock.now_ms(Instant::now(), now_unix_ms())
        } else {
            let newest_ms = schema::time_range(conn)?.map(|(_, last)| last);
            self.clock
                .start(Instant::now(), now_unix_ms(), newest_ms, self.retention_ms)
        };
        match event {
            Some(clock::ClockEvent::StepAhead(ms)) => tracing::warn!(
                step_s = ms / 1000,
                "the wall clock stepped ahead (set by hand, by a time server, or after a suspend): records are stamped with it, but age retention does not follow the step and counts on from the time before it, until the clock is set back or the gateway restarts; check the clock"
            ),
            Some(clock::ClockEvent::StepBack(ms)) => tracing::warn!(
                step_s = ms / 1000,
                "the wall clock stepped back: records from now on are stamped before some already recorded; check the clock"
            ),
            Some(clock::ClockEvent::BackInLine) => {
                tracing::info!("the wall clock is back in line: age retention follows it again")
            }
            Some(clock::ClockEvent::StartAhead(ms)) => tracing::warn!(
                days = ms / 86_400_000,
                "the wall clock is further past the newest record than retention_days: age retention would delete every record, so it counts on from the newest record until the gateway starts again; if the PC was off that long, nothing is lost by waiting; if the clock is wrong, set it before then"
            ),
            Some(clock::ClockEvent::StartBehind(ms)) => tracing::warn!(
                step_s = ms / 1000,
                "the wall clock is before the newest record (a dead RTC battery, or a clock set back while the gateway was stopped): records from now on are stamped before some already recorded; check the clock"
            ),
            None => {}
        }
        self.stats.clock_ahead_ms.store(
            u64::try_from(self.clock.ahead_ms()).unwrap_or(0),
            Ordering::Relaxed,
        );
        let cutoff = now_ms - self.retention_ms;
        // A stop does not wait for a long pass (the first after a long downtime, or
        // after the limits were lowered): it ends after the chunk it is in, and the
        // next pass goes on from there.
        let go_on = || !self.shared.stopping.load(Ordering::Relaxed);
        let aged = schema::delete_before(conn, cutoff, &go_on)?;
        let mut cut = schema::Deleted::default();
        let used = schema::data_bytes(conn)?;
        if used > self.max_bytes {
            // Unsent MQTT messages go before the recorded history, or an outbox
            // grown during a broker outage would push the records out: a tenth of
            // it at a time, at most all of it in one pass.
            let step = schema::outbox_len(conn)?.div_ceil(10);
            for _ in 0..10 {
                if step == 0 || schema::data_bytes(conn)? <= self.max_bytes {
                    break;
                }
                let n = schema::delete_oldest_outbox(conn, step)?;
                if n == 0 {
                    break;
                }
                cut.outbox += n;
            }
            // Then the oldest tenth of the records' time range at a time.
            for _ in 0..10 {
                if schema::data_bytes(conn)? <= self.max_bytes {
                    break;
                }
                let Some((first, last)) = schema::time_range(conn)? else {
                    break;
                };
                // Tenths of the time recorded up to now: readings stamped ahead of it
                // (by a clock set wrong) would stretch the range, and its first tenth
                // would take every reading before them.
                let last = if first < now_ms {
                    last.min(now_ms)
                } else {
                    last
                };
                // Never the newest records: a limit below the schema's own pages would
                // otherwise empty the database pass after pass.
                if last <= first {
                    break;
                }
                cut += schema::delete_before(conn, first + ((last - first) / 10).max(1), &go_on)?;
            }
        }
        schema::release_free_pages(conn, &go_on)?;
        if !go_on() && schema::time_range(conn)?.is_some_and(|(first, _)| first < cutoff) {
            tracing::info!("recorder stopping: the retention pass ended after its current chunk, with older records left; the next start goes on with them");
        }
        let now_used = schema::data_bytes(conn)?;
        checkpoint(conn);
        self.stats
            .outbox_deleted
            .fetch_add(cut.outbox, Ordering::Relaxed);
        let mut total = aged;
        total += cut;
        let starts_deleting_outbox = cut.outbox > 0 && !self.deleting_outbox;
        self.deleting_outbox = cut.outbox > 0;
        // One line a pass at most; WARN when unsent messages begin to go.
        macro_rules! pass {
            ($level:ident, $msg:expr) => {
                tracing::$level!(
                    readings = total.readings,
                    jobs = total.jobs,
                    nc = total.nc,
                    outbox = total.outbox,
                    outbox_deleted_total = self.stats.outbox_deleted.load(Ordering::Relaxed),
                    used_bytes = now_used,
                    max_bytes = self.max_bytes,
                    $msg
                )
            };
        }
        if starts_deleting_outbox {
            pass!(warn, "recorder over max_size_mb with MQTT messages unsent (the broker away?): the oldest messages are deleted first and never published, then the oldest records if need be; each further pass logs what it deleted");
        } else if !cut.is_empty() {
            pass!(info, "recorder over max_size_mb: the oldest deleted");
        } else if !total.is_empty() {
            pass!(debug, "recorder: records older than retention_days deleted");
        }
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
