//! A reload keeps the state of whatever did not change: channel processors (filters,
//! quality), device links (the open connection) and failure counts, NC module
//! connections, and axis compensators with their baseline read from the NC. SYNC
//! producers keep nothing: each generation starts those of its own config.

use std::collections::BTreeMap;
use std::sync::Arc;

use super::{Built, Poller, Running};
use crate::config::Config;

/// The state of the next generation: `new` (built from `new_cfg`) with the parts of
/// `old` (running `old_cfg`) that are configured the same.
pub(super) fn transplant(old_cfg: &Config, new_cfg: &Config, old: Running, new: Built) -> Running {
    let old_channel: BTreeMap<String, usize> = old
        .pipeline
        .channel_names
        .iter()
        .enumerate()
        .map(|(i, n)| (n.clone(), i))
        .collect();
    let mut next = Running::new(new);
    let Running {
        pipeline: mut old_pipeline,
        devices: old_devices,
        nc_modules: mut old_nc,
        status: old_status,
        baselined: old_baselined,
        nc_facts: old_nc_facts,
        nc_logs: old_nc_logs,
        nc_errors: old_nc_errors,
        device_logs: old_device_logs,
        channel_logs: old_channel_logs,
        axis_logs: old_axis_logs,
        ..
    } = old;
    // Carried processors keep their time base.
    next.pipeline.epoch = old_pipeline.epoch;

    let mut old_processors: Vec<_> = old_pipeline
        .take_processors()
        .into_iter()
        .map(Some)
        .collect();
    let mut kept_channels = 0;
    for (j, name) in next.pipeline.channel_names.iter().enumerate() {
        let same = old_cfg.channels.get(name) == new_cfg.channels.get(name);
        if let (true, Some(&i)) = (same, old_channel.get(name)) {
            if let Some(p) = old_processors[i].take() {
                next.pipeline.processors[j] = p;
                kept_channels += 1;
            }
        }
    }
    next.status.channels = next.pipeline.channel_statuses();
    // The journal was told each channel's (and below, each axis') state, changed or
    // not: what comes after the reload is logged against that (a channel bad before
    // and good after is "usable again", one still bad is not named again).
    for (j, name) in next.pipeline.channel_names.iter().enumerate() {
        if let Some(old_log) = old_channel.get(name).and_then(|&i| old_channel_logs.get(i)) {
            next.channel_logs[j] = *old_log;
        }
    }

    // Devices: an unchanged device keeps its link; devices sharing a new link (a serial
    // line, a TCP address) follow it onto the old one, so a line stays shared.
    let old_devices: BTreeMap<String, (usize, super::DeviceRt)> = old_devices
        .into_iter()
        .enumerate()
        .filter_map(|(i, d)| d.map(|d| (d.poller.name().to_string(), (i, d))))
        .collect();
    let mut relink = Vec::new();
    let mut kept_devices = 0;
    for (j, dev) in next.devices.iter_mut().enumerate() {
        let Some(dev) = dev else { continue };
        let name = dev.poller.name().to_string();
        if old_cfg.devices.get(&name) != new_cfg.devices.get(&name) {
            continue;
        }
        let Some((i, old_dev)) = old_devices.get(&name) else {
            continue;
        };
        // A CAN node's poller starts afresh (NMT start, heartbeat watch); its
        // channels keep their filter state like any other.
        if let (Poller::Modbus(new), Poller::Modbus(old)) = (&mut dev.poller, &old_dev.poller) {
            // The old generation's tasks have stopped: nothing else holds a link.
            match (old.link().try_lock(), new.link().try_lock()) {
                (Ok(mut kept), Ok(line)) => kept.adopt_settings(&line),
                _ => tracing::warn!(device = %name, "reload: link busy, its settings kept"),
            }
            relink.push((Arc::as_ptr(new.link()), old.link().clone()));
            new.carry_over(old);
        }
        if let Some(s) = old_status.devices.get(*i) {
            next.status.devices[j] = s.clone();
        }
        // The journal was told its link's state: not again after the reload.
        if let (Some(log), Some(&old_log)) = (next.device_logs.get_mut(j), old_device_logs.get(*i))
        {
            *log = old_log;
        }
        kept_devices += 1;
    }
    for dev in next.devices.iter_mut().flatten() {
        if let Poller::Modbus(p) = &mut dev.poller {
            let ptr = Arc::as_ptr(p.link());
            if let Some((_, link)) = relink.iter().find(|(q, _)| *q == ptr) {
                p.set_link(link.clone());
            }
        }
    }

    // NC writers (one per axis): an unchanged axis on an unchanged target keeps its
    // connection, unless its task was stopped mid-request: the new writer connects
    // afresh, and the axis is still the same.
    let old_axis_index: BTreeMap<&str, usize> = old_cfg
        .axes
        .keys()
        .enumerate()
        .map(|(i, n)| (n.as_str(), i))
        .collect();
    let mut same_nc = BTreeMap::new();
    for (j, (name, axis)) in new_cfg.axes.iter().enumerate() {
        let old_log = old_axis_index
            .get(name.as_str())
            .and_then(|&i| old_axis_logs.get(i));
        if let (Some(log), Some(old_log)) = (next.axis_logs.get_mut(j), old_log) {
            *log = *old_log;
        }
        // The journal was told whether the target is down: a reload is no news of it.
        let old_target = old_cfg.axes.get(name).map(|a| old_cfg.target(&a.nc_module));
        if let (Some(&i), Some(old_target)) = (old_axis_index.get(name.as_str()), old_target) {
            if old_target == new_cfg.target(&axis.nc_module) {
                if let (Some(log), Some(error)) = (old_nc_logs.get(i), old_nc_errors.get(i)) {
                    next.nc_logs[j] = *log;
                    next.nc_errors[j].clone_from(error);
                }
            }
        }
        // The credentials too: a file rewritten with a new password (a rotation)
        // leaves the configuration unchanged, and the kept session's writer would log
        // in with the old one at its next reconnect.
        let login = |m: Option<&Option<super::NcModuleRt>>| {
            m.and_then(Option::as_ref)
                .and_then(|m| m.writer.inner().credentials().cloned())
        };
        let same_cfg = old_cfg.axes.get(name) == Some(axis)
            && old_cfg.target(&axis.nc_module) == new_cfg.target(&axis.nc_module);
        let same_login = old_axis_index
            .get(name.as_str())
            .is_some_and(|&i| login(old_nc.get(i)) == login(next.nc_modules.get(j)));
        if same_cfg && !same_login {
            // Else the log only says that the target's parameters were read again.
            tracing::info!(axis = %name, "reload: the credentials of axis {name}'s NC target changed in their file; a new session logs in with them");
        }
        let same = same_cfg && same_login;
        if let (true, Some(&i)) = (same, old_axis_index.get(name.as_str())) {
            if let Some(m) = old_nc.get_mut(i).and_then(Option::take) {
                next.nc_modules[j] = Some(m);
            }
            same_nc.insert(name.clone(), ());
        }
    }
    // The writers not kept end their sessions politely: a control admits only a few,
    // and one dropped stays open there until its timeout.
    let runtime = tokio::runtime::Handle::try_current();
    for mut m in old_nc.into_iter().flatten() {
        // (No runtime only in the unit tests that call this directly.)
        let Ok(runtime) = &runtime else { break };
        runtime.spawn(async move {
            let _ = tokio::time::timeout(
                std::time::Duration::from_secs(2),
                crate::nc::NcWriter::close(&mut m.writer),
            )
            .await;
        });
    }

    // Axes: an unchanged axis on an unchanged NC module keeps its compensator, its
    // baseline and its status.
    let mut old_axes: BTreeMap<String, (usize, super::AxisRt)> = old_pipeline
        .axes
        .into_iter()
        .enumerate()
        .map(|(i, a)| (a.name.clone(), (i, a)))
        .collect();
    for (j, axis) in next.pipeline.axes.iter_mut().enumerate() {
        // The job counts go on, as `compgate_nc_jobs_total` does, whatever changed.
        let old_st = old_axis_index
            .get(axis.name.as_str())
            .and_then(|&i| old_status.axes.get(i));
        if let (Some(old_st), Some(st)) = (old_st, next.status.axes.get_mut(j)) {
            st.jobs_ok = old_st.jobs_ok;
            st.jobs_failed = old_st.jobs_failed;
            st.jobs_shadow = old_st.jobs_shadow;
            st.last_failure.clone_from(&old_st.last_failure);
            // The journal and the alert know the model extrapolates: the next decision
            // says whether it still does (a changed range clears or names it anew).
            let old_fit = old_cfg.axes.get(&axis.name).map(|a| &a.fitted_degc);
            if old_fit == new_cfg.axes.get(&axis.name).map(|a| &a.fitted_degc) {
                st.outside_fit.clone_from(&old_st.outside_fit);
            }
        }
        let cfg_same = old_cfg.axes.get(&axis.name) == new_cfg.axes.get(&axis.name);
        let nc_same = same_nc.contains_key(&axis.name);
        if !(cfg_same && nc_same) {
            continue;
        }
        // Into or out of shadow mode (`gateway.shadow`): the compensator's baseline
        // must come from the NC again, not from the would-be values.
        if old_axes
            .get(&axis.name)
            .is_some_and(|(_, a)| a.shadow != axis.shadow)
        {
            continue;
        }
        if let Some((i, old_axis)) = old_axes.remove(&axis.name) {
            axis.comp = old_axis.comp;
            next.baselined[j] = old_baselined.get(i).copied().unwrap_or(false);
            // A wrong MD32750 keeps the axis holding until a snapshot says otherwise.
            next.nc_facts[j] = old_nc_facts.get(i).copied().unwrap_or_default();
            if let Some(s) = old_status.axes.get(i) {
                next.status.axes[j] = s.clone();
            }
        }
    }
    next.status.samples = old_status.samples;
    next.status.jobs = old_status.jobs;
    tracing::info!(
        channels_kept = kept_channels,
        channels = next.pipeline.channel_names.len(),
        devices_kept = kept_devices,
        devices = next.devices.len(),
        "reload: unchanged channels and devices keep their state"
    );
    next
}

/// The service sections as the running service set them up at start: a reload
/// leaves them as they are.
pub(super) struct RestartOnly {
    recorder: Option<crate::config::RecorderConfig>,
    metrics: Option<crate::config::MetricsConfig>,
    mqtt: Option<crate::config::MqttConfig>,
}

impl RestartOnly {
    pub(super) fn of(cfg: &Config) -> Self {
        Self {
            recorder: cfg.recorder.clone(),
            metrics: cfg.metrics.clone(),
            mqtt: cfg.mqtt.clone(),
        }
    }

    /// Logs a WARN naming the sections that differ in `new_cfg` from what runs: they
    /// are set up once at start, and a reload that ignored them silently left the old
    /// database, port or broker in use with nothing saying so. Compared with what
    /// runs, not with the file loaded last: a file put back says nothing.
    pub(super) fn warn_changed(&self, new_cfg: &Config) {
        let changed: Vec<&str> = [
            ("[recorder]", self.recorder != new_cfg.recorder),
            ("[metrics]", self.metrics != new_cfg.metrics),
            ("[mqtt]", self.mqtt != new_cfg.mqtt),
        ]
        .into_iter()
        .filter_map(|(name, changed)| changed.then_some(name))
        .collect();
        if !changed.is_empty() {
            let sections = changed.join(", ");
            tracing::warn!(%sections, "reload: {sections} changed in the file and take effect at the next restart; the running ones stay");
        }
    }
}
