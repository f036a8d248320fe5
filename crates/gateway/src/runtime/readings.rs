//! What one device sample produced. The core loop builds it once, right after the
//! sample went through the channel processors, and hands it forward: the status
//! snapshot and every observer (recorder, metrics, MQTT, systemd) read this value, so
//! none of them looks a channel up in the pipeline again.

use std::sync::Arc;
use std::time::Duration;

use crate::source::SourceError;
use compgate_core::channel::Reading;

/// One channel's reading after a device sample.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelReading {
    /// Channel index, config order: an index into [`SampleReadings::channel_names`].
    pub channel: usize,
    /// The reading after this sample.
    pub reading: Reading,
}

/// One device sample's outcome: the link's and that of each of its channels.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SampleReadings {
    /// Device index, config order.
    pub device: usize,
    /// Device name.
    pub device_name: Arc<str>,
    /// Time the poll cycle took.
    pub poll_elapsed: Duration,
    /// Connections the device's link has made so far (a rise means it reconnected).
    pub connects: u64,
    /// The cycle's first error; `None` when everything was read.
    pub error: Option<SourceError>,
    /// The device answered this cycle (a value or an exception): its link is up, even
    /// when one of its reads failed ([`DeviceSample::answered`](crate::source::DeviceSample::answered)).
    pub link_up: bool,
    /// The kind of every request of the cycle that failed, retried ones included
    /// ([`DeviceSample::faults`](crate::source::DeviceSample::faults)).
    pub faults: Vec<&'static str>,
    /// Every channel name of the configuration, by index: one shared table per
    /// configuration, so handing it on costs a reference count.
    pub channel_names: Arc<[String]>,
    /// The readings of the sample's channels, in the sample's order.
    pub channels: Vec<ChannelReading>,
}

impl SampleReadings {
    /// The sample's channels with their names.
    pub fn named(&self) -> impl Iterator<Item = (&str, &ChannelReading)> {
        self.channels.iter().filter_map(|c| {
            let name = self.channel_names.get(c.channel)?;
            Some((name.as_str(), c))
        })
    }
}
