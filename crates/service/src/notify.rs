//! systemd `Type=notify`: READY=1 once start-up is done (the control loop runs with
//! every task started), whatever the devices answer, WATCHDOG=1 from the control
//! loop's own watchdog tick (every half `WATCHDOG_USEC`, see [`watchdog_interval`])
//! and with each status tick, and a STATUS= line with link states, bad channels, the
//! last write and what holds an axis, and why the last reload was refused (until one
//! succeeds). Without `NOTIFY_SOCKET` (not under systemd) every call
//! does nothing.

use std::fmt::Write as _;
use std::sync::Mutex;

use sd_notify::NotifyState;

use compgate_core::channel::Quality;
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

/// Bad channels the STATUS= line names; the rest are counted.
const BAD_CHANNELS_NAMED: usize = 3;

/// The STATUS= line: each device's link state, the bad channels, then each axis' last
/// write, and what keeps an axis from following its model (a hold, its limit, the NC
/// unreachable): `systemctl status` is where an operator looks first.
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
    let bad: Vec<String> = s
        .channels
        .iter()
        .filter_map(|c| match c.reading.quality {
            Quality::Bad(reason) => Some(format!("{} ({reason})", c.name)),
            _ => None,
        })
        .collect();
    if !bad.is_empty() {
        let more = bad.len().saturating_sub(BAD_CHANNELS_NAMED);
        let _ = write!(
            out,
            "bad: {}",
            bad[..bad.len().min(BAD_CHANNELS_NAMED)].join(", ")
        );
        if more > 0 {
            let _ = write!(out, " and {more} more");
        }
        out.push_str("; ");
    }
    for a in &s.axes {
        match &a.written {
            Some(p) => {
                let _ = write!(
                    out,
                    "{}: SD43900={:.4}mm SD43910={:.3e} SD43920={:.1}mm jobs {} ok {} failed",
                    a.name, p.k0_mm, p.tan_beta, p.p0_mm, a.jobs_ok, a.jobs_failed
                );
                // Jobs that fail now and then (an NC that answers slowly) leave no
                // error in the status between two failures: the last one stays.
                if let Some((_, why)) = &a.last_failure {
                    let _ = write!(out, " (last: {why})");
                }
            }
            None => {
                let _ = write!(out, "{}: nothing written yet", a.name);
            }
        }
        // Writing or within the deadband is the normal course, and flips every
        // update: only a decision that is not is shown.
        let usual = ["write", "write (limited)", "within deadband", ""];
        if !usual.contains(&a.decision.as_str()) {
            let _ = write!(out, ", {}", a.decision);
        }
        if let Some(w) = &a.warning {
            let _ = write!(out, ", {w}");
        }
        out.push_str("; ");
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

/// The last refused reload's STATUS= text, until a reload succeeds: the status line
/// carries it, so it is still there when someone looks a minute later. One per
/// process, like the notify socket it goes to.
static RELOAD_REFUSED: Mutex<Option<String>> = Mutex::new(None);

fn set_reload_refused(line: Option<String>) {
    *RELOAD_REFUSED
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner) = line;
}

fn with_reload_refused(mut line: String) -> String {
    let refused = RELOAD_REFUSED
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(r) = refused.as_deref() {
        if !line.is_empty() {
            line.push_str("; ");
        }
        line.push_str(r);
    }
    line
}

/// Tells systemd that a reload was refused and the old configuration runs on, as
/// STATUS= ([`reload_refused_line`]). Every refusal comes here: a file that does not
/// load (the SIGHUP handler) and a config the gateway cannot build ([`Notifier`]'s
/// `on_reload`).
pub fn reload_refused(reason: &dyn std::fmt::Display) {
    let line = reload_refused_line(reason);
    Notifier::send(&[NotifyState::Status(&line)]);
    set_reload_refused(Some(line));
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
        let line = with_reload_refused(status_line(status));
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
        match result {
            Err(e) => reload_refused(e),
            Ok(()) => set_reload_refused(None),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use compgate_core::channel::{Reading, Reason};
    use compgate_core::comp::CompParams;
    use compgate_gateway::runtime::{AxisStatus, ChannelStatus, DeviceStatus};

    fn channel(name: &str, quality: Quality) -> ChannelStatus {
        ChannelStatus {
            name: name.into(),
            reading: Reading {
                value_degc: Some(25.0),
                quality,
                ..Reading::no_data()
            },
        }
    }

    // What `systemctl status` showed during an NC outage and a wire break, with the
    // axis holding: "ain1 up; X: SD43900=... jobs 5 ok 0 failed", as if all were well.
    #[test]
    fn the_status_line_names_bad_channels_and_what_holds_an_axis() {
        let mut s = Status {
            devices: vec![DeviceStatus {
                name: "ain1".into(),
                cycles: 9,
                link_up: true,
                ..DeviceStatus::default()
            }],
            channels: vec![
                channel("T_bed", Quality::Good),
                channel("T_screw", Quality::Bad(Reason::Ne43Low)),
                channel("T_col", Quality::Uncertain(Reason::Comm)),
            ],
            axes: vec![AxisStatus {
                name: "X".into(),
                written: Some(CompParams {
                    k0_mm: 0.0534,
                    tan_beta: 0.0,
                    p0_mm: 100.0,
                }),
                decision: "hold: bad input T_screw".into(),
                warning: Some("NC unreachable: connect timed out".into()),
                jobs_ok: 5,
                ..AxisStatus::default()
            }],
            ..Status::default()
        };
        assert_eq!(
            status_line(&s),
            "ain1 up; bad: T_screw (NE43 low); X: SD43900=0.0534mm SD43910=0.000e0 \
             SD43920=100.0mm jobs 5 ok 0 failed, hold: bad input T_screw, NC unreachable: \
             connect timed out"
        );
        // The usual course says nothing more: it changes every update.
        s.channels.truncate(1);
        s.axes[0].warning = None;
        for usual in ["write", "write (limited)", "within deadband"] {
            s.axes[0].decision = usual.into();
            assert!(status_line(&s).ends_with("jobs 5 ok 0 failed"), "{usual}");
        }
        // Jobs that failed once stay named after jobs succeed again.
        s.axes[0].jobs_failed = 9;
        s.axes[0].last_failure = Some((
            std::time::SystemTime::UNIX_EPOCH,
            "job 184 did not finish within 2s: the values may have landed".into(),
        ));
        assert!(
            status_line(&s).ends_with(
                "jobs 5 ok 9 failed (last: job 184 did not finish within 2s: the values may have landed)"
            ),
            "{}",
            status_line(&s)
        );
        s.axes[0].jobs_failed = 0;
        s.axes[0].last_failure = None;
        // Many bad channels: three named, the rest counted.
        s.channels = (0..5)
            .map(|i| channel(&format!("T_{i}"), Quality::Bad(Reason::DeviceDegraded)))
            .collect();
        let line = status_line(&s);
        assert!(
            line.contains("bad: T_0 (device degraded), T_1 (device degraded), T_2 (device degraded) and 2 more;"),
            "{line}"
        );
    }

    #[test]
    fn a_refused_reload_stays_in_the_status_line_until_one_succeeds() {
        let mut n = Notifier::new();
        reload_refused(&"channels.T: no device x");
        let line = with_reload_refused("ain1 up".into());
        assert_eq!(
            line,
            "ain1 up; reload refused, old configuration running: channels.T: no device x"
        );
        n.on_reload(&Ok(()));
        assert_eq!(with_reload_refused("ain1 up".into()), "ain1 up");
    }

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
