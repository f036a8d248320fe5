//! MQTT publishing against a real Mosquitto broker: topics, JSON payloads with time
//! and quality, QoS 1, and a broker outage that loses nothing recorded.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::Duration;

use common::broker::{retained, subscribe, Broker, Received};
use common::process::Gateway;

/// Times of the readings messages on `topic` that carry channel `T_bed`.
fn times(got: &Received, topic: &str) -> Vec<i64> {
    let mut t: Vec<i64> = got
        .lock()
        .expect("lock")
        .iter()
        .filter(|(tp, _)| tp == topic)
        .filter_map(|(_, v)| v["t_unix_ms"].as_i64())
        .collect();
    t.sort_unstable();
    t.dedup();
    t
}

async fn wait_until(secs: f64, what: &str, mut pred: impl FnMut() -> bool) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f64(secs);
    while !pred() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "timed out waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn now_ms() -> i64 {
    compgate_service::record::now_unix_ms()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readings_writes_and_health_survive_a_broker_outage() {
    let dir = tempfile::tempdir().unwrap();
    let mut broker = tokio::task::block_in_place(|| Broker::start(dir.path()));
    let (got, sub) = subscribe(broker.port, "compgate/#");
    let extra = format!(
        "\n[recorder]\npath = {:?}\ncommit_interval_s = 0.2\n\n[mqtt]\nbroker = \"127.0.0.1:{}\"\nmachine = \"mill-7\"\npublish_interval_s = 0.2\nretry_s = 0.5\n",
        dir.path().join("rec.db").display().to_string(),
        broker.port
    );
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));

    let has = |topic: &'static str| {
        let got = got.clone();
        move || got.lock().unwrap().iter().any(|(t, _)| t == topic)
    };
    wait_until(10.0, "a reading", has("compgate/mill-7/readings/ain1")).await;
    wait_until(10.0, "a write", has("compgate/mill-7/writes/X")).await;
    let g2 = got.clone();
    wait_until(10.0, "health with the link up", move || {
        g2.lock()
            .unwrap()
            .iter()
            .any(|(t, v)| t == "compgate/mill-7/health" && v["devices"][0]["link"] == "up")
    })
    .await;
    {
        let g = got.lock().unwrap();
        let msg = &g
            .iter()
            .find(|(t, _)| t == "compgate/mill-7/readings/ain1")
            .unwrap()
            .1;
        assert!(
            msg["t_unix_ms"].as_i64().unwrap() > 1_700_000_000_000,
            "{msg}"
        );
        let chans = msg["channels"].as_array().unwrap();
        assert_eq!(chans.len(), 3, "{msg}");
        let reading = chans.iter().find(|c| c["channel"] == "T_bed").unwrap();
        assert_eq!(reading["quality"], "good", "{reading}");
        assert!(
            (reading["value_degc"].as_f64().unwrap() - 30.0).abs() < 0.1,
            "{reading}"
        );
        let write = &g
            .iter()
            .find(|(t, _)| t == "compgate/mill-7/writes/X")
            .unwrap()
            .1;
        assert_eq!(write["ok"], true, "{write}");
        assert_eq!(write["quality"], "good");
        assert!(
            (write["sd43900_mm"].as_f64().unwrap() - 0.04).abs() < 0.001,
            "{write}"
        );
        let health = &g
            .iter()
            .rev()
            .find(|(t, _)| t == "compgate/mill-7/health")
            .unwrap()
            .1;
        assert_eq!(health["devices"][0]["link"], "up", "{health}");
        assert!(health["quality"].is_string() && health["t_unix_ms"].is_i64());
    }

    // The broker goes down; the gateway goes on recording, and the temperature moves.
    tokio::task::block_in_place(|| broker.stop());
    let down_ms = now_ms();
    plant.field["ain1"]
        .set_temperature_override(plant.transmitter["T_bed"], Some(35.0))
        .unwrap();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let up_ms = now_ms();
    tokio::task::block_in_place(|| broker.restart());

    // Everything recorded during the outage arrives afterwards, in order.
    let topic = "compgate/mill-7/readings/ain1";
    // The broker may hand the subscriber live messages before the queued backlog:
    // wait until the outage is covered without gaps (or fail on the asserts below).
    let complete = || {
        let t: Vec<i64> = times(&got, topic)
            .into_iter()
            .filter(|x| *x >= down_ms - 1000 && *x <= up_ms + 500)
            .collect();
        t.last().is_some_and(|l| *l > up_ms) && t.windows(2).all(|w| w[1] - w[0] <= 600)
    };
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    while !complete() && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let t = times(&got, topic);
    let window: Vec<i64> = t
        .iter()
        .copied()
        .filter(|x| *x >= down_ms - 1000 && *x <= up_ms + 500)
        .collect();
    assert!(
        window.len() >= 10,
        "{} readings around the outage; every one, ms after the stop: {:?}; restart at {}",
        window.len(),
        t.iter().map(|x| x - down_ms).collect::<Vec<_>>(),
        up_ms - down_ms
    );
    let max_gap = window.windows(2).map(|w| w[1] - w[0]).max().unwrap();
    assert!(max_gap <= 600, "a gap of {max_gap} ms: messages lost");
    let g = got.lock().unwrap();
    assert!(
        g.iter().any(|(tp, v)| tp == "compgate/mill-7/writes/X"
            && v["t_unix_ms"].as_i64().unwrap() > down_ms
            && v["t_unix_ms"].as_i64().unwrap() < up_ms
            && (v["sd43900_mm"].as_f64().unwrap() - 0.06).abs() < 0.001),
        "the write made during the outage was published"
    );
    drop(g);
    // Logged once going down and once coming back, not at every retry (the broker
    // was away for about six `retry_s`).
    tokio::task::block_in_place(|| gw.wait_log(10.0, "MQTT: broker reachable again"));
    let log = gw.stderr_text();
    let down = log.matches("MQTT: broker unreachable").count();
    assert_eq!(down, 1, "{log}");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    sub.abort();
    drop(plant);
}

/// `(rows, highest id)` of the outbox in the database at `db`; `None` before the
/// recorder created it.
fn outbox_rows(db: &std::path::Path) -> Option<(i64, i64)> {
    let conn =
        rusqlite::Connection::open_with_flags(db, rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY)
            .ok()?;
    conn.busy_timeout(Duration::from_secs(5)).ok()?;
    conn.query_row(
        "SELECT count(*), coalesce(max(id), 0) FROM mqtt_outbox",
        [],
        |r| Ok((r.get(0)?, r.get(1)?)),
    )
    .ok()
}

/// `[recorder]` and `[mqtt]` for a broker on `port`, recording into `db`, with
/// `mqtt_extra` appended to `[mqtt]`.
fn service_sections(db: &std::path::Path, port: u16, mqtt_extra: &str) -> String {
    format!(
        "\n[recorder]\npath = {:?}\ncommit_interval_s = 0.2\n\n[mqtt]\nbroker = \"127.0.0.1:{port}\"\nmachine = \"mill-7\"\npublish_interval_s = 0.05\nretry_s = 0.2\n{mqtt_extra}\n",
        db.display().to_string(),
    )
}

// While no broker listened, the cap was only enforced inside a session, which a
// refused connect never reached: the outbox grew without bound and filled the
// recorder's database, and the drops were counted only once a broker was back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_outbox_cap_holds_while_no_broker_listens() {
    let dir = tempfile::tempdir().unwrap();
    // A port for the broker, which starts later.
    let mut broker = tokio::task::block_in_place(|| Broker::start(dir.path()));
    tokio::task::block_in_place(|| broker.stop());
    let db = dir.path().join("rec.db");
    let extra = service_sections(&db, broker.port, "outbox_max_messages = 20");
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_log(20.0, "MQTT: broker unreachable"));

    // Many times the cap recorded, at most the cap kept: trimmed during the outage.
    let mut last = (0, 0);
    wait_until(
        30.0,
        "the outbox trimmed to the cap during the outage",
        || {
            last = outbox_rows(&db).unwrap_or_default();
            last.1 >= 200 && last.0 <= 20
        },
    )
    .await;
    let log = gw.stderr_text();
    assert_eq!(
        log.matches("over outbox_max_messages").count(),
        1,
        "the drops are logged once per outage: {log}"
    );

    // The broker comes: the line saying so counts the outage's drops.
    tokio::task::block_in_place(|| broker.restart());
    let back = tokio::task::block_in_place(|| gw.wait_log(20.0, "MQTT: broker reachable again"));
    let dropped: u64 = back
        .split("dropped=")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no dropped= in {back}"));
    assert!(dropped >= 100, "{back}");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

/// Runs the gateway with a broker, does `change` to the recorder's files while it
/// publishes, and waits for a reading recorded a second after it and the publisher's
/// `line`.
async fn publishing_goes_on_after(change: impl FnOnce(&std::path::Path), line: &str) {
    let dir = tempfile::tempdir().unwrap();
    let broker = tokio::task::block_in_place(|| Broker::start(dir.path()));
    let (got, sub) = subscribe(broker.port, "compgate/#");
    let db = dir.path().join("rec.db");
    let extra = service_sections(&db, broker.port, "");
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let topic = "compgate/mill-7/readings/ain1";
    wait_until(20.0, "a reading", || !times(&got, topic).is_empty()).await;

    change(&db);
    let changed_ms = now_ms();
    // A second after the change every reading goes into the database at the path.
    wait_until(20.0, "a reading recorded after the change", || {
        times(&got, topic)
            .last()
            .is_some_and(|t| *t > changed_ms + 1000)
    })
    .await;
    tokio::task::block_in_place(|| gw.wait_log(10.0, line));
    assert!(tokio::task::block_in_place(|| gw.stop()));
    sub.abort();
    drop((plant, broker));
}

// The publisher kept its connection to the database it opened first: after the file
// was renamed the recorder wrote a new one at the path, whose outbox nobody read, and
// publishing stopped without a word.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publishing_goes_on_after_the_database_is_renamed() {
    publishing_goes_on_after(
        |db| std::fs::rename(db, db.with_file_name("renamed.db")).unwrap(),
        "MQTT: the recorder database was created again",
    )
    .await;
}

// The recorder's -wal deleted: the publisher's connection still had the deleted file
// open, and once the recorder had checkpointed it and opened the database again with a
// new -wal, every exchange through it failed with a disk I/O error: publishing stopped
// until a restart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publishing_goes_on_after_the_wal_is_deleted() {
    publishing_goes_on_after(
        |db| std::fs::remove_file(db.with_file_name("rec.db-wal")).unwrap(),
        "MQTT: the recorder database was opened again with a new -wal",
    )
    .await;
}

/// A broker in `dir` with `settings` in place of `allow_anonymous true`.
fn broker_with(dir: &std::path::Path, settings: &str) -> Broker {
    let port = common::free_port();
    let text = Broker::conf_text(dir, port, "").replace("allow_anonymous true", settings);
    tokio::task::block_in_place(|| Broker::start_conf(dir, port, &text))
}

// The gateway connected without user name and password only: a plant broker that
// asks for them (as most do) could not be used.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gateway_logs_in_to_a_broker_that_asks_for_a_password() {
    let dir = tempfile::tempdir().unwrap();
    let passwords = dir.path().join("passwords");
    let ok = std::process::Command::new("mosquitto_passwd")
        .args(["-c", "-b"])
        .arg(&passwords)
        .args(["compgate", "pa ss:w0rd"])
        .status()
        .unwrap()
        .success();
    assert!(ok, "mosquitto_passwd");
    // Anonymous clients (the test's subscriber) may read; only the user may publish:
    // a message arrives only from a gateway that logged in.
    let acl = dir.path().join("acl");
    std::fs::write(
        &acl,
        "topic read #\n\nuser compgate\ntopic readwrite compgate/#\n",
    )
    .unwrap();
    let mut broker = broker_with(
        dir.path(),
        &format!(
            "allow_anonymous true\npassword_file {}\nacl_file {}",
            passwords.display(),
            acl.display()
        ),
    );
    let (got, sub) = subscribe(broker.port, "compgate/#");
    let login = dir.path().join("mqtt.login");
    std::fs::write(&login, "compgate\npa ss:w0rd\n").unwrap();
    std::fs::set_permissions(&login, std::os::unix::fs::PermissionsExt::from_mode(0o600)).unwrap();
    let db = dir.path().join("rec.db");
    let keys = format!("credentials_file = {:?}", login.display().to_string());
    let extra = service_sections(&db, broker.port, &keys);
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    wait_until(20.0, "a health message", || {
        got.lock()
            .unwrap()
            .iter()
            .any(|(t, _)| t == "compgate/mill-7/health")
    })
    .await;
    assert!(
        !gw.stderr_text().contains("readable by group"),
        "{}",
        gw.stderr_text()
    );

    // The password is changed at the broker and in the file, and the broker restarts:
    // the next connection reads the file again (it was read only at start, and the
    // gateway was refused until a restart).
    let ok = std::process::Command::new("mosquitto_passwd")
        .args(["-b"])
        .arg(&passwords)
        .args(["compgate", "n3w pa55"])
        .status()
        .unwrap()
        .success();
    assert!(ok, "mosquitto_passwd");
    std::fs::write(&login, "compgate\nn3w pa55\n").unwrap();
    tokio::task::block_in_place(|| {
        broker.stop();
        broker.restart();
    });
    let restarted_ms = now_ms();
    wait_until(20.0, "a health message after the password changed", || {
        got.lock().unwrap().iter().any(|(t, v)| {
            t == "compgate/mill-7/health" && v["t_unix_ms"].as_i64().unwrap() > restarted_ms
        })
    })
    .await;
    let log = gw.stderr_text();
    assert!(log.contains("MQTT: the credentials changed"), "{log}");

    // The file is gone (moved away by an operator) when the broker restarts: the
    // gateway says so once and logs in with what it read before.
    let moved = dir.path().join("mqtt.login.moved");
    std::fs::rename(&login, &moved).unwrap();
    tokio::task::block_in_place(|| {
        broker.stop();
        broker.restart();
    });
    let restarted_ms = now_ms();
    wait_until(
        20.0,
        "a health message without the credentials file",
        || {
            got.lock().unwrap().iter().any(|(t, v)| {
                t == "compgate/mill-7/health" && v["t_unix_ms"].as_i64().unwrap() > restarted_ms
            })
        },
    )
    .await;
    let before_used = "the credentials read before are used";
    let log = gw.stderr_text();
    assert_eq!(log.matches(before_used).count(), 1, "{log}");
    assert!(log.contains("mqtt.credentials_file"), "{log}");
    assert!(tokio::task::block_in_place(|| gw.stop()));

    // A wrong password, from the environment: refused, and said so.
    let text = std::fs::read_to_string(&path).unwrap();
    let path = dir.path().join("env.toml");
    let env_keys = "user_env = \"MQ_USER\"\npassword_env = \"MQ_PASS\"";
    std::fs::write(&path, text.replace(&keys, env_keys)).unwrap();
    let gw = Gateway::start(
        dir.path(),
        &path,
        &[("MQ_USER", "compgate"), ("MQ_PASS", "wrong")],
    );
    tokio::task::block_in_place(|| {
        gw.wait_log(
            20.0,
            "MQTT: broker refused the connection: not authorized (a wrong user name or password",
        )
    });
    assert!(tokio::task::block_in_place(|| gw.stop()));
    sub.abort();
    drop((plant, broker));
}

/// Runs `openssl` with `args` in `dir`.
fn openssl(dir: &std::path::Path, args: &[&str]) {
    let out = std::process::Command::new("openssl")
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "openssl {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

// compgate speaks plain MQTT; a plant broker that takes only TLS is reached through a
// Mosquitto bridge on the gateway PC, as `deploy/mqtt/compgate-bridge.conf` ships it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_local_bridge_forwards_to_a_tls_broker() {
    let dir = tempfile::tempdir().unwrap();
    let (plant_dir, bridge_dir) = (dir.path().join("plant"), dir.path().join("bridge"));
    std::fs::create_dir_all(&plant_dir).unwrap();
    std::fs::create_dir_all(&bridge_dir).unwrap();
    // A CA, and the plant broker's certificate for 127.0.0.1 signed by it.
    let d = plant_dir.as_path();
    openssl(
        d,
        &[
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            "ca.key",
            "-out",
            "ca.crt",
            "-days",
            "2",
            "-subj",
            "/CN=plant test CA",
        ],
    );
    openssl(
        d,
        &[
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            "server.key",
            "-out",
            "server.csr",
            "-subj",
            "/CN=127.0.0.1",
        ],
    );
    std::fs::write(d.join("san.ext"), "subjectAltName=IP:127.0.0.1\n").unwrap();
    openssl(
        d,
        &[
            "x509",
            "-req",
            "-in",
            "server.csr",
            "-CA",
            "ca.crt",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-out",
            "server.crt",
            "-days",
            "2",
            "-extfile",
            "san.ext",
        ],
    );
    let ok = std::process::Command::new("mosquitto_passwd")
        .args(["-c", "-b"])
        .arg(d.join("passwords"))
        .args(["compgate-mill-7", "br1dge pw"])
        .status()
        .unwrap()
        .success();
    assert!(ok, "mosquitto_passwd");
    // The plant broker: TLS for the bridge, where only the user may publish; a plain
    // loopback listener for the test's subscriber.
    std::fs::write(
        d.join("acl"),
        "topic read #\n\nuser compgate-mill-7\ntopic readwrite compgate/#\n",
    )
    .unwrap();
    let tls_port = common::free_port();
    let plant = Broker::start_with(
        d,
        &format!(
            "password_file {0}/passwords\nacl_file {0}/acl\nlistener {tls_port} 127.0.0.1\ncafile {0}/ca.crt\ncertfile {0}/server.crt\nkeyfile {0}/server.key\n",
            d.display()
        ),
    );
    let (got, sub) = subscribe(plant.port, "compgate/#");

    // The bridge as shipped, its EDIT lines set for this test.
    let shipped = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/deploy/mqtt/compgate-bridge.conf"
    ))
    .unwrap();
    let bridge_port = common::free_port();
    let mut edits = 0;
    let text: String = shipped
        .lines()
        .map(|line| {
            let edited = match line.split_whitespace().next() {
                Some("listener") => format!("listener {bridge_port} 127.0.0.1"),
                Some("address") => format!("address 127.0.0.1:{tls_port}"),
                Some("bridge_cafile") => format!("bridge_cafile {}/ca.crt", d.display()),
                Some("remote_password") => "remote_password br1dge pw".into(),
                _ => return line.to_string(),
            };
            edits += 1;
            edited
        })
        .collect::<Vec<_>>()
        .join("\n");
    assert_eq!(edits, 4, "the shipped bridge changed: {shipped}");
    let text = format!("{text}\nuser root\n");
    let bridge =
        tokio::task::block_in_place(|| Broker::start_conf(&bridge_dir, bridge_port, &text));

    let db = dir.path().join("rec.db");
    let extra = service_sections(&db, bridge.port, "");
    let (field, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    wait_until(
        30.0,
        "health and the online state at the plant broker",
        || {
            let got = got.lock().unwrap();
            got.iter().any(|(t, _)| t == "compgate/mill-7/health")
                && got
                    .iter()
                    .any(|(t, v)| t == "compgate/mill-7/state" && v["state"] == "online")
        },
    )
    .await;
    assert!(tokio::task::block_in_place(|| gw.stop()));
    sub.abort();
    drop((field, bridge, plant));
}

// A broker refusing the client (not authorized) was logged as "broker unreachable",
// as if it did not answer.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_broker_refusing_the_client_is_named_as_refusing_it_once() {
    let dir = tempfile::tempdir().unwrap();
    let broker = broker_with(dir.path(), "allow_anonymous false");

    let extra = service_sections(&dir.path().join("rec.db"), broker.port, "");
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let gw = Gateway::start_with_args(
        dir.path(),
        &path,
        &["--log", "info,compgate_service::mqtt=debug"],
    );
    let line = tokio::task::block_in_place(|| {
        gw.wait_log(20.0, "MQTT: broker refused the connection: not authorized")
    });
    assert!(line.contains("WARN"), "{line}");
    // Tried again, logged once.
    wait_until(20.0, "three more refused attempts", || {
        gw.stderr_text()
            .matches("MQTT: broker still not connected")
            .count()
            >= 3
    })
    .await;
    let log = gw.stderr_text();
    assert_eq!(
        log.matches("MQTT: broker refused the connection").count(),
        1,
        "{log}"
    );
    assert!(!log.contains("broker unreachable"), "{log}");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop((plant, broker));
}

// A database error of the outbox (here a lock held past the busy timeout) was logged
// as "broker unreachable", and then "broker reachable again".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_outbox_database_error_is_named_as_the_database_s() {
    let dir = tempfile::tempdir().unwrap();
    let broker = tokio::task::block_in_place(|| Broker::start(dir.path()));
    let (got, sub) = subscribe(broker.port, "compgate/#");
    let db = dir.path().join("rec.db");
    let extra = service_sections(&db, broker.port, "");
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let topic = "compgate/mill-7/readings/ain1";
    wait_until(20.0, "a reading", || !times(&got, topic).is_empty()).await;

    // Held until the publisher gave up on it.
    let lock = rusqlite::Connection::open(&db).unwrap();
    lock.busy_timeout(Duration::from_secs(10)).unwrap();
    lock.execute_batch("BEGIN EXCLUSIVE").unwrap();
    let line =
        tokio::task::block_in_place(|| gw.wait_log(30.0, "MQTT: the outbox database failed"));
    assert!(
        line.contains(&db.display().to_string()) && line.contains("locked"),
        "{line}"
    );
    lock.execute_batch("COMMIT").unwrap();
    drop(lock);
    tokio::task::block_in_place(|| gw.wait_log(30.0, "MQTT: the outbox database works again"));
    let log = gw.stderr_text();
    assert!(!log.contains("broker unreachable"), "{log}");
    assert!(!log.contains("reachable again"), "{log}");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    sub.abort();
    drop((plant, broker));
}

// The first health message said "down" for a device the gateway was still connecting
// to, where the status API said "connecting".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_says_connecting_as_the_status_api_does() {
    let dir = tempfile::tempdir().unwrap();
    let broker = tokio::task::block_in_place(|| Broker::start(dir.path()));
    let (got, sub) = subscribe(broker.port, "compgate/#");
    // A device that accepts the connection and never answers: its first poll cycle
    // lasts its 60 s timeout, and until then it is connecting.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let config = common::config("hold", "", "")
        .replacen(
            "address = \"127.0.0.1:0\"",
            &format!("address = \"{}\"", silent.local_addr().unwrap()),
            1,
        )
        .replacen(
            "address = \"127.0.0.1:0\"",
            &format!("address = \"127.0.0.1:{}\"", common::free_port()),
            1,
        )
        .replacen("\ntimeout_s = 0.2\n", "\ntimeout_s = 60\n", 1);
    let path = dir.path().join("compgate.toml");
    std::fs::write(
        &path,
        config + &service_sections(&dir.path().join("rec.db"), broker.port, ""),
    )
    .unwrap();
    let gw = Gateway::start(dir.path(), &path, &[]);
    let health = "compgate/mill-7/health";
    wait_until(20.0, "a health message", || {
        got.lock().unwrap().iter().any(|(t, _)| t == health)
    })
    .await;
    let first = got
        .lock()
        .unwrap()
        .iter()
        .find(|(t, _)| t == health)
        .unwrap()
        .1
        .clone();
    assert_eq!(first["devices"][0]["link"], "connecting", "{first}");
    assert_eq!(first["quality"], "uncertain", "{first}");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    sub.abort();
    drop((broker, silent));
}

// The gateway's state, retained, as SCADA and MES clients expect of a field device:
// online while connected, offline after a clean stop, lost (the broker's last will)
// when the gateway died. Health only stopped coming, and a client could not tell a
// dead gateway from a slow one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_retained_state_says_online_offline_and_lost() {
    let dir = tempfile::tempdir().unwrap();
    let broker = tokio::task::block_in_place(|| Broker::start(dir.path()));
    let db = dir.path().join("rec.db");
    let extra = service_sections(&db, broker.port, "keep_alive_s = 1");
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let topic = "compgate/mill-7/state";
    let state = |want: &'static str| async move {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        loop {
            let got = retained(broker.port, topic).await;
            if got.as_ref().and_then(|v| v["state"].as_str()) == Some(want) {
                return;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "retained state {want:?} never came; last {got:?}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    };
    let gw = Gateway::start(dir.path(), &path, &[]);
    state("online").await;
    assert!(tokio::task::block_in_place(|| gw.stop()));
    state("offline").await;

    let gw = Gateway::start(dir.path(), &path, &[]);
    state("online").await;
    gw.signal("KILL");
    // keep_alive_s = 1: the broker gives up after 1.5 s.
    state("lost").await;
    drop(gw);
    drop(plant);
}

/// Holds the write lock of the database at `db` for `hold` (as a backup tool or a
/// slow card's commit would), from a thread; returns once the lock is held.
fn hold_write_lock(db: &std::path::Path, hold: Duration) -> std::thread::JoinHandle<()> {
    let conn = rusqlite::Connection::open(db).unwrap();
    conn.busy_timeout(Duration::from_secs(10)).unwrap();
    conn.execute_batch("BEGIN IMMEDIATE").unwrap();
    std::thread::spawn(move || {
        std::thread::sleep(hold);
        conn.execute_batch("COMMIT").unwrap();
    })
}

// The MQTT connection was polled inside the session's `select!`: a connect cut off
// there (rumqttc's connect is not cancel safe) made the broker publish the last
// will, "lost", at most starts; and while an outbox round trip waited on the
// database's lock (up to the 5 s busy timeout) nothing kept the connection alive, so
// the broker published "lost" for a gateway that was running, or stopping cleanly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_held_database_does_not_stall_the_broker_connection() {
    let dir = tempfile::tempdir().unwrap();
    let broker = tokio::task::block_in_place(|| Broker::start(dir.path()));
    let topic = "compgate/mill-7/state";
    let (got, sub) = subscribe(broker.port, topic);
    let db = dir.path().join("rec.db");
    // keep_alive_s = 1: the broker gives up after 1.5 s without a packet.
    let extra = service_sections(&db, broker.port, "keep_alive_s = 1");
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let states = || {
        got.lock()
            .unwrap()
            .iter()
            .filter_map(|(_, v)| v["state"].as_str().map(str::to_string))
            .collect::<Vec<_>>()
    };
    wait_until(20.0, "the state online", || {
        states().contains(&"online".into())
    })
    .await;
    // Rows to acknowledge, so the outbox wants the write lock.
    wait_until(10.0, "messages in the outbox", || {
        outbox_rows(&db).is_some_and(|(_, id)| id > 20)
    })
    .await;

    let held = hold_write_lock(&db, Duration::from_secs(4));
    tokio::task::block_in_place(|| held.join().unwrap());
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        states(),
        ["online"],
        "while the database was held: {}",
        gw.stderr_text()
    );

    let held = hold_write_lock(&db, Duration::from_secs(4));
    let log = gw.stderr.clone();
    assert!(tokio::task::block_in_place(|| gw.stop()));
    tokio::task::block_in_place(|| held.join().unwrap());
    wait_until(5.0, "the state offline", || states().len() > 1).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert_eq!(
        states(),
        ["online", "offline"],
        "a clean stop while the database was held: {}",
        log.lock().unwrap().join("\n")
    );
    sub.abort();
    drop((plant, broker));
}
