//! What the running gateway shows: the status snapshot of devices, channels and axes.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use crate::nc::NcSnapshot;
use compgate_core::channel::Reading;
use compgate_core::comp::CompParams;

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
    /// Errors counted by kind (timeout, transport, exception, ...).
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
    /// Jobs that ended verified.
    pub jobs_ok: u64,
    /// Jobs that failed.
    pub jobs_failed: u64,
    /// The last job error.
    pub last_job_error: Option<String>,
    /// The NC's last snapshot.
    pub nc: Option<NcSnapshot>,
    /// A warning a commissioning engineer must see (MD32750 mismatch, NC unreachable).
    pub warning: Option<String>,
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

#[cfg(test)]
mod tests {
    use super::*;

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
