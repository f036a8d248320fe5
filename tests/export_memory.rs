//! `compgate export` streams: its heap does not grow with the window. It read every
//! reading of the window into memory, built every row, then the whole CSV: a month
//! of 64 channels took 3 GB on the PC the gateway runs on.
//!
//! Its own test binary: the allocator below counts this process's heap, and the one
//! test is the only thing allocating.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]
// A global allocator is unsafe to implement: it counts, and passes every call on.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use compgate_service::record::export::{self, ExportArgs};

/// The system allocator, counting the bytes in use and their peak.
struct Counting;

static IN_USE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call goes to the system allocator unchanged; the counters only add.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's layout, passed on.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = IN_USE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: a block this allocator gave out, with its layout.
        unsafe { System.dealloc(ptr, layout) };
        IN_USE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

const CHANNELS: i64 = 16;
const PERIOD_S: i64 = 10;
const DAY_S: i64 = 86_400;

/// Peak heap of exporting `days` of the record to nowhere, above what was in use
/// before, bytes; and its rows.
fn export_peak(db: &std::path::Path, days: i64) -> (usize, usize) {
    let args = ExportArgs {
        db: db.to_path_buf(),
        since: "0".into(),
        until: (days * DAY_S).to_string(),
        csv: true,
        out: None,
        axis: None,
        err_channel: None,
        step_s: PERIOD_S as f64,
        max_hold_s: 60.0,
        add_applied_comp: false,
    };
    let base = IN_USE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let summary = export::write_csv(&args, std::io::sink()).unwrap();
    (PEAK.load(Ordering::Relaxed) - base, summary.rows)
}

#[test]
fn the_heap_of_an_export_does_not_grow_with_its_window() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    // A week of 16 channels every 10 s: 967 680 readings.
    let mut conn = compgate_service::record::open(&db).unwrap();
    let tx = conn.transaction().unwrap();
    {
        let mut ch = tx
            .prepare("INSERT INTO channels(id, name) VALUES (?1, ?2)")
            .unwrap();
        for c in 0..CHANNELS {
            ch.execute(rusqlite::params![c, format!("T_{c:02}")])
                .unwrap();
        }
        let mut ins = tx
            .prepare("INSERT INTO readings(t_unix_ms, channel, raw, value_degc, quality) VALUES (?1, ?2, 12000.0, ?3, 0)")
            .unwrap();
        for t in (0..7 * DAY_S).step_by(PERIOD_S as usize) {
            for c in 0..CHANNELS {
                ins.execute(rusqlite::params![t * 1000, c, 20.0 + c as f64 / 10.0])
                    .unwrap();
            }
        }
    }
    tx.commit().unwrap();
    drop(conn);

    let (day, day_rows) = export_peak(&db, 1);
    let (week, week_rows) = export_peak(&db, 7);
    assert_eq!((day_rows, week_rows), (8640, 60480));
    assert!(
        week < day * 3 / 2,
        "peak heap above the start: {day} bytes for a day, {week} for a week"
    );
}
