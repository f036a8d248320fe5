//! The status on stdout: temperatures with quality, the SD43900/43910/43920 values last
//! written, and the compensation the NC applies now.
//!
//! On a terminal a small table ([`render_table`]) is redrawn in place ([`redraw`]:
//! cursor up by the height drawn last, every line cleared and drawn again), so nothing
//! wraps and no trail is left. On a pipe or a file one plain line ([`render`]) is
//! printed per status update, naming every value so it can be grepped; in the journal
//! or `/dev/null` nothing is ([`stdout_is_journal`], [`stdout_is_null`]). Both are
//! printed from the snapshot the control loop publishes at each status tick, the one
//! the metrics see at the same moment: no lag behind them.

use std::fmt::Write as _;
use std::io::Write;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

use compgate_core::channel::{Quality, Reading};
use compgate_gateway::runtime::{AxisStatus, Status};

/// Characters of the widest line of the terminal table: fits an 80-column terminal.
pub const TABLE_WIDTH: usize = 78;

fn quality_word(q: &Quality) -> String {
    match q {
        Quality::Good => "good".into(),
        Quality::Uncertain(r) => format!("uncertain({r:?})"),
        Quality::Bad(r) => format!("bad({r:?})"),
    }
}

/// The temperature shown for a reading: none for a bad one, whose value is only the
/// last good one held (as `compgate probe` shows it).
fn shown_degc(r: &Reading) -> String {
    match (&r.quality, r.value_degc) {
        (Quality::Bad(_), _) | (_, None) => "-".into(),
        (_, Some(v)) => format!("{v:.2}"),
    }
}

/// One line describing the gateway's state (the journal's form).
pub fn render(s: &Status) -> String {
    let mut out = String::new();
    for c in &s.channels {
        let v = shown_degc(&c.reading);
        let _ = write!(
            out,
            "{}={}degC[{}] ",
            c.name,
            v,
            quality_word(&c.reading.quality)
        );
    }
    for a in &s.axes {
        let _ = write!(out, "| axis {}: ", a.name);
        match &a.written {
            Some(p) => {
                let _ = write!(
                    out,
                    "SD43900={:.4}mm SD43910={:.3e} SD43920={:.1}mm ",
                    p.k0_mm, p.tan_beta, p.p0_mm
                );
            }
            None => out.push_str("SD43900=- SD43910=- SD43920=- "),
        }
        if a.shadow {
            out.push_str("SHADOW ");
            if let Some(p) = &a.would_write {
                let _ = write!(
                    out,
                    "would_write SD43900={:.4}mm SD43910={:.3e} SD43920={:.1}mm ",
                    p.k0_mm, p.tan_beta, p.p0_mm
                );
            }
        }
        let nc = a.nc.unwrap_or_default();
        match (nc.position_mm, nc.applied_comp_mm) {
            (Some(pos_mm), Some(comp_mm)) => {
                let _ = write!(out, "NC pos={pos_mm:.1}mm comp={comp_mm:.4}mm ");
            }
            (Some(pos_mm), None) => {
                let _ = write!(out, "NC pos={pos_mm:.1}mm comp=- ");
            }
            (None, _) => out.push_str("NC comp=- "),
        }
        let _ = write!(
            out,
            "jobs={}/{} ({})",
            a.jobs_ok,
            a.jobs_ok + a.jobs_failed,
            a.decision
        );
        if let Some(w) = &a.warning {
            let _ = write!(out, " WARNING: {w}");
        }
        if let Some(e) = &a.last_job_error {
            let _ = write!(out, " last job: {e}");
        }
    }
    for d in &s.devices {
        if let Some(e) = &d.last_error {
            let _ = write!(out, " | device {}: {}", d.name, e);
        }
    }
    out.trim_end().to_string()
}

/// `s` cut to `width` characters, the cut marked with `~`.
fn fit(s: &str, width: usize) -> String {
    if s.chars().count() <= width {
        return s.to_string();
    }
    let mut out: String = s.chars().take(width.saturating_sub(1)).collect();
    out.push('~');
    out
}

fn params_cells(a: &AxisStatus) -> String {
    match &a.written {
        Some(p) => format!(
            "SD43900 {:>8.4} mm  SD43910 {:>10.3e}  SD43920 {:>7.1} mm",
            p.k0_mm, p.tan_beta, p.p0_mm
        ),
        None => "SD43900 -  SD43910 -  SD43920 -".into(),
    }
}

/// The terminal table: devices, channels, axes. Every line is at most
/// [`TABLE_WIDTH`] characters (longer texts are cut), so the table never wraps and
/// [`redraw`] can move over it by its line count.
pub fn render_table(s: &Status) -> Vec<String> {
    let mut lines = Vec::new();
    let rule = "-".repeat(TABLE_WIDTH);
    lines.push(format!(
        "{:<16} {:>10}  {:<22} samples {}",
        "channel", "degC", "quality", s.samples
    ));
    lines.push(rule.clone());
    for c in &s.channels {
        let v = shown_degc(&c.reading);
        lines.push(format!(
            "{:<16} {:>10}  {}",
            fit(&c.name, 16),
            v,
            c.reading.quality
        ));
    }
    lines.push(rule.clone());
    for d in &s.devices {
        let state = match &d.last_error {
            None if d.cycles == 0 => "connecting".to_string(),
            None => "up".to_string(),
            Some(e) if d.link_up => format!("up, a read fails: {e}"),
            Some(e) => format!("DOWN: {e}"),
        };
        lines.push(format!("device {:<9} {state}", fit(&d.name, 9)));
    }
    for a in &s.axes {
        lines.push(format!("axis {:<11}{}", fit(&a.name, 11), params_cells(a)));
        if a.shadow {
            lines.push(match &a.would_write {
                Some(p) => format!(
                    "  SHADOW: would SD43900 {:>8.4} mm  SD43910 {:>10.3e}  SD43920 {:>7.1} mm",
                    p.k0_mm, p.tan_beta, p.p0_mm
                ),
                None => "  SHADOW: nothing to write yet; the NC is never written".into(),
            });
        }
        let nc = match &a.nc {
            Some(nc) => match (nc.applied_comp_mm, nc.position_mm) {
                (Some(comp_mm), Some(pos_mm)) => {
                    format!("NC applies {comp_mm:.4} mm at {pos_mm:.1} mm")
                }
                (None, Some(pos_mm)) => format!("NC at {pos_mm:.1} mm"),
                _ => "NC answers (reports the setting data only)".into(),
            },
            None => "NC -".into(),
        };
        lines.push(format!(
            "  {nc}; jobs {} ok, {} failed; {}",
            a.jobs_ok, a.jobs_failed, a.decision
        ));
        if let Some(w) = &a.warning {
            lines.push(format!("  WARNING: {w}"));
        }
        if let Some(e) = &a.last_job_error {
            lines.push(format!("  last job: {e}"));
        }
    }
    lines.iter().map(|l| fit(l, TABLE_WIDTH)).collect()
}

/// The bytes that replace a table of `previous` lines (0: none drawn yet) by `lines`,
/// with the cursor left on the line below the table: up `previous` lines, each line
/// cleared and drawn, and the rest of a taller previous table cleared.
pub fn redraw(previous: usize, lines: &[String]) -> String {
    let mut out = String::new();
    if previous > 0 {
        let _ = write!(out, "\r\x1b[{previous}A");
    }
    for l in lines {
        let _ = write!(out, "\r\x1b[2K{l}\n");
    }
    if previous > lines.len() {
        // The table shrank (a warning went away): clear what is left below it and
        // come back up.
        let extra = previous - lines.len();
        for _ in 0..extra {
            out.push_str("\r\x1b[2K\n");
        }
        let _ = write!(out, "\x1b[{extra}A");
    }
    out
}

/// Prints to `out` as it appears: on a terminal (`tty`) the table redrawn in place,
/// otherwise one line per status update.
pub struct Printer<W> {
    out: W,
    tty: bool,
    /// Lines of the table on screen.
    drawn: usize,
}

impl<W: Write> Printer<W> {
    /// A printer to `out`.
    pub fn new(out: W, tty: bool) -> Self {
        Printer { out, tty, drawn: 0 }
    }

    /// Shows `s`.
    pub fn show(&mut self, s: &Status) {
        // A closed stdout (pipe reader gone) is not worth stopping the gateway for.
        let _ = if self.tty {
            let lines = render_table(s);
            let text = redraw(self.drawn, &lines);
            self.drawn = lines.len();
            self.out.write_all(text.as_bytes())
        } else {
            writeln!(self.out, "{}", render(s))
        };
        let _ = self.out.flush();
    }

    /// The writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}

/// Whether `journal_stream` (systemd's `JOURNAL_STREAM`, `DEV:INODE` of the stream it
/// connected to the journal) names the file `dev`/`ino`.
pub fn is_journal_stream(journal_stream: &str, dev: u64, ino: u64) -> bool {
    journal_stream
        .split_once(':')
        .and_then(|(d, i)| Some((d.parse::<u64>().ok()?, i.parse::<u64>().ok()?)))
        == Some((dev, ino))
}

/// Whether stdout is the journal: then the per-update line is not printed. With a
/// line of every channel each `gateway.status_interval_s`, the journal would hold
/// more status than events (1000 channels: 23 KB a second, 2 GB a day) and rotate
/// the warnings out; `systemctl status`, the status page and `/metrics` show it.
pub fn stdout_is_journal() -> bool {
    fd_is_journal(1)
}

/// Whether stderr is the journal: then each log line carries its level for journald.
pub fn stderr_is_journal() -> bool {
    fd_is_journal(2)
}

/// Whether this process' descriptor `fd` is the stream `JOURNAL_STREAM` names.
fn fd_is_journal(fd: u8) -> bool {
    use std::os::unix::fs::MetadataExt;
    let Some(stream) = std::env::var_os("JOURNAL_STREAM") else {
        return false;
    };
    std::fs::metadata(format!("/proc/self/fd/{fd}"))
        .is_ok_and(|m| is_journal_stream(&stream.to_string_lossy(), m.dev(), m.ino()))
}

/// Whether stdout is `/dev/null`: then the line is not rendered either. Nobody reads
/// it, and rendering is not free: at 1000 channels the line took a seventh of the
/// gateway's instructions at 10k points/s (callgrind).
pub fn stdout_is_null() -> bool {
    use std::os::unix::fs::{FileTypeExt, MetadataExt};
    match (
        std::fs::metadata("/proc/self/fd/1"),
        std::fs::metadata("/dev/null"),
    ) {
        (Ok(out), Ok(null)) => out.file_type().is_char_device() && out.rdev() == null.rdev(),
        _ => false,
    }
}

/// Prints every status the gateway publishes (once per `gateway.status_interval_s`)
/// until `shutdown` or the gateway's end, then the last one.
pub async fn print_loop(rx: watch::Receiver<Status>, tty: bool, shutdown: CancellationToken) {
    print_to(rx, Printer::new(std::io::stdout(), tty), shutdown).await;
}

/// [`print_loop`] to any printer; returns it at the end.
pub async fn print_to<W: Write>(
    mut rx: watch::Receiver<Status>,
    mut printer: Printer<W>,
    shutdown: CancellationToken,
) -> Printer<W> {
    // Copied out before printing: a borrow held while stdout blocks (a paused pager, a
    // full pipe) keeps the control loop from publishing its next status.
    let mut shown = Status::default();
    loop {
        let stop = tokio::select! {
            _ = shutdown.cancelled() => true,
            changed = rx.changed() => changed.is_err(),
        };
        // The gateway publishes its final status as it stops.
        if !stop || rx.has_changed().unwrap_or(true) {
            shown.clone_from(&rx.borrow_and_update());
            printer.show(&shown);
        }
        if stop {
            break;
        }
    }
    printer
}

#[cfg(test)]
mod tests {
    use super::*;
    use compgate_core::channel::Reason;
    use compgate_core::comp::CompParams;
    use compgate_gateway::nc::NcSnapshot;
    use compgate_gateway::runtime::{ChannelStatus, DeviceStatus};

    #[test]
    fn journal_stream_names_the_file_by_device_and_inode() {
        assert!(is_journal_stream("25:1234567", 25, 1_234_567));
        assert!(!is_journal_stream("25:1234567", 25, 1_234_568));
        assert!(!is_journal_stream("26:1234567", 25, 1_234_567));
        assert!(!is_journal_stream("", 25, 1_234_567));
        assert!(!is_journal_stream("25", 25, 1_234_567));
    }

    fn status(t_bed: f64, warning: Option<&str>) -> Status {
        let reading = |v: f64, q: Quality| Reading {
            value_degc: Some(v),
            quality: q,
            ..Reading::no_data()
        };
        Status {
            channels: vec![
                ChannelStatus {
                    name: "T_bed".into(),
                    reading: reading(t_bed, Quality::Good),
                },
                ChannelStatus {
                    name: "T_a_channel_with_a_very_long_name_indeed".into(),
                    reading: reading(21.5, Quality::Bad(Reason::Ne43Low)),
                },
            ],
            devices: vec![DeviceStatus {
                name: "ain1".into(),
                cycles: 5,
                last_error: Some("timeout after 0.5 s reading input registers 0..4 of a device far away on the plant network".into()),
                ..DeviceStatus::default()
            }],
            axes: vec![AxisStatus {
                name: "X".into(),
                written: Some(CompParams {
                    k0_mm: 0.0123,
                    tan_beta: 1.15e-4,
                    p0_mm: 100.0,
                }),
                decision: "write".into(),
                jobs_ok: 3,
                nc: Some(NcSnapshot {
                    applied_comp_mm: Some(0.0345),
                    position_mm: Some(1234.5),
                    ..NcSnapshot::default()
                }),
                warning: warning.map(str::to_string),
                shadow: true,
                would_write: Some(CompParams {
                    k0_mm: 0.02,
                    tan_beta: 2e-4,
                    p0_mm: 100.0,
                }),
                ..AxisStatus::default()
            }],
            samples: 42,
            jobs: Default::default(),
        }
    }

    #[test]
    fn the_table_is_no_wider_than_its_width_and_shows_every_value() {
        let s = status(24.31, Some(&"x".repeat(300)));
        let lines = render_table(&s);
        for l in &lines {
            assert!(l.chars().count() <= TABLE_WIDTH, "{} chars: {l}", l.len());
            assert!(!l.contains('\n') && !l.contains('\r'), "{l:?}");
        }
        let text = lines.join("\n");
        for want in [
            "T_bed",
            "24.31",
            "bad (NE43 low)",
            "SD43900   0.0123 mm",
            "SHADOW: would SD43900   0.0200 mm",
            "NC applies 0.0345 mm at 1234.5 mm",
            "SHADOW",
            "WARNING: xxx",
            "DOWN: timeout",
        ] {
            assert!(text.contains(want), "{want:?} missing from\n{text}");
        }
    }

    /// A bad channel shows no temperature, in the line and in the table: it showed
    /// the value held from before it went bad (`T_bed=25.00degC[bad(Ne43Low)]`).
    #[test]
    fn a_bad_channel_shows_no_temperature() {
        let s = status(24.31, None);
        let line = render(&s);
        assert!(
            line.contains("T_a_channel_with_a_very_long_name_indeed=-degC[bad(Ne43Low)]")
                && !line.contains("21.50"),
            "{line}"
        );
        let table = render_table(&s).join("\n");
        assert!(
            table.contains("24.31") && !table.contains("21.50"),
            "{table}"
        );
    }

    /// The `n` of every cursor-up sequence `ESC [ n A`, in order.
    fn ups(s: &str) -> Vec<usize> {
        s.split("\x1b[")
            .skip(1)
            .filter_map(|rest| {
                let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
                (rest[digits.len()..].starts_with('A')).then(|| digits.parse().ok())?
            })
            .collect()
    }

    // The redraw goes up exactly the height drawn before, draws every line on a
    // cleared line, and clears what a taller previous table left.
    #[test]
    fn the_redraw_moves_up_exactly_the_tables_height() {
        let tall = render_table(&status(24.0, Some("NC unreachable")));
        let short = render_table(&status(24.0, None));
        assert_eq!(tall.len(), short.len() + 1);

        let first = redraw(0, &tall);
        assert_eq!(ups(&first), Vec::<usize>::new());
        assert_eq!(first.matches('\n').count(), tall.len());

        let again = redraw(tall.len(), &tall);
        assert_eq!(ups(&again), vec![tall.len()], "{again:?}");
        assert!(again.starts_with(&format!("\r\x1b[{}A", tall.len())));
        assert_eq!(again.matches("\x1b[2K").count(), tall.len());
        assert_eq!(again.matches('\n').count(), tall.len());

        // Shrinking: the leftover line is cleared, and the cursor comes back up to the
        // line below the new table.
        let shrink = redraw(tall.len(), &short);
        assert_eq!(ups(&shrink), vec![tall.len(), 1], "{shrink:?}");
        assert_eq!(shrink.matches("\x1b[2K").count(), tall.len());
        assert_eq!(shrink.matches('\n').count(), tall.len());
    }

    /// A writer the test can read while the printer owns it.
    #[derive(Clone, Default)]
    struct Shared(std::sync::Arc<std::sync::Mutex<Vec<u8>>>);

    impl Write for Shared {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0.lock().expect("lock").extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Shared {
        fn lines(&self) -> Vec<String> {
            let text = String::from_utf8(self.0.lock().expect("lock").clone()).expect("utf-8");
            text.lines().map(str::to_string).collect()
        }
    }

    // Journal mode: one line per published status, with that status' values (not
    // an older one's), and the final status once more at the end.
    #[tokio::test]
    async fn plain_mode_prints_one_line_per_status_with_current_values() {
        let (tx, rx) = watch::channel(Status::default());
        let shutdown = CancellationToken::new();
        let out = Shared::default();
        let printer = tokio::spawn(print_to(
            rx,
            Printer::new(out.clone(), false),
            shutdown.clone(),
        ));
        for k in 0..5 {
            tx.send_replace(status(20.0 + f64::from(k), None));
            // The next status tick comes after the printer printed this one.
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
            while out.lines().len() < k as usize + 1 {
                assert!(std::time::Instant::now() < deadline, "{:?}", out.lines());
                tokio::time::sleep(std::time::Duration::from_millis(1)).await;
            }
        }
        tx.send_replace(status(30.0, None));
        shutdown.cancel();
        printer.await.expect("printer");
        let lines = out.lines();
        assert_eq!(lines.len(), 6, "{lines:#?}");
        for (k, l) in lines.iter().enumerate() {
            let want = if k == 5 {
                "T_bed=30.00degC[good]".to_string()
            } else {
                format!("T_bed={:.2}degC[good]", 20.0 + k as f64)
            };
            assert!(l.starts_with(&want), "line {k}: {l}");
            assert!(l.contains("SHADOW would_write SD43900=0.0200mm"), "{l}");
            assert!(!l.contains('\r') && !l.contains('\x1b'), "{l:?}");
        }
    }

    /// Stdout that takes nothing until `release` is dropped: a paused pager.
    struct Stalled {
        release: std::sync::mpsc::Receiver<()>,
    }

    impl Write for Stalled {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            let _ = self.release.recv();
            Ok(buf.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    // A stdout that blocks holds the printer up, never the control loop's next status.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_blocked_stdout_does_not_hold_up_the_next_status() {
        let (tx, rx) = watch::channel(Status::default());
        let shutdown = CancellationToken::new();
        let (release, stalled) = std::sync::mpsc::channel();
        let printer = tokio::spawn(print_to(
            rx,
            Printer::new(Stalled { release: stalled }, false),
            shutdown.clone(),
        ));
        tx.send_replace(status(20.0, None));
        // The printer is now stuck writing that status.
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
        let (sent, done) = std::sync::mpsc::channel();
        let published = std::thread::scope(|scope| {
            scope.spawn(|| {
                tx.send_replace(status(21.0, None));
                let _ = sent.send(());
            });
            let published = done.recv_timeout(std::time::Duration::from_secs(2));
            drop(release);
            published
        });
        assert!(published.is_ok(), "the next status waited for stdout");
        shutdown.cancel();
        printer.await.expect("printer");
    }
}
