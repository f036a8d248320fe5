//! The status line: temperatures with quality, the SD43900/43910/43920 values last
//! written, and the compensation the NC applies now.
//!
//! On a terminal the line is redrawn in place; otherwise (journal, pipe, file) one
//! plain line is printed per update, naming every value so it can be grepped.

use std::fmt::Write as _;
use std::io::Write as _;
use std::time::Duration;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

use compgate_core::channel::Quality;
use compgate_gateway::runtime::Status;

fn quality_word(q: &Quality) -> String {
    match q {
        Quality::Good => "good".into(),
        Quality::Uncertain(r) => format!("uncertain({r:?})"),
        Quality::Bad(r) => format!("bad({r:?})"),
    }
}

/// One line describing the gateway's state.
pub fn render(s: &Status) -> String {
    let mut out = String::new();
    for c in &s.channels {
        let v = c
            .reading
            .value_degc
            .map_or_else(|| "-".to_string(), |v| format!("{v:.2}"));
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
        match &a.nc {
            Some(nc) => {
                let _ = write!(
                    out,
                    "NC pos={:.1}mm comp={:.4}mm ",
                    nc.position_mm, nc.applied_comp_mm
                );
            }
            None => out.push_str("NC comp=- "),
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

/// Prints the status every `interval` until `shutdown`, then once more.
pub async fn print_loop(
    mut rx: watch::Receiver<Status>,
    interval: Duration,
    tty: bool,
    shutdown: CancellationToken,
) {
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let stop = tokio::select! {
            _ = shutdown.cancelled() => true,
            _ = tick.tick() => false,
        };
        let line = render(&rx.borrow_and_update());
        let mut out = std::io::stdout().lock();
        // A closed stdout (pipe reader gone) is not worth stopping the gateway for.
        let _ = if tty {
            write!(out, "\r\x1b[K{line}")
        } else {
            writeln!(out, "{line}")
        };
        let _ = out.flush();
        if stop {
            if tty {
                let _ = writeln!(out);
            }
            break;
        }
    }
}
