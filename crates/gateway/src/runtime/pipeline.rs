//! The synchronous part of the gateway: channel processors and axis compensators.

use std::time::Duration;

use tokio::time::Instant;

use crate::source::DeviceSample;
use compgate_core::channel::{Bank, ChannelProcessor, LowPassGain, Reading};
use compgate_core::comp::{AxisCompensator, Decision};

use super::ChannelStatus;

/// One axis at run time.
#[derive(Debug)]
pub struct AxisRt {
    /// Axis name.
    pub name: String,
    /// Index of its NC module.
    pub nc_module: usize,
    /// Channel index of each model input.
    pub inputs: Vec<usize>,
    /// The compensator.
    pub comp: AxisCompensator,
    /// MD32750 the config expects.
    pub md32750: u16,
    /// Time between updates.
    pub update_interval: Duration,
}

/// The synchronous part of the gateway: channel processors and axis compensators.
/// The core loop and `compgate bench` drive the same code.
#[derive(Debug)]
pub struct Pipeline {
    /// Channel names, in config order.
    pub channel_names: Vec<String>,
    /// One processor per channel; out of date for a channel its device's bank holds.
    pub(super) processors: Vec<ChannelProcessor>,
    /// One bank per device, for its steady channels.
    pub(super) banks: Vec<Bank>,
    /// Each channel's device and its lane in the device's bank.
    pub(super) homes: Vec<(usize, usize)>,
    /// Axes.
    pub axes: Vec<AxisRt>,
    /// Model inputs of the last decision (kept for its allocation).
    pub(super) temps_degc: Vec<Option<f64>>,
    pub(super) epoch: Instant,
}

impl Pipeline {
    /// Seconds since the pipeline started: the time base of channels and axes.
    pub fn now_s(&self, at: Instant) -> f64 {
        at.saturating_duration_since(self.epoch).as_secs_f64()
    }

    /// A pipeline over `processors` (config order), the channels of device `d` being
    /// `device_channels[d]`.
    pub(super) fn new(
        channel_names: Vec<String>,
        processors: Vec<ChannelProcessor>,
        device_channels: Vec<Vec<usize>>,
        axes: Vec<AxisRt>,
    ) -> Self {
        let mut homes = vec![(usize::MAX, 0); processors.len()];
        for (device, channels) in device_channels.iter().enumerate() {
            for (lane, &ch) in channels.iter().enumerate() {
                homes[ch] = (device, lane);
            }
        }
        let banks = device_channels
            .into_iter()
            .map(|channels| Bank::new(channels, &processors))
            .collect();
        Self {
            channel_names,
            processors,
            banks,
            homes,
            axes,
            temps_degc: Vec::new(),
            epoch: Instant::now(),
        }
    }

    /// The latest reading of channel `ch` (config order); `None` past the last channel.
    pub fn reading(&self, ch: usize) -> Option<Reading> {
        match self.held(ch) {
            Some((bank, lane)) => Some(bank.reading(lane)),
            None => self.processors.get(ch).map(|p| p.last().clone()),
        }
    }

    /// The bank and lane of channel `ch` if its device's bank holds it.
    pub(super) fn held(&self, ch: usize) -> Option<(&Bank, usize)> {
        let (device, lane) = *self.homes.get(ch)?;
        let bank = self.banks.get(device)?;
        bank.holds(lane).then_some((bank, lane))
    }

    /// Every channel's name and reading, in config order.
    pub fn channel_statuses(&self) -> Vec<ChannelStatus> {
        self.channel_names
            .iter()
            .enumerate()
            .map(|(ch, name)| ChannelStatus {
                name: name.clone(),
                reading: self.reading(ch).unwrap_or_else(Reading::no_data),
            })
            .collect()
    }

    /// The channel processors, brought up to date and taken out (the pipeline is
    /// left without channels): what a reload carries over.
    pub(super) fn take_processors(&mut self) -> Vec<ChannelProcessor> {
        for bank in &mut self.banks {
            bank.release_all(&mut self.processors);
        }
        self.banks.clear();
        self.homes.clear();
        std::mem::take(&mut self.processors)
    }

    /// Feeds one device sample through the channel processors: the values of steady
    /// channels through the device's bank, the rest one by one.
    pub fn ingest(&mut self, sample: &DeviceSample) {
        let t_s = self.now_s(sample.started);
        let mut gain = LowPassGain::default();
        let mut no_bank = Bank::default();
        let bank = self.banks.get_mut(sample.device).unwrap_or(&mut no_bank);
        for (ch, value) in &sample.values {
            let Some(p) = self.processors.get_mut(*ch) else {
                continue;
            };
            let (device, lane) = self.homes[*ch];
            let in_bank = device == sample.device;
            match value {
                Ok(raw) if in_bank => bank.sample(lane, p, t_s, *raw, &mut gain),
                Ok(raw) => {
                    p.on_sample_with(t_s, *raw, &mut gain);
                }
                Err(fault) if in_bank => {
                    bank.missing(lane, p, t_s, fault.reason, fault.degraded);
                }
                Err(fault) => {
                    p.on_missing(t_s, fault.reason, fault.degraded);
                }
            }
        }
        bank.step(t_s, &mut gain, &mut self.processors);
    }

    /// The value of channel `ch` if its quality allows using it.
    pub fn usable_degc(&self, ch: usize) -> Option<f64> {
        match self.held(ch) {
            Some((bank, lane)) => Some(bank.value_degc(lane)),
            None => self.processors.get(ch)?.last().usable_degc(),
        }
    }

    /// Runs one compensation decision for axis `axis`.
    pub fn decide(&mut self, axis: usize, at: Instant) -> Decision {
        let now_s = self.now_s(at);
        // The inputs in a buffer kept between calls: the bench decides on every cycle.
        let mut temps_degc = std::mem::take(&mut self.temps_degc);
        temps_degc.clear();
        temps_degc.extend(
            self.axes[axis]
                .inputs
                .iter()
                .map(|&ch| self.usable_degc(ch)),
        );
        let decision = self.axes[axis].comp.decide(now_s, &temps_degc);
        self.temps_degc = temps_degc;
        decision
    }
}
