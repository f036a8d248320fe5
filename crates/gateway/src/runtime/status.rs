//! What the running gateway shows: the status snapshot of devices, channels and axes.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use crate::nc::NcSnapshot;
use compgate_core::channel::{Quality, Reading, Reason};
use compgate_core::comp::{CompParams, Decision};

/// What the gateway shows of one channel.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelStatus {
    /// Channel name. Shared: the status is cloned for its readers once per status
    /// interval, and copying 10000 names each time held the polls up for a millisecond.
    pub name: Arc<str>,
    /// The last reading.
    pub reading: Reading,
}

/// What the gateway shows of one device.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DeviceStatus {
    /// Device name.
    pub name: String,
    /// Link description.
    pub link: String,
    /// Poll cycles run.
    pub cycles: u64,
    /// Cycles with at least one failed read, in a row.
    pub failed_cycles: u32,
    /// Last error, if the last cycle had one.
    pub last_error: Option<String>,
    /// The device answered in its last cycle (a value or an exception): a failed read
    /// of one block leaves it up, only that read's channels go bad.
    pub link_up: bool,
    /// Failed requests counted by kind (timeout, frame, transport, exception, ...),
    /// retries included; a cycle the reconnect backoff refused counts one `backoff`.
    pub errors: BTreeMap<&'static str, u64>,
    /// Duration of the last poll cycle.
    pub last_cycle: Duration,
    /// Connections made to the device so far.
    pub connects: u64,
}

/// What the gateway shows of one axis.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct AxisStatus {
    /// Axis name.
    pub name: String,
    /// Parameters the NC accepted last (read at start, then each verified write).
    pub written: Option<CompParams>,
    /// The last decision, in words.
    pub decision: String,
    /// The last decision found the model's value beyond `max_abs_k0_mm` or
    /// `max_abs_tan_beta`: the NC gets the limit (the decision names the value).
    pub at_limit: bool,
    /// An input reads outside the temperatures the model was fitted over
    /// (`fitted_degc`): which, and by how much.
    pub outside_fit: Option<String>,
    /// Jobs that ended verified.
    pub jobs_ok: u64,
    /// Jobs that failed.
    pub jobs_failed: u64,
    /// Shadow mode: jobs computed and not sent.
    pub jobs_shadow: u64,
    /// The last job error, while jobs fail.
    pub last_job_error: Option<String>,
    /// The last job that failed, when and why: kept after jobs succeed again, so a
    /// failure between two looks at the status is still seen.
    pub last_failure: Option<(std::time::SystemTime, String)>,
    /// The NC's last snapshot.
    pub nc: Option<NcSnapshot>,
    /// When it was read (its answer came): the status is published up to a status
    /// interval later, and a record stamped then lagged the NC by that much.
    pub nc_read_at: Option<std::time::Instant>,
    /// Reads of the NC that answered: a new count is a new snapshot (the status is
    /// published more often than the NC is read).
    pub nc_reads: u64,
    /// A warning a commissioning engineer must see (MD32750 mismatch, NC unreachable).
    pub warning: Option<String>,
    /// The NC's last read found its MD32750 other than the config's: the axis holds.
    pub md32750_wrong: bool,
    /// The NC's last read found the axis not referenced: the NC applies no
    /// compensation.
    pub unreferenced: bool,
    /// Shadow mode: the axis computes and records what it would write, and never
    /// writes the NC.
    pub shadow: bool,
    /// Shadow mode: the parameters the gateway would have written last.
    pub would_write: Option<CompParams>,
}

/// NC jobs kept in [`Status::jobs`].
pub const JOB_HISTORY: usize = 20;

/// One NC job, or in shadow mode one write the gateway would have made.
#[derive(Debug, Clone, PartialEq)]
pub struct JobStatus {
    /// Axis name.
    pub axis: String,
    /// When the job ended (shadow: when it was decided).
    pub at: SystemTime,
    /// The parameters written (shadow: that would have been written).
    pub params: CompParams,
    /// Not sent: the axis runs in shadow mode.
    pub shadow: bool,
    /// The NC's job id (a verified job only).
    pub job_id: Option<u16>,
    /// Time from the first request to the verified read-back (a verified job only).
    pub elapsed: Option<Duration>,
    /// Why the job failed.
    pub error: Option<String>,
}

/// Everything the status line, logs and tests look at.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Status {
    /// Per channel, in config order.
    pub channels: Vec<ChannelStatus>,
    /// Per device.
    pub devices: Vec<DeviceStatus>,
    /// Per axis.
    pub axes: Vec<AxisStatus>,
    /// Device samples processed.
    pub samples: u64,
    /// The last [`JOB_HISTORY`] NC jobs of every axis, oldest first.
    pub jobs: VecDeque<JobStatus>,
}

impl Status {
    /// Adds `job` to [`Self::jobs`], dropping the oldest beyond [`JOB_HISTORY`].
    pub fn push_job(&mut self, job: JobStatus) {
        while self.jobs.len() >= JOB_HISTORY {
            self.jobs.pop_front();
        }
        self.jobs.push_back(job);
    }
}

/// A channel or an axis logs at most [`CHANGE_LOG_LINES`] changes per this many
/// seconds; the next line counts the changes in between.
pub(super) const CHANGE_LOG_WINDOW_S: f64 = 10.0;
/// Two: a fault and its recovery are both logged when they happen.
pub(super) const CHANGE_LOG_LINES: u32 = 2;

/// What the journal says of a channel (`Some(usable)`), or `None` when its reading
/// only says that its device's link failed: the device's own line covers that, and a
/// device with many channels would otherwise log one line for each.
#[inline]
pub(super) fn journal_usable(q: &Quality) -> Option<bool> {
    match q {
        Quality::Bad(
            Reason::Comm | Reason::DeviceException | Reason::DeviceDegraded | Reason::NoData,
        ) => None,
        q => Some(q.is_usable()),
    }
}

/// What the journal says of an axis' decisions: only a change between these is logged,
/// not one between writing and within deadband, nor a ramp that reached zero and holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum AxisCourse {
    /// Writing, or within the deadband: the axis follows its model.
    Model,
    /// Writing or within the deadband, but the model's value is beyond an absolute
    /// limit: the NC gets the limit, not the model.
    AtLimit,
    /// Holding or ramping to zero: a bad input (or a model value not finite).
    Fallback,
}

impl AxisCourse {
    pub(super) fn of(d: &Decision, beyond_limit: bool) -> Self {
        match d {
            Decision::Write { .. } | Decision::WithinDeadband if beyond_limit => Self::AtLimit,
            Decision::Write { .. } | Decision::WithinDeadband => Self::Model,
            Decision::Hold { .. } | Decision::Ramp { .. } => Self::Fallback,
        }
    }
}

/// Logs a state once per change, never once per sample, and at most
/// [`CHANGE_LOG_LINES`] times per [`CHANGE_LOG_WINDOW_S`]: a state flapping every
/// sample must not flood the journal.
#[derive(Debug, Clone, Copy)]
pub(super) struct ChangeLog<S> {
    /// The state last seen (logged or not).
    seen: S,
    /// Changes since the last line that were not logged yet.
    unlogged: u32,
    /// Lines in the window that ends at `window_end_s`.
    lines: u32,
    window_end_s: f64,
}

impl<S: Copy + PartialEq> ChangeLog<S> {
    /// A log that takes `seen` as said already (nothing is logged while it holds).
    pub(super) fn new(seen: S) -> Self {
        Self {
            seen,
            unlogged: 0,
            lines: 0,
            window_end_s: f64::NEG_INFINITY,
        }
    }

    /// `state` seen at `t_s`: `Some(n)` when it is to be logged now, `n` being the
    /// changes before it that were not logged. In the steady state this is two
    /// compares: it runs for every channel of every sample.
    #[inline]
    pub(super) fn note(&mut self, state: S, t_s: f64) -> Option<u32> {
        if state == self.seen && self.unlogged == 0 {
            return None;
        }
        self.note_change(state, t_s)
    }

    #[cold]
    fn note_change(&mut self, state: S, t_s: f64) -> Option<u32> {
        if state != self.seen {
            self.seen = state;
            self.unlogged = self.unlogged.saturating_add(1);
        }
        if t_s >= self.window_end_s {
            self.window_end_s = t_s + CHANGE_LOG_WINDOW_S;
            self.lines = 0;
        }
        // Past the limit the line waits for the next window, even for a state that
        // settled back to what was logged: the journal's last word is the state as
        // it is, with the count of what it missed.
        if self.lines >= CHANGE_LOG_LINES {
            return None;
        }
        self.lines += 1;
        let more = self.unlogged.saturating_sub(1);
        self.unlogged = 0;
        Some(more)
    }

    /// The state and the changes before it, when changes were seen but not logged
    /// yet (for a last line before this log is dropped); marks them logged.
    pub(super) fn take_unlogged(&mut self) -> Option<(S, u32)> {
        let n = std::mem::take(&mut self.unlogged);
        (n > 0).then(|| (self.seen, n - 1))
    }
}

/// `""`, or how many changes before this line were not logged.
pub(super) fn unlogged_suffix(more: u32) -> String {
    if more == 0 {
        String::new()
    } else {
        format!(" ({more} more changes since the last line: at most {CHANGE_LOG_LINES} lines per {CHANGE_LOG_WINDOW_S} s)")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // A change is logged once, however many samples repeat it, and a fault and its
    // recovery both when they happen; the state at start is taken as said.
    #[test]
    fn a_change_is_logged_once_when_it_happens() {
        let mut log = ChangeLog::new(true);
        assert_eq!(log.note(true, 0.0), None);
        assert_eq!(log.note(false, 1.0), Some(0));
        for k in 0..100 {
            assert_eq!(log.note(false, 1.0 + 0.01 * f64::from(k)), None);
        }
        assert_eq!(log.note(true, 2.0), Some(0));
        assert_eq!(log.note(true, 2.1), None);
    }

    // A state flapping every sample gets two lines per window, the first of which
    // counts the changes in between; it settles with one line more, on the state as
    // it is.
    #[test]
    fn a_flapping_state_is_logged_twice_per_window_with_a_count() {
        let mut log = ChangeLog::new(true);
        let mut lines = Vec::new();
        // A change every 0.125 s sample for 25 s.
        for k in 0..200 {
            let t_s = 0.125 * f64::from(k);
            if let Some(more) = log.note(k % 2 == 0, t_s) {
                lines.push((t_s, k % 2 == 0, more));
            }
        }
        assert_eq!(
            lines,
            [
                (0.125, false, 0),
                (0.25, true, 0),
                (10.125, false, 78),
                (10.25, true, 0),
                (20.125, false, 78),
                (20.25, true, 0)
            ]
        );
        // It settles on the last state seen: one line when the window is over.
        let mut settled = Vec::new();
        for k in 200..400 {
            let t_s = 0.125 * f64::from(k);
            settled.extend(log.note(false, t_s).map(|more| (t_s, more)));
        }
        assert_eq!(settled, [(30.125, 36)]);
        assert_eq!(log.take_unlogged(), None);
        // Seen but not logged yet: handed out once.
        assert_eq!(log.note(true, 41.0), Some(0));
        assert_eq!(log.note(false, 42.0), Some(0));
        assert_eq!(log.note(true, 43.0), None);
        assert_eq!(log.take_unlogged(), Some((true, 0)));
        assert_eq!(log.take_unlogged(), None);
    }

    // A device's link failure is left to the device's line; a sensor's own fault is
    // the channel's.
    #[test]
    fn link_failures_are_left_to_the_device() {
        assert_eq!(journal_usable(&Quality::Good), Some(true));
        assert_eq!(
            journal_usable(&Quality::Uncertain(Reason::Comm)),
            Some(true)
        );
        assert_eq!(journal_usable(&Quality::Bad(Reason::Ne43Low)), Some(false));
        assert_eq!(journal_usable(&Quality::Bad(Reason::Stale)), Some(false));
        assert_eq!(journal_usable(&Quality::Bad(Reason::DeviceDegraded)), None);
        assert_eq!(journal_usable(&Quality::Bad(Reason::NoData)), None);
    }

    // The job history keeps the newest JOB_HISTORY jobs, oldest first.
    #[test]
    fn the_job_history_keeps_the_newest_jobs() {
        let mut s = Status::default();
        for id in 0..(JOB_HISTORY as u16 + 5) {
            s.push_job(JobStatus {
                axis: "X".into(),
                at: SystemTime::UNIX_EPOCH,
                params: CompParams::default(),
                shadow: false,
                job_id: Some(id),
                elapsed: None,
                error: None,
            });
        }
        assert_eq!(s.jobs.len(), JOB_HISTORY);
        assert_eq!(s.jobs.front().and_then(|j| j.job_id), Some(5));
        assert_eq!(
            s.jobs.back().and_then(|j| j.job_id),
            Some(JOB_HISTORY as u16 + 4)
        );
    }
}
