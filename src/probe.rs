//! `compgate probe`: poll every Modbus channel of a config once and show what the
//! gateway would make of it: the raw registers, the value in the configured type and,
//! for 32-bit types, in every byte order with the plausible one marked, the loop
//! current, the temperature and the quality. The first thing to run against a new
//! device: a wrong `byte_order`, a 1-based `address` or a wrong scaling shows here,
//! before any NC is written. A CANopen node is asked for its TPDO settings instead
//! (transmission type, event timer, mapping), which are checked against each
//! channel's `pdo`, `offset_bytes` and `data_type`, and its SDO channels are read.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use compgate_core::channel::{Quality, Reason};
use compgate_gateway::channel::{ChannelConfig, Scaling};
use compgate_gateway::config::{self, Config, DeviceConfig};
use compgate_gateway::source::modbus::config::Parity;
use compgate_gateway::source::modbus::{Backoff, LinkSpec, ModbusLink};
use compgate_gateway::source::plan::{self, ByteOrder, DataType, Slot};
use compgate_gateway::source::SourceError;

/// `compgate probe` arguments.
#[derive(Debug, clap::Args)]
pub struct ProbeArgs {
    /// Configuration file (TOML).
    #[arg(long, short)]
    pub config: PathBuf,
    /// Probe only this device.
    #[arg(long)]
    pub device: Option<String>,
    /// Probe only this channel.
    #[arg(long)]
    pub channel: Option<String>,
}

/// What a probe found.
#[derive(Debug)]
pub struct ProbeReport {
    /// The text to print.
    pub text: String,
    /// Channels whose quality is bad.
    pub bad: Vec<String>,
    /// The config's warnings, for standard error.
    pub warnings: Vec<String>,
}

/// Loads the config, polls the selected channels once and reports them.
pub async fn run(args: &ProbeArgs) -> Result<ProbeReport, String> {
    let cfg = config::load(&args.config).map_err(|e| e.to_string())?;
    let warnings = config::warnings(&cfg, &args.config.display().to_string())
        .into_iter()
        .map(|w| w.to_string())
        .collect();
    let report = probe(&cfg, args.device.as_deref(), args.channel.as_deref()).await?;
    Ok(ProbeReport { warnings, ..report })
}

/// Polls the channels of `cfg` (only `device`'s, only `channel`, when given) once.
pub async fn probe(
    cfg: &Config,
    device: Option<&str>,
    channel: Option<&str>,
) -> Result<ProbeReport, String> {
    let names = |m: &mut dyn Iterator<Item = &String>| {
        m.map(|n| format!("`{n}`")).collect::<Vec<_>>().join(", ")
    };
    if let Some(d) = device.filter(|d| !cfg.devices.contains_key(*d)) {
        return Err(format!(
            "--device {d}: no such device in [devices]; expected one of {}",
            names(&mut cfg.devices.keys())
        ));
    }
    if let Some(c) = channel.filter(|c| !cfg.channels.contains_key(*c)) {
        return Err(format!(
            "--channel {c}: no such channel in [channels]; expected one of {}",
            names(&mut cfg.channels.keys())
        ));
    }
    if let (Some(d), Some(c)) = (device, channel) {
        let on = &cfg.channels[c].device;
        if on != d {
            return Err(format!(
                "--channel {c} is on device `{on}`, not on --device {d}: nothing to probe; \
                 drop --device, or give --device {on}"
            ));
        }
    }
    let mut report = ProbeReport {
        text: String::new(),
        bad: Vec::new(),
        warnings: Vec::new(),
    };
    for (dev_name, dev) in &cfg.devices {
        if device.is_some_and(|d| d != dev_name) {
            continue;
        }
        let selected: Vec<(&String, &ChannelConfig)> = cfg
            .channels
            .iter()
            .filter(|(n, c)| &c.device == dev_name && channel.is_none_or(|w| w == n.as_str()))
            .collect();
        if selected.is_empty() {
            continue;
        }
        let (spec, params) = match dev {
            DeviceConfig::Tcp(t) => (t.link_spec(), t.poll_params()),
            DeviceConfig::Rtu(r) => (r.link_spec(), r.poll_params()),
            DeviceConfig::Can(c) => {
                probe_can(&mut report, dev_name, c, &selected).await;
                continue;
            }
        };
        let unit = params.unit_id;
        let common = dev.common();
        let framing = dev.rtu().map(|r| rtu_framing(r.parity(), r.stop_bits()));
        let framing = framing.map_or_else(String::new, |f| format!(", {f}"));
        let _ = writeln!(
            report.text,
            "device {dev_name}: {spec}{framing}, unit {unit}"
        );
        // No reconnect wait: one attempt per channel.
        let mut link = ModbusLink::new(
            spec,
            common.timeout(),
            Backoff::new(Duration::ZERO, Duration::ZERO),
        );
        // After a device did not answer (or its link did not open), its other channels
        // are not tried: each would wait for the same timeout. Connected first, so
        // that the reads' round trips are the device's alone.
        let mut silent: Option<SourceError> = link.open().await.err();
        // Each channel's slot and how long its read took (not counting a connect), and
        // its name.
        let mut round_trips: Vec<(Slot, Duration)> = Vec::new();
        let mut read_names: Vec<&String> = Vec::new();
        for (name, ch) in selected {
            if let Some(e) = &silent {
                let _ = writeln!(report.text, "  {name}: not read, {} ({e})", not_read(e));
                report.bad.push(name.clone());
                continue;
            }
            let (connects, started) = (link.connects(), Instant::now());
            let read = probe_channel(&mut link, unit, name, ch, &mut report.text).await;
            if let (Some(slot), true) = (slot(ch), link.connects() == connects) {
                if read.is_ok() {
                    round_trips.push((slot, started.elapsed()));
                    read_names.push(name);
                }
            }
            match read {
                Ok(true) => {}
                Ok(false) => report.bad.push(name.clone()),
                Err(e) => {
                    report.bad.push(name.clone());
                    if matches!(e.kind(), "timeout" | "deadline" | "connect" | "backoff") {
                        silent = Some(e);
                    }
                }
            }
        }
        if let Some(line) = slow_cycle(dev_name, &round_trips, common.poll_interval(), &params) {
            let _ = writeln!(report.text, "  {line}");
        }
        if silent.is_none() {
            let slots: Vec<Slot> = round_trips.iter().map(|(s, _)| *s).collect();
            let refused =
                refused_merged_reads(&mut link, dev_name, unit, &slots, &read_names, &params).await;
            for (line, channels) in refused {
                let _ = writeln!(report.text, "  {line}");
                report.bad.extend(channels);
            }
        }
        report.text.push('\n');
    }
    Ok(report)
}

/// An RTU line's character framing as modules print it (`8E1`: 8 data bits, even
/// parity, 1 stop bit), with the config's words.
fn rtu_framing(parity: Parity, stop_bits: u8) -> String {
    let (letter, word) = match parity {
        Parity::None => ('N', "none"),
        Parity::Even => ('E', "even"),
        Parity::Odd => ('O', "odd"),
    };
    let s = if stop_bits == 1 { "" } else { "s" };
    format!("8{letter}{stop_bits} (parity {word}, {stop_bits} stop bit{s})")
}

/// What to check when an RTU device does not answer at all.
const RTU_NO_REPLY: &str = "no reply: check unit_id, baud and parity against the module's \
                            switches, the A/B wiring, termination and the module's power";

/// Another reading of a bad channel's raw value `raw` (its registers as `ty`) that is
/// plausible, as a hint: as the signed type of an unsigned one (a u16 that is an i16),
/// or, with `direct` scaling, in tenths or hundredths of the configured gain (a module
/// counting 0.1 degC), or both; the first of these that is plausible, simplest first.
/// `plausible` is the channel's own check of a raw value, `valid` its valid range
/// (degC).
fn reading_hint(
    ch: &ChannelConfig,
    ty: DataType,
    raw: f64,
    plausible: impl Fn(f64) -> Option<f64>,
    valid: (f64, f64),
) -> Option<String> {
    let signed = match ty {
        DataType::U16 if raw >= 32_768.0 => Some((raw - 65_536.0, DataType::I16.name())),
        DataType::U32 if raw >= 2_147_483_648.0 => {
            Some((raw - 4_294_967_296.0, DataType::I32.name()))
        }
        _ => None,
    };
    if let Some((v, t)) = signed {
        if let Some(degc) = plausible(v) {
            return Some(format!(
                "as {t} it reads {degc:.1} degC: set data_type = \"{t}\""
            ));
        }
    }
    // A float carries its own unit; only integer counts come in tenths.
    let (Scaling::Direct(d), false) = (&ch.scaling, ty == DataType::F32) else {
        return None;
    };
    let in_range = |degc: f64| (valid.0..=valid.1).contains(&degc);
    for factor in [0.1, 0.01] {
        // Rounded: 0.1 * 0.1 is "0.01", not "0.010000000000000002".
        let gain = (d.gain * factor * 1e12).round() / 1e12;
        let decimals = (-gain.abs().log10()).ceil().clamp(1.0, 4.0) as usize;
        let degc = raw * gain + d.offset_degc;
        if in_range(degc) {
            return Some(format!(
                "as {gain} degC counts it reads {degc:.decimals$} degC: set scaling gain = \
                 {gain}"
            ));
        }
        if let Some((v, t)) = signed {
            let degc = v * gain + d.offset_degc;
            if in_range(degc) {
                return Some(format!(
                    "as {t} in {gain} degC counts it reads {degc:.decimals$} degC: set \
                     data_type = \"{t}\" and scaling gain = {gain}"
                ));
            }
        }
    }
    None
}

/// Why a channel of a device was not read after `e`, in words.
fn not_read(e: &SourceError) -> &'static str {
    match e.kind() {
        "timeout" | "deadline" => "the device did not answer",
        _ => "the link to the device could not be opened",
    }
}

/// The registers channel `ch` reads, as the run's read plan takes them.
fn slot(ch: &ChannelConfig) -> Option<Slot> {
    Some(Slot {
        channel: 0,
        kind: ch.register?,
        address: ch.address?,
        len: ch.data_type.registers(),
    })
}

/// A warning when the reads `run` makes of a device in one poll cycle (as it merges
/// them, `params`) take longer together than `poll_interval`, going by the round trips
/// the probe saw: `run` would poll it less often than configured, and fail the reads
/// that do not fit in the cycle's deadline every cycle.
fn slow_cycle(
    device: &str,
    round_trips: &[(Slot, Duration)],
    poll_interval: Duration,
    params: &compgate_gateway::source::PollParams,
) -> Option<String> {
    let slots: Vec<Slot> = round_trips
        .iter()
        .enumerate()
        .map(|(i, (s, _))| Slot { channel: i, ..*s })
        .collect();
    let blocks = plan::plan(&slots, params.max_gap_registers, params.max_read_registers);
    let cycle: Duration = blocks
        .iter()
        .filter_map(|b| {
            b.members
                .iter()
                .map(|(s, _)| round_trips[s.channel].1)
                .max()
        })
        .sum();
    (cycle > poll_interval).then(|| {
        format!(
            "warning: device {device}: its {} read(s) of a poll cycle took {:.3} s together, \
             longer than poll_interval_s = {} s; `run` fails the reads that do not fit in \
             {} s (the larger of poll_interval_s and timeout_s) every cycle: raise \
             poll_interval_s",
            blocks.len(),
            cycle.as_secs_f64(),
            poll_interval.as_secs_f64(),
            params.cycle_deadline.as_secs_f64()
        )
    })
}

/// The reads `run` merges from channels that each read well alone, made as `run`
/// makes them: a module may refuse a read across a hole in its map (0x02) or longer
/// than it takes (0x03), which one channel at a time never shows. Per refused read, a
/// warning naming what to change, and its channels (`names` are the slots').
async fn refused_merged_reads(
    link: &mut ModbusLink,
    device: &str,
    unit: u8,
    slots: &[Slot],
    names: &[&String],
    params: &compgate_gateway::source::PollParams,
) -> Vec<(String, Vec<String>)> {
    let slots: Vec<Slot> = slots
        .iter()
        .enumerate()
        .map(|(i, s)| Slot { channel: i, ..*s })
        .collect();
    let mut refused = Vec::new();
    for b in plan::plan(&slots, params.max_gap_registers, params.max_read_registers) {
        if b.members.len() < 2 {
            continue;
        }
        let Err(e) = link.read(unit, b.kind, b.start, b.count).await else {
            continue;
        };
        if e.kind() != "exception" {
            continue;
        }
        let hint = compgate_gateway::source::refused_read_hint(&b, device, &e)
            .map_or_else(String::new, |h| format!(": {h}"));
        let channels: Vec<String> = b
            .members
            .iter()
            .map(|(s, _)| names[s.channel].clone())
            .collect();
        refused.push((
            format!(
                "warning: device {device}: `run` reads {} in one request ({} registers from \
                 {}), and the module refused it: {e}{hint}",
                channels.join(", "),
                b.count,
                b.start
            ),
            channels,
        ));
    }
    refused
}

/// Reads and shows one channel: whether its quality is usable, or the read's error.
async fn probe_channel(
    link: &mut ModbusLink,
    unit: u8,
    name: &str,
    ch: &ChannelConfig,
    out: &mut String,
) -> Result<bool, SourceError> {
    let (Some(kind), Some(address)) = (ch.register, ch.address) else {
        return Ok(false);
    };
    let ty = ch.data_type;
    let order = ch.byte_order;
    let kind_name = match kind {
        plan::RegisterKind::Input => "input",
        plan::RegisterKind::Holding => "holding",
    };
    let _ = writeln!(
        out,
        "  {name}: {kind_name} register {address}, {} {}",
        ty.name(),
        order.name()
    );
    let regs = match link.read(unit, kind, address, ty.registers()).await {
        Ok(regs) => regs,
        Err(e) => {
            let _ = writeln!(out, "    error      {e}");
            let _ = writeln!(out, "    quality    bad ({})", e.reason());
            if e.kind() == "timeout" && matches!(link.spec(), LinkSpec::Rtu { .. }) {
                let _ = writeln!(out, "    hint       {RTU_NO_REPLY}");
            }
            return Err(e);
        }
    };
    let hex: Vec<String> = regs.iter().map(|r| format!("0x{r:04X}")).collect();
    let _ = writeln!(out, "    registers  {}", hex.join(" "));
    let mut processor = ch.build();
    let Some(raw) = plan::decode(&regs, ty, order) else {
        let _ = writeln!(out, "    quality    bad (comm: short reply)");
        return Ok(false);
    };
    let _ = writeln!(
        out,
        "    value      {} ({} {})",
        show(raw, ty),
        ty.name(),
        order.name()
    );
    // NaN and infinity are the fault values of float transmitters, not a byte order.
    let float_fault = ty.registers() == 2 && !raw.is_finite();
    let likely = (!float_fault)
        .then(|| {
            let f = processor.filter_params();
            let middle_degc = (f.valid_min_degc + f.valid_max_degc) / 2.0;
            plan::likely_order(
                &regs,
                ty,
                order,
                |r| processor.plausible_degc(r),
                middle_degc,
            )
        })
        .flatten();
    if float_fault {
        let _ = writeln!(
            out,
            "    note       not finite: the transmitter reports a fault (no byte order hint)"
        );
    } else if ty.registers() == 2 {
        for o in ByteOrder::ALL {
            let Some(v) = plan::decode(&regs, ty, o) else {
                continue;
            };
            let judged = match processor.plausible_degc(v) {
                Some(d) if d != 0.0 && d.abs() < 0.01 => format!("{d:.2e} degC"),
                Some(d) => format!("{d:.2} degC"),
                None => "not plausible".into(),
            };
            let mark = if likely.is_some_and(|(l, _)| l == o) {
                "  <- plausible"
            } else {
                ""
            };
            let _ = writeln!(
                out,
                "    as {}    {:<14} {judged}{mark}",
                o.name(),
                show(v, ty)
            );
        }
    }
    let order_hint = likely.filter(|(l, _)| *l != order);
    if let Some((l, degc)) = order_hint {
        // A 16-bit register has only its bytes to swap.
        let which = if ty.registers() == 1 {
            " (low byte first)"
        } else {
            ""
        };
        let _ = writeln!(
            out,
            "    hint       as {}{which} it reads {degc:.2} degC: set byte_order = \"{}\"",
            l.name(),
            l.name()
        );
    }
    let order_hinted = order_hint.is_some();
    let f = processor.filter_params();
    let valid = (f.valid_min_degc, f.valid_max_degc);
    // A byte order that reads plausibly as configured otherwise beats a scaling guess.
    let hint = (!order_hinted)
        .then(|| reading_hint(ch, ty, raw, |v| processor.plausible_degc(v), valid))
        .flatten();
    let r = processor.on_sample(0.0, raw);
    let ma = r
        .current_ma
        .map_or_else(|| "-".to_string(), |ma| format!("{ma:.3} mA"));
    let degc = r
        .unfiltered_degc
        .map_or_else(|| "-".to_string(), |d| format!("{d:.2} degC"));
    let _ = writeln!(out, "    current    {ma}");
    let _ = writeln!(out, "    temp       {degc}");
    let quality = describe(&r.quality);
    // NE43 low from a register of zeros: a broken loop, or no transmitter there at all.
    let zeros = matches!(ch.scaling, Scaling::Transmitter(_))
        && r.quality == Quality::Bad(Reason::Ne43Low)
        && regs.iter().all(|&w| w == 0);
    let zeros = if zeros {
        " (a register that reads 0 may also be the wrong address or register table)"
    } else {
        ""
    };
    let _ = writeln!(out, "    quality    {quality}{zeros}");
    let usable = r.quality.is_usable();
    if let (false, Some(h)) = (usable, hint) {
        let _ = writeln!(out, "    hint       {h}");
    }
    Ok(usable)
}

/// A raw value as its type shows it: integers whole, floats in single precision
/// (shortest form), tiny or huge ones with an exponent.
fn show(v: f64, ty: DataType) -> String {
    match ty {
        DataType::F32 => {
            let f = v as f32;
            let a = f.abs();
            if a != 0.0 && !(1e-4..1e7).contains(&a) {
                format!("{f:e}")
            } else {
                format!("{f}")
            }
        }
        _ => format!("{v}"),
    }
}

fn describe(q: &Quality) -> String {
    match q {
        Quality::Good => "good".into(),
        Quality::Uncertain(r) => format!("uncertain ({r})"),
        Quality::Bad(r @ Reason::Implausible) => {
            format!("bad ({r}: no sensor produces it; see the byte orders above)")
        }
        Quality::Bad(r) => format!("bad ({r})"),
    }
}

/// One TPDO's settings as the node reports them.
struct TpdoSettings {
    /// COB-ID (1800h+n-1 sub 1); bit 31 set: the TPDO is off.
    cob_id: u32,
    /// Transmission type (sub 2): 1..=240 after every n-th SYNC, 254/255 event-driven.
    transmission: u32,
    /// Event timer, ms (sub 5), when the node has one.
    event_timer_ms: Option<u32>,
    /// Mapped objects (1A00h+n-1 subs 1..): (index, sub, bits), in byte order.
    mapped: Vec<(u16, u8, u32)>,
}

impl TpdoSettings {
    /// How the node sends it, in words.
    fn sending(&self) -> String {
        match self.transmission {
            _ if self.cob_id & 0x8000_0000 != 0 => "off (COB-ID bit 31 set)".into(),
            0 => "synchronous, acyclic (type 0: after a SYNC when changed)".into(),
            n @ 1..=240 => format!(
                "synchronous (type {n}: after every SYNC{})",
                match n {
                    1 => String::new(),
                    n => format!(" {n}"),
                }
            ),
            n @ (254 | 255) => match self.event_timer_ms {
                Some(ms) if ms > 0 => format!("event-driven (type {n}, event timer {ms} ms)"),
                _ => format!("event-driven (type {n}, no event timer: on change only)"),
            },
            n => format!("transmission type {n}"),
        }
    }

    fn event_driven(&self) -> bool {
        matches!(self.transmission, 254 | 255)
    }

    /// The mapped object that starts at byte `offset`: (index, sub, bits).
    fn at(&self, offset: u8) -> Option<(u16, u8, u32)> {
        let mut bit = 0;
        for &(index, sub, bits) in &self.mapped {
            if bit == u32::from(offset) * 8 {
                return Some((index, sub, bits));
            }
            bit += bits;
        }
        None
    }
}

/// Reads TPDO `pdo`'s settings by SDO.
async fn read_tpdo(
    poller: &mut compgate_gateway::source::can::CanPoller,
    pdo: u8,
) -> Result<TpdoSettings, compgate_gateway::source::can::CanError> {
    let (com, map) = (0x1800 + u16::from(pdo) - 1, 0x1A00 + u16::from(pdo) - 1);
    let cob_id = poller.read_object(com, 1).await?;
    let transmission = poller.read_object(com, 2).await?;
    // Only an event-driven TPDO's timer says anything; many nodes lack sub 5.
    let event_timer_ms = match transmission {
        254 | 255 => poller.read_object(com, 5).await.ok(),
        _ => None,
    };
    let count = poller.read_object(map, 0).await?;
    let mut mapped = Vec::new();
    for sub in 1..=count.min(64) as u8 {
        let entry = poller.read_object(map, sub).await?;
        mapped.push(((entry >> 16) as u16, (entry >> 8) as u8, entry & 0xFF));
    }
    Ok(TpdoSettings {
        cob_id,
        transmission,
        event_timer_ms,
        mapped,
    })
}

/// `compgate probe` of a CANopen node: the settings of the TPDOs its channels use,
/// checked against them, and its SDO channels read once.
async fn probe_can(
    report: &mut ProbeReport,
    dev_name: &str,
    c: &compgate_gateway::source::can::config::CanDeviceConfig,
    selected: &[(&String, &ChannelConfig)],
) {
    use compgate_gateway::source::can::{CanChannelSpec, CanObject, CanPoller};
    let _ = writeln!(
        report.text,
        "device {dev_name}: CANopen node {} on {}",
        c.node_id, c.interface
    );
    let mut poller = CanPoller::new(
        0,
        dev_name.to_string(),
        c.params(c.common.poll_interval()),
        Vec::<CanChannelSpec>::new(),
    );
    let mut tpdos: Vec<u8> = selected
        .iter()
        .filter_map(|(_, ch)| ch.can.and_then(|m| m.pdo))
        .collect();
    tpdos.sort_unstable();
    tpdos.dedup();
    let mut settings = std::collections::BTreeMap::new();
    for pdo in tpdos {
        match read_tpdo(&mut poller, pdo).await {
            Ok(t) => {
                let _ = writeln!(
                    report.text,
                    "  TPDO{pdo}: COB-ID {:X}h, {}",
                    t.cob_id & 0x7FF,
                    t.sending()
                );
                let mut byte = 0;
                for &(index, sub, bits) in &t.mapped {
                    let _ = writeln!(
                        report.text,
                        "    bytes {byte}..{}: {index:04X}h sub {sub} ({bits} bit)",
                        byte + bits / 8
                    );
                    byte += bits / 8;
                }
                settings.insert(pdo, t);
            }
            Err(e) => {
                let _ = writeln!(report.text, "  TPDO{pdo}: settings not read: {e}");
            }
        }
    }
    let key = format!("devices.{dev_name}.tpdo_max_age_s");
    for (name, ch) in selected {
        let Some(object) = ch.can.and_then(|m| m.object()) else {
            continue;
        };
        let ok = match object {
            CanObject::Pdo { pdo, offset_bytes } => match settings.get(&pdo) {
                None => {
                    let _ = writeln!(report.text, "  {name}: TPDO{pdo} unknown, not checked");
                    false
                }
                Some(t) => {
                    let bits = u32::from(ch.data_type.registers()) * 16;
                    let (line, fits) = match t.at(offset_bytes) {
                        Some((index, sub, b)) if b == bits => (
                            format!(
                                "TPDO{pdo} byte {offset_bytes}: {index:04X}h sub {sub}, {b} bit, \
                                 as data_type = \"{}\"",
                                ch.data_type.name()
                            ),
                            true,
                        ),
                        Some((index, sub, b)) => (
                            format!(
                                "TPDO{pdo} byte {offset_bytes}: {index:04X}h sub {sub} is {b} bit, \
                                 data_type = \"{}\" reads {bits}: check data_type",
                                ch.data_type.name()
                            ),
                            false,
                        ),
                        None => (
                            format!(
                                "TPDO{pdo} maps no object starting at byte {offset_bytes}: check \
                                 offset_bytes against the mapping above"
                            ),
                            false,
                        ),
                    };
                    let timing = match (t.event_driven(), c.tpdo_max_age_s) {
                        (true, None) => Some(format!(
                            "the node sends TPDO{pdo} event-driven: set {key} (above its \
                             event timer)"
                        )),
                        (false, Some(_)) => Some(format!(
                            "the node sends TPDO{pdo} after the SYNC: remove {key}"
                        )),
                        _ => None,
                    };
                    let _ = writeln!(report.text, "  {name}: {line}");
                    if let Some(t) = &timing {
                        let _ = writeln!(report.text, "  {name}: {t}");
                    }
                    fits && timing.is_none()
                }
            },
            CanObject::Sdo { index, sub } => match poller.read_object(index, sub).await {
                Ok(raw) => {
                    let value = compgate_gateway::source::can::codec::decode_value(
                        &raw.to_le_bytes(),
                        0,
                        ch.data_type,
                    )
                    .unwrap_or(f64::NAN);
                    let _ = writeln!(
                        report.text,
                        "  {name}: SDO {index:04X}h sub {sub} = {value} as data_type = \"{}\"",
                        ch.data_type.name()
                    );
                    true
                }
                Err(e) => {
                    let _ = writeln!(report.text, "  {name}: {e}");
                    false
                }
            },
        };
        if !ok {
            report.bad.push((*name).clone());
        }
    }
    report.text.push('\n');
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hint for `raw` of a channel `data_type = ty` with `scaling`, in the default
    /// valid range (-20..=80 degC).
    fn hint(ty: &str, scaling: &str, raw: f64) -> Option<String> {
        let text = format!(
            "[devices.d]\ntransport = \"tcp\"\naddress = \"127.0.0.1:502\"\nunit_id = 1\n\
             [channels.c]\ndevice = \"d\"\nregister = \"input\"\naddress = 0\n\
             data_type = \"{ty}\"\nscaling = {scaling}\n"
        );
        let cfg = config::load_str(&text, "t.toml").expect("valid");
        let ch = &cfg.channels["c"];
        let p = ch.build();
        let f = p.filter_params();
        let ty = DataType::ALL
            .into_iter()
            .find(|t| t.name() == ch.data_type.name())
            .expect("a type");
        reading_hint(
            ch,
            ty,
            raw,
            |v| p.plausible_degc(v),
            (f.valid_min_degc, f.valid_max_degc),
        )
    }

    // Both wrong at once, hundredths of a configured tenth, and nothing plausible.
    #[test]
    fn a_reading_hint_names_the_first_plausible_type_and_gain() {
        let direct = |gain: f64| format!("{{ kind = \"direct\", gain = {gain} }}");
        assert_eq!(
            hint("u16", &direct(1.0), 65_386.0).as_deref(),
            Some("as i16 in 0.1 degC counts it reads -15.0 degC: set data_type = \"i16\" and scaling gain = 0.1")
        );
        assert_eq!(
            hint("u16", &direct(0.1), 2345.0).as_deref(),
            Some("as 0.01 degC counts it reads 23.45 degC: set scaling gain = 0.01")
        );
        assert_eq!(
            hint("u32", &direct(1.0), 4_294_967_291.0).as_deref(),
            Some("as i32 it reads -5.0 degC: set data_type = \"i32\"")
        );
        assert_eq!(hint("u16", &direct(1.0), 50_000.0), None);
        // Transmitter counts have no gain to change.
        let transmitter = r#"{ kind = "transmitter", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, range_min_degc = -50.0, range_max_degc = 150.0 }"#;
        assert_eq!(hint("u16", transmitter, 4000.0), None);
    }

    #[test]
    fn the_rtu_framing_is_shown_as_modules_print_it() {
        assert_eq!(
            rtu_framing(Parity::None, 2),
            "8N2 (parity none, 2 stop bits)"
        );
        assert_eq!(rtu_framing(Parity::Odd, 1), "8O1 (parity odd, 1 stop bit)");
    }
}
