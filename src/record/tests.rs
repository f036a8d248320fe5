use std::sync::atomic::Ordering;
use std::time::Duration;

use super::*;

fn cycle(name: &Arc<str>, v: f64) -> Record {
    Record::Cycle {
        t_unix_ms: now_unix_ms(),
        rows: vec![Row {
            channel: name.clone(),
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
    let name: Arc<str> = Arc::from("T_a");
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
