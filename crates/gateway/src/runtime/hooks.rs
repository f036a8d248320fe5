//! What the service hangs on the control loop: an [`Observer`] called from the loop
//! itself, and a source of reloaded configurations.
//!
//! Observers must return quickly: anything slow (disk, network) goes through a bounded
//! channel to a task of its own, and drops rather than blocks when that task lags.

use tokio::sync::mpsc;

use super::{GatewayError, SampleReadings, Status};
use crate::config::Config;
use crate::nc::{JobReport, NcError};
use compgate_core::comp::CompParams;

/// Called by the control loop; every method defaults to doing nothing.
pub trait Observer: Send {
    /// One device poll cycle went through the channel processors: its link outcome
    /// and its channels' new readings.
    fn on_sample(&mut self, _readings: &SampleReadings) {}
    /// An NC job for axis `axis` ended.
    fn on_job(&mut self, _axis: &str, _params: &CompParams, _result: &Result<JobReport, NcError>) {}
    /// Shadow mode: axis `axis` would have written `params` now (the NC is not written).
    fn on_shadow(&mut self, _axis: &str, _params: &CompParams) {}
    /// The status tick of the loop (every `gateway.status_interval_s`).
    fn on_status(&mut self, _status: &Status) {}
    /// The liveness tick of the loop (every [`Hooks::watchdog_interval`]): called by
    /// the core loop itself between samples, so it stops when the loop is stuck.
    fn on_watchdog(&mut self) {}
    /// A reload took effect (`Ok`) or was refused and the old config stays (`Err`).
    fn on_reload(&mut self, _result: &Result<(), GatewayError>) {}
}

/// The observer that does nothing.
impl Observer for () {}

/// Several observers, called in order.
#[derive(Default)]
pub struct Observers(pub Vec<Box<dyn Observer>>);

impl Observer for Observers {
    fn on_sample(&mut self, readings: &SampleReadings) {
        for o in &mut self.0 {
            o.on_sample(readings);
        }
    }
    fn on_job(&mut self, axis: &str, params: &CompParams, result: &Result<JobReport, NcError>) {
        for o in &mut self.0 {
            o.on_job(axis, params, result);
        }
    }
    fn on_shadow(&mut self, axis: &str, params: &CompParams) {
        for o in &mut self.0 {
            o.on_shadow(axis, params);
        }
    }
    fn on_status(&mut self, status: &Status) {
        for o in &mut self.0 {
            o.on_status(status);
        }
    }
    fn on_watchdog(&mut self) {
        for o in &mut self.0 {
            o.on_watchdog();
        }
    }
    fn on_reload(&mut self, result: &Result<(), GatewayError>) {
        for o in &mut self.0 {
            o.on_reload(result);
        }
    }
}

/// Hooks of [`run_with`](super::run_with).
pub struct Hooks {
    /// Called from the control loop.
    pub observer: Box<dyn Observer>,
    /// New configurations (already loaded and validated), e.g. on SIGHUP.
    pub reload: Option<mpsc::Receiver<Config>>,
    /// Period of [`Observer::on_watchdog`], independent of the status interval (e.g.
    /// half of systemd's `WATCHDOG_USEC`). `None`: never called.
    pub watchdog_interval: Option<std::time::Duration>,
}

impl Default for Hooks {
    fn default() -> Self {
        Hooks {
            observer: Box::new(()),
            reload: None,
            watchdog_interval: None,
        }
    }
}
