//! Durable recording with real processes: kill -9 at random moments, export to the
//! measurement CSV, retention by size, and a full disk.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::path::Path;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use common::process::{Gateway, BIN};
use compgate_core::measure::Measurements;
use rusqlite::Connection;

fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .expect("clock after 1970")
        .as_millis() as i64
}

fn recorder_section(db: &Path, extra: &str) -> String {
    format!(
        "\n[recorder]\npath = {:?}\ncommit_interval_s = 0.5\n{extra}\n",
        db.display().to_string()
    )
}

fn max_t(db: &Path) -> i64 {
    let conn = Connection::open(db).expect("database opens");
    let ok: String = conn
        .query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .expect("integrity check runs");
    assert_eq!(ok, "ok");
    conn.query_row("SELECT max(t_unix_ms) FROM readings", [], |r| r.get(0))
        .expect("readings")
}

/// The test plant and a config file recording into `db` (with `extra` recorder keys).
async fn plant_recording(
    dir: &std::path::Path,
    db: &std::path::Path,
    extra: &str,
) -> (compgate::plant::Plant, std::path::PathBuf) {
    common::plant_and_file(
        dir,
        &common::config("hold", "", ""),
        &recorder_section(db, extra),
    )
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_loses_at_most_the_last_second_and_the_database_opens_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let (plant, path) = plant_recording(dir.path(), &db, "").await;
    // Pseudo-random kill moments from the clock: 1.0 .. 3.0 s after READY.
    let mut seed = now_ms() as u64;
    let mut rows_before = 0i64;
    for round in 0..3 {
        let mut gw = Gateway::start(dir.path(), &path, &[]);
        tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let wait_ms = 1000 + (seed >> 33) % 2000;
        tokio::time::sleep(Duration::from_millis(wait_ms)).await;
        let killed_at = now_ms();
        gw.signal("KILL");
        let _ = gw.child.wait();
        let last = max_t(&db);
        let lost_ms = killed_at - last;
        println!("round {round}: killed {wait_ms} ms after READY, last reading {lost_ms} ms before the kill");
        assert!(
            lost_ms <= 1000,
            "round {round}: {lost_ms} ms of readings lost"
        );
        let conn = Connection::open(&db).unwrap();
        let rows: i64 = conn
            .query_row("SELECT count(*) FROM readings", [], |r| r.get(0))
            .unwrap();
        assert!(rows > rows_before, "round {round} recorded nothing");
        rows_before = rows;
        drop(gw);
    }
    drop(plant);
}

// `rm rec.db-wal` while the gateway records, then kill -9: SQLite would go on
// appending to the unlinked WAL, and the kill would take every reading since the
// deletion (and those only in the WAL before it). The recorder checkpoints the old WAL
// into the database at its next commit and opens it again with a new -wal: the kill
// loses at most the last second, and the readings before the deletion are kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wal_deleted_while_recording_then_kill_9_loses_at_most_the_last_second() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    // No checkpoint by retention after the first pass: the readings stay in the WAL.
    let (plant, path) = plant_recording(dir.path(), &db, "retention_interval_s = 3600.0").await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let deleted_at = now_ms();
    std::fs::remove_file(dir.path().join("rec.db-wal")).unwrap();
    // A few commits (commit_interval_s = 0.5) after the deletion.
    tokio::time::sleep(Duration::from_millis(2000)).await;
    let killed_at = now_ms();
    gw.signal("KILL");
    let _ = gw.child.wait();

    let conn = Connection::open(&db).unwrap();
    let ok: String = conn
        .query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .unwrap();
    assert_eq!(ok, "ok");
    let (before, first, last): (i64, Option<i64>, Option<i64>) = conn
        .query_row(
            "SELECT count(*) FILTER (WHERE t_unix_ms < ?1), min(t_unix_ms), max(t_unix_ms) FROM readings",
            [deleted_at],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
        )
        .unwrap();
    let lost_ms = last.map(|t| killed_at - t);
    assert!(
        lost_ms.is_some_and(|ms| ms <= 1000),
        "readings lost before the kill: {} (the -wal was deleted {} ms before it)",
        lost_ms.map_or("every one".to_string(), |ms| format!("{ms} ms")),
        killed_at - deleted_at
    );
    // Three channels every 0.05 s for over a second before the deletion.
    assert!(
        before >= 60 && first.is_some_and(|t| deleted_at - t >= 1000),
        "{before} readings before the deletion, the first {:?} ms before it",
        first.map(|t| deleted_at - t)
    );
    let line = gw.wait_log(1.0, "recorder WAL file deleted");
    assert!(
        line.contains("ERROR") && line.contains("rec.db-wal"),
        "{line}"
    );
    drop(gw);
    drop(plant);
}

/// A device whose process is paused (SIGSTOP) with its accept queue full: a TCP
/// listener nothing accepts from, with room for one connection. The first connect
/// completes (the kernel answers for the process) and its request times out; every
/// later one hangs, its SYNs dropped.
#[allow(unsafe_code)]
fn paused_device() -> std::net::TcpListener {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("binds");
    // listen() again sets the queue's length: 0 leaves room for one connection.
    // SAFETY: a valid listening socket, borrowed for the call.
    let rc = unsafe { libc::listen(std::os::fd::AsRawFd::as_raw_fd(&l), 0) };
    assert_eq!(rc, 0, "listen");
    l
}

// A device that stops answering with its connects hanging (a paused process): a cycle
// whose connect the cycle deadline cut ends after the poll interval, so the next cycle
// starts at once, and the reconnect backoff the failed connect started refuses it
// within microseconds. Two cycles of the device in one millisecond: both are recorded,
// each at its own millisecond; none is dropped as a duplicate with a "wall clock set
// back?" warning.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_device_with_hanging_connects_loses_no_reading_as_a_duplicate() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let paused = paused_device();
    let extra = format!(
        r#"
[devices.ain2]
transport = "tcp"
address = "{address}"
unit_id = 1
timeout_s = 0.5
poll_interval_s = 0.5
backoff_initial_s = 0.2
backoff_max_s = 0.4

[channels.T_paused]
device = "ain2"
register = "input"
address = 0
data_type = "u16"
scaling = {scaling}
filter = {filter}

[metrics]
bind = "127.0.0.1:0"
{recorder}"#,
        address = paused.local_addr().unwrap(),
        scaling = common::SCALING,
        filter = common::FILTER,
        recorder = recorder_section(&db, ""),
    );
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    let port = tokio::task::block_in_place(|| gw.metrics_port(10.0));
    // A failed connect and its refused successor about every second.
    tokio::time::sleep(Duration::from_millis(4000)).await;
    let (body, _) = tokio::task::block_in_place(|| {
        common::metrics::scrape(port, Duration::from_secs(5)).expect("metrics")
    });
    let errors = |kind: &str| -> f64 {
        let kind = format!("kind=\"{kind}\"");
        body.lines()
            .filter(|l| {
                l.starts_with("compgate_device_errors_total{")
                    && l.contains("device=\"ain2\"")
                    && l.contains(&kind)
            })
            .filter_map(|l| l.rsplit_once(' ')?.1.parse::<f64>().ok())
            .sum()
    };
    let refused = errors("backoff");
    assert!(
        refused >= 2.0 && errors("connect") >= 2.0 && errors("deadline") == 0.0,
        "the device's connects hang (connect timeouts, not the cycle deadline's) and the \
         backoff refuses the cycles after them:\n{body}"
    );
    let duplicates =
        common::metrics::value(&body, "compgate_recorder_duplicate_readings_total").unwrap_or(0.0);
    let stderr = gw.stderr.clone();
    assert!(tokio::task::block_in_place(|| gw.stop()));
    let log = stderr.lock().unwrap().join("\n");
    assert!(
        duplicates == 0.0 && !log.contains("wall clock set back"),
        "{duplicates} readings dropped as duplicates:\n{log}"
    );
    // Every refused cycle is recorded just after the one before it (within a tenth of
    // the poll interval: the control loop may be busy in between).
    let conn = Connection::open(&db).unwrap();
    let times: Vec<i64> = conn
        .prepare(
            "SELECT t_unix_ms FROM readings r JOIN channels c ON c.id = r.channel
             WHERE c.name = 'T_paused' ORDER BY t_unix_ms",
        )
        .unwrap()
        .query_map([], |r| r.get(0))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    let back_to_back = times.windows(2).filter(|w| w[1] - w[0] <= 50).count();
    assert!(
        back_to_back as f64 >= refused,
        "{back_to_back} cycles of T_paused recorded within 50 ms of the one before, {refused} refused by the backoff: {times:?}"
    );
    drop(paused);
    drop(plant);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recorded_operation_exports_to_the_measurement_csv() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let (plant, path) = plant_recording(dir.path(), &db, "").await;
    let since = now_ms() as f64 / 1000.0;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "a verified write", |m| m.contains("jobs 1 ok"))
    });
    // A bad reading in the record must not reach the CSV: T_col fails for a while.
    let col = plant.transmitter["T_col"];
    plant.field["ain1"]
        .set_sensor_fault(col, compgate_plc::field::SensorFault::Open)
        .unwrap();
    tokio::time::sleep(Duration::from_millis(1500)).await;
    plant.field["ain1"]
        .set_sensor_fault(col, compgate_plc::field::SensorFault::None)
        .unwrap();
    // Long enough after the fault for 10 rows: rows in it are left out.
    tokio::time::sleep(Duration::from_millis(3000)).await;
    assert!(tokio::task::block_in_place(|| gw.stop()));

    let conn = Connection::open(&db).unwrap();
    let (readings, jobs, nc) = compgate_service::record::counts(&conn).unwrap();
    assert!(
        readings > 100 && jobs >= 1 && nc >= 1,
        "{readings} {jobs} {nc}"
    );
    let bad: i64 = conn
        .query_row(
            "SELECT count(*) FROM readings r JOIN channels c ON c.id = r.channel WHERE c.name = 'T_col' AND quality = 2 AND reason = 'NE43 low'",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert!(bad > 0, "the NE43 fault is recorded with its quality");
    let ok_job: (f64, i64) = conn
        .query_row(
            "SELECT sd43900_mm, ok FROM jobs ORDER BY t_unix_ms LIMIT 1",
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    assert!(
        (ok_job.0 - 0.04).abs() < 0.001 && ok_job.1 == 1,
        "{ok_job:?}"
    );
    // A clean stop checkpoints the WAL into the database.
    let wal = dir.path().join("rec.db-wal");
    assert!(!wal.exists() || std::fs::metadata(&wal).unwrap().len() == 0);

    let csv = dir.path().join("out.csv");
    let out = std::process::Command::new(BIN)
        .args(["export", "--db"])
        .arg(&db)
        .args([
            "--since",
            &format!("{since}"),
            "--until",
            &format!("{}", since + 600.0),
        ])
        .args(["--csv", "--axis", "X", "--step-s", "0.2", "--out"])
        .arg(&csv)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("err_um is 0"), "{err}");
    assert!(err.contains("was no measurement"), "{err}");
    let m = Measurements::read_path(&csv).expect("calibrate/diagnose read the export");
    assert!(m.len() >= 10, "{} rows", m.len());
    for (name, degc) in [("bed", 30.0), ("screw", 25.0), ("col", 60.0)] {
        let col = m.temp(name).unwrap_or_else(|| panic!("column T_{name}"));
        assert!(
            col.iter().all(|v| (v - degc).abs() < 0.2),
            "T_{name}: {col:?}"
        );
    }
    assert!(m.pos_mm.iter().all(|p| (p - 500.0).abs() < 1e-9));
    assert!(m.err_um.iter().all(|e| *e == 0.0));

    // Bad arguments name the flag.
    let out = std::process::Command::new(BIN)
        .args(["export", "--db"])
        .arg(&db)
        .args(["--since", "yesterday", "--until", "1", "--csv"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--since: `yesterday` is not a time"));
    drop(plant);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retention_by_size_keeps_the_database_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let extra = "max_size_mb = 0.03\nretention_interval_s = 0.2";
    let (plant, path) = plant_recording(dir.path(), &db, extra).await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    // 3 channels at 20 Hz: about 80 kB in 6 s without retention.
    tokio::time::sleep(Duration::from_secs(6)).await;
    let conn = Connection::open(&db).unwrap();
    let pages: i64 = conn
        .query_row("PRAGMA page_count", [], |r| r.get(0))
        .unwrap();
    let free: i64 = conn
        .query_row("PRAGMA freelist_count", [], |r| r.get(0))
        .unwrap();
    let size: i64 = conn
        .query_row("PRAGMA page_size", [], |r| r.get(0))
        .unwrap();
    let (first, last): (i64, i64) = conn
        .query_row(
            "SELECT min(t_unix_ms), max(t_unix_ms) FROM readings",
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    println!(
        "data {} bytes, span {} ms",
        (pages - free) * size,
        last - first
    );
    // One batch may land between retention passes.
    assert!(
        (pages - free) * size < 64 * 1024,
        "{} bytes in use",
        (pages - free) * size
    );
    assert!(last - first < 5500, "the oldest readings were not deleted");
    assert!(now_ms() - last < 1500, "recording goes on");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

/// A size-limited filesystem for the database (tmpfs; the tests run as root).
struct SmallFs(std::path::PathBuf);

impl SmallFs {
    fn mount(at: &Path, size: &str) -> Self {
        std::fs::create_dir_all(at).expect("mount point created");
        let st = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(at)
            .status()
            .expect("mount runs");
        assert!(st.success(), "mounting a tmpfs needs root");
        SmallFs(at.to_path_buf())
    }
}

impl SmallFs {
    fn remount_read_only(&self) {
        let st = std::process::Command::new("mount")
            .args(["-o", "remount,ro"])
            .arg(&self.0)
            .status()
            .expect("mount runs");
        assert!(st.success(), "remounting read-only");
    }
}

impl Drop for SmallFs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_disk_loses_records_but_never_stops_the_gateway() {
    let dir = tempfile::tempdir().unwrap();
    let fs = SmallFs::mount(&dir.path().join("small"), "160k");
    let db = fs.0.join("rec.db");
    let (plant, path) = plant_recording(dir.path(), &db, "").await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    tokio::task::block_in_place(|| gw.wait_log(30.0, "recorder commit failed"));
    // The control loop goes on: temperatures followed, jobs written, watchdog fed.
    let jobs = plant.nc["nc_x"].jobs_executed();
    plant.field["ain1"]
        .set_temperature_override(plant.transmitter["T_bed"], Some(35.0))
        .unwrap();
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "write after the disk filled", |m| {
            m.contains("WATCHDOG=1") && m.contains("SD43900=0.060")
        })
    });
    assert!(plant.nc["nc_x"].jobs_executed() > jobs);
    assert!(
        tokio::task::block_in_place(|| gw.stop()),
        "clean stop with a full disk"
    );
    // What was committed before the disk filled is intact.
    let conn = Connection::open(&db).unwrap();
    let ok: String = conn
        .query_row("PRAGMA quick_check", [], |r| r.get(0))
        .unwrap();
    assert_eq!(ok, "ok");
    drop(conn);
    drop(fs);
    drop(plant);
}

// A database of the layout before NULL positions is rebuilt once on open, which
// needs about three times its nc table's size free. On a nearly full disk the rebuild
// failed and the gateway did not start at all: no poll, no NC job. It now starts with
// the old layout, says why, and keeps every row.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_nc_table_that_cannot_be_rebuilt_for_lack_of_space_does_not_stop_the_gateway() {
    let dir = tempfile::tempdir().unwrap();
    let made = dir.path().join("made.db");
    const OLD_ROWS: i64 = 60_000;
    {
        let conn = compgate_service::record::open(&made).unwrap();
        conn.execute_batch(
            "DROP TABLE nc; CREATE TABLE nc (t_unix_ms INTEGER NOT NULL, axis TEXT NOT NULL,
                position_mm REAL NOT NULL, applied_comp_mm REAL NOT NULL,
                sd43900_mm REAL NOT NULL, sd43910 REAL NOT NULL, sd43920_mm REAL NOT NULL);
             CREATE INDEX nc_t ON nc(t_unix_ms);",
        )
        .unwrap();
        // The last hours, within the retention.
        conn.execute(
            "WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n WHERE i < ?1)
             INSERT INTO nc SELECT ?2 + i * 100, 'X', i * 0.001, 0.002, 0.01, 0, 0 FROM n",
            [OLD_ROWS, now_ms() - OLD_ROWS * 100],
        )
        .unwrap();
        conn.execute_batch("PRAGMA wal_checkpoint(TRUNCATE);")
            .unwrap();
    }
    // Room for the file and a little more, not for a second copy of the table.
    let size_kb = std::fs::metadata(&made).unwrap().len() / 1024 + 1024;
    let fs = SmallFs::mount(&dir.path().join("small"), &format!("{size_kb}k"));
    let db = fs.0.join("rec.db");
    std::fs::copy(&made, &db).unwrap();
    // The MQTT outbox opens the database too (no broker needed for that).
    let mqtt = "\n[mqtt]\nbroker = \"127.0.0.1:9\"\nmachine = \"mill-7\"\n";
    let (plant, path) = plant_recording(dir.path(), &db, mqtt).await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(20.0, "READY=1", |m| m.contains("READY=1")));
    let log = gw.stderr_text();
    assert!(
        log.contains("the nc table could not be rebuilt")
            && log.contains("keeps its old layout")
            && log.contains("disk is full"),
        "{log}"
    );
    // The control loop runs: a temperature change reaches the NC.
    plant.field["ain1"]
        .set_temperature_override(plant.transmitter["T_bed"], Some(35.0))
        .unwrap();
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "the write after the change", |m| {
            m.contains("SD43900=0.060")
        })
    });
    // Tried once: the MQTT outbox's open (by now) does not try again.
    let log = gw.stderr_text();
    assert_eq!(
        log.matches("rebuilding the nc table once").count(),
        1,
        "{log}"
    );
    assert!(tokio::task::block_in_place(|| gw.stop()));
    fs_rows_check(&db, OLD_ROWS);
    drop(fs);
    drop(plant);
}

/// Asserts that the `nc` table at `db` still has its NOT NULL layout and at least
/// `old_rows` rows.
fn fs_rows_check(db: &Path, old_rows: i64) {
    let conn = Connection::open(db).unwrap();
    let (rows, not_null): (i64, bool) = conn
        .query_row(
            "SELECT (SELECT COUNT(*) FROM nc), (SELECT \"notnull\" FROM pragma_table_info('nc') WHERE name = 'position_mm')",
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    assert!(not_null, "the old layout stays");
    assert!(rows >= old_rows, "{rows} rows");
}

// An error after the recorder started (here the metrics port in use) ends the run
// with the error; it used to hang, the recorder waiting for an observer's sender
// that the unwinding had not dropped yet.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_metrics_port_in_use_ends_a_recording_run_with_the_error() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let extra = format!("\n[metrics]\nbind = \"127.0.0.1:{port}\"");
    let (plant, path) = plant_recording(dir.path(), &db, &extra).await;
    let out = tokio::task::block_in_place(|| {
        let mut child = std::process::Command::new(BIN)
            .args(["--log", "warn", "run", "--config"])
            .arg(&path)
            .env_remove("NOTIFY_SOCKET")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        while child.try_wait().unwrap().is_none() {
            if std::time::Instant::now() > deadline {
                let _ = child.kill();
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        child.wait_with_output().unwrap()
    });
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("Address already in use"), "{err}");
    drop(taken);
    drop(plant);
}

/// Runs the binary with `args` to its end (at most 20 s, then killed).
fn run_to_end(args: &[&str]) -> std::process::Output {
    let mut child = std::process::Command::new(BIN)
        .args(args)
        .env_remove("NOTIFY_SOCKET")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("the binary starts");
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while child.try_wait().expect("waitpid").is_none() {
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().expect("its output")
}

// Two gateways recording into one database mixed their rows with nothing to tell
// them apart (and lost some). The second now refuses to start, naming the database;
// `export` (read-only) still works while the first records.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_gateway_on_the_same_database_is_refused_and_export_still_works() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let (plant, path) = plant_recording(dir.path(), &db, "").await;
    let since = now_ms() / 1000;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    let config = path.to_str().unwrap();
    let out =
        tokio::task::block_in_place(|| run_to_end(&["--log", "warn", "run", "--config", config]));
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&db.display().to_string()) && err.contains("another gateway records into it"),
        "{err}"
    );
    // Export while the gateway records, once a commit holds good readings of every
    // channel (on a loaded machine the first commits may hold only the start-up's).
    let csv = dir.path().join("live.csv");
    let (db_s, csv_s) = (db.to_str().unwrap(), csv.to_str().unwrap());
    let (from, to) = (since.to_string(), (since + 600).to_string());
    let deadline = std::time::Instant::now() + Duration::from_secs(15);
    let out = loop {
        let out = tokio::task::block_in_place(|| {
            run_to_end(&[
                "export", "--db", db_s, "--since", &from, "--until", &to, "--csv", "--out", csv_s,
            ])
        });
        if out.status.success() || std::time::Instant::now() > deadline {
            break out;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!Measurements::read_path(&csv).unwrap().is_empty());
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

// `validate` (the unit's ExecStartPre) passed recorder paths that `run` refused: a
// missing directory, a read-only database or directory. It now refuses them too,
// naming recorder.path and the file, and creates nothing.
#[test]
fn validate_refuses_a_recorder_path_that_run_cannot_write() {
    let dir = tempfile::tempdir().unwrap();
    let write_config = |db: &Path| {
        let path = dir.path().join("plant.toml");
        // Port 0 is for the simulated plant only: `validate` checks for `run`.
        let port = format!("127.0.0.1:{}", common::free_port());
        let text = common::config("hold", "", "").replace("127.0.0.1:0", &port)
            + &recorder_section(db, "");
        std::fs::write(&path, text).unwrap();
        path
    };
    let validate_fails = |config: &Path, db: &Path, why: &str| {
        let out = run_to_end(&["validate", "--config", config.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(
            err.contains("recorder.path")
                && err.contains(&db.display().to_string())
                && err.contains(why),
            "{err}"
        );
        // `run` refuses it with the same words.
        let out = run_to_end(&["--log", "warn", "run", "--config", config.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains(why), "{err}");
    };

    let missing = dir.path().join("nodir").join("sub").join("g.db");
    let config = write_config(&missing);
    let why = format!(
        "the directory {} does not exist",
        missing.parent().unwrap().display()
    );
    validate_fails(&config, &missing, &why);
    assert!(!dir.path().join("nodir").exists(), "nothing created");
    // The warnings are printed with the path's error, not only once it is fixed.
    let text =
        std::fs::read_to_string(&config)
            .unwrap()
            .replacen("address = 2\n", "address = 30003\n", 1);
    std::fs::write(&config, text).unwrap();
    validate_fails(&config, &missing, &why);
    let out = run_to_end(&["validate", "--config", config.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("warning: ") && err.contains("channels.T_col.address: 30003 looks like"),
        "{err}"
    );

    // A read-only file system (root writes any file that its mode forbids).
    let fs = SmallFs::mount(&dir.path().join("ro"), "1m");
    let db = fs.0.join("g.db");
    let config = write_config(&db);
    let ok = run_to_end(&["validate", "--config", config.to_str().unwrap()]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    compgate_service::record::open(&db).unwrap();
    fs.remount_read_only();
    validate_fails(&config, &db, "the database is not writable");
    let fresh = fs.0.join("new.db");
    let config = write_config(&fresh);
    validate_fails(&config, &fresh, "is not writable");
    drop(fs);
}

// A database copied to a new PC as root, and only the database given to the service
// user, as the guide says: its -wal, copied along, stayed root's. `validate` (the
// unit's ExecStartPre) passed it, and `run` failed at the first write ("attempt to
// write a readonly database"), restarting in a loop (review W).
#[test]
fn validate_refuses_a_wal_the_service_user_cannot_write() {
    let uid = std::process::Command::new("id").arg("-u").output().unwrap();
    if String::from_utf8_lossy(&uid.stdout).trim() != "0" {
        println!("SKIPPED: needs root to run validate as another user");
        return;
    }
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o777)).unwrap();
    let db = dir.path().join("g.db");
    compgate_service::record::open(&db).unwrap();
    let config = dir.path().join("plant.toml");
    let port = format!("127.0.0.1:{}", common::free_port());
    let text =
        common::config("hold", "", "").replace("127.0.0.1:0", &port) + &recorder_section(&db, "");
    std::fs::write(&config, text).unwrap();
    let nobody = 65534;
    std::os::unix::fs::chown(&db, Some(nobody), Some(nobody)).unwrap();
    let validate = || {
        std::process::Command::new("setpriv")
            .args(["--reuid=65534", "--regid=65534", "--clear-groups", BIN])
            .args(["validate", "--config", config.to_str().unwrap()])
            .output()
            .unwrap()
    };
    let ok = validate();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    // Root's -wal beside it.
    let wal = dir.path().join("g.db-wal");
    std::fs::write(&wal, "").unwrap();
    let out = validate();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "its {} is not writable: Permission denied",
            wal.display()
        )),
        "{err}"
    );
}

/// A database at `db` with `n` readings of one channel, a second apart, the newest
/// `age_ms` old, and one reading now; its file size.
fn aged_database(db: &Path, n: i64, age_ms: i64) -> u64 {
    let mut conn = compgate_service::record::open(db).unwrap();
    let tx = conn.transaction().unwrap();
    tx.execute("INSERT INTO channels(id, name) VALUES (1, 'T_bed')", [])
        .unwrap();
    {
        let mut ins = tx
            .prepare("INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, 1, 12000.0, 20.0, 0)")
            .unwrap();
        let newest = now_ms() - age_ms;
        for k in 0..n {
            ins.execute([newest - (n - 1 - k) * 1000]).unwrap();
        }
        ins.execute([now_ms()]).unwrap();
    }
    tx.commit().unwrap();
    conn.query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |_| Ok(()))
        .unwrap();
    drop(conn);
    std::fs::metadata(db).unwrap().len()
}

/// Runs a recorder over `db` with `extra` in `[recorder]` until its first retention
/// pass has left only the reading of now and no free page (a stop would cut the pass
/// short); panics after 60 s.
fn one_recorder_pass(db: &Path, extra: &str) {
    let cfg: compgate_gateway::config::RecorderConfig =
        toml::from_str(&format!("path = {:?}\n{extra}\n", db.display().to_string())).unwrap();
    let rec = compgate_service::record::Recorder::start(&cfg).unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        let conn = Connection::open(db).unwrap();
        let (rows, free): (i64, i64) = conn
            .query_row(
                "SELECT (SELECT count(*) FROM readings), (SELECT freelist_count FROM pragma_freelist_count)",
                [],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .unwrap();
        if rows == 1 && free == 0 {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the retention pass did not finish in 60 s: {rows} readings, {free} free pages"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    rec.finish();
}

/// The database's file size and its free pages.
fn file_and_free(db: &Path) -> (u64, i64) {
    let conn = Connection::open(db).unwrap();
    let free = conn
        .query_row("PRAGMA freelist_count", [], |r| r.get(0))
        .unwrap();
    (std::fs::metadata(db).unwrap().len(), free)
}

// Retention gave one page (4 KiB) a pass back to the disk: `PRAGMA incremental_vacuum`
// frees a page per step, and it was stepped once. A database cut from 1 GB to 30 MB
// stayed 1 GB on disk, 96 % of it free pages.
#[test]
fn retention_gives_the_space_it_frees_back_to_the_disk() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let before = aged_database(&db, 200_000, 2 * 86_400_000);
    one_recorder_pass(&db, "retention_days = 1");
    let (after, free) = file_and_free(&db);
    assert!(
        after < before / 10 && free < 16,
        "{before} bytes before, {after} after with {free} free pages"
    );
}

// On a nearly full disk retention could never free anything: it deleted everything
// older than its cut in one transaction, whose WAL needed about as much room as the
// rows it deleted. It now deletes in chunks, each checkpointed.
#[test]
fn retention_frees_space_on_a_nearly_full_disk() {
    let dir = tempfile::tempdir().unwrap();
    let fs = SmallFs::mount(&dir.path().join("small"), "24m");
    let db = fs.0.join("rec.db");
    let before = aged_database(&db, 300_000, 2 * 86_400_000);
    // All but 2 MB of the disk taken.
    let out = std::process::Command::new("stat")
        .args(["-f", "--format=%a %S"])
        .arg(&fs.0)
        .output()
        .unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    let free_bytes = text
        .split_whitespace()
        .map(|v| v.parse::<u64>().unwrap())
        .product::<u64>();
    let filler = vec![0u8; (free_bytes - 2 * 1024 * 1024) as usize];
    std::fs::write(fs.0.join("filler"), filler).unwrap();
    one_recorder_pass(&db, "retention_days = 1");
    let (after, free) = file_and_free(&db);
    assert!(
        after < before / 10 && free < 16,
        "{before} bytes before, {after} after with {free} free pages"
    );
    drop(fs);
}

// A stop waited for a running retention pass to its end (SIGTERM 2 s into a 10 s
// pass: 10 s to stop, nothing logged meanwhile), and systemd kills a stop after
// `TimeoutStopSec=`: the records queued during the pass were lost. The pass now ends
// after its current chunk, says so, and the next start goes on with it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_cuts_a_long_retention_pass_short() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    aged_database(&db, 500_000, 2 * 86_400_000);
    let (plant, path) = plant_recording(dir.path(), &db, "retention_days = 1").await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    // The first pass comes a commit interval after the start: the stop meets it.
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    let stderr = gw.stderr.clone();
    assert!(tokio::task::block_in_place(|| gw.stop()), "clean stop");
    let log = stderr.lock().unwrap().join("\n");
    assert!(
        log.contains("the retention pass ended after its current chunk"),
        "{log}"
    );
    let old: i64 = Connection::open(&db)
        .unwrap()
        .query_row(
            "SELECT count(*) FROM readings WHERE t_unix_ms < ?1",
            [now_ms() - 86_400_000],
            |r| r.get(0),
        )
        .unwrap();
    assert!(old > 400_000, "{old} old readings left");
    drop(plant);
}

// The minute of records a pass deletes leaves its pages to the next commits: giving
// them back would copy as many pages of the newest records into their place, once a
// minute, to shrink a file that grows again at once.
#[test]
fn retention_leaves_a_small_share_of_free_pages_to_the_next_commits() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    // 100 000 readings, a second apart, up to now: the oldest 5 % are over a day old.
    let before = aged_database(&db, 100_000, 0);
    let cfg: compgate_gateway::config::RecorderConfig = toml::from_str(&format!(
        "path = {:?}\nretention_days = {}\n",
        db.display().to_string(),
        95_000.0 / 86_400.0
    ))
    .unwrap();
    let rec = compgate_service::record::Recorder::start(&cfg).unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while file_and_free(&db).1 == 0 {
        assert!(std::time::Instant::now() < deadline, "no pass in 60 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    rec.finish();
    let (after, free) = file_and_free(&db);
    assert!(
        after == before && free > 0,
        "{before} bytes before, {after} after with {free} free pages"
    );
}
