//! The SYNC producer: one task per CAN interface sends SYNC (COB-ID 0x080) on a
//! fixed-rate timer, whatever the pollers of that interface are doing.
//!
//! A CANopen master's SYNC is its bus' clock: synchronous TPDOs sample on it, so its
//! period must not stretch when a poll cycle waits out a PDO or SDO timeout. Sending
//! SYNC from a node's poll cycle did exactly that (131 ms mean at a 100 ms poll
//! interval); here it comes from its own timer and socket, and the pollers only read
//! the TPDOs that followed the newest SYNC ([`super::node::PdoStore`]).
//!
//! The period is the `poll_interval_s` of the interface's CAN devices. Validation
//! requires one value per interface (the bus has one SYNC period); [`plan`] takes the
//! smallest, so a configuration that skipped validation still gets a SYNC at least
//! as often as any of its devices polls.
//!
//! [`plan`] and [`max_age`] are pure; [`run`] is the task.

use std::collections::BTreeMap;
use std::time::Duration;

use socketcan::tokio::CanSocket;
use socketcan::SocketOptions;
use tokio::time::{Instant, MissedTickBehavior};
use tokio_util::sync::CancellationToken;

use super::codec;
use crate::source::modbus::Backoff;

/// SYNC periods a poller tolerates without a SYNC before it reports the SYNC
/// missing: one late or lost SYNC is not an error, a stopped producer is.
pub const MISSING_AFTER_PERIODS: u32 = 2;

/// The age beyond which the newest SYNC no longer counts as current.
pub fn max_age(period: Duration) -> Duration {
    period * MISSING_AFTER_PERIODS
}

/// What one interface's SYNC producer needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SyncParams {
    /// SocketCAN interface.
    pub interface: String,
    /// Time between SYNCs.
    pub period: Duration,
    /// First wait before reopening the socket after an error; it doubles per
    /// further error up to `backoff_max`.
    pub backoff_initial: Duration,
    /// Longest wait before reopening.
    pub backoff_max: Duration,
}

/// One CAN device as the SYNC plan sees it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SyncDevice {
    /// Its interface.
    pub interface: String,
    /// Its poll interval.
    pub poll_interval: Duration,
    /// Its reconnect backoff, first wait.
    pub backoff_initial: Duration,
    /// Its reconnect backoff, longest wait.
    pub backoff_max: Duration,
}

/// One SYNC producer per interface of `devices`, in interface name order: the
/// smallest poll interval and the smallest backoff of the interface's devices.
pub fn plan(devices: impl IntoIterator<Item = SyncDevice>) -> Vec<SyncParams> {
    let mut by_interface: BTreeMap<String, SyncParams> = BTreeMap::new();
    for d in devices {
        by_interface
            .entry(d.interface.clone())
            .and_modify(|p| {
                p.period = p.period.min(d.poll_interval);
                p.backoff_initial = p.backoff_initial.min(d.backoff_initial);
                p.backoff_max = p.backoff_max.min(d.backoff_max);
            })
            .or_insert(SyncParams {
                interface: d.interface,
                period: d.poll_interval,
                backoff_initial: d.backoff_initial,
                backoff_max: d.backoff_max,
            });
    }
    by_interface.into_values().collect()
}

/// What a SYNC producer did until it stopped.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SyncStats {
    /// SYNC frames sent.
    pub sent: u64,
    /// Sockets opened.
    pub opens: u64,
    /// Failed opens.
    pub open_errors: u64,
    /// Failed sends (each closes the socket).
    pub send_errors: u64,
}

fn open(interface: &str) -> std::io::Result<CanSocket> {
    let socket = CanSocket::open(interface)?;
    // The socket only sends: a receive queue nobody reads would fill with the bus'
    // traffic.
    socket.set_filter_drop_all()?;
    Ok(socket)
}

/// What the journal says of a producer's faults: a line per change (the first fault,
/// a different one, the recovery), never one per retry, as for a device's link; a
/// missing interface would otherwise log at every backoff step for ever.
#[derive(Debug, Default)]
struct FaultLog {
    /// The fault last logged; `None` while sending.
    last: Option<String>,
}

impl FaultLog {
    /// A failure described by `fault`: whether it is news (to log at WARN).
    fn failed(&mut self, fault: String) -> bool {
        let news = self.last.as_deref() != Some(fault.as_str());
        self.last = Some(fault);
        news
    }

    /// Logs `fault`: at WARN when it is news, at DEBUG on every further retry.
    fn log(&mut self, interface: &str, fault: String, backoff: &Backoff, stats: &SyncStats) {
        let retry_in_s = retry_in_s(backoff);
        let failures = stats.open_errors + stats.send_errors;
        if self.failed(fault.clone()) {
            tracing::warn!(interface, retry_in_s, "SYNC producer: {fault}");
        } else {
            tracing::debug!(
                interface,
                retry_in_s,
                failures,
                "SYNC producer still failing: {fault}"
            );
        }
    }

    /// A SYNC sent: whether it ends a fault (to log at INFO).
    fn sent(&mut self) -> bool {
        self.last.take().is_some()
    }
}

fn retry_in_s(backoff: &Backoff) -> f64 {
    backoff
        .remaining(Instant::now())
        .unwrap_or_default()
        .as_secs_f64()
}

/// Sends SYNC on `params.interface` every `params.period` until `stop` is cancelled.
///
/// An open or send error closes the socket; the next attempt waits for the capped
/// backoff (the ticks in between send nothing), and SYNC resumes on the fixed grid
/// once the interface is back. A fault is logged at WARN once per change and its end
/// at INFO; each further retry only at DEBUG.
pub async fn run(params: SyncParams, stop: CancellationToken) -> SyncStats {
    let mut stats = SyncStats::default();
    let mut tick = tokio::time::interval(params.period);
    // Skip: a late tick sends one SYNC and the next stays on the original grid, so
    // the mean period keeps the configured value and a stall never bursts the missed
    // SYNCs onto the bus (Burst would, and synchronous nodes would answer each); Delay
    // would shift the grid by every late tick and stretch the mean period.
    tick.set_missed_tick_behavior(MissedTickBehavior::Skip);
    let mut backoff = Backoff::new(params.backoff_initial, params.backoff_max);
    let mut socket: Option<CanSocket> = None;
    let mut faults = FaultLog::default();
    let iface = params.interface.as_str();

    loop {
        tokio::select! {
            biased;
            _ = stop.cancelled() => break,
            _ = tick.tick() => {}
        }
        let now = Instant::now();
        if backoff.remaining(now).is_some() {
            continue;
        }
        if socket.is_none() {
            match open(iface) {
                Ok(s) => {
                    stats.opens += 1;
                    socket = Some(s);
                }
                Err(e) => {
                    stats.open_errors += 1;
                    backoff.failed(now);
                    let fault = format!("cannot open the interface: {e}");
                    faults.log(iface, fault, &backoff, &stats);
                    continue;
                }
            }
        }
        let Some(s) = socket.as_ref() else {
            continue;
        };
        let Some(frame) = super::to_socketcan(&codec::sync()) else {
            continue;
        };
        // A send that cannot go out within a period (transmit queue full on a bus
        // without acknowledging nodes) is as good as lost.
        let sent = tokio::select! {
            _ = stop.cancelled() => break,
            r = tokio::time::timeout(params.period, s.write_frame(frame)) => r,
        };
        match sent {
            Ok(Ok(())) => {
                stats.sent += 1;
                backoff.reset();
                if faults.sent() {
                    tracing::info!(interface = iface, "SYNC producer: sending again");
                }
            }
            Ok(Err(e)) => {
                stats.send_errors += 1;
                socket = None;
                backoff.failed(Instant::now());
                let fault = format!("send failed, reopening: {e}");
                faults.log(iface, fault, &backoff, &stats);
            }
            Err(_) => {
                stats.send_errors += 1;
                socket = None;
                backoff.failed(Instant::now());
                let fault = format!(
                    "send not done within a period ({} s), reopening",
                    params.period.as_secs_f64()
                );
                faults.log(iface, fault, &backoff, &stats);
            }
        }
    }
    tracing::debug!(
        interface = iface,
        sent = stats.sent,
        opens = stats.opens,
        open_errors = stats.open_errors,
        send_errors = stats.send_errors,
        "SYNC producer stopped"
    );
    stats
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dev(interface: &str, poll_ms: u64, initial_ms: u64, max_ms: u64) -> SyncDevice {
        SyncDevice {
            interface: interface.into(),
            poll_interval: Duration::from_millis(poll_ms),
            backoff_initial: Duration::from_millis(initial_ms),
            backoff_max: Duration::from_millis(max_ms),
        }
    }

    #[test]
    fn one_producer_per_interface_at_the_smallest_interval() {
        let p = plan([
            dev("can1", 500, 500, 30_000),
            dev("can0", 200, 1_000, 10_000),
            dev("can0", 100, 500, 30_000),
            dev("can0", 300, 200, 20_000),
        ]);
        assert_eq!(
            p,
            vec![
                SyncParams {
                    interface: "can0".into(),
                    period: Duration::from_millis(100),
                    backoff_initial: Duration::from_millis(200),
                    backoff_max: Duration::from_millis(10_000),
                },
                SyncParams {
                    interface: "can1".into(),
                    period: Duration::from_millis(500),
                    backoff_initial: Duration::from_millis(500),
                    backoff_max: Duration::from_millis(30_000),
                },
            ]
        );
        assert!(plan(Vec::new()).is_empty());
    }

    #[test]
    fn a_fault_is_logged_once_per_change_not_per_retry() {
        let mut log = FaultLog::default();
        assert!(!log.sent(), "no fault yet: nothing to recover from");
        let gone = || "cannot open the interface: No such device (os error 19)".to_string();
        assert!(log.failed(gone()));
        // Every backoff step of the same fault: no further line.
        for _ in 0..10 {
            assert!(!log.failed(gone()));
        }
        // Another fault is news, and so is the recovery, once.
        assert!(log.failed("send failed, reopening: Network is down (os error 100)".into()));
        assert!(log.sent());
        assert!(!log.sent());
        // The same fault again after a recovery is a change again.
        assert!(log.failed(gone()));
    }

    #[test]
    fn a_sync_is_missing_after_two_periods() {
        assert_eq!(
            max_age(Duration::from_millis(100)),
            Duration::from_millis(200)
        );
    }
}
