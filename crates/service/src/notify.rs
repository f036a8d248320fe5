//! systemd `Type=notify`: READY=1 once the first poll cycle succeeded, WATCHDOG=1 from
//! the control loop's own watchdog tick (every half `WATCHDOG_USEC`, see
//! [`watchdog_interval`]) and with each status tick, and a STATUS= line with link
//! states and the last write. Without `NOTIFY_SOCKET` (not under systemd) every call
//! does nothing.

use std::fmt::Write as _;

use sd_notify::NotifyState;

use compgate_gateway::runtime::{GatewayError, Observer, SampleReadings, Status};

/// The systemd notifier, an [`Observer`] of the control loop.
#[derive(Debug, Default)]
pub struct Notifier {
    ready: bool,
    last_status: String,
}

impl Notifier {
    /// A notifier; it sends only when `NOTIFY_SOCKET` is set.
    pub fn new() -> Self {
        Self::default()
    }

    fn send(states: &[NotifyState]) {
        if let Err(e) = sd_notify::notify(states) {
            tracing::warn!(error = %e, "sd_notify failed");
        }
    }
}

/// How often the control loop pings systemd's watchdog: half of `WATCHDOG_USEC` when
/// systemd set it for this process (`WatchdogSec=`), else `None`.
pub fn watchdog_interval() -> Option<std::time::Duration> {
    sd_notify::watchdog_enabled().map(|d| d / 2)
}

/// The STATUS= line: each device's link state, then each axis' last write.
pub fn status_line(s: &Status) -> String {
    let mut out = String::new();
    for d in &s.devices {
        let state = match (&d.last_error, d.cycles) {
            (_, 0) => "connecting".to_string(),
            (None, _) => "up".to_string(),
            (Some(_), _) if !d.link_up => format!("down ({} failed)", d.failed_cycles),
            (Some(_), _) => "errors".to_string(),
        };
        let _ = write!(out, "{} {}; ", d.name, state);
    }
    for a in &s.axes {
        match &a.written {
            Some(p) => {
                let _ = write!(
                    out,
                    "{}: SD43900={:.4}mm SD43910={:.3e} SD43920={:.1}mm jobs {} ok {} failed; ",
                    a.name, p.k0_mm, p.tan_beta, p.p0_mm, a.jobs_ok, a.jobs_failed
                );
            }
            None => {
                let _ = write!(out, "{}: nothing written yet; ", a.name);
            }
        }
        if let (true, Some(p)) = (a.shadow, &a.would_write) {
            let _ = write!(
                out,
                "{} SHADOW (NC not written): would write SD43900={:.4}mm SD43910={:.3e} SD43920={:.1}mm; ",
                a.name, p.k0_mm, p.tan_beta, p.p0_mm
            );
        } else if a.shadow {
            let _ = write!(out, "{} SHADOW (NC not written); ", a.name);
        }
    }
    out.trim_end_matches([' ', ';']).to_string()
}

impl Observer for Notifier {
    fn on_sample(&mut self, readings: &SampleReadings) {
        if !self.ready && readings.error.is_none() {
            self.ready = true;
            tracing::info!("first poll cycle succeeded: ready");
            Self::send(&[NotifyState::Ready]);
        }
    }

    fn on_status(&mut self, status: &Status) {
        let line = status_line(status);
        if line != self.last_status {
            Self::send(&[NotifyState::Watchdog, NotifyState::Status(&line)]);
            self.last_status = line;
        } else {
            Self::send(&[NotifyState::Watchdog]);
        }
    }

    fn on_watchdog(&mut self) {
        Self::send(&[NotifyState::Watchdog]);
    }

    fn on_reload(&mut self, result: &Result<(), GatewayError>) {
        if let Err(e) = result {
            let line = format!("reload refused, old configuration running: {e}");
            Self::send(&[NotifyState::Status(&line)]);
        }
    }
}
