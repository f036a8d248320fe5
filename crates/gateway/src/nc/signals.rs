//! SIGINT, SIGTERM and SIGHUP for a command that acts on the NC (`nc write`, the
//! backlash test): their default action ends the process at once, mid-job or with the
//! axis moving; caught, the command finishes or undoes what it started and says so.

use std::future::Future;

use tokio::signal::unix::{signal, Signal, SignalKind};

/// The three signals, caught from [`Self::register`] on (for the rest of the
/// process: tokio never hands a signal back to its default action).
pub struct StopSignals {
    int: Option<Signal>,
    term: Option<Signal>,
    hup: Option<Signal>,
}

impl StopSignals {
    /// Catches them; one that cannot be caught keeps its default action.
    pub fn register() -> Self {
        Self {
            int: signal(SignalKind::interrupt()).ok(),
            term: signal(SignalKind::terminate()).ok(),
            hup: signal(SignalKind::hangup()).ok(),
        }
    }

    /// One of them that came and was not taken yet, without waiting.
    pub fn pending(&mut self) -> Option<&'static str> {
        let mut next = std::pin::pin!(self.recv());
        let waker = std::task::Waker::noop();
        match next
            .as_mut()
            .poll(&mut std::task::Context::from_waker(waker))
        {
            std::task::Poll::Ready(signal) => Some(signal),
            std::task::Poll::Pending => None,
        }
    }

    /// The next of them, by name.
    pub async fn recv(&mut self) -> &'static str {
        let Self { int, term, hup } = self;
        tokio::select! {
            Some(()) = async { int.as_mut()?.recv().await } => "SIGINT",
            Some(()) = async { term.as_mut()?.recv().await } => "SIGTERM",
            Some(()) = async { hup.as_mut()?.recv().await } => "SIGHUP",
            else => std::future::pending().await,
        }
    }
}
