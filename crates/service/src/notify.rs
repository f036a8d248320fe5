//! systemd `Type=notify`: READY=1 once start-up is done (the control loop runs with
//! every task started), whatever the devices answer, WATCHDOG=1 from the control
//! loop's own watchdog tick (every half `WATCHDOG_USEC`, see [`watchdog_interval`])
//! and with each status tick, and a STATUS= line with link states and the last write,
//! or why a reload was refused. Without `NOTIFY_SOCKET` (not under systemd) every call
//! does nothing.

use std::fmt::Write as _;

use sd_notify::NotifyState;

use compgate_gateway::runtime::{GatewayError, Observer, Status};

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

/// Tells systemd that a reload was refused and the old configuration runs on, as
/// STATUS= ([`reload_refused_line`]). Every refusal comes here: a file that does not
/// load (the SIGHUP handler) and a config the gateway cannot build ([`Notifier`]'s
/// `on_reload`).
pub fn reload_refused(reason: &dyn std::fmt::Display) {
    Notifier::send(&[NotifyState::Status(&reload_refused_line(reason))]);
}

/// The STATUS= line of a refused reload, on one line (a newline would end the
/// STATUS= assignment): `systemctl status` shows it.
pub fn reload_refused_line(reason: &dyn std::fmt::Display) -> String {
    let reason = reason.to_string();
    let mut lines = reason.lines().map(str::trim).filter(|l| !l.is_empty());
    let first = lines.next().unwrap_or("");
    let rest: Vec<&str> = lines.collect();
    if rest.is_empty() {
        format!("reload refused, old configuration running: {first}")
    } else {
        format!(
            "reload refused, old configuration running: {first} {}",
            rest.join("; ")
        )
    }
}

impl Observer for Notifier {
    fn on_status(&mut self, status: &Status) {
        let line = status_line(status);
        if !self.ready {
            // The first status tick comes as the control loop starts, with the device
            // and NC tasks running: start-up is done. Devices that do not answer (the
            // machine's I/O not powered yet) are in the STATUS line, not a reason to
            // keep systemd waiting until its start timeout kills the service.
            self.ready = true;
            tracing::info!(status = %line, "started: ready");
            Self::send(&[
                NotifyState::Ready,
                NotifyState::Watchdog,
                NotifyState::Status(&line),
            ]);
            self.last_status = line;
        } else if line != self.last_status {
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
            reload_refused(e);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refused_reload_is_one_status_line_with_every_problem() {
        let e = compgate_gateway::config::load_str("[devices.a]\ntimeot_s = 1\n", "plant.toml")
            .unwrap_err();
        assert!(e.to_string().contains('\n'), "{e}");
        let line = reload_refused_line(&e);
        assert!(!line.contains('\n'), "{line}");
        assert!(
            line.starts_with("reload refused, old configuration running: "),
            "{line}"
        );
        for p in e.problems() {
            assert!(line.contains(&p.to_string()), "{line} lacks {p}");
        }
        assert_eq!(
            reload_refused_line(&"channels.T: no device x"),
            "reload refused, old configuration running: channels.T: no device x"
        );
    }
}
