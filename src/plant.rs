//! The simulated plant for a config: one field I/O module per device and one NC axis
//! module per NC module, from `compgate-plc`, on the config's addresses.
//!
//! Used by the demo (no arguments), `compgate sim` and the integration tests. The
//! gateway's service code never calls this; it only ever sees sockets and serial paths.
//!
//! With [`Bind::Ephemeral`] every TCP server binds `127.0.0.1:0`, every RTU line is a
//! fresh pseudo-terminal, and the returned config names the addresses really used, so
//! any number of plants can run side by side. With [`Bind::AsConfigured`] the servers
//! bind the configured addresses and each RTU line's configured path becomes a symlink
//! to its pseudo-terminal; a path that exists and is not such a link is refused.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use compgate_plc::canopen::{CanopenError, CanopenNode, MAX_PDO_TRANSMITTERS};
use compgate_plc::field::{
    self, AdcFullScale, FieldModule, FieldModuleSpec, Profile, TransmitterSpec, COUNTS_BASE,
};
use compgate_plc::nc::{Motion, NcAxis, NcAxisModule};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

use compgate_gateway::config::{
    CanChannelConfig, ChannelConfig, Config, DeviceConfig, Scaling, SimProfile,
};
use compgate_gateway::source::plan::{ByteOrder, DataType};

/// Errors of the plant.
#[derive(Debug, thiserror::Error)]
pub enum PlantError {
    /// A channel sits where the simulated module has no register for it.
    #[error("channels.{channel}: {message}")]
    Channel {
        /// Channel name.
        channel: String,
        /// What is wrong.
        message: String,
    },
    /// Binding or opening failed.
    #[error("{what}: {message}")]
    Io {
        /// What was being set up.
        what: String,
        /// The error.
        message: String,
    },
}

/// Where the plant's servers go.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bind {
    /// Loopback port 0 and fresh pseudo-terminals; the config is rewritten.
    Ephemeral,
    /// The addresses and paths the config names.
    AsConfigured,
}

/// A running simulated plant. Dropping it stops every server.
#[derive(Debug)]
pub struct Plant {
    /// The config with the addresses actually used.
    pub config: Config,
    /// Field modules by device name.
    pub field: BTreeMap<String, FieldModule>,
    /// NC axis modules by NC module name.
    pub nc: BTreeMap<String, NcAxisModule>,
    /// Simulated CANopen nodes by device name (they publish `field[name]`).
    pub can: BTreeMap<String, CanopenNode>,
    /// Transmitter index in its field module, by channel name.
    pub transmitter: BTreeMap<String, usize>,
    shutdown: CancellationToken,
    // Slave ends of the ptys: the line dies when the last one closes.
    _ptys: Vec<tokio_serial::SerialStream>,
    /// The links made for RTU lines and the ptys they point at.
    symlinks: Vec<(PathBuf, PathBuf)>,
}

impl Drop for Plant {
    fn drop(&mut self) {
        self.shutdown.cancel();
        for node in self.can.values() {
            node.stop();
        }
        // Only a link that still points at this plant's pty: one replaced meanwhile
        // (udev, another plant) is not this plant's to remove.
        for (link, pty) in &self.symlinks {
            if std::fs::read_link(link).is_ok_and(|t| t == *pty) {
                let _ = std::fs::remove_file(link);
            }
        }
    }
}

/// Where pseudo-terminals live: a link into it is one an earlier `sim` made.
const PTY_DIR: &str = "/dev/pts";

/// Makes room for an RTU line's link at `link`: nothing there, or a link into
/// [`PTY_DIR`] that an earlier `sim` left (it is removed). Anything else, say a udev
/// link `/dev/serial/by-id/...` to a real adapter, is refused with the reason: replacing
/// it, and removing it at exit, would take the adapter from the gateway until replug.
fn clear_own_link(link: &Path) -> Result<(), String> {
    let meta = match link.symlink_metadata() {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(e.to_string()),
    };
    let refuse = |what: String| {
        Err(format!(
            "{what} `compgate sim` made (those point into {PTY_DIR}); sim replaces only \
             its own links, never a real adapter's: give the simulated line a free path \
             as serial_path"
        ))
    };
    if !meta.file_type().is_symlink() {
        return refuse("exists and is not a link".into());
    }
    match std::fs::read_link(link) {
        Ok(target) if target.starts_with(PTY_DIR) => {
            std::fs::remove_file(link).map_err(|e| format!("cannot remove the stale link: {e}"))
        }
        Ok(target) => refuse(format!("is a link to {}, not one", target.display())),
        Err(e) => Err(e.to_string()),
    }
}

/// How to bring up `interface` with the script the project ships (its usage:
/// `can-up.sh IFACE [BITRATE]`, a vcan needing no bitrate).
fn can_up_hint(interface: &str) -> String {
    let bitrate = if interface.starts_with("vcan") {
        ""
    } else {
        " BITRATE"
    };
    format!("bring it up first: sudo deploy/can/can-up.sh {interface}{bitrate}")
}

/// The config key of the serial line at `path`: the first RTU device on it.
fn rtu_key(cfg: &Config, path: &str) -> String {
    cfg.devices
        .iter()
        .find(|(_, d)| matches!(d, DeviceConfig::Rtu(r) if r.serial_path == path))
        .map_or_else(
            || format!("serial line {path}"),
            |(name, _)| format!("devices.{name}.serial_path"),
        )
}

/// The transmitter index a channel reads, from the field module's register layout.
fn transmitter_index(address: u16, ty: DataType, order: ByteOrder) -> Option<usize> {
    match (ty, address) {
        (DataType::U16 | DataType::I16, a) if a < field::FLOAT_CDAB_BASE => {
            Some(usize::from(a - COUNTS_BASE))
        }
        (DataType::F32, a) if a >= field::FLOAT_ABCD_BASE && order == ByteOrder::Abcd => {
            Some(usize::from((a - field::FLOAT_ABCD_BASE) / 2))
        }
        (DataType::F32, a)
            if (field::FLOAT_CDAB_BASE..field::FLOAT_ABCD_BASE).contains(&a)
                && order == ByteOrder::Cdab =>
        {
            Some(usize::from((a - field::FLOAT_CDAB_BASE) / 2))
        }
        _ => None,
    }
}

/// The transmitter index a CAN channel reads, from the simulated node's TPDO layout
/// and object dictionary (`compgate_plc::canopen`).
fn can_transmitter_index(can: &CanChannelConfig, ty: DataType) -> Option<usize> {
    match (
        can.pdo,
        can.offset_bytes,
        can.sdo_index,
        can.sdo_subindex,
        ty,
    ) {
        (Some(p @ 1..=4), Some(o), None, None, DataType::U16 | DataType::I16) if o % 2 == 0 => {
            Some(4 * usize::from(p - 1) + usize::from(o / 2))
        }
        (None, None, Some(0x6401), Some(i @ 1..), DataType::U16 | DataType::I16)
        | (None, None, Some(0x9130), Some(i @ 1..), DataType::F32) => Some(usize::from(i) - 1),
        _ => None,
    }
}

/// The transmitter index of any channel, or why the simulated device has none.
fn channel_transmitter(name: &str, ch: &ChannelConfig) -> Result<usize, PlantError> {
    let refuse = |message: String| PlantError::Channel {
        channel: name.to_string(),
        message,
    };
    match (ch.can, ch.address) {
        (Some(can), _) => can_transmitter_index(&can, ch.data_type)
            .filter(|&i| i < MAX_PDO_TRANSMITTERS || can.sdo_index.is_some())
            .ok_or_else(|| {
                refuse(format!(
                    "the simulated CANopen node has u16 counts in TPDO1..4 (4 per PDO, even \
                     offsets), at 0x6401 sub 1.. (u16) and 0x9130 sub 1.. (f32); {can:?} as {:?} is none of them",
                    ch.data_type
                ))
            }),
        (None, Some(address)) => transmitter_index(address, ch.data_type, ch.byte_order).ok_or_else(|| {
            refuse(format!(
                "the simulated module has counts at 0.., f32 CDAB at {}.., f32 ABCD at {}..; address {} as {:?} {:?} is none of them",
                field::FLOAT_CDAB_BASE, field::FLOAT_ABCD_BASE, address, ch.data_type, ch.byte_order
            ))
        }),
        (None, None) => Err(refuse("no register address".into())),
    }
}

impl Plant {
    /// Starts the plant for `cfg`.
    pub async fn start(cfg: &Config, bind: Bind) -> Result<Self, PlantError> {
        let mut config = cfg.clone();
        let sim = cfg.sim.clone().unwrap_or_default();
        let shutdown = CancellationToken::new();
        let mut plant = Plant {
            config: cfg.clone(),
            field: BTreeMap::new(),
            nc: BTreeMap::new(),
            can: BTreeMap::new(),
            transmitter: BTreeMap::new(),
            shutdown: shutdown.clone(),
            _ptys: Vec::new(),
            symlinks: Vec::new(),
        };

        // One field module per device, with a transmitter for every channel on it.
        let mut rtu_lines: BTreeMap<String, Vec<(u8, FieldModule)>> = BTreeMap::new();
        for (dev_name, dev) in &cfg.devices {
            let mut transmitters: Vec<Option<TransmitterSpec>> = Vec::new();
            for (ch_name, ch) in cfg.channels.iter().filter(|(_, c)| &c.device == dev_name) {
                let idx = channel_transmitter(ch_name, ch)?;
                let s = sim.channel(ch_name);
                let profile = match s.profile {
                    SimProfile::Constant => Profile::Constant { degc: s.mean_degc },
                    SimProfile::Ramp => Profile::Ramp {
                        start_degc: s.mean_degc,
                        rate_degc_per_s: s.rate_degc_per_s,
                    },
                    SimProfile::Sine => Profile::Sine {
                        mean_degc: s.mean_degc,
                        amplitude_degc: s.amplitude_degc,
                        period_s: s.period_s,
                    },
                };
                plant.transmitter.insert(ch_name.clone(), idx);
                // Two channels may read one transmitter (counts and float view): the
                // first one, or one with an explicit [sim] entry, sets its profile.
                if transmitters.len() <= idx {
                    transmitters.resize(idx + 1, None);
                } else if transmitters[idx].is_some() && !sim.channels.contains_key(ch_name) {
                    continue;
                }
                // The channel's own scaling encodes it: what the gateway decodes with.
                let mut t = match &ch.scaling {
                    Scaling::Transmitter(sc) => TransmitterSpec {
                        range_low_ma: sc.current_range.min_ma(),
                        adc_full_scale: Some(AdcFullScale {
                            counts: u16::try_from(sc.adc_full_scale_counts).unwrap_or(u16::MAX),
                            ma: sc.adc_full_scale_ma,
                        }),
                        ..TransmitterSpec::new(profile, sc.range_min_degc, sc.range_max_degc)
                    },
                    Scaling::Direct(_) => TransmitterSpec::new(profile, -50.0, 150.0),
                };
                t.noise_degc = s.noise_degc;
                transmitters[idx] = Some(t);
            }
            let idle = || TransmitterSpec::new(Profile::Constant { degc: 20.0 }, -50.0, 150.0);
            let mut transmitters: Vec<TransmitterSpec> = transmitters
                .into_iter()
                .map(|t| t.unwrap_or_else(idle))
                .collect();
            if transmitters.is_empty() {
                transmitters.push(idle());
            }
            let spec = FieldModuleSpec::new(transmitters, sim.seed ^ plant.field.len() as u64);
            let module = FieldModule::new(spec).map_err(|e| PlantError::Io {
                what: format!("devices.{dev_name}"),
                message: e.to_string(),
            })?;
            plant.field.insert(dev_name.clone(), module.clone());
            match dev {
                DeviceConfig::Tcp(tcp) => {
                    let want = match bind {
                        Bind::Ephemeral => "127.0.0.1:0".to_string(),
                        Bind::AsConfigured => tcp.address.clone(),
                    };
                    let (listener, addr) = bind_tcp(&want, &format!("devices.{dev_name}")).await?;
                    if let Some(DeviceConfig::Tcp(d)) = config.devices.get_mut(dev_name) {
                        d.address = addr;
                    }
                    tokio::spawn(module.serve_tcp(listener, shutdown.clone()));
                }
                DeviceConfig::Rtu(rtu) => {
                    let path = rtu.serial_path.clone();
                    rtu_lines
                        .entry(path)
                        .or_default()
                        .push((rtu.unit_id, module));
                }
                // A CAN node sits on the configured interface in either bind mode:
                // vcan keeps nodes of several plants apart by node id only.
                DeviceConfig::Can(can) => {
                    let interface = can.interface.clone();
                    // Heartbeat well inside the consumer timeout (4 per timeout).
                    let timeout_s = can.heartbeat_timeout().as_secs_f64();
                    let heartbeat_ms = if timeout_s > 0.0 {
                        (timeout_s * 250.0).clamp(10.0, 1000.0) as u16
                    } else {
                        1000
                    };
                    let node = CanopenNode::spawn(&interface, can.node_id, heartbeat_ms, module)
                        .map_err(|e| PlantError::Io {
                            what: format!("devices.{dev_name}"),
                            message: match e {
                                CanopenError::Socket { .. } => {
                                    format!("{e}; {}", can_up_hint(&interface))
                                }
                                e => e.to_string(),
                            },
                        })?;
                    plant.can.insert(dev_name.clone(), node);
                }
            }
        }
        for (path, units) in rtu_lines {
            let what = format!("serial line {path}");
            let (master, slave, pty_path) = field::pty_pair().map_err(|e| PlantError::Io {
                what: what.clone(),
                message: e.to_string(),
            })?;
            let used = match bind {
                Bind::Ephemeral => pty_path,
                Bind::AsConfigured => {
                    let link = std::path::PathBuf::from(&path);
                    clear_own_link(&link).map_err(|why| PlantError::Io {
                        what: rtu_key(cfg, &path),
                        message: format!("{path}: {why}"),
                    })?;
                    std::os::unix::fs::symlink(&pty_path, &link).map_err(|e| PlantError::Io {
                        what: what.clone(),
                        message: format!("cannot link {path} to {pty_path}: {e}"),
                    })?;
                    plant.symlinks.push((link, pty_path.into()));
                    path.clone()
                }
            };
            for d in config.devices.values_mut() {
                if let DeviceConfig::Rtu(d) = d {
                    if d.serial_path == path {
                        d.serial_path = used.clone();
                    }
                }
            }
            plant._ptys.push(slave);
            tokio::spawn(field::serve_rtu(units, master, shutdown.clone()));
        }

        for (name, m) in &cfg.modbus_targets() {
            let s = sim.nc_module(name);
            // Unless told otherwise the simulated NC is set up as the axis on it expects.
            let md32750 = s.md32750.unwrap_or_else(|| {
                cfg.axes
                    .values()
                    .find(|a| a.nc_module == *name)
                    .map_or(3, |a| a.md32750)
            });
            let axis = NcAxis {
                md32750,
                referenced: s.referenced,
                position_mm: s.motion_min_mm,
                motion: if s.motion_speed_mm_per_s > 0.0 && s.motion_max_mm > s.motion_min_mm {
                    Motion::Oscillate {
                        min_mm: s.motion_min_mm,
                        max_mm: s.motion_max_mm,
                        speed_mm_per_s: s.motion_speed_mm_per_s,
                    }
                } else {
                    Motion::Stopped
                },
                ..NcAxis::default()
            };
            let module = NcAxisModule::new(axis);
            let want = match bind {
                Bind::Ephemeral => "127.0.0.1:0".to_string(),
                Bind::AsConfigured => m.address.clone(),
            };
            let section = if cfg.nc_modules.contains_key(name) {
                "nc_modules"
            } else {
                "targets"
            };
            let (listener, addr) = bind_tcp(&want, &format!("{section}.{name}")).await?;
            if let Some(c) = config.modbus_target_mut(name) {
                c.address = addr;
            }
            tokio::spawn(module.clone().serve_tcp(listener, shutdown.clone()));
            plant.nc.insert(name.clone(), module);
        }
        plant.config = config;
        Ok(plant)
    }

    /// Stops every server.
    pub fn stop(&self) {
        self.shutdown.cancel();
    }
}

async fn bind_tcp(addr: &str, what: &str) -> Result<(TcpListener, String), PlantError> {
    let listener = TcpListener::bind(addr).await.map_err(|e| PlantError::Io {
        what: what.to_string(),
        message: format!("cannot listen on {addr}: {e}"),
    })?;
    let local = listener.local_addr().map_err(|e| PlantError::Io {
        what: what.to_string(),
        message: e.to_string(),
    })?;
    Ok((listener, local.to_string()))
}

/// Serves the simulated axis of `compgate backlash --sim`: an NC axis module with the
/// `--sim-*` parameters on loopback.
/// Returns its address, the module and the token that stops it.
pub async fn backlash_axis(
    args: &compgate_commission::backlash::BacklashArgs,
) -> Result<
    (
        String,
        compgate_plc::nc::NcAxisModule,
        tokio_util::sync::CancellationToken,
    ),
    compgate_commission::backlash::BacklashError,
> {
    use compgate_plc::axis::AxisParams;
    use compgate_plc::nc::{NcAxis, NcAxisModule};
    let params = AxisParams {
        backlash_mm: args.sim_backlash_um / 1000.0,
        encoder_noise_mm: args.sim_noise_um / 1000.0,
        scale_noise_mm: args.sim_noise_um / 1000.0,
        elastic_tau_s: args.sim_elastic_ms / 1000.0,
        seed: args.sim_seed,
        ..AxisParams::default()
    };
    let mut problems = Vec::new();
    if !(0.0..=1000.0).contains(&args.sim_backlash_um) {
        problems.push(format!(
            "--sim-backlash-um {} outside 0..=1000",
            args.sim_backlash_um
        ));
    }
    if !(0.0..=100.0).contains(&args.sim_noise_um) {
        problems.push(format!(
            "--sim-noise-um {} outside 0..=100",
            args.sim_noise_um
        ));
    }
    // Above Kv x tau = 0.25 the loop overshoots and the motor creeps across the gap
    // during the dwell: the axis the test must refuse. Up to 0.5 it can be simulated.
    let max_tau_ms = 0.5 / params.kv_per_s * 1000.0;
    if !(0.0..=max_tau_ms).contains(&args.sim_elastic_ms) {
        problems.push(format!(
            "--sim-elastic-ms {} outside 0..={max_tau_ms} (Kv x tau at most 0.5, Kv = {} 1/s)",
            args.sim_elastic_ms, params.kv_per_s
        ));
    }
    if !(args.sim_speed > 0.0 && args.sim_speed <= 1e6) {
        problems.push(format!("--sim-speed {} outside (0, 1e6]", args.sim_speed));
    }
    if !problems.is_empty() {
        return Err(compgate_commission::backlash::BacklashError::Invalid(
            problems,
        ));
    }
    let module = NcAxisModule::new(NcAxis {
        allow_md32450_write: true,
        referenced: true,
        ..NcAxis::default()
    });
    module.set_servo(params);
    module.set_sim_speed(args.sim_speed);
    let (address, shutdown) = module.serve_loopback().await.map_err(|e| {
        compgate_commission::backlash::BacklashError::Io(format!("bind loopback: {e}"))
    })?;
    Ok((address, module, shutdown))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every simulated channel reads back the configured temperature through its own
    /// scaling: 0-20 mA was encoded as 4-20 (25 degC read as 40), and a channel took
    /// the ADC full scale of the device's first channel (a 24 mA channel after a
    /// 20 mA one read 50.04 degC).
    #[tokio::test]
    async fn each_channel_is_simulated_with_its_own_scaling() {
        let scaling = |range: &str, ma: f64| {
            format!(
                "scaling = {{ kind = \"transmitter\", adc_full_scale_counts = 4095, \
                 adc_full_scale_ma = {ma:.1}, current_range = \"{range}\", \
                 range_min_degc = 0.0, range_max_degc = 100.0 }}"
            )
        };
        let mut text = "[devices.f]\ntransport = \"tcp\"\naddress = \"127.0.0.1:1\"\nunit_id = 1\n"
            .to_string();
        for (i, (name, range, ma)) in [("T1", "0-20", 20.0), ("T2", "4-20", 24.0)]
            .into_iter()
            .enumerate()
        {
            text += &format!(
                "[channels.{name}]\ndevice = \"f\"\nregister = \"input\"\naddress = {i}\n\
                 data_type = \"u16\"\n{}\n[sim.channels.{name}]\nprofile = \"constant\"\n\
                 mean_degc = 25.0\nnoise_degc = 0.0\n",
                scaling(range, ma)
            );
        }
        let cfg = compgate_gateway::config::load_str(&text, "f.toml").expect("config");
        let plant = Plant::start(&cfg, Bind::Ephemeral).await.expect("plant");
        let report = crate::probe::probe(&plant.config, None, None)
            .await
            .expect("probe");
        plant.stop();
        let temps: Vec<&str> = report
            .text
            .lines()
            .filter_map(|l| l.trim().strip_prefix("temp"))
            .map(str::trim)
            .collect();
        // 1024 counts of 4095 at 20 mA: 5.001 mA, 25.01 degC; 1365 at 24 mA: 8 mA.
        assert_eq!(temps, ["25.01 degC", "25.00 degC"], "{}", report.text);
    }
}
