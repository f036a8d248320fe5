use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::Duration;

use super::*;

fn cycle(names: &Arc<[String]>, v: f64) -> Record {
    Record::Cycle {
        t_unix_ms: now_unix_ms(),
        names: names.clone(),
        rows: vec![Row {
            channel: 0,
            raw: Some(v),
            unfiltered_degc: Some(v),
            value_degc: Some(v),
            quality: 0,
            reason: None,
        }],
    }
}

#[test]
fn writer_commits_every_interval_and_on_finish() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        commit_interval_s: 0.1,
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let tx = rec.sender();
    let name: Arc<[String]> = Arc::from(vec!["T_a".to_string()]);
    for i in 0..20 {
        tx.send(cycle(&name, f64::from(i)));
        std::thread::sleep(Duration::from_millis(20));
    }
    // Committed while running, not only at the end.
    let conn = open(rec.path()).expect("opens");
    let (n, _, _) = counts(&conn).expect("counts");
    assert!(n >= 10, "{n} readings committed after 0.4 s");
    drop(tx);
    let stats = rec.sender().stats().clone();
    rec.finish();
    assert_eq!(counts(&conn).expect("counts").0, 20);
    assert_eq!(stats.written.load(Ordering::Relaxed), 20);
    assert_eq!(stats.dropped_queue.load(Ordering::Relaxed), 0);
}

fn reading(channel: u32, v: f64, quality: u8) -> Row {
    Row {
        channel,
        raw: Some(v * 10.0),
        unfiltered_degc: Some(v + 0.5),
        value_degc: Some(v),
        quality,
        reason: (quality > 0).then_some("NE43 low"),
    }
}

#[test]
fn multi_row_inserts_keep_every_reading_under_its_channel_name() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut conn = open(&dir.path().join("m.db")).expect("opens");
    let mut statements = schema::Statements::default();
    // 130 channels: two full 64-row statements and a 2-row one.
    let names: Arc<[String]> = (0..130).map(|i| format!("T_{i}")).collect();
    let rows = (0..130u32)
        .map(|i| reading(i, f64::from(i), u8::from(i == 7) * 2))
        .collect();
    let first = Record::Cycle {
        t_unix_ms: 1_000,
        names: names.clone(),
        rows,
    };
    // A reload: a new name table in another order; the same name keeps its id.
    let reloaded: Arc<[String]> = vec!["T_5".to_string(), "T_new".to_string()].into();
    let second = Record::Cycle {
        t_unix_ms: 2_000,
        names: reloaded,
        rows: vec![reading(0, 55.0, 0), reading(1, 66.0, 1)],
    };
    schema::insert(&mut conn, &mut statements, &[first, second]).expect("inserted");
    assert_eq!(counts(&conn).expect("counts").0, 132);
    let value = |name: &str, t: i64| -> (f64, f64, f64, u8, Option<String>) {
        conn.query_row(
            "SELECT raw, unfiltered_degc, value_degc, quality, reason FROM readings r JOIN channels c ON c.id = r.channel WHERE c.name = ?1 AND t_unix_ms = ?2",
            rusqlite::params![name, t],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?, r.get(4)?)),
        )
        .expect("reading")
    };
    assert_eq!(value("T_129", 1_000), (1290.0, 129.5, 129.0, 0, None));
    assert_eq!(
        value("T_7", 1_000),
        (70.0, 7.5, 7.0, 2, Some("NE43 low".to_string()))
    );
    assert_eq!(value("T_5", 2_000).2, 55.0);
    assert_eq!(value("T_new", 2_000).3, 1);
    let channels: i64 = conn
        .query_row("SELECT count(*) FROM channels", [], |r| r.get(0))
        .expect("channels");
    assert_eq!(channels, 131);
}

// A device polled every 10 ms, recorded once a second: on a grid, so poll jitter does
// not stretch the spacing; each device on its own grid; zero records every cycle. One
// polled once a second is recorded every second, not every other one.
#[test]
fn the_observer_records_a_device_once_per_interval_on_a_grid() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let mut obs = rec.observer().with_interval(Duration::from_secs(1));
    let t0 = Instant::now();
    let ms = |m: u64| t0 + Duration::from_millis(m);
    let recorded: Vec<u64> = (0..300u64)
        // Every other poll 1 ms early: a poll up to a tenth of the interval before
        // its due time is taken (899 ms is too early, 910 is not), the grid stays.
        .map(|k| k * 10 - u64::from(k % 2 == 0 && k > 0))
        .filter(|&m| obs.due(0, ms(m)))
        .collect();
    assert_eq!(recorded, [0, 910, 1910, 2910]);
    assert!(obs.due(3, ms(5)), "another device has its own grid");
    assert!(!obs.due(3, ms(900)));
    // Back after an outage: a new grid from its first cycle.
    assert!(obs.due(0, ms(7777)));
    assert!(!obs.due(0, ms(8600)));
    assert!(obs.due(0, ms(8680)));
    // Polled at the interval, a poll a little early is not skipped.
    let mut at_interval = rec.observer().with_interval(Duration::from_secs(1));
    let jitter = |k: u64| if k.is_multiple_of(2) { 0 } else { 2 };
    assert!((0..10u64).all(|k| at_interval.due(0, ms(k * 1000 + 2 - jitter(k)))));
    let mut every = rec.observer();
    assert!((0..5).all(|k| every.due(0, ms(k))));
}

// Two cycles of one device in one millisecond (a cycle the reconnect backoff refused
// right after one the cycle deadline ended) are two cycles: the later is recorded 1 ms
// after the earlier, and neither counts as a duplicate. A clock set back still does.
#[test]
fn two_cycles_of_a_device_in_one_millisecond_are_both_recorded_and_a_clock_set_back_is_not() {
    use compgate_gateway::runtime::ChannelReading;
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let stats = rec.sender().stats().clone();
    let clock_ms = Arc::new(AtomicU64::new(10_000));
    let clock = clock_ms.clone();
    let mut obs = rec.observer_with_clock(Arc::new(move || clock.load(Ordering::Relaxed) as i64));
    let names: Arc<[String]> = Arc::from(vec!["T_a".to_string(), "T_b".to_string()]);
    let sample = |device: usize, v: f64| SampleReadings {
        device,
        channel_names: names.clone(),
        channels: vec![ChannelReading {
            channel: device,
            reading: compgate_core::channel::Reading {
                value_degc: Some(v),
                ..compgate_core::channel::Reading::no_data()
            },
        }],
        ..SampleReadings::default()
    };
    let at = |ms: u64| clock_ms.store(ms, Ordering::Relaxed);
    obs.on_sample(&sample(0, 0.0));
    obs.on_sample(&sample(0, 1.0));
    // Another device in the same millisecond keeps it.
    obs.on_sample(&sample(1, 2.0));
    // Its first cycle the next millisecond goes after the one moved there.
    at(10_001);
    obs.on_sample(&sample(0, 3.0));
    at(10_050);
    obs.on_sample(&sample(0, 4.0));
    // The clock set back onto recorded readings: stored at the next free millisecond.
    at(10_001);
    obs.on_sample(&sample(0, 5.0));
    drop(obs);
    rec.finish();
    let conn = open(&dir.path().join("r.db")).expect("opens");
    let rows: Vec<(String, i64, f64)> = conn
        .prepare(
            "SELECT c.name, t_unix_ms, value_degc FROM readings r JOIN channels c ON c.id = r.channel
             ORDER BY c.name, t_unix_ms",
        )
        .expect("query")
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("rows");
    let row = |name: &str, t: i64, v: f64| (name.to_string(), t, v);
    assert_eq!(
        rows,
        [
            row("T_a", 10_000, 0.0),
            row("T_a", 10_001, 1.0),
            row("T_a", 10_002, 3.0),
            row("T_a", 10_003, 5.0),
            row("T_a", 10_050, 4.0),
            row("T_b", 10_000, 2.0),
        ]
    );
    assert_eq!(stats.shifted_readings.load(Ordering::Relaxed), 1);
    assert_eq!(stats.duplicate_readings.load(Ordering::Relaxed), 0);
}

// A database recorded before shadow mode gets the `shadow` column on open, its old
// jobs counted as sent; shadow jobs are recorded with shadow 1 and ok 0.
#[test]
fn an_old_database_gets_the_shadow_column_and_shadow_jobs_are_marked() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("old.db");
    {
        let old = rusqlite::Connection::open(&path).expect("create");
        old.execute_batch(
            "CREATE TABLE jobs (t_unix_ms INTEGER NOT NULL, axis TEXT NOT NULL,
                sd43900_mm REAL NOT NULL, sd43910 REAL NOT NULL, sd43920_mm REAL NOT NULL,
                ok INTEGER NOT NULL, job_id INTEGER, elapsed_ms REAL, error TEXT);
             INSERT INTO jobs VALUES (1, 'X', 0.01, 0.0, 0.0, 1, 7, 1.0, NULL);",
        )
        .expect("old schema");
    }
    let mut conn = open(&path).expect("opens and migrates");
    let job = |shadow: bool| Record::Job {
        t_unix_ms: 2,
        axis: "X".into(),
        params: CompParams {
            k0_mm: 0.04,
            tan_beta: 0.0,
            p0_mm: 0.0,
        },
        job_id: None,
        elapsed_ms: None,
        error: None,
        shadow,
    };
    schema::insert(&mut conn, &mut schema::Statements::default(), &[job(true)]).expect("insert");
    let rows: Vec<(i64, i64, f64)> = conn
        .prepare("SELECT shadow, ok, sd43900_mm FROM jobs ORDER BY t_unix_ms")
        .expect("query")
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("rows");
    assert_eq!(rows, vec![(0, 1, 0.01), (1, 0, 0.04)]);
    // Opening again does not add it twice.
    drop(conn);
    open(&path).expect("opens again");
}

/// The `nc` table of the layout before NULL positions, with one row.
const OLD_NC: &str = "CREATE TABLE nc (t_unix_ms INTEGER NOT NULL, axis TEXT NOT NULL,
        position_mm REAL NOT NULL, applied_comp_mm REAL NOT NULL,
        sd43900_mm REAL NOT NULL, sd43910 REAL NOT NULL, sd43920_mm REAL NOT NULL);
    CREATE INDEX nc_t ON nc(t_unix_ms);
    INSERT INTO nc VALUES (1, 'X', 12.5, 0.002, 0.01, 0.0, 0.0);";

// A target that reports no position (OPC UA, ADS) recorded 0 mm, and an export
// with --axis took it for a standing axis. It records NULL now; a database of the
// layout before (NOT NULL columns) is rebuilt once on open, its rows kept.
#[test]
fn an_nc_read_without_a_position_is_recorded_as_null_in_old_databases_too() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("old.db");
    {
        let old = rusqlite::Connection::open(&path).expect("create");
        old.execute_batch(OLD_NC).expect("old schema");
    }
    let mut conn = open(&path).expect("opens and migrates");
    let read = Record::Nc {
        t_unix_ms: 2,
        axis: "X".into(),
        position_mm: None,
        applied_comp_mm: None,
        params: CompParams {
            k0_mm: 0.02,
            tan_beta: 0.0,
            p0_mm: 0.0,
        },
    };
    schema::insert(&mut conn, &mut schema::Statements::default(), &[read]).expect("insert");
    let rows: Vec<(i64, Option<f64>, Option<f64>, f64)> = conn
        .prepare(
            "SELECT t_unix_ms, position_mm, applied_comp_mm, sd43900_mm FROM nc ORDER BY t_unix_ms",
        )
        .expect("query")
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("rows");
    assert_eq!(
        rows,
        vec![(1, Some(12.5), Some(0.002), 0.01), (2, None, None, 0.02)]
    );
    let index: i64 = conn
        .query_row(
            "SELECT COUNT(*) FROM sqlite_schema WHERE type = 'index' AND name = 'nc_t' AND tbl_name = 'nc'",
            [],
            |r| r.get(0),
        )
        .expect("index");
    assert_eq!(index, 1);
    drop(conn);
    open(&path).expect("opens again");
}

// Where the rebuild failed (a nearly full disk), the old table refuses a NULL
// position: that row is skipped, and the rest of the commit goes in.
#[test]
fn an_nc_table_left_in_the_old_layout_skips_reads_without_a_position_only() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut conn = open(&dir.path().join("old.db")).expect("create");
    conn.execute_batch(&format!("DROP TABLE nc; {OLD_NC}"))
        .expect("old schema");
    let read = |t_unix_ms, position_mm| Record::Nc {
        t_unix_ms,
        axis: "X".into(),
        position_mm,
        applied_comp_mm: position_mm.map(|_| 0.0),
        params: CompParams {
            k0_mm: 0.02,
            tan_beta: 0.0,
            p0_mm: 0.0,
        },
    };
    schema::insert(
        &mut conn,
        &mut schema::Statements::default(),
        &[read(2, None), read(3, Some(4.0))],
    )
    .expect("the commit goes in");
    let rows: Vec<i64> = conn
        .prepare("SELECT t_unix_ms FROM nc ORDER BY t_unix_ms")
        .expect("query")
        .query_map([], |r| r.get(0))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("rows");
    assert_eq!(rows, vec![1, 3]);
}

// The one-time rebuild holds the write lock as long as the table takes (3 million
// rows, about 5 s): a second connection opening meanwhile (the MQTT outbox) gave up
// after the 5 s busy timeout, and nothing was published. It now waits for it.
#[test]
fn an_open_waits_for_another_connections_rebuild() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("old.db");
    // A recorder's database whose `nc` table is of the layout before.
    let old = open(&path).expect("create");
    old.execute_batch(&format!("DROP TABLE nc; {OLD_NC} BEGIN IMMEDIATE;"))
        .expect("old schema, write lock held");
    // A rebuild that takes longer than BUSY_TIMEOUT, in another connection.
    let holder = std::thread::spawn(move || {
        std::thread::sleep(schema::BUSY_TIMEOUT + std::time::Duration::from_secs(1));
        old.execute_batch("COMMIT").expect("commit");
    });
    let conn = open(&path).expect("waits for the other connection and opens");
    holder.join().expect("holder");
    let kept: i64 = conn
        .query_row(
            "SELECT COUNT(*) FROM nc WHERE position_mm = 12.5",
            [],
            |r| r.get(0),
        )
        .expect("row");
    assert_eq!(kept, 1);
}

// An export with --axis of an axis whose target reports no position gave pos_mm 0 in
// every row, without a word.
#[test]
fn export_refuses_pos_mm_of_a_target_that_reports_no_position() {
    let (_dir, db) = recorded(&[(0, 20)]);
    let conn = schema::open(&db).unwrap();
    for t in 0..20i64 {
        conn.execute(
            "INSERT INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (?1, 'X', NULL, NULL, 0.01, 0, 0)",
            [t * 1000],
        )
        .unwrap();
    }
    let mut args = export_args(&db, 0, 20);
    args.axis = Some("X".into());
    let e = export::measurements(&args).unwrap_err().to_string();
    assert!(
        e.starts_with("--axis: the NC target of axis `X` reports no position")
            && e.contains("leave --axis out"),
        "{e}"
    );
    // Without --axis the same window exports, pos_mm 0 as stated.
    args.axis = None;
    let (m, summary) = export::measurements(&args).unwrap();
    assert_eq!(m.len(), 20);
    assert!(summary.notes.iter().any(|n| n.contains("pos_mm is 0")));
}

// With a target that reports no applied compensation (or without --axis) an export of
// a compensated recording said nothing of it: the jobs table is the record that
// compgate wrote compensation, in the window or before it.
#[test]
fn export_names_the_compensation_compgate_wrote_where_none_was_reported() {
    let (_dir, db) = recorded(&[(0, 100)]);
    let conn = with_laser(&db);
    let job = |t_s: i64, axis: &str, k0_mm: f64, ok: bool, shadow: bool| {
        conn.execute(
            "INSERT INTO jobs(t_unix_ms, axis, sd43900_mm, sd43910, sd43920_mm, ok, shadow) VALUES (?1, ?2, ?3, 0, 0, ?4, ?5)",
            rusqlite::params![t_s * 1000, axis, k0_mm, ok, shadow],
        )
        .unwrap();
    };
    // X: one job left 30 um on the NC before the window, two more in it; Y: shadow
    // and failed jobs only, which compensated nothing.
    job(5, "X", 0.01, true, false);
    job(10, "X", 0.03, true, false);
    job(60, "X", 0.02, true, false);
    job(70, "X", 0.025, true, false);
    job(60, "Y", 0.05, false, true);
    job(61, "Y", 0.05, false, false);
    let mut args = export_args(&db, 50, 100);
    args.err_channel = Some("laser_um".into());
    let (_, summary) = export::measurements(&args).unwrap();
    let notes: Vec<&String> = summary
        .notes
        .iter()
        .filter(|n| n.contains("compgate compensated"))
        .collect();
    assert_eq!(notes.len(), 1, "{:?}", summary.notes);
    assert!(
        notes[0].contains("axis `X` in the window (2 verified jobs in it, SD43900 up to 30.0 um")
            && notes[0].contains("shadow = true"),
        "{}",
        notes[0]
    );
    // Before any job nothing was compensated: no note.
    args.since = "0".into();
    args.until = "5".into();
    let (_, summary) = export::measurements(&args).unwrap();
    assert!(
        !summary.notes.iter().any(|n| n.contains("compensated")),
        "{:?}",
        summary.notes
    );
}

// Review Z2: a job that landed but whose read-back was too slow (OPC UA) was not
// counted, so nothing was said; an axis with applied compensation recorded (the
// Modbus NC module) was told the record held none to add back; and an old recording
// with 0 stored for an OPC UA axis's position and applied compensation was exported
// with --axis without a word (and --add-applied-comp said the NC applied none).
#[test]
fn export_notes_go_by_what_the_nc_held_and_what_the_record_holds() {
    let (_dir, db) = recorded(&[(0, 100)]);
    let conn = with_laser(&db);
    let nc = |t_s: i64, axis: &str, pos: Option<f64>, applied: Option<f64>, k0_mm: f64| {
        conn.execute(
            "INSERT INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (?1, ?2, ?3, ?4, ?5, 0, 0)",
            rusqlite::params![t_s * 1000, axis, pos, applied, k0_mm],
        )
        .unwrap();
    };
    let job = |t_s: i64, axis: &str, k0_mm: f64, ok: bool| {
        conn.execute(
            "INSERT INTO jobs(t_unix_ms, axis, sd43900_mm, sd43910, sd43920_mm, ok, shadow) VALUES (?1, ?2, ?3, 0, 0, ?4, 0)",
            rusqlite::params![t_s * 1000, axis, k0_mm, ok],
        )
        .unwrap();
    };
    for t in (0..100).step_by(5) {
        // O: OPC UA, every read-back too slow, the value on the NC all the same.
        nc(t, "O", None, None, 0.012);
        job(t, "O", 0.012, false);
        // M: the Modbus NC module, applying 30 um.
        nc(t, "M", Some(5.0), Some(0.03), 0.03);
        job(t, "M", 0.03, true);
        // Z: an OPC UA axis recorded by a build that stored 0 for what it lacks.
        nc(t, "Z", Some(0.0), Some(0.0), 0.012);
        job(t, "Z", 0.012, true);
    }
    let mut args = export_args(&db, 50, 100);
    args.err_channel = Some("laser_um".into());
    let notes = |args: &export::ExportArgs| export::measurements(args).unwrap().1.notes;
    let all = notes(&args);
    let of = |notes: &[String], axis: &str| -> Vec<String> {
        notes
            .iter()
            .filter(|n| n.contains(&format!("axis `{axis}`")))
            .cloned()
            .collect()
    };
    let o = of(&all, "O");
    assert!(
        o.len() == 1
            && o[0].contains("SD43900 up to 12.0 um on the NC")
            && o[0].contains("holds no applied compensation"),
        "{all:?}"
    );
    let m = of(&all, "M");
    assert!(
        m.len() == 1
            && m[0].contains("up to 30.0 um")
            && m[0].contains("--axis M --add-applied-comp"),
        "{all:?}"
    );
    args.axis = Some("Z".into());
    let z = notes(&args);
    assert!(
        z.iter().any(
            |n| n.contains("axis `Z`") && n.contains("yet the record says the NC applied none")
        ),
        "{z:?}"
    );
    args.add_applied_comp = true;
    let z = notes(&args);
    assert!(
        z.iter()
            .any(|n| n.contains("yet the record says the NC applied none"))
            && z.iter().any(|n| n.contains(
                "--add-applied-comp: the record holds no applied compensation of axis `Z`"
            )),
        "{z:?}"
    );
}

// Review Z3: a read before the window that a verified job of 0 had replaced still
// called the window compensated; and applied compensation recorded with SD43900 and
// SD43910 at 0 was not named without --axis.
#[test]
fn export_notes_take_what_the_nc_held_last_and_applied_compensation_first() {
    let (_dir, db) = recorded(&[(0, 100)]);
    let conn = with_laser(&db);
    // B: the NC read 50 um at 10 s, a verified job set 0 at 20 s, no read after.
    conn.execute_batch(
        "INSERT INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (10000, 'B', NULL, NULL, 0.05, 0, 0);
         INSERT INTO jobs(t_unix_ms, axis, sd43900_mm, sd43910, sd43920_mm, ok, shadow) VALUES (20000, 'B', 0.0, 0, 0, 1, 0);",
    )
    .unwrap();
    // C: 20 um applied with the setting data at 0.
    for t in (50..100).step_by(5) {
        conn.execute(
            "INSERT INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (?1, 'C', 5.0, 0.02, 0, 0, 0)",
            [t * 1000],
        )
        .unwrap();
    }
    let mut args = export_args(&db, 50, 100);
    args.err_channel = Some("laser_um".into());
    let notes = export::measurements(&args).unwrap().1.notes;
    assert!(!notes.iter().any(|n| n.contains("axis `B`")), "{notes:?}");
    assert!(
        notes
            .iter()
            .any(|n| n.contains("axis `C` in the window (up to 20.0 um)")
                && n.contains("--axis C --add-applied-comp")),
        "{notes:?}"
    );
}

/// The database at `db` opened, with a channel `laser_um` reading 1 um once a second
/// over the first 100 s.
fn with_laser(db: &std::path::Path) -> rusqlite::Connection {
    let conn = schema::open(db).unwrap();
    conn.execute("INSERT INTO channels(id, name) VALUES (2, 'laser_um')", [])
        .unwrap();
    for t in 0..100i64 {
        conn.execute(
            "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, 2, 0.0, 1.0, 0)",
            [t * 1000],
        )
        .unwrap();
    }
    conn
}

/// A database holding channel `T_a`, read once a second over `spans` (start, end in
/// s, end exclusive), value 20 + t / 1000.
fn recorded(spans: &[(i64, i64)]) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    let conn = schema::open(&path).expect("opens");
    conn.execute("INSERT INTO channels(id, name) VALUES (1, 'T_a')", [])
        .unwrap();
    for &(from_s, to_s) in spans {
        for t in from_s..to_s {
            conn.execute(
                "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, 1, 12000.0, ?2, 0)",
                rusqlite::params![t * 1000, 20.0 + t as f64 / 1000.0],
            )
            .unwrap();
        }
    }
    (dir, path)
}

fn export_args(db: &std::path::Path, since_s: i64, until_s: i64) -> export::ExportArgs {
    export::ExportArgs {
        db: db.to_path_buf(),
        since: since_s.to_string(),
        until: until_s.to_string(),
        csv: true,
        out: None,
        axis: None,
        err_channel: None,
        step_s: 1.0,
        max_hold_s: 60.0,
        add_applied_comp: false,
    }
}

#[test]
fn export_holds_a_value_at_most_max_hold_s_across_a_gap() {
    // Recorded 0..10 s, nothing for an hour, then 4000..4010 s.
    let (_dir, db) = recorded(&[(0, 10), (4000, 4010)]);
    let (m, summary) = export::measurements(&export_args(&db, 0, 100_000)).unwrap();
    // Each span, the first held 60 s into the gap; neither the rest of the gap nor
    // the window past the record's last reading is filled.
    let t_s = &m.t_s;
    assert_eq!(m.len(), 10 + 60 + 10, "{t_s:?}");
    assert!(t_s
        .iter()
        .all(|t| *t <= 69.0 || (4000.0..=4009.0).contains(t)));
    let held = m.temp("a").unwrap();
    assert_eq!(held[69], 20.009, "the last reading of the first span, held");
    assert!(
        summary.notes.iter().any(|n| n.contains("--max-hold-s 60")),
        "{:?}",
        summary.notes
    );
    // A longer hold fills the gap; the last reading ends the rows.
    let mut args = export_args(&db, 0, 5000);
    args.max_hold_s = 4000.0;
    assert_eq!(export::measurements(&args).unwrap().0.len(), 4010);
}

// A channel renamed inside the window (B until 100 s, C from then on): every row
// needs every channel, so only the rows within --max-hold-s of the change could be
// exported, the rows before it were left out without a word and the rest blamed on
// "a gap in the record".
#[test]
fn a_channel_renamed_inside_the_window_is_named() {
    let (_dir, db) = recorded(&[(0, 200)]);
    let conn = schema::open(&db).unwrap();
    conn.execute_batch("INSERT INTO channels(id, name) VALUES (2, 'T_b'), (3, 'T_c')")
        .unwrap();
    for t in 0..200i64 {
        conn.execute(
            "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, ?2, 12000.0, 21.0, 0)",
            rusqlite::params![t * 1000, if t < 100 { 2 } else { 3 }],
        )
        .unwrap();
    }
    let (m, summary) = export::measurements(&export_args(&db, 0, 200)).unwrap();
    let note = summary
        .notes
        .iter()
        .find(|n| n.contains("renamed, added or removed"))
        .unwrap_or_else(|| panic!("{:?}", summary.notes));
    assert!(
        note.contains("`T_b` (ends inside the window)")
            && note.contains("`T_c` (starts inside the window)"),
        "{note}"
    );
    let counted: usize = note.split_whitespace().next().unwrap().parse().unwrap();
    assert_eq!(m.len() + counted, 200, "{note}");
    assert!(
        !summary
            .notes
            .iter()
            .any(|n| n.contains("a gap in the record")),
        "{:?}",
        summary.notes
    );
}

// `--axis` read the axis' positions from the start of the record (3.1 M rows for a
// 60 s export); now from the last one before the window, after the last move before
// it, which still gives the direction of the first rows and their position.
#[test]
fn an_axis_export_starts_from_the_position_before_the_window() {
    let (_dir, db) = recorded(&[(0, 100)]);
    let conn = schema::open(&db).unwrap();
    // Moved down from 10 to 5 mm at 1 s, idle since; up to 7 mm at 80 s.
    for (t_s, p) in [
        (0, 10.0),
        (1, 5.0),
        (2, 5.0),
        (30, 5.0),
        (80, 7.0),
        (90, 7.0),
    ] {
        conn.execute(
            "INSERT INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (?1, 'X', ?2, 0, 0, 0, 0)",
            rusqlite::params![t_s * 1000, p],
        )
        .unwrap();
    }
    let mut args = export_args(&db, 50, 100);
    args.axis = Some("X".into());
    args.max_hold_s = 1000.0;
    let (m, _) = export::measurements(&args).unwrap();
    assert_eq!((m.pos_mm[0], m.dir[0], m.travel_mm[0]), (5.0, -1, 0.0));
    let at_80 = m.t_s.iter().position(|t| *t == 30.0).unwrap();
    assert_eq!(
        (m.pos_mm[at_80], m.dir[at_80], m.travel_mm[at_80]),
        (7.0, 1, 2.0)
    );
}

#[test]
fn a_channel_reading_no_temperature_is_left_out_and_named() {
    let (_dir, db) = recorded(&[(0, 10)]);
    let conn = schema::open(&db).unwrap();
    conn.execute("INSERT INTO channels(id, name) VALUES (2, 'laser_um')", [])
        .unwrap();
    for t in 0..10 {
        conn.execute(
            "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, 2, 0.0, ?2, 0)",
            rusqlite::params![t * 1000, -250.0 + t as f64],
        )
        .unwrap();
    }
    let (m, summary) = export::measurements(&export_args(&db, 0, 10)).unwrap();
    assert!(m.temp("a").is_some() && m.temp("laser_um").is_none());
    assert!(
        summary
            .notes
            .iter()
            .any(|n| n.contains("`laser_um` left out: it reads -250")),
        "{:?}",
        summary.notes
    );
    // Given as the error channel, it is the error.
    let mut args = export_args(&db, 0, 10);
    args.err_channel = Some("laser_um".into());
    let (m, _) = export::measurements(&args).unwrap();
    assert_eq!(m.err_um.first(), Some(&-250.0));
}

#[test]
fn an_export_without_a_row_is_an_error_and_writes_nothing() {
    let (dir, db) = recorded(&[(0, 10)]);
    let out = dir.path().join("m.csv");
    std::fs::write(&out, "kept").unwrap();
    let mut args = export_args(&db, 100, 200);
    args.out = Some(out.clone());
    let e = export::run(&args).unwrap_err();
    assert!(e.to_string().contains("no reading in the window"), "{e}");
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "kept");
    // The database as the output: refused before anything is read or written.
    args.out = Some(db.clone());
    let e = export::run(&args).unwrap_err();
    assert!(e.to_string().contains("refusing to overwrite"), "{e}");
    assert!(schema::open(&db).is_ok());
    // A step that makes the record's span absurdly long is refused, naming the flag.
    let (_dir, db) = recorded(&[(0, 2), (7000, 7002)]);
    let mut args = export_args(&db, 0, 8000);
    args.step_s = 0.001;
    let e = export::run(&args).unwrap_err();
    assert!(e.to_string().contains("--step-s"), "{e}");
}

/// Waits up to 5 s for the writer to have committed `n` records in all.
fn wait_written(stats: &RecorderStats, n: u64) {
    let deadline = Instant::now() + Duration::from_secs(5);
    while stats.written.load(Ordering::Relaxed) < n && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(10));
    }
    assert_eq!(
        stats.written.load(Ordering::Relaxed),
        n,
        "records committed"
    );
}

/// The readings of channel `T_a` in `path`, oldest first.
fn values_of_t_a(path: &Path) -> Vec<f64> {
    let conn = open(path).expect("opens");
    let integrity: String = conn
        .query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .expect("integrity check");
    assert_eq!(integrity, "ok");
    let values = conn
        .prepare(
            "SELECT value_degc FROM readings r JOIN channels c ON c.id = r.channel
         WHERE c.name = 'T_a' ORDER BY t_unix_ms",
        )
        .expect("query")
        .query_map([], |r| r.get(0))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("rows");
    values
}

/// Starts a recorder committing every 50 ms, sends readings 0..5 of `T_a` (on their
/// own channel table, so `T_a` is not channel 1 and a stale channel id shows), runs
/// `delete` on the database path once they are committed, then sends 10..15 and
/// waits for their commit. Returns the path and the recorder's counters.
fn record_across(
    dir: &tempfile::TempDir,
    delete: impl FnOnce(&Path),
) -> (PathBuf, Arc<RecorderStats>) {
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        commit_interval_s: 0.05,
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let tx = rec.sender();
    let stats = tx.stats().clone();
    let name: Arc<[String]> = Arc::from(vec!["T_other".to_string(), "T_a".to_string()]);
    let send = |v: f64| {
        let mut c = cycle(&name, v);
        if let Record::Cycle { rows, .. } = &mut c {
            rows[0].channel = 1;
        }
        tx.send(c);
        // Distinct milliseconds: the time and channel are the readings' key.
        std::thread::sleep(Duration::from_millis(2));
    };
    (0..5).for_each(|i| send(f64::from(i)));
    wait_written(&stats, 5);
    delete(rec.path());
    (10..15).for_each(|i| send(f64::from(i)));
    wait_written(&stats, 10);
    let path = rec.path().to_path_buf();
    drop(tx);
    rec.finish();
    (path, stats)
}

// `rm r.db*` while recording: the writer notices at its next commit, creates the
// database again at its path, and what was sent after the deletion is in it.
#[test]
fn a_database_deleted_while_recording_is_created_again() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (path, stats) = record_across(&dir, |db| {
        for suffix in ["", "-wal", "-shm"] {
            std::fs::remove_file(with_suffix(db, suffix)).expect("deleted");
        }
    });
    assert!(path.exists(), "the database is created again");
    assert_eq!(values_of_t_a(&path), [10.0, 11.0, 12.0, 13.0, 14.0]);
    assert_eq!(stats.reopened.load(Ordering::Relaxed), 1);
    assert_eq!(stats.dropped_write.load(Ordering::Relaxed), 0);
}

// The database replaced (a backup moved over it) while another connection (the MQTT
// outbox) holds the old one: the old -wal and -shm stay at the path, and must not be
// paired with the new file (SQLite would replay the old WAL into it).
#[test]
fn a_replaced_database_is_not_paired_with_the_old_wal() {
    let dir = tempfile::tempdir().expect("tempdir");
    let backup = dir.path().join("backup.db");
    open(&backup)
        .expect("opens")
        .execute_batch("INSERT INTO mqtt_outbox(topic, payload) VALUES ('t', 'backup');")
        .expect("writes");
    let mut outbox = None;
    let (path, stats) = record_across(&dir, |db| {
        let conn = open(db).expect("opens");
        // Frames in the old WAL, not checkpointed into the old file.
        conn.execute_batch(
            "PRAGMA wal_autocheckpoint = 0;
             INSERT INTO mqtt_outbox(topic, payload) VALUES ('t', 'old');",
        )
        .expect("writes");
        std::fs::rename(&backup, db).expect("replaced");
        outbox = Some(conn);
    });
    assert_eq!(values_of_t_a(&path), [10.0, 11.0, 12.0, 13.0, 14.0]);
    let payloads: Vec<String> = open(&path)
        .expect("opens")
        .prepare("SELECT payload FROM mqtt_outbox")
        .expect("query")
        .query_map([], |r| r.get(0))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("rows");
    assert_eq!(
        payloads,
        ["backup"],
        "the backup and nothing of the old file"
    );
    assert_eq!(stats.reopened.load(Ordering::Relaxed), 1);
    drop(outbox);
}

// `rm r.db-wal` while recording: SQLite would go on appending to the unlinked WAL, so
// a crash (what is left at the path, copied while the writer still runs) would lose
// every record since. The writer notices at its next commit, checkpoints the old WAL
// into the database and opens it again with a new -wal: the records before and after
// the deletion are in the files at the path.
#[test]
fn a_wal_deleted_while_recording_keeps_every_record_through_a_crash() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (rec, tx, stats, names) = recorder_keeping_the_wal(&dir);
    (1..5).for_each(|i| send_t_a(&tx, &names, f64::from(i)));
    wait_written(&stats, 5);
    let wal = with_suffix(rec.path(), "-wal");
    std::fs::remove_file(&wal).expect("deleted");
    (10..15).for_each(|i| send_t_a(&tx, &names, f64::from(i)));
    wait_written(&stats, 10);
    // A crash now: what is left is the files at the path.
    let crashed = dir.path().join("crashed.db");
    std::fs::copy(rec.path(), &crashed).expect("copied");
    if wal.exists() {
        std::fs::copy(&wal, with_suffix(&crashed, "-wal")).expect("copied");
    }
    let all = [0.0, 1.0, 2.0, 3.0, 4.0, 10.0, 11.0, 12.0, 13.0, 14.0];
    assert_eq!(values_of_t_a(&crashed), all);
    assert!(wal.exists(), "a new -wal at the path");
    assert_eq!(stats.reopened.load(Ordering::Relaxed), 1);
    drop(tx);
    let path = rec.path().to_path_buf();
    rec.finish();
    assert_eq!(values_of_t_a(&path), all);
    assert_eq!(stats.dropped_write.load(Ordering::Relaxed), 0);
    assert_eq!(stats.duplicate_readings.load(Ordering::Relaxed), 0);
}

// Nothing deleted: no reopening, however many commits and retention passes.
#[test]
fn a_database_left_alone_is_not_reopened() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (path, stats) = record_across(&dir, |_| {});
    assert_eq!(values_of_t_a(&path).len(), 10);
    assert_eq!(stats.reopened.load(Ordering::Relaxed), 0);
}

// Two gateways on one database would mix their rows: the second recorder is refused
// while the first lives, naming the database; once the first is gone (its process
// ended, here its recorder dropped) the lock is free again.
#[test]
fn a_second_recorder_on_one_database_is_refused_while_the_first_runs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        ..RecorderConfig::default()
    };
    let first = Recorder::start(&cfg).expect("starts");
    let e = Recorder::start(&cfg).expect_err("a second recorder is refused");
    assert!(matches!(e, RecordError::InUse { .. }), "{e:?}");
    let text = e.to_string();
    assert!(
        text.contains(&cfg.path) && text.contains("another gateway records into it"),
        "{text}"
    );
    // Readers are not locked out.
    assert!(export::open_read_only(first.path()).is_ok());
    first.finish();
    // A recorder that finished leaves no lock file behind (an output directory
    // holds what was recorded, nothing else).
    let lock_file = dir.path().join("r.db.lock");
    assert!(!lock_file.exists());
    let second = Recorder::start(&cfg).expect("starts after the first stopped");
    assert!(lock_file.exists());
    second.finish();
    assert!(!lock_file.exists());
}

// A cycle whose channel the database already holds at its millisecond (the wall clock
// set back over recorded time) is stored at the next free millisecond and counted; the
// one recorded first stays. `INSERT OR REPLACE` once overwrote the recorded row, then
// `INSERT OR IGNORE` dropped the new one: a clock set back 30 s by hand dropped 204 of
// 240 readings, the poll grid landing on the recorded milliseconds. Only a channel
// held at every millisecond of a second is not stored.
#[test]
fn a_reading_that_meets_a_recorded_one_is_stored_after_it_and_never_replaces_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut conn = open(&dir.path().join("d.db")).expect("opens");
    let mut statements = schema::Statements::default();
    let names: Arc<[String]> = Arc::from(vec!["T_a".to_string(), "T_b".to_string()]);
    let at = |t_unix_ms: i64, v: f64| Record::Cycle {
        t_unix_ms,
        names: names.clone(),
        rows: vec![reading(0, v, 0), reading(1, v, 0)],
    };
    let done = schema::insert(&mut conn, &mut statements, &[at(1_000, 20.0)]).expect("insert");
    assert_eq!(done, schema::Inserted::default());
    // Set back onto 1000 twice in one batch, then on past it.
    let done = schema::insert(
        &mut conn,
        &mut statements,
        &[at(1_000, 99.0), at(1_000, 98.0), at(2_000, 21.0)],
    )
    .expect("insert");
    assert_eq!(
        done,
        schema::Inserted {
            ignored: 0,
            shifted: 4
        }
    );
    let t_a = |conn: &Connection| -> Vec<(i64, f64)> {
        conn.prepare("SELECT t_unix_ms, value_degc FROM readings WHERE channel = (SELECT id FROM channels WHERE name = 'T_a') ORDER BY t_unix_ms")
            .expect("query")
            .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
            .expect("rows")
            .collect::<Result<_, _>>()
            .expect("rows")
    };
    assert_eq!(
        t_a(&conn),
        [(1_000, 20.0), (1_001, 99.0), (1_002, 98.0), (2_000, 21.0)],
        "the first recording kept, the later ones after it"
    );
    // A fresh statement cache looks the newest reading up and shifts the same way.
    let done = schema::insert(
        &mut conn,
        &mut schema::Statements::default(),
        &[at(2_000, 22.0)],
    )
    .expect("insert");
    assert_eq!(done.shifted, 2);
    // Every millisecond of a second held: not stored.
    let full: Vec<Record> = (3_000..=4_000).map(|t| at(t, 1.0)).collect();
    schema::insert(&mut conn, &mut statements, &full).expect("insert");
    let done = schema::insert(&mut conn, &mut statements, &[at(3_000, 2.0)]).expect("insert");
    assert_eq!(
        done,
        schema::Inserted {
            ignored: 2,
            shifted: 0
        }
    );

    // Through the writer: counted in the stats.
    let cfg = RecorderConfig {
        path: dir.path().join("w.db").display().to_string(),
        commit_interval_s: 0.05,
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let tx = rec.sender();
    let stats = tx.stats().clone();
    tx.send(at(5_000, 20.0));
    tx.send(at(5_000, 30.0));
    drop(tx);
    rec.finish();
    assert_eq!(stats.shifted_readings.load(Ordering::Relaxed), 2);
    assert_eq!(stats.duplicate_readings.load(Ordering::Relaxed), 0);
    assert_eq!(stats.dropped_write.load(Ordering::Relaxed), 0);
}

// Another connection (the MQTT outbox) holds the write lock when a commit starts:
// the commit waits for it (busy timeout) instead of failing at once. A deferred
// transaction that first read the channel ids got SQLITE_BUSY on its first insert
// without waiting, and the batch was dropped.
#[test]
fn a_commit_waits_for_another_writer_instead_of_failing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("busy.db");
    let mut conn = open(&path).expect("opens");
    let other = open(&path).expect("opens");
    other
        .execute_batch(
            "BEGIN IMMEDIATE; INSERT INTO mqtt_outbox(topic, payload) VALUES ('t', 'p');",
        )
        .expect("holds the write lock");
    let (started_tx, started_rx) = mpsc::channel();
    let writer = std::thread::spawn(move || {
        let names: Arc<[String]> = Arc::from(vec!["T_a".to_string()]);
        started_tx.send(()).expect("main waits");
        // A fresh statement cache: the transaction starts with the channel id lookup.
        schema::insert(
            &mut conn,
            &mut schema::Statements::default(),
            &[cycle(&names, 1.0)],
        )
    });
    started_rx.recv().expect("writer started");
    // Long enough for the insert to meet the lock (it does not matter if it does
    // not: the test then passes either way, it cannot fail spuriously).
    std::thread::sleep(Duration::from_millis(200));
    other.execute_batch("COMMIT;").expect("commits");
    let result = writer.join().expect("writer thread");
    assert_eq!(
        result.expect("the commit waited for the lock"),
        schema::Inserted::default()
    );
}

// `validate` runs this check: a database in a missing directory, or one this process
// cannot write, is refused naming recorder.path and the file, and nothing is
// created.
#[test]
fn check_path_refuses_a_missing_directory_and_creates_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let missing = dir.path().join("nodir").join("sub").join("g.db");
    let e = check_path(&missing).expect_err("refused");
    let text = e.to_string();
    assert!(
        text.starts_with("recorder.path")
            && text.contains(&missing.display().to_string())
            && text.contains(&format!(
                "the directory {} does not exist",
                missing.parent().unwrap().display()
            )),
        "{text}"
    );
    assert!(!dir.path().join("nodir").exists(), "nothing created");
    let e = check_path(dir.path()).expect_err("a directory is no database");
    assert!(e.to_string().contains("is a directory"), "{e}");
    let fresh = dir.path().join("g.db");
    check_path(&fresh).expect("a new database in a writable directory");
    assert!(!fresh.exists(), "nothing created");
    // The same check in `run`: the message names the directory.
    let cfg = RecorderConfig {
        path: missing.display().to_string(),
        ..RecorderConfig::default()
    };
    let e = Recorder::start(&cfg).expect_err("refused");
    assert!(e.to_string().contains("does not exist"), "{e}");
}

// A device outage: the gateway records its channels' held values as uncertain (comm)
// without a raw value. Those are no measurements, and the last measured value is not
// held across them either, however short the outage: the record says nobody measured
// then. Before, the rows of an outage shorter than --max-hold-s carried the frozen
// last value, and the note counted only rows left out.
#[test]
fn held_values_of_a_device_outage_are_a_gap_not_measurements() {
    // Measured 0..10 s, then 20 s of comm rows holding 20.009, then measured again.
    let (_dir, db) = recorded(&[(0, 10), (30, 40)]);
    let conn = schema::open(&db).unwrap();
    for t in 10..30 {
        conn.execute(
            "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality, reason) VALUES (?1, 1, NULL, 20.009, 1, 'comm')",
            [t * 1000],
        )
        .unwrap();
    }
    // The default --max-hold-s of 60 s would cover the whole outage.
    let (m, summary) = export::measurements(&export_args(&db, 0, 100)).unwrap();
    let t_s = &m.t_s;
    assert_eq!(m.len(), 10 + 10, "{t_s:?}");
    assert!(
        t_s.iter().all(|t| *t <= 9.0 || *t >= 30.0),
        "no row in the outage: {t_s:?}"
    );
    assert!(
        summary
            .notes
            .iter()
            .any(|n| n.starts_with("20 rows left out: a channel's latest reading")),
        "{:?}",
        summary.notes
    );
    // A bad reading is no measurement either: no value is held across it.
    conn.execute(
        "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality, reason) VALUES (40000, 1, 12000.0, 20.04, 2, 'NE43 low')",
        [],
    )
    .unwrap();
    let mut args = export_args(&db, 0, 100);
    args.step_s = 0.5;
    let (m, _) = export::measurements(&args).unwrap();
    assert_eq!(m.t_s.last(), Some(&39.5), "{:?}", m.t_s);
}

// The rows end at the last reading, not --max-hold-s after it; t_s counts from the
// first row, so an early --since gives times `calibrate` takes.
#[test]
fn rows_stop_at_the_last_reading_and_t_s_counts_from_the_first_row() {
    let (dir, db) = recorded(&[(1_000_000_000, 1_000_000_010)]);
    schema::open(&db)
        .unwrap()
        .execute(
            "UPDATE readings SET value_degc = 25.0 + (t_unix_ms % 10000) / 1000.0",
            [],
        )
        .unwrap();
    let (m, _) = export::measurements(&export_args(&db, 0, 2_000_000_000)).unwrap();
    assert_eq!(m.t_s, (0..10).map(f64::from).collect::<Vec<_>>());
    assert_eq!(m.temp("a").unwrap().last(), Some(&34.0), "the last reading");
    // The written file is one calibrate reads back.
    let out = dir.path().join("m.csv");
    let mut args = export_args(&db, 0, 2_000_000_000);
    args.out = Some(out.clone());
    export::run(&args).unwrap();
    let back = compgate_core::measure::Measurements::read_path(&out).expect("reads back");
    assert_eq!(back.len(), 10);
}

// `--out` naming the database's -wal, -shm, -journal or lock file, in any spelling,
// is refused whether or not that file exists now (a running gateway's WAL holds
// committed transactions not yet in the database).
#[test]
fn an_output_on_the_databases_companion_files_is_refused() {
    let (dir, db) = recorded(&[(0, 10)]);
    let sub = dir.path().join("sub");
    std::fs::create_dir(&sub).unwrap();
    // A connection keeps the -wal and -shm files in place.
    let live = schema::open(&db).unwrap();
    assert!(with_suffix(&db, "-wal").exists());
    for suffix in ["", "-wal", "-shm", "-journal", ".lock"] {
        let name = format!("r.db{suffix}");
        for out in [
            dir.path().join(&name),
            sub.join("..").join(&name),
            dir.path().join(".").join("sub").join("..").join(&name),
        ] {
            let before = std::fs::read(&out).ok();
            let mut args = export_args(&db, 0, 10);
            args.out = Some(out.clone());
            let e = export::run(&args).unwrap_err();
            assert!(
                e.to_string().contains("refusing to overwrite"),
                "{}: {e}",
                out.display()
            );
            assert_eq!(
                std::fs::read(&out).ok(),
                before,
                "{} untouched",
                out.display()
            );
        }
    }
    // Another name in the same directory is fine.
    let mut args = export_args(&db, 0, 10);
    args.out = Some(sub.join("..").join("r.db.csv"));
    export::run(&args).unwrap();
    drop(live);
}

// The status is published more often than the NC is read: one `nc` row per read.
#[test]
fn one_nc_row_per_read_of_the_nc_not_per_status() {
    use compgate_gateway::nc::NcSnapshot;
    use compgate_gateway::runtime::AxisStatus;
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let mut obs = rec.observer();
    let mut status = Status {
        axes: vec![AxisStatus {
            name: "X".into(),
            nc: Some(NcSnapshot::default()),
            ..AxisStatus::default()
        }],
        ..Status::default()
    };
    for reads in [1, 1, 1, 2, 2, 3] {
        status.axes[0].nc_reads = reads;
        obs.on_status(&status);
    }
    drop(obs);
    rec.finish();
    let conn = Connection::open(dir.path().join("r.db")).expect("open");
    let rows: i64 = conn
        .query_row("SELECT count(*) FROM nc", [], |r| r.get(0))
        .expect("nc rows");
    assert_eq!(rows, 3);
}

// An `nc` row was stamped when the status came out, up to a status interval after
// the read: the positions export took lagged the axis by that (review Y).
#[test]
fn an_nc_row_is_stamped_when_the_nc_was_read() {
    use compgate_gateway::nc::NcSnapshot;
    use compgate_gateway::runtime::AxisStatus;
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let mut obs = rec.observer();
    let read_at = std::time::Instant::now() - std::time::Duration::from_millis(800);
    let status = Status {
        axes: vec![AxisStatus {
            name: "X".into(),
            nc: Some(NcSnapshot::default()),
            nc_reads: 1,
            nc_read_at: Some(read_at),
            ..AxisStatus::default()
        }],
        ..Status::default()
    };
    let before_ms = now_unix_ms();
    obs.on_status(&status);
    let after_ms = now_unix_ms();
    drop(obs);
    rec.finish();
    let conn = Connection::open(dir.path().join("r.db")).expect("open");
    let t: i64 = conn
        .query_row("SELECT t_unix_ms FROM nc", [], |r| r.get(0))
        .expect("nc row");
    assert!(
        (before_ms - 810..=after_ms - 790).contains(&t),
        "{t} not 800 ms before {before_ms}..{after_ms}"
    );
}

// SQLite stores a NaN as NULL: a NaN raw value is told apart from a device that gave
// none by its reason, `not finite` (quality bad), not by `raw`; an infinite one is
// stored as it came.
#[test]
fn a_nan_raw_value_is_null_with_reason_not_finite_and_a_comm_failure_is_not() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut conn = open(&dir.path().join("n.db")).expect("opens");
    let names: Arc<[String]> = vec!["T_nan".into(), "T_inf".into(), "T_comm".into()].into();
    let bad = |channel, raw, reason| Row {
        channel,
        raw,
        unfiltered_degc: raw,
        value_degc: Some(20.0),
        quality: 2,
        reason: Some(reason),
    };
    let not_finite = compgate_core::channel::Reason::NotFinite.as_str();
    let comm = compgate_core::channel::Reason::Comm.as_str();
    let cycle = Record::Cycle {
        t_unix_ms: 1_000,
        names,
        rows: vec![
            bad(0, Some(f64::NAN), not_finite),
            bad(1, Some(f64::INFINITY), not_finite),
            bad(2, None, comm),
        ],
    };
    schema::insert(&mut conn, &mut schema::Statements::default(), &[cycle]).expect("inserted");
    let row = |name: &str| -> (Option<f64>, u8, String) {
        conn.query_row(
            "SELECT raw, quality, reason FROM readings r JOIN channels c ON c.id = r.channel WHERE c.name = ?1",
            [name],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
        )
        .expect("reading")
    };
    assert_eq!(row("T_nan"), (None, 2, "not finite".into()));
    assert_eq!(row("T_inf"), (Some(f64::INFINITY), 2, "not finite".into()));
    assert_eq!(row("T_comm"), (None, 2, "comm".into()));
}

/// Sends one reading of `T_a` (on the channel table `names`, index 1) valued `v`.
fn send_t_a(tx: &RecordSender, names: &Arc<[String]>, v: f64) {
    let mut c = cycle(names, v);
    if let Record::Cycle { rows, .. } = &mut c {
        rows[0].channel = 1;
    }
    tx.send(c);
    // Distinct milliseconds: the time and channel are the readings' key.
    std::thread::sleep(Duration::from_millis(2));
}

/// A recorder at `r.db` in `dir`, committing every 0.05 s, whose retention checkpoints
/// only in its first pass (later records stay in the WAL), with the first record of
/// [`send_t_a`] committed; its sender, stats and channel names.
fn recorder_keeping_the_wal(
    dir: &tempfile::TempDir,
) -> (Recorder, RecordSender, Arc<RecorderStats>, Arc<[String]>) {
    let cfg = RecorderConfig {
        path: dir.path().join("r.db").display().to_string(),
        commit_interval_s: 0.05,
        retention_interval_s: 3600.0,
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let tx = rec.sender();
    let stats = tx.stats().clone();
    let names: Arc<[String]> = Arc::from(vec!["T_other".to_string(), "T_a".to_string()]);
    send_t_a(&tx, &names, 0.0);
    wait_written(&stats, 1);
    (rec, tx, stats, names)
}

// `mv r.db archived.db` while recording: the moved file keeps every record committed
// to it, those still in the WAL too (SQLite does not checkpoint at close a file that
// moved, and the WAL at the old path was removed with them in it); the recorder goes
// on in a new database at its path.
#[test]
fn a_database_moved_while_recording_keeps_every_committed_record() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (rec, tx, stats, names) = recorder_keeping_the_wal(&dir);
    // Committed into the WAL only.
    (1..6).for_each(|i| send_t_a(&tx, &names, f64::from(i)));
    wait_written(&stats, 6);
    let archived = dir.path().join("archived.db");
    std::fs::rename(rec.path(), &archived).expect("moved");
    (10..15).for_each(|i| send_t_a(&tx, &names, f64::from(i)));
    wait_written(&stats, 11);
    drop(tx);
    let path = rec.path().to_path_buf();
    rec.finish();
    assert_eq!(values_of_t_a(&archived), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    assert_eq!(values_of_t_a(&path), [10.0, 11.0, 12.0, 13.0, 14.0]);
    assert_eq!(stats.reopened.load(Ordering::Relaxed), 1);
    assert_eq!(stats.dropped_write.load(Ordering::Relaxed), 0);

    // Where a moved file went is found by the file the process has open; a deleted
    // one is nowhere.
    let f = std::fs::File::create(dir.path().join("a")).expect("created");
    let id = file_id(&dir.path().join("a")).expect("there");
    std::fs::rename(dir.path().join("a"), dir.path().join("b")).expect("moved");
    assert_eq!(open_path_of(id), Some(dir.path().join("b")));
    std::fs::remove_file(dir.path().join("b")).expect("deleted");
    assert_eq!(open_path_of(id), None);
    drop(f);
}

/// A good reading of channel 1 at `t_unix_ms`, written straight into the database.
fn good_reading_at(conn: &Connection, t_unix_ms: i64) {
    conn.execute(
        "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, 1, 12000.0, 20.0, 0)",
        [t_unix_ms],
    )
    .expect("reading");
}

// The size limit with the MQTT outbox grown (the broker away): the unsent messages go
// first, oldest first, and the recorded history stays. Before, retention cut the
// readings' time range only, and the outbox pushed the records out.
#[test]
fn over_its_size_the_recorder_deletes_unsent_messages_before_records() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    let conn = open(&path).expect("opens");
    conn.execute("INSERT INTO channels(id, name) VALUES (1, 'T_a')", [])
        .expect("channel");
    let now = now_unix_ms();
    // The last minute, every 20 ms; then 3000 messages of 200 bytes.
    for k in 0..3000i64 {
        good_reading_at(&conn, now - 60_000 + k * 20);
    }
    let records_bytes = schema::data_bytes(&conn).expect("size");
    for k in 0..3000 {
        conn.execute(
            "INSERT INTO mqtt_outbox(topic, payload) VALUES ('compgate/readings', ?1)",
            [format!("{k:0200}")],
        )
        .expect("message");
    }
    let all_bytes = schema::data_bytes(&conn).expect("size");
    let (first_id, last_id): (i64, i64) = conn
        .query_row("SELECT min(id), max(id) FROM mqtt_outbox", [], |r| {
            Ok((r.get(0)?, r.get(1)?))
        })
        .expect("ids");
    drop(conn);
    // Room for the records and half the messages.
    let max_bytes = records_bytes + (all_bytes - records_bytes) / 2;
    let cfg = RecorderConfig {
        path: path.display().to_string(),
        max_size_mb: max_bytes as f64 / 1024.0 / 1024.0,
        ..RecorderConfig::default()
    };
    let rec = Recorder::start(&cfg).expect("starts");
    let stats = rec.sender().stats().clone();
    // Its one retention pass runs before the last commit.
    rec.finish();
    let conn = open(&path).expect("opens");
    assert!(schema::data_bytes(&conn).expect("size") <= max_bytes);
    assert_eq!(counts(&conn).expect("counts").0, 3000, "every reading kept");
    let (left, oldest, newest): (i64, i64, i64) = conn
        .query_row(
            "SELECT count(*), min(id), max(id) FROM mqtt_outbox",
            [],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
        )
        .expect("outbox");
    assert!(
        left > 0 && oldest > first_id && newest == last_id,
        "{left} messages left, ids {oldest}..={newest}"
    );
    assert_eq!(
        stats.outbox_deleted.load(Ordering::Relaxed),
        3000 - left as u64
    );
}

// A database gets the layout version on open; one of a later version (written by a
// newer build) is refused by `validate`'s check and by `open`, naming both versions,
// and left as it was: an older build would otherwise fail every commit into it.
#[test]
fn a_database_of_a_newer_layout_is_refused_and_ours_gets_its_version() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("v.db");
    let version = |path: &Path| -> i64 {
        export::open_read_only(path)
            .expect("opens")
            .query_row("PRAGMA user_version", [], |r| r.get(0))
            .expect("version")
    };
    drop(open(&path).expect("opens"));
    assert_eq!(version(&path), schema::LAYOUT_VERSION);
    rusqlite::Connection::open(&path)
        .expect("opens")
        .execute_batch(&format!(
            "PRAGMA user_version = {};",
            schema::LAYOUT_VERSION + 1
        ))
        .expect("set");
    for e in [
        check_path(&path).expect_err("validate refuses").to_string(),
        open(&path).expect_err("open refuses").to_string(),
    ] {
        assert!(
            e.contains(&path.display().to_string())
                && e.contains(&format!(
                    "newer compgate (recorder layout {}; this build knows up to {})",
                    schema::LAYOUT_VERSION + 1,
                    schema::LAYOUT_VERSION
                )),
            "{e}"
        );
    }
    assert_eq!(version(&path), schema::LAYOUT_VERSION + 1);
}

// Readings stamped 400 days ahead (a clock set wrong, then right) do not stretch the
// time range the size limit cuts tenths of: the first tenth took every reading of the
// last minute in one step, and kept the ones of the wrong clock.
#[test]
fn over_its_size_readings_stamped_ahead_do_not_take_the_recorded_ones_at_once() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    let conn = open(&path).expect("opens");
    conn.execute("INSERT INTO channels(id, name) VALUES (1, 'T_a')", [])
        .expect("channel");
    let now = now_unix_ms();
    for k in 0..3000i64 {
        good_reading_at(&conn, now - 60_000 + k * 20);
    }
    let records_bytes = schema::data_bytes(&conn).expect("size");
    for k in 0..100i64 {
        good_reading_at(&conn, now + 400 * 86_400_000 + k * 20);
    }
    drop(conn);
    let max_bytes = records_bytes * 8 / 10;
    let cfg = RecorderConfig {
        path: path.display().to_string(),
        max_size_mb: max_bytes as f64 / 1024.0 / 1024.0,
        ..RecorderConfig::default()
    };
    Recorder::start(&cfg).expect("starts").finish();
    let conn = open(&path).expect("opens");
    assert!(schema::data_bytes(&conn).expect("size") <= max_bytes);
    let kept: i64 = conn
        .query_row(
            "SELECT count(*) FROM readings WHERE t_unix_ms <= ?1",
            [now],
            |r| r.get(0),
        )
        .expect("count");
    assert!(
        kept >= 1500,
        "{kept} of the last minute's 3000 readings kept"
    );
}

// A database of another layout (the readings of an older recorder, without the
// unfiltered temperature) is refused by `validate`'s check and by `run`, naming the
// file, the table and the column, before anything is written to it or beside it;
// before, it was accepted and every commit of the run failed.
#[test]
fn a_database_of_an_older_layout_is_refused_naming_table_and_column() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("old.db");
    rusqlite::Connection::open(&path)
        .expect("created")
        .execute_batch(
            "CREATE TABLE channels(id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE);
             CREATE TABLE readings(t_unix_ms INTEGER NOT NULL, channel INTEGER NOT NULL,
                raw REAL, value_degc REAL, quality INTEGER NOT NULL,
                PRIMARY KEY (t_unix_ms, channel)) WITHOUT ROWID;",
        )
        .expect("old layout");
    let before = std::fs::read(&path).expect("read");
    let e = check_path(&path).expect_err("refused");
    let text = e.to_string();
    assert!(
        text.contains(&path.display().to_string())
            && text.contains("table readings has no column unfiltered_degc, reason"),
        "{text}"
    );
    let cfg = RecorderConfig {
        path: path.display().to_string(),
        ..RecorderConfig::default()
    };
    let e = Recorder::start(&cfg).expect_err("refused");
    assert!(e.to_string().contains("no column unfiltered_degc"), "{e}");
    let e = open(&path).expect_err("refused");
    assert!(e.to_string().contains("no column unfiltered_degc"), "{e}");
    assert_eq!(std::fs::read(&path).expect("read"), before, "untouched");
    let files: Vec<_> = std::fs::read_dir(dir.path())
        .expect("dir")
        .map(|e| e.expect("entry").file_name())
        .collect();
    assert_eq!(files, ["old.db"], "nothing created beside it");
}

// `validate` (check_path) passed what `run` refuses or must not touch: random bytes,
// the config file, a device. Each is refused naming the path, and `run` refuses them
// before it creates its lock file; a recording of the current layout and an empty
// file pass.
#[test]
fn check_path_refuses_what_is_no_recorder_database() {
    let dir = tempfile::tempdir().expect("tempdir");
    let garbage = dir.path().join("garbage.db");
    let mut bytes = vec![0u8; 100_000];
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    for b in &mut bytes {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        *b = x as u8;
    }
    std::fs::write(&garbage, &bytes).expect("written");
    let config = dir.path().join("g.toml");
    std::fs::write(&config, "[recorder]\npath = \"g.toml\"\n").expect("written");
    let foreign = dir.path().join("foreign.db");
    rusqlite::Connection::open(&foreign)
        .expect("created")
        .execute_batch("CREATE TABLE users(name TEXT);")
        .expect("table");
    for (path, why) in [
        (garbage.as_path(), "is not an SQLite database"),
        (config.as_path(), "is not an SQLite database"),
        (
            foreign.as_path(),
            "without any of the recorder's tables (it holds users)",
        ),
        (Path::new("/dev/null"), "is not a regular file"),
    ] {
        let e = check_path(path).expect_err("refused");
        let text = e.to_string();
        assert!(
            text.contains(&path.display().to_string()) && text.contains(why),
            "{text}"
        );
    }
    let listing = || {
        let mut files: Vec<_> = std::fs::read_dir(dir.path())
            .expect("dir")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        files.sort();
        files
    };
    let before = listing();
    let cfg = RecorderConfig {
        path: garbage.display().to_string(),
        ..RecorderConfig::default()
    };
    let e = Recorder::start(&cfg).expect_err("refused");
    assert!(e.to_string().contains("is not an SQLite database"), "{e}");
    assert_eq!(listing(), before, "no lock file, no -wal");
    // What passes: a recording (closed, and while open), an empty file.
    let good = dir.path().join("good.db");
    let conn = open(&good).expect("created");
    check_path(&good).expect("a recording in use");
    drop(conn);
    check_path(&good).expect("a recording");
    let empty = dir.path().join("empty.db");
    std::fs::write(&empty, "").expect("written");
    check_path(&empty).expect("an empty file");
    assert_eq!(
        listing(),
        ["empty.db", "foreign.db", "g.toml", "garbage.db", "good.db"],
        "the checks leave nothing behind"
    );
}

// A power cut took the last 20 s of commits (`synchronous = NORMAL` syncs the WAL only
// at checkpoints): every connection the recorder and the outbox open syncs each commit.
#[test]
fn every_connection_syncs_each_commit() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    for _ in 0..2 {
        let conn = open(&path).expect("opens");
        let level: i64 = conn
            .query_row("PRAGMA synchronous", [], |r| r.get(0))
            .expect("synchronous");
        assert_eq!(level, 2, "FULL");
    }
}

// A database cut short (a disk that lost its end): `validate` and `run` refuse it as
// damaged, and say what to do about it.
#[test]
fn a_truncated_database_is_refused_with_what_to_do() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    {
        let mut conn = open(&path).expect("opens");
        let names: Arc<[String]> = Arc::from(vec!["T_a".to_string()]);
        let batch: Vec<Record> = (0..2000)
            .map(|k| Record::Cycle {
                t_unix_ms: 1_000 + k,
                names: names.clone(),
                rows: vec![reading(0, 1.0, 0)],
            })
            .collect();
        schema::insert(&mut conn, &mut schema::Statements::default(), &batch).expect("rows");
        assert!(checkpoint(&conn));
    }
    let len = std::fs::metadata(&path).expect("file").len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&path)
        .and_then(|f| f.set_len(4096))
        .expect("truncated");
    assert!(len > 4096 * 4, "{len}");
    let e = check_path(&path).expect_err("refused").to_string();
    for want in [
        "the file is damaged",
        "move it away (the recorder then starts a new one at its path",
    ] {
        assert!(e.contains(want), "{want}: {e}");
    }
}

// ext4 (`errors=remount-ro`) turns read-only under the open database after a disk
// error; SQLite says only "disk I/O error". The ERROR names the read-only file system.
#[test]
fn a_read_only_file_system_is_named_in_the_commit_error() {
    let io = RecordError::Sqlite(rusqlite::Error::SqliteFailure(
        rusqlite::ffi::Error::new(rusqlite::ffi::SQLITE_IOERR_WRITE),
        Some("disk I/O error".into()),
    ));
    let text = commit_error(&io, true);
    assert!(
        text.starts_with("recorder database: disk I/O error: the file system is read-only (EROFS"),
        "{text}"
    );
    assert_eq!(commit_error(&io, false), io.to_string());
    // A writable file system is not taken for read-only, and the probe leaves nothing.
    let dir = tempfile::tempdir().expect("tempdir");
    assert!(!read_only_fs(&dir.path().join("r.db")));
    std::fs::write(dir.path().join("r.db.probe"), "").expect("left by a crash");
    assert!(!read_only_fs(&dir.path().join("r.db")));
    assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 0);
}

// The oldest records beyond the limit go first, NC jobs last.
#[test]
fn records_beyond_the_limit_are_shed_oldest_first_jobs_last() {
    let names: Arc<[String]> = Arc::from(vec!["T_a".to_string()]);
    let job = |t_unix_ms| Record::Job {
        t_unix_ms,
        axis: "X".into(),
        params: CompParams::default(),
        job_id: None,
        elapsed_ms: None,
        error: None,
        shadow: false,
    };
    let kind = |b: &[Record]| -> Vec<String> {
        b.iter()
            .map(|r| match r {
                Record::Job { t_unix_ms, .. } => format!("job{t_unix_ms}"),
                Record::Cycle { rows, .. } => format!("cycle{}", rows[0].raw.unwrap_or(0.0)),
                Record::Nc { .. } => "nc".into(),
                Record::Outbox { .. } => "outbox".into(),
            })
            .collect()
    };
    let mut batch = vec![
        cycle(&names, 1.0),
        job(1),
        cycle(&names, 2.0),
        job(2),
        cycle(&names, 3.0),
    ];
    assert_eq!(shed(&mut batch, 5), (0, 0));
    assert_eq!(shed(&mut batch, 4), (1, 1));
    assert_eq!(kind(&batch), ["job1", "cycle2", "job2", "cycle3"]);
    assert_eq!(shed(&mut batch, 1), (3, 2));
    assert_eq!(kind(&batch), ["job2"]);
}

/// The message of every event, with its level.
#[derive(Clone, Default)]
struct Logged(Arc<std::sync::Mutex<Vec<String>>>);

impl Logged {
    fn lines(&self, needle: &str) -> Vec<String> {
        let lines = self.0.lock().expect("log");
        lines
            .iter()
            .filter(|l| l.contains(needle))
            .cloned()
            .collect()
    }

    fn subscriber(&self) -> impl tracing::Subscriber + Send + Sync {
        use tracing_subscriber::layer::SubscriberExt;
        tracing_subscriber::registry().with(self.clone())
    }
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for Logged {
    fn on_event(&self, event: &tracing::Event<'_>, _: tracing_subscriber::layer::Context<'_, S>) {
        struct Message(String);
        impl tracing::field::Visit for Message {
            fn record_debug(&mut self, f: &tracing::field::Field, v: &dyn std::fmt::Debug) {
                if f.name() == "message" {
                    self.0 = format!("{v:?}");
                }
            }
        }
        let mut m = Message(String::new());
        event.record(&mut m);
        let line = format!("{} {}", event.metadata().level(), m.0);
        self.0.lock().expect("log").push(line);
    }
}

/// Waits up to 10 s for `done`.
fn wait_until(what: &str, done: impl Fn() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !done() {
        assert!(Instant::now() < deadline, "{what}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

// Another process holds the database's write lock longer than the busy timeout (here
// 20 ms, the connection's own setting), twice: the records of the failed commits wait
// and are all committed once the lock is free, NC jobs included; each lock is logged
// once when commits start failing and once when they succeed again. Before, each
// failed commit dropped its batch, and only the first failure of the process was
// logged.
#[test]
fn a_locked_database_keeps_the_records_and_each_outage_is_logged_once() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    let conn = open(&path).expect("opens");
    conn.busy_timeout(Duration::from_millis(20))
        .expect("timeout");
    let cfg = RecorderConfig {
        path: path.display().to_string(),
        commit_interval_s: 0.01,
        ..RecorderConfig::default()
    };
    let (tx, rx) = mpsc::sync_channel(1000);
    let (writer, stats, shared) = test_writer(&cfg, &path, conn, 500);
    let logged = Logged::default();
    let subscriber = logged.subscriber();
    let thread = std::thread::spawn(move || {
        tracing::subscriber::with_default(subscriber, || writer.run(rx));
    });
    let tx = RecordSender {
        tx,
        stats: stats.clone(),
        shared,
    };
    let names: Arc<[String]> = Arc::from(vec!["T_other".to_string(), "T_a".to_string()]);
    let job = |id: u16| Record::Job {
        t_unix_ms: now_unix_ms(),
        axis: "X".into(),
        params: CompParams::default(),
        job_id: Some(id),
        elapsed_ms: Some(1.0),
        error: None,
        shadow: false,
    };
    let other = open(&path).expect("opens");
    let mut sent = 0;
    let mut job_id = 0;
    for outage in 1..=2u64 {
        other
            .execute_batch("BEGIN IMMEDIATE;")
            .expect("holds the write lock");
        for v in 0..3 {
            send_t_a(&tx, &names, f64::from(v));
            job_id += 1;
            tx.send(job(job_id));
            sent += 2;
        }
        let failed = |n| stats.failed_commits.load(Ordering::Relaxed) >= n;
        wait_until("commits fail", || failed(3 * outage));
        assert!(stats.failing.load(Ordering::Relaxed));
        other.execute_batch("COMMIT;").expect("lock released");
        wait_until("the waiting records committed", || {
            stats.written.load(Ordering::Relaxed) == sent && !stats.failing.load(Ordering::Relaxed)
        });
    }
    drop(tx);
    thread.join().expect("writer");
    assert_eq!(stats.dropped_write.load(Ordering::Relaxed), 0);
    let ids: Vec<u16> = other
        .prepare("SELECT job_id FROM jobs ORDER BY job_id")
        .expect("query")
        .query_map([], |r| r.get(0))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("rows");
    assert_eq!(ids, (1..=6).collect::<Vec<u16>>(), "every NC job recorded");
    assert_eq!(values_of_t_a(&path).len(), 6);
    let failed = logged.lines("recorder commit failed");
    assert_eq!(failed.len(), 2, "{failed:?}");
    assert!(
        failed
            .iter()
            .all(|l| l.starts_with("ERROR") && l.contains("the records wait for the next commit")),
        "{failed:?}"
    );
    assert_eq!(logged.lines("recorder commits succeed again").len(), 2);
}

// The queue's overflow is logged when it begins and when it ends, once each.
#[test]
fn a_full_queue_is_logged_when_it_begins_and_when_it_ends() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    let (mut writer, stats, _) = test_writer(
        &RecorderConfig::default(),
        &path,
        open(&path).expect("opens"),
        1,
    );
    let logged = Logged::default();
    tracing::subscriber::with_default(logged.subscriber(), || {
        for dropped in [0, 5, 9, 9, 9, 12, 12] {
            stats.dropped_queue.store(dropped, Ordering::Relaxed);
            writer.report_queue();
        }
    });
    assert_eq!(
        logged.lines("recorder queue").len(),
        4,
        "{:?}",
        logged.lines("")
    );
    assert_eq!(logged.lines("recorder queue full").len(), 2);
    assert_eq!(logged.lines("recorder queue no longer full").len(), 2);
}

// A damaged page in the file (here the `nc` table's root): the commits that touch it
// fail, the others succeed. That is one outage, logged once, not one line per commit
// as failure and success alternate; it ends when the file is replaced.
#[test]
fn a_damaged_database_is_logged_once_and_never_taken_for_recovered() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    let nc = |t_unix_ms| Record::Nc {
        t_unix_ms,
        axis: "X".into(),
        position_mm: Some(1.0),
        applied_comp_mm: Some(0.0),
        params: CompParams::default(),
    };
    let root: i64 = {
        let mut conn = open(&path).expect("opens");
        let batch: Vec<Record> = (0..500).map(nc).collect();
        schema::insert(&mut conn, &mut schema::Statements::default(), &batch).expect("rows");
        assert!(checkpoint(&conn));
        conn.query_row(
            "SELECT rootpage FROM sqlite_schema WHERE name = 'nc'",
            [],
            |r| r.get(0),
        )
        .expect("root page")
    };
    {
        use std::io::{Seek, Write};
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .expect("opens");
        f.seek(std::io::SeekFrom::Start((root as u64 - 1) * 4096))
            .expect("seek");
        f.write_all(&[0xff; 2000]).expect("damaged");
    }
    let (mut writer, stats, _) = test_writer(
        &RecorderConfig::default(),
        &path,
        open(&path).expect("the schema is intact"),
        1,
    );
    let names: Arc<[String]> = Arc::from(vec!["T_a".to_string()]);
    let logged = Logged::default();
    tracing::subscriber::with_default(logged.subscriber(), || {
        for k in 0..3 {
            writer.commit(&mut vec![nc(10_000 + k)]);
            writer.commit(&mut vec![Record::Cycle {
                t_unix_ms: 20_000 + k,
                names: names.clone(),
                rows: vec![reading(0, 1.0, 0)],
            }]);
        }
    });
    assert_eq!(stats.failed_commits.load(Ordering::Relaxed), 3);
    assert_eq!(stats.written.load(Ordering::Relaxed), 3);
    assert!(stats.failing.load(Ordering::Relaxed));
    let lines = logged.lines("recorder");
    assert_eq!(lines.len(), 1, "{lines:?}");
    assert!(lines[0].contains("the database is damaged"), "{lines:?}");
}

// Unsent messages deleted pass after pass are one episode: WARN when it begins, then
// one INFO line a pass with what went; a pass that deleted none ends it. Before, each
// pass logged up to ten lines.
#[test]
fn deleting_unsent_messages_is_warned_once_per_episode_and_each_pass_is_one_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("r.db");
    let messages = |conn: &Connection, n: usize| {
        for k in 0..n {
            conn.execute(
                "INSERT INTO mqtt_outbox(topic, payload) VALUES ('t', ?1)",
                [format!("{k:0400}")],
            )
            .expect("message");
        }
    };
    let conn = open(&path).expect("opens");
    let empty_bytes = schema::data_bytes(&conn).expect("size");
    let cfg = RecorderConfig {
        // Room for about 50 messages.
        max_size_mb: (empty_bytes + 20 * 1024) as f64 / 1024.0 / 1024.0,
        ..RecorderConfig::default()
    };
    let (mut writer, stats, _) = test_writer(&cfg, &path, open(&path).expect("opens"), 1);
    let logged = Logged::default();
    tracing::subscriber::with_default(logged.subscriber(), || {
        for more in [300, 300, 0, 300] {
            messages(&conn, more);
            writer.retention().expect("pass");
        }
    });
    let lines = logged.lines("recorder");
    assert_eq!(lines.len(), 3, "{lines:?}");
    assert!(lines[0].starts_with("WARN") && lines[0].contains("MQTT messages unsent"));
    assert!(lines[1].starts_with("INFO"), "{lines:?}");
    assert!(lines[2].starts_with("WARN"), "a new episode: {lines:?}");
    assert!(stats.outbox_deleted.load(Ordering::Relaxed) > 600);
}

/// A writer on `conn` with fresh statistics, queue state waking it at `wake_at`
/// pending records, and an outbox notification nobody waits on.
fn test_writer(
    cfg: &RecorderConfig,
    path: &Path,
    conn: Connection,
    wake_at: usize,
) -> (Writer, Arc<RecorderStats>, Arc<QueueShared>) {
    let stats = Arc::new(RecorderStats::default());
    let shared = Arc::new(QueueShared {
        pending: AtomicUsize::new(0),
        wake_at,
        writer: OnceLock::new(),
        stopping: AtomicBool::new(false),
    });
    let writer = Writer::new(
        cfg,
        path,
        conn,
        stats.clone(),
        shared.clone(),
        Arc::default(),
    );
    (writer, stats, shared)
}

/// A recording of 0..100 s with the error channel `laser_um` reading what is left
/// after the NC's compensation: the machine's error is `t` um at `t` s, the NC applied
/// 30 um (0.03 mm) from 40 s to 69 s, so the laser read `t - 30` there.
fn recorded_with_compensation() -> (tempfile::TempDir, std::path::PathBuf) {
    let (dir, db) = recorded(&[(0, 100)]);
    let conn = schema::open(&db).unwrap();
    conn.execute("INSERT INTO channels(id, name) VALUES (2, 'laser_um')", [])
        .unwrap();
    for t in 0..100i64 {
        let applied_mm = if (40..70).contains(&t) { 0.03 } else { 0.0 };
        conn.execute(
            "INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, 2, 0.0, ?2, 0)",
            rusqlite::params![t * 1000, t as f64 - 1000.0 * applied_mm],
        )
        .unwrap();
        conn.execute(
            "INSERT INTO nc(t_unix_ms, axis, position_mm, applied_comp_mm, sd43900_mm, sd43910, sd43920_mm) VALUES (?1, 'X', 5.0, ?2, ?2, 0, 0)",
            rusqlite::params![t * 1000, applied_mm],
        )
        .unwrap();
    }
    (dir, db)
}

// Export read only the NC's position: a recording made with compensation on gave the
// same CSV as one without and said nothing, and a model calibrated on it was a model
// of the residual.
#[test]
fn an_export_names_the_span_with_compensation_applied() {
    let (_dir, db) = recorded_with_compensation();
    let mut args = export_args(&db, 0, 100);
    args.axis = Some("X".into());
    args.err_channel = Some("laser_um".into());
    let (m, summary) = export::measurements(&args).unwrap();
    let note = summary
        .notes
        .iter()
        .find(|n| n.contains("compensation to axis `X`"))
        .unwrap_or_else(|| panic!("{:?}", summary.notes));
    assert!(
        note.contains("from 1970-01-01T00:00:40.000Z to 1970-01-01T00:01:09.000Z")
            && note.contains("up to 30.0 um")
            && note.contains("left after the NC's compensation")
            && note.contains("--add-applied-comp"),
        "{note}"
    );
    // Without the flag err_um is what the laser read.
    assert_eq!(m.err_um[50], 20.0);
    // Only non-zero compensation counts: the same window before 40 s says nothing.
    let mut args = export_args(&db, 0, 40);
    args.axis = Some("X".into());
    args.err_channel = Some("laser_um".into());
    let (_, summary) = export::measurements(&args).unwrap();
    assert!(
        !summary.notes.iter().any(|n| n.contains("compensation")),
        "{:?}",
        summary.notes
    );
}

#[test]
fn add_applied_comp_writes_the_error_without_compensation() {
    let (_dir, db) = recorded_with_compensation();
    let mut args = export_args(&db, 0, 100);
    args.axis = Some("X".into());
    args.err_channel = Some("laser_um".into());
    args.add_applied_comp = true;
    let (m, summary) = export::measurements(&args).unwrap();
    assert_eq!(m.len(), 100);
    for (t, e) in m.t_s.iter().zip(&m.err_um) {
        assert!((e - t).abs() < 1e-9, "at {t} s: {e}");
    }
    assert!(
        summary
            .notes
            .iter()
            .any(|n| n.contains("up to 30.0 um") && n.contains("without compensation")),
        "{:?}",
        summary.notes
    );
    // Held like the position: a gap in the NC's record longer than --max-hold-s
    // leaves the rows out rather than adding a stale compensation.
    let conn = schema::open(&db).unwrap();
    conn.execute("DELETE FROM nc WHERE t_unix_ms BETWEEN 45000 AND 60000", [])
        .unwrap();
    args.max_hold_s = 5.0;
    let (m, _) = export::measurements(&args).unwrap();
    // No NC row from 45 s to 60 s: 50..=60 s are more than 5 s after the one at 44 s.
    assert_eq!(m.len(), 100 - 11, "{:?}", m.t_s);
    // It needs the axis, and a measured error to add to.
    args.axis = None;
    let e = export::measurements(&args).unwrap_err().to_string();
    assert!(e.starts_with("--add-applied-comp: needs --axis"), "{e}");
    args.axis = Some("X".into());
    args.err_channel = None;
    let e = export::measurements(&args).unwrap_err().to_string();
    assert!(
        e.starts_with("--add-applied-comp: needs --err-channel"),
        "{e}"
    );
}
