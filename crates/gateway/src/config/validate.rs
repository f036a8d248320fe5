//! Semantic validation: everything the parser cannot see.

use std::collections::{BTreeMap, BTreeSet};
use std::net::SocketAddr;

use super::schema::*;
use super::ConfigProblem;

/// Checks the meaning of a parsed configuration and returns every problem found
/// (empty = valid). `file` names the origin in the problems.
///
/// What is checked:
///
/// - **Names** of devices, channels, NC modules and axes: 1..=64 characters of
///   `A-Z a-z 0-9 _ -`, no `__` (the environment separator), unique ignoring case
///   (environment overrides match names ignoring case).
/// - **References**: `channels.*.device`, `axes.*.nc_module`, every channel of a
///   `k0`/`tan_beta` term, and the names under `[sim.channels]`/`[sim.nc_modules]`
///   must exist. One axis per NC module; a channel at most once per model.
/// - **Transport**: `tcp` needs `address` (`host:port`) and takes none of
///   `serial_path`, `baud`, `parity`, `stop_bits`; `rtu` needs `serial_path` and takes
///   neither `address` nor `connect_timeout_s`; baud 1200..=115200, stop bits 1 or 2.
///   Devices sharing a `serial_path` must agree on baud, parity and stop bits
///   (defaults applied) and have distinct unit ids.
/// - **CAN**: `interface` and `node_id` 1..=127 on `can` devices and none of the
///   Modbus keys; node ids distinct per interface, and one `poll_interval_s` per
///   interface (its SYNC period).
/// - **Unit ids** 0..=247; on RTU 1..=247 (0 is broadcast).
/// - **Times**: every timeout and interval > 0, `backoff_initial_s <= backoff_max_s`;
///   filter times >= 0 (0 = off).
/// - **Registers**: the value's last register (2 for 32-bit types) <= 65535. The same
///   register read by two channels is fine.
/// - **Scaling**: `adc_full_scale_counts` > 0 and representable in the data type
///   (`f32` counts are allowed, read as fractional counts), `adc_full_scale_ma >= 20`,
///   `range_min_degc < range_max_degc`; direct `gain` finite and not 0.
/// - **Filter**: `median_samples` odd 1..=99, `max_rejected_samples >= 1`,
///   `valid_min_degc < valid_max_degc`.
/// - **Axes**: `md32750` 0..=7 and its bits enabling every model in use, limits and
///   steps > 0, deadbands >= 0, `max_abs_tan_beta <= 0.1` (MD32760 is 0.01 by
///   default; above 0.1 is not a thermal slope), ramp rates > 0 with `ramp_to_zero`.
/// - **Sim**: `period_s > 0`, amplitude and noise >= 0, `md32750` 0..=7,
///   `motion_min_mm <= motion_max_mm`, speed >= 0.
/// - Every number finite (TOML allows `nan` and `inf`).
pub fn validate(cfg: &Config, file: &str) -> Vec<ConfigProblem> {
    validate_assuming(cfg, file, &Assumed::default())
}

/// Names that count as defined although the parsed configuration lacks them: entries
/// the loader had to drop for structural problems (already reported), so that
/// references to them do not add a second, misleading problem.
#[derive(Debug, Default)]
pub(super) struct Assumed {
    pub devices: Names,
    pub channels: Names,
    pub nc_modules: Names,
}

/// A set of names, or every name.
#[derive(Debug, Default)]
pub(super) struct Names {
    /// Every name counts as defined (the whole section was missing or broken).
    pub any: bool,
    names: BTreeSet<String>,
}

impl Names {
    pub fn insert(&mut self, name: String) {
        self.names.insert(name);
    }
    fn contains(&self, name: &str) -> bool {
        self.any || self.names.contains(name)
    }
}

pub(super) fn validate_assuming(cfg: &Config, file: &str, assumed: &Assumed) -> Vec<ConfigProblem> {
    let mut ck = Checker {
        file,
        out: Vec::new(),
    };
    ck.names("devices", cfg.devices.keys());
    ck.names("channels", cfg.channels.keys());
    ck.names("nc_modules", cfg.nc_modules.keys());
    ck.names("axes", cfg.axes.keys());

    ck.positive(
        "gateway.status_interval_s",
        cfg.gateway.status_interval_s,
        "seconds",
    );

    for (name, dev) in &cfg.devices {
        ck.device(name, dev);
    }
    ck.serial_lines(&cfg.devices);
    ck.can_buses(&cfg.devices);

    let has = |set: &Names, map_has: bool, name: &str| map_has || set.contains(name);
    for (name, ch) in &cfg.channels {
        let known = has(
            &assumed.devices,
            cfg.devices.contains_key(&ch.device),
            &ch.device,
        );
        if !known {
            ck.problem(
                field("channels", name, "device"),
                format!(
                    "unknown device `{}`; expected one of the names in [devices]: {}",
                    ch.device,
                    list(cfg.devices.keys())
                ),
            );
        }
        ck.channel_place(name, ch, cfg.devices.get(&ch.device).map(|d| d.transport));
        ck.channel(name, ch);
    }

    for (name, nc) in &cfg.nc_modules {
        ck.nc_module(name, nc);
    }

    let mut carried: BTreeMap<&str, &str> = BTreeMap::new();
    for (name, axis) in &cfg.axes {
        let module = axis.nc_module.as_str();
        if !has(
            &assumed.nc_modules,
            cfg.nc_modules.contains_key(module),
            module,
        ) {
            ck.problem(
                field("axes", name, "nc_module"),
                format!(
                    "unknown NC module `{module}`; expected one of the names in [nc_modules]: {}",
                    list(cfg.nc_modules.keys())
                ),
            );
        } else if let Some(other) = carried.insert(module, name) {
            ck.problem(
                field("axes", name, "nc_module"),
                format!("NC module `{module}` already carries axis `{other}`; one axis per module"),
            );
        }
        let channel_known = |c: &str| has(&assumed.channels, cfg.channels.contains_key(c), c);
        ck.axis(name, axis, &channel_known, cfg);
    }

    if let Some(sim) = &cfg.sim {
        for (name, sc) in &sim.channels {
            let key = format!("sim.channels.{}", seg(name));
            if !has(&assumed.channels, cfg.channels.contains_key(name), name) {
                ck.problem(
                    key.clone(),
                    format!("no channel `{name}` in [channels] to simulate"),
                );
            }
            ck.sim_channel(&key, sc);
        }
        for (name, sn) in &sim.nc_modules {
            let key = format!("sim.nc_modules.{}", seg(name));
            if !has(&assumed.nc_modules, cfg.nc_modules.contains_key(name), name) {
                ck.problem(
                    key.clone(),
                    format!("no NC module `{name}` in [nc_modules] to simulate"),
                );
            }
            ck.sim_nc_module(&key, sn);
        }
    }
    ck.out.extend(super::validate_service::validate(cfg, file));
    ck.out
}

/// Longest name accepted.
const MAX_NAME_LEN: usize = 64;
/// Largest median window accepted.
const MAX_MEDIAN_SAMPLES: u32 = 99;
/// Largest Modbus unit id that addresses one device.
const MAX_UNIT_ID: u8 = 247;
/// Above this |tan(beta)| limit the value cannot be a thermal slope.
const TAN_BETA_LIMIT_CEILING: f64 = 0.1;

struct Checker<'a> {
    file: &'a str,
    out: Vec<ConfigProblem>,
}

/// `section.name.field`, the name quoted when it is not a bare TOML key.
fn field(section: &str, name: &str, field: &str) -> String {
    format!("{section}.{}.{field}", seg(name))
}

fn seg(name: &str) -> std::borrow::Cow<'_, str> {
    super::load::key_segment(name)
}

fn list<'a>(names: impl Iterator<Item = &'a String>) -> String {
    let v: Vec<String> = names.map(|n| format!("`{n}`")).collect();
    if v.is_empty() {
        "(none defined)".to_string()
    } else {
        v.join(", ")
    }
}

impl Checker<'_> {
    fn problem(&mut self, key: String, message: String) {
        self.out.push(ConfigProblem::new(self.file, key, message));
    }

    fn finite(&mut self, key: &str, v: f64) -> bool {
        if v.is_finite() {
            true
        } else {
            self.problem(key.to_string(), format!("must be a finite number, got {v}"));
            false
        }
    }

    /// `v > 0`; `unit` names what the number is, e.g. "seconds".
    fn positive(&mut self, key: &str, v: f64, unit: &str) -> bool {
        if v.is_finite() && v > 0.0 {
            true
        } else {
            self.problem(key.to_string(), format!("must be > 0 ({unit}), got {v}"));
            false
        }
    }

    /// `v >= 0`; 0 usually means "off".
    fn non_negative(&mut self, key: &str, v: f64, unit: &str) -> bool {
        if v.is_finite() && v >= 0.0 {
            true
        } else {
            self.problem(key.to_string(), format!("must be >= 0 ({unit}), got {v}"));
            false
        }
    }

    fn names<'n>(&mut self, section: &str, names: impl Iterator<Item = &'n String>) {
        let mut folded: BTreeMap<String, &str> = BTreeMap::new();
        for name in names {
            let key = format!("{section}.{}", seg(name));
            if name.is_empty() {
                self.problem(key, "name must not be empty".into());
                continue;
            }
            if name.chars().count() > MAX_NAME_LEN {
                self.problem(
                    key.clone(),
                    format!("name is longer than {MAX_NAME_LEN} characters"),
                );
            }
            if !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            {
                self.problem(
                    key.clone(),
                    "name may contain only A-Z, a-z, 0-9, `_` and `-`".into(),
                );
            } else if name.contains("__") {
                self.problem(
                    key.clone(),
                    "name must not contain `__`, the level separator of environment overrides"
                        .into(),
                );
            }
            if let Some(other) = folded.insert(name.to_lowercase(), name) {
                self.problem(
                    key,
                    format!(
                        "differs from `{other}` only in case; environment overrides match \
                         names ignoring case and could not tell them apart"
                    ),
                );
            }
        }
    }

    fn host_port(&mut self, key: String, addr: &str) {
        if let Err(why) = check_host_port(addr) {
            self.problem(key, why);
        }
    }

    fn unit_id(&mut self, key: String, id: u8) {
        if id > MAX_UNIT_ID {
            self.problem(key, format!("must be 0..=247 (Modbus unit id), got {id}"));
        }
    }

    fn device(&mut self, name: &str, d: &DeviceConfig) {
        let k = |f: &str| field("devices", name, f);
        match d.transport {
            Transport::Tcp => {
                match &d.address {
                    Some(a) => self.host_port(k("address"), a),
                    None => self.problem(
                        k("address"),
                        "required with transport = \"tcp\": host:port of the Modbus TCP \
                         server, e.g. \"192.168.0.10:502\""
                            .into(),
                    ),
                }
                let serial = [
                    ("serial_path", d.serial_path.is_some()),
                    ("baud", d.baud.is_some()),
                    ("parity", d.parity.is_some()),
                    ("stop_bits", d.stop_bits.is_some()),
                ];
                for (f, present) in serial {
                    if present {
                        self.problem(
                            k(f),
                            "only for transport = \"rtu\"; remove it or set transport = \"rtu\""
                                .into(),
                        );
                    }
                }
                self.not_can(name, d);
                match d.unit_id {
                    Some(id) => self.unit_id(k("unit_id"), id),
                    None => self.problem(
                        k("unit_id"),
                        "required with transport = \"tcp\": the Modbus unit id, 0..=247".into(),
                    ),
                }
            }
            Transport::Rtu => {
                match d.serial_path.as_deref() {
                    Some(p) if !p.trim().is_empty() => {}
                    Some(_) => self.problem(
                        k("serial_path"),
                        "must name the serial device, e.g. \"/dev/ttyUSB0\"".into(),
                    ),
                    None => self.problem(
                        k("serial_path"),
                        "required with transport = \"rtu\": the serial device, e.g. \
                         \"/dev/ttyUSB0\""
                            .into(),
                    ),
                }
                for (f, present) in [
                    ("address", d.address.is_some()),
                    ("connect_timeout_s", d.connect_timeout_s.is_some()),
                ] {
                    if present {
                        self.problem(
                            k(f),
                            "only for transport = \"tcp\"; remove it or set transport = \"tcp\""
                                .into(),
                        );
                    }
                }
                if let Some(b) = d.baud {
                    if !(1200..=115_200).contains(&b) {
                        self.problem(k("baud"), format!("must be 1200..=115200, got {b}"));
                    }
                }
                if let Some(s) = d.stop_bits {
                    if !(1..=2).contains(&s) {
                        self.problem(k("stop_bits"), format!("must be 1 or 2, got {s}"));
                    }
                }
                self.not_can(name, d);
                match d.unit_id {
                    Some(0) => self.problem(
                        k("unit_id"),
                        "must be 1..=247 on RTU: 0 is the broadcast address, which never \
                         answers"
                            .into(),
                    ),
                    Some(id) => self.unit_id(k("unit_id"), id),
                    None => self.problem(
                        k("unit_id"),
                        "required with transport = \"rtu\": the Modbus unit id, 1..=247".into(),
                    ),
                }
            }
            Transport::Can => self.can_device(name, d),
        }
        self.positive(&k("timeout_s"), d.timeout_s, "seconds");
        if let Some(c) = d.connect_timeout_s {
            self.positive(&k("connect_timeout_s"), c, "seconds");
        }
        self.positive(&k("poll_interval_s"), d.poll_interval_s, "seconds");
        let init_ok = self.positive(&k("backoff_initial_s"), d.backoff_initial_s, "seconds");
        let max_ok = self.positive(&k("backoff_max_s"), d.backoff_max_s, "seconds");
        if init_ok && max_ok && d.backoff_initial_s > d.backoff_max_s {
            self.problem(
                k("backoff_max_s"),
                format!(
                    "must be >= backoff_initial_s ({} s), got {} s",
                    d.backoff_initial_s, d.backoff_max_s
                ),
            );
        }
        if d.degrade_after_cycles == 0 {
            self.problem(
                k("degrade_after_cycles"),
                "must be >= 1 (failed poll cycles before the channels turn bad)".into(),
            );
        }
    }

    /// The CAN-only keys are absent on a Modbus device.
    fn not_can(&mut self, name: &str, d: &DeviceConfig) {
        for (f, present) in [
            ("interface", d.interface.is_some()),
            ("node_id", d.node_id.is_some()),
            ("heartbeat_timeout_s", d.heartbeat_timeout_s.is_some()),
        ] {
            if present {
                self.problem(
                    field("devices", name, f),
                    "only for transport = \"can\"; remove it or set transport = \"can\"".into(),
                );
            }
        }
    }

    fn can_device(&mut self, name: &str, d: &DeviceConfig) {
        let k = |f: &str| field("devices", name, f);
        match d.interface.as_deref() {
            Some(i) if !i.trim().is_empty() && i.len() < 16 && !i.contains('/') => {}
            Some(i) => self.problem(
                k("interface"),
                format!("`{i}` is not a network interface name (1..=15 characters, no `/`), e.g. \"can0\""),
            ),
            None => self.problem(
                k("interface"),
                "required with transport = \"can\": the SocketCAN interface, e.g. \"can0\"".into(),
            ),
        }
        match d.node_id {
            Some(1..=127) => {}
            Some(n) => self.problem(
                k("node_id"),
                format!("must be 1..=127 (CANopen node id), got {n}"),
            ),
            None => self.problem(
                k("node_id"),
                "required with transport = \"can\": the CANopen node id, 1..=127".into(),
            ),
        }
        if let Some(h) = d.heartbeat_timeout_s {
            if !(h.is_finite() && h >= 0.0) {
                self.problem(
                    k("heartbeat_timeout_s"),
                    format!("must be >= 0 seconds (0 = no heartbeat check), got {h}"),
                );
            }
        }
        for (f, present) in [
            ("address", d.address.is_some()),
            ("connect_timeout_s", d.connect_timeout_s.is_some()),
            ("serial_path", d.serial_path.is_some()),
            ("baud", d.baud.is_some()),
            ("parity", d.parity.is_some()),
            ("stop_bits", d.stop_bits.is_some()),
            ("unit_id", d.unit_id.is_some()),
        ] {
            if present {
                self.problem(
                    k(f),
                    "not used by transport = \"can\" (a CAN node is addressed by interface \
                     and node_id); remove it"
                        .into(),
                );
            }
        }
    }

    /// CAN nodes on one interface need distinct node ids and share its SYNC period.
    fn can_buses(&mut self, devices: &BTreeMap<String, DeviceConfig>) {
        let mut seen: BTreeMap<(&str, u8), &String> = BTreeMap::new();
        let mut period: BTreeMap<&str, (&String, f64)> = BTreeMap::new();
        for (name, d) in devices {
            let (Transport::Can, Some(i)) = (d.transport, d.interface.as_deref()) else {
                continue;
            };
            if let Some(n) = d.node_id {
                if let Some(other) = seen.insert((i, n), name) {
                    self.problem(
                        field("devices", name, "node_id"),
                        format!("node id {n} is already used by `{other}` on interface {i}"),
                    );
                }
            }
            // One SYNC producer per interface sends at the poll interval: two values
            // would leave one device's cycle and the bus' SYNC out of step.
            match period.get(i) {
                None => {
                    period.insert(i, (name, d.poll_interval_s));
                }
                Some(&(first, p)) if p != d.poll_interval_s => self.problem(
                    field("devices", name, "poll_interval_s"),
                    format!(
                        "interface {i} is shared with `{first}`, which uses poll_interval_s = \
                         {p}; the interface has one SYNC, sent every poll_interval_s, so all \
                         CAN devices on one interface must use the same poll_interval_s"
                    ),
                ),
                Some(_) => {}
            }
        }
    }

    /// Devices on one serial line share its settings and its address space.
    fn serial_lines(&mut self, devices: &BTreeMap<String, DeviceConfig>) {
        let mut lines: BTreeMap<&str, Vec<(&String, &DeviceConfig)>> = BTreeMap::new();
        for (name, d) in devices {
            if let (Transport::Rtu, Some(path)) = (d.transport, d.serial_path.as_deref()) {
                lines.entry(path).or_default().push((name, d));
            }
        }
        for (path, devs) in lines {
            let Some(&(first_name, first)) = devs.first() else {
                continue;
            };
            let mut ids: BTreeMap<u8, &String> = BTreeMap::new();
            ids.insert(first.unit_id.unwrap_or_default(), first_name);
            for &(name, d) in devs.iter().skip(1) {
                let k = |f: &str| field("devices", name, f);
                let shared = |what: &str, theirs: String| {
                    format!(
                        "serial line {path} is shared with `{first_name}`, which uses \
                         {what} {theirs}; all devices on one line must use the same {what}"
                    )
                };
                if d.baud() != first.baud() {
                    self.problem(k("baud"), shared("baud", first.baud().to_string()));
                }
                if d.parity() != first.parity() {
                    self.problem(
                        k("parity"),
                        shared("parity", format!("{:?}", first.parity()).to_lowercase()),
                    );
                }
                if d.stop_bits() != first.stop_bits() {
                    self.problem(
                        k("stop_bits"),
                        shared("stop_bits", first.stop_bits().to_string()),
                    );
                }
                if let Some(other) = ids.insert(d.unit_id.unwrap_or_default(), name) {
                    self.problem(
                        k("unit_id"),
                        format!(
                            "unit id {} is already used by `{other}` on serial line {path}; \
                             devices on one line need distinct unit ids",
                            d.unit_id.unwrap_or_default()
                        ),
                    );
                }
            }
        }
    }

    /// Where a channel is: registers on a Modbus device, `can` on a CAN device.
    fn channel_place(&mut self, name: &str, c: &ChannelConfig, transport: Option<Transport>) {
        let k = |f: &str| field("channels", name, f);
        let on_can = match transport {
            Some(t) => t == Transport::Can,
            None => c.can.is_some(),
        };
        if !on_can {
            if c.can.is_some() {
                self.problem(
                    k("can"),
                    format!(
                        "only for a channel on a CAN device (transport = \"can\"); `{}` is a Modbus device",
                        c.device
                    ),
                );
            }
            for (f, present) in [
                ("register", c.register.is_some()),
                ("address", c.address.is_some()),
            ] {
                if !present {
                    self.problem(k(f), "required for a channel on a Modbus device".into());
                }
            }
            return;
        }
        for (f, present) in [
            ("register", c.register.is_some()),
            ("address", c.address.is_some()),
        ] {
            if present {
                self.problem(
                    k(f),
                    format!(
                        "not used on the CAN device `{}`; give the TPDO or SDO object in `can`",
                        c.device
                    ),
                );
            }
        }
        let Some(can) = c.can else {
            self.problem(
                k("can"),
                format!(
                    "required for a channel on the CAN device `{}`: {{ pdo = 1, offset_bytes = 0 }} \
                     or {{ sdo_index = 0x6401, sdo_subindex = 1 }}",
                    c.device
                ),
            );
            return;
        };
        let size = u32::from(c.registers()) * 2;
        let pdo = can.pdo.is_some() || can.offset_bytes.is_some();
        let sdo = can.sdo_index.is_some() || can.sdo_subindex.is_some();
        match (pdo, sdo) {
            (true, true) => self.problem(
                k("can"),
                "either a TPDO mapping (pdo, offset_bytes) or an SDO object (sdo_index, \
                 sdo_subindex), not both"
                    .into(),
            ),
            (false, false) => self.problem(
                k("can"),
                "empty: give pdo and offset_bytes, or sdo_index and sdo_subindex".into(),
            ),
            (true, false) => {
                match can.pdo {
                    Some(1..=4) => {}
                    Some(p) => self.problem(
                        k("can.pdo"),
                        format!("must be 1..=4 (TPDO1..TPDO4), got {p}"),
                    ),
                    None => self.problem(
                        k("can.pdo"),
                        "required with offset_bytes: the TPDO number 1..=4".into(),
                    ),
                }
                match can.offset_bytes {
                    Some(o) if u32::from(o) + size <= 8 => {}
                    Some(o) => self.problem(
                        k("can.offset_bytes"),
                        format!(
                            "a {} value at byte {o} takes {size} bytes and would end past the 8 bytes of a PDO; expected offset_bytes <= {}",
                            type_name(c.data_type),
                            8 - size
                        ),
                    ),
                    None => self.problem(k("can.offset_bytes"), "required with pdo: the value's byte offset in the PDO".into()),
                }
            }
            (false, true) => {
                if can.sdo_index.is_none() {
                    self.problem(
                        k("can.sdo_index"),
                        "required with sdo_subindex: the object index, e.g. 0x6401".into(),
                    );
                }
                if can.sdo_subindex.is_none() {
                    self.problem(
                        k("can.sdo_subindex"),
                        "required with sdo_index: the sub-index, 0..=255".into(),
                    );
                }
            }
        }
    }

    fn channel(&mut self, name: &str, c: &ChannelConfig) {
        let k = |f: &str| field("channels", name, f);
        let n = u32::from(c.registers());
        if c.address.is_some_and(|a| u32::from(a) + n > 65_536) {
            self.problem(
                k("address"),
                format!(
                    "a {} value takes {n} registers and would run past address 65535; \
                     expected address <= {}",
                    type_name(c.data_type),
                    65_536 - n
                ),
            );
        }
        match &c.scaling {
            Scaling::Transmitter(t) => {
                let max_counts = match c.data_type {
                    DataType::U16 => Some(u32::from(u16::MAX)),
                    DataType::I16 => Some(i16::MAX as u32),
                    DataType::U32 | DataType::I32 | DataType::F32 => None,
                };
                let key = k("scaling.adc_full_scale_counts");
                if t.adc_full_scale_counts == 0 {
                    self.problem(key, "must be > 0, e.g. 4095 for a 12-bit ADC".into());
                } else if let Some(max) = max_counts.filter(|m| t.adc_full_scale_counts > *m) {
                    self.problem(
                        key,
                        format!(
                            "{} counts cannot be read as {}; expected <= {max}",
                            t.adc_full_scale_counts,
                            type_name(c.data_type)
                        ),
                    );
                }
                let ma = t.adc_full_scale_ma;
                if !(ma.is_finite() && ma >= 20.0) {
                    self.problem(
                        k("scaling.adc_full_scale_ma"),
                        format!(
                            "must be >= 20 mA so the top of the {}-20 mA range is reachable \
                             (above 21 keeps NE43 over-range visible), got {ma}",
                            t.current_range.min_ma()
                        ),
                    );
                }
                let lo = self.finite(&k("scaling.range_min_degc"), t.range_min_degc);
                let hi = self.finite(&k("scaling.range_max_degc"), t.range_max_degc);
                if lo && hi && t.range_min_degc >= t.range_max_degc {
                    self.problem(
                        k("scaling.range_max_degc"),
                        format!(
                            "must be > range_min_degc ({} degC), got {} degC",
                            t.range_min_degc, t.range_max_degc
                        ),
                    );
                }
            }
            Scaling::Direct(d) => {
                if !(d.gain.is_finite() && d.gain != 0.0) {
                    self.problem(
                        k("scaling.gain"),
                        format!("must be a finite number other than 0, got {}", d.gain),
                    );
                }
                self.finite(&k("scaling.offset_degc"), d.offset_degc);
            }
        }
        let f = &c.filter;
        let m = f.median_samples;
        if m == 0 || m > MAX_MEDIAN_SAMPLES || m.is_multiple_of(2) {
            self.problem(
                k("filter.median_samples"),
                format!(
                    "must be an odd number 1..={MAX_MEDIAN_SAMPLES} (1 = off; an even \
                     window has no middle sample), got {m}"
                ),
            );
        }
        self.non_negative(
            &k("filter.lowpass_tau_s"),
            f.lowpass_tau_s,
            "seconds, 0 = off",
        );
        self.non_negative(
            &k("filter.max_rate_degc_per_s"),
            f.max_rate_degc_per_s,
            "degC per second, 0 = off",
        );
        if f.max_rejected_samples == 0 {
            self.problem(
                k("filter.max_rejected_samples"),
                "must be >= 1 (rejected samples before the channel turns bad)".into(),
            );
        }
        self.non_negative(
            &k("filter.stale_after_s"),
            f.stale_after_s,
            "seconds, 0 = off",
        );
        let lo = self.finite(&k("filter.valid_min_degc"), f.valid_min_degc);
        let hi = self.finite(&k("filter.valid_max_degc"), f.valid_max_degc);
        if lo && hi && f.valid_min_degc >= f.valid_max_degc {
            self.problem(
                k("filter.valid_max_degc"),
                format!(
                    "must be > valid_min_degc ({} degC), got {} degC",
                    f.valid_min_degc, f.valid_max_degc
                ),
            );
        }
    }

    fn nc_module(&mut self, name: &str, n: &NcModuleConfig) {
        let k = |f: &str| field("nc_modules", name, f);
        self.host_port(k("address"), &n.address);
        self.unit_id(k("unit_id"), n.unit_id);
        self.positive(&k("timeout_s"), n.timeout_s, "seconds");
        self.positive(&k("connect_timeout_s"), n.connect_timeout_s, "seconds");
        self.positive(&k("job_timeout_s"), n.job_timeout_s, "seconds");
    }

    fn axis(
        &mut self,
        name: &str,
        a: &AxisConfig,
        channel_known: &dyn Fn(&str) -> bool,
        cfg: &Config,
    ) {
        let k = |f: &str| field("axes", name, f);
        if a.md32750 > 7 {
            self.problem(
                k("md32750"),
                format!(
                    "must be 0..=7 (bit 0: K0, bit 1: slope, bit 2: tool direction), got {}",
                    a.md32750
                ),
            );
        } else {
            let k0_used = a.k0.offset_mm != 0.0 || !a.k0.terms.is_empty();
            let tb_used = a.tan_beta.offset != 0.0 || !a.tan_beta.terms.is_empty();
            if k0_used && a.md32750 & 1 == 0 {
                self.problem(
                    k("k0"),
                    format!(
                        "a K0 model is configured but md32750 = {} has bit 0 clear: the NC \
                         would ignore SD43900; set bit 0 or remove the model",
                        a.md32750
                    ),
                );
            }
            if tb_used && a.md32750 & 2 == 0 {
                self.problem(
                    k("tan_beta"),
                    format!(
                        "a tan(beta) model is configured but md32750 = {} has bit 1 clear: \
                         the NC would ignore SD43910; set bit 1 or remove the model",
                        a.md32750
                    ),
                );
            }
        }
        self.finite(&k("p0_mm"), a.p0_mm);
        self.positive(&k("update_interval_s"), a.update_interval_s, "seconds");
        self.non_negative(&k("deadband_k0_mm"), a.deadband_k0_mm, "mm");
        self.non_negative(&k("deadband_tan_beta"), a.deadband_tan_beta, "mm/mm");
        self.positive(&k("max_abs_k0_mm"), a.max_abs_k0_mm, "mm");
        if self.positive(&k("max_abs_tan_beta"), a.max_abs_tan_beta, "mm/mm")
            && a.max_abs_tan_beta > TAN_BETA_LIMIT_CEILING
        {
            self.problem(
                k("max_abs_tan_beta"),
                format!(
                    "must be <= {TAN_BETA_LIMIT_CEILING} and below the NC's MD32760 \
                     (default 0.01), got {}",
                    a.max_abs_tan_beta
                ),
            );
        }
        self.positive(&k("max_step_k0_mm"), a.max_step_k0_mm, "mm per update");
        self.positive(&k("max_step_tan_beta"), a.max_step_tan_beta, "per update");
        match a.on_bad_input {
            OnBadInput::RampToZero => {
                self.positive(&k("ramp_k0_mm_per_s"), a.ramp_k0_mm_per_s, "mm per second");
                self.positive(
                    &k("ramp_tan_beta_per_s"),
                    a.ramp_tan_beta_per_s,
                    "per second",
                );
            }
            OnBadInput::Hold => {
                self.non_negative(&k("ramp_k0_mm_per_s"), a.ramp_k0_mm_per_s, "mm per second");
                self.non_negative(
                    &k("ramp_tan_beta_per_s"),
                    a.ramp_tan_beta_per_s,
                    "per second",
                );
            }
        }
        self.finite(&k("k0.offset_mm"), a.k0.offset_mm);
        self.finite(&k("tan_beta.offset"), a.tan_beta.offset);
        let k0_terms = a.k0.terms.iter().map(|t| {
            (
                t.channel.as_str(),
                t.ref_degc,
                ("coeff_mm_per_degc", t.coeff_mm_per_degc),
            )
        });
        self.terms(&k("k0.terms"), k0_terms, channel_known, cfg);
        let tb_terms = a.tan_beta.terms.iter().map(|t| {
            (
                t.channel.as_str(),
                t.ref_degc,
                ("coeff_per_degc", t.coeff_per_degc),
            )
        });
        self.terms(&k("tan_beta.terms"), tb_terms, channel_known, cfg);
    }

    fn terms<'t>(
        &mut self,
        key: &str,
        terms: impl Iterator<Item = (&'t str, f64, (&'static str, f64))>,
        channel_known: &dyn Fn(&str) -> bool,
        cfg: &Config,
    ) {
        let mut seen: BTreeMap<&str, usize> = BTreeMap::new();
        for (i, (channel, ref_degc, (coeff_name, coeff))) in terms.enumerate() {
            let tk = |f: &str| format!("{key}[{i}].{f}");
            if !channel_known(channel) {
                self.problem(
                    tk("channel"),
                    format!(
                        "unknown channel `{channel}`; expected one of the names in \
                         [channels]: {}",
                        list(cfg.channels.keys())
                    ),
                );
            } else if let Some(first) = seen.insert(channel, i) {
                self.problem(
                    tk("channel"),
                    format!(
                        "channel `{channel}` already has term [{first}]; combine the \
                         coefficients into one term"
                    ),
                );
            }
            self.finite(&tk("ref_degc"), ref_degc);
            self.finite(&tk(coeff_name), coeff);
        }
    }

    fn sim_channel(&mut self, key: &str, s: &SimChannelConfig) {
        let k = |f: &str| format!("{key}.{f}");
        self.finite(&k("mean_degc"), s.mean_degc);
        self.non_negative(&k("amplitude_degc"), s.amplitude_degc, "degC");
        self.positive(&k("period_s"), s.period_s, "seconds");
        self.finite(&k("rate_degc_per_s"), s.rate_degc_per_s);
        self.non_negative(&k("noise_degc"), s.noise_degc, "degC");
    }

    fn sim_nc_module(&mut self, key: &str, s: &SimNcModuleConfig) {
        let k = |f: &str| format!("{key}.{f}");
        if s.md32750 > 7 {
            self.problem(k("md32750"), format!("must be 0..=7, got {}", s.md32750));
        }
        let lo = self.finite(&k("motion_min_mm"), s.motion_min_mm);
        let hi = self.finite(&k("motion_max_mm"), s.motion_max_mm);
        if lo && hi && s.motion_min_mm > s.motion_max_mm {
            self.problem(
                k("motion_max_mm"),
                format!(
                    "must be >= motion_min_mm ({} mm), got {} mm",
                    s.motion_min_mm, s.motion_max_mm
                ),
            );
        }
        self.non_negative(
            &k("motion_speed_mm_per_s"),
            s.motion_speed_mm_per_s,
            "mm per second, 0 = standing",
        );
    }
}

fn type_name(t: DataType) -> &'static str {
    match t {
        DataType::U16 => "u16",
        DataType::I16 => "i16",
        DataType::U32 => "u32",
        DataType::I32 => "i32",
        DataType::F32 => "f32",
    }
}

/// Accepts `host:port` with a host name, an IPv4 address or a bracketed IPv6
/// address, and a port 0..=65535.
fn check_host_port(addr: &str) -> Result<(), String> {
    if addr.parse::<SocketAddr>().is_ok() {
        return Ok(());
    }
    let example = "expected host:port, e.g. \"192.168.0.10:502\"";
    let Some((host, port)) = addr.rsplit_once(':') else {
        return Err(format!("`{addr}` has no port; {example}"));
    };
    if port.parse::<u16>().is_err() {
        return Err(format!(
            "port `{port}` is not a number 0..=65535; {example}"
        ));
    }
    if host.is_empty() {
        return Err(format!("`{addr}` has no host; {example}"));
    }
    if host.contains(':') {
        return Err(format!(
            "`{addr}`: write an IPv6 address in brackets, e.g. \"[::1]:502\""
        ));
    }
    let label_ok = |l: &str| {
        !l.is_empty()
            && l.len() <= 63
            && l.chars().all(|c| c.is_ascii_alphanumeric() || c == '-')
            && !l.starts_with('-')
            && !l.ends_with('-')
    };
    if host.len() > 253 || !host.split('.').all(label_ok) {
        return Err(format!(
            "`{host}` is not a valid host name or IP address; {example}"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn host_port_forms() {
        for ok in [
            "127.0.0.1:502",
            "127.0.0.1:0",
            "[::1]:5020",
            "plc-7.hall2.local:502",
            "localhost:1502",
        ] {
            assert_eq!(check_host_port(ok), Ok(()), "{ok}");
        }
        for bad in [
            "127.0.0.1",
            "127.0.0.1:70000",
            ":502",
            "::1:502",
            "bad host:502",
            "a..b:1",
        ] {
            assert!(check_host_port(bad).is_err(), "{bad}");
        }
    }
}

#[cfg(test)]
mod rules {
    use super::*;
    use crate::config::load_str;

    fn example() -> Config {
        match load_str(
            include_str!("../../../../config/example.toml"),
            "example.toml",
        ) {
            Ok(cfg) => cfg,
            Err(e) => panic!("{e}"),
        }
    }

    /// Keys of the problems after `change` was applied to the example.
    fn problems_after(change: impl FnOnce(&mut Config)) -> Vec<String> {
        let mut cfg = example();
        change(&mut cfg);
        validate(&cfg, "v.toml")
            .into_iter()
            .map(|p| {
                assert_eq!(p.file, "v.toml");
                assert!(!p.message.is_empty());
                p.key
            })
            .collect()
    }

    fn dev<'a>(cfg: &'a mut Config, name: &str) -> &'a mut DeviceConfig {
        cfg.devices.get_mut(name).expect("device in example")
    }
    fn ch<'a>(cfg: &'a mut Config, name: &str) -> &'a mut ChannelConfig {
        cfg.channels.get_mut(name).expect("channel in example")
    }
    fn x(cfg: &mut Config) -> &mut AxisConfig {
        cfg.axes.get_mut("X").expect("axis in example")
    }

    #[test]
    fn example_is_clean() {
        assert_eq!(problems_after(|_| {}), Vec::<String>::new());
    }

    #[test]
    fn tcp_and_rtu_fields() {
        assert_eq!(
            problems_after(|c| {
                let d = dev(c, "ain1");
                d.address = None;
                d.serial_path = Some("/dev/ttyS0".into());
                d.baud = Some(9600);
            }),
            [
                "devices.ain1.address",
                "devices.ain1.serial_path",
                "devices.ain1.baud",
            ]
        );
        assert_eq!(
            problems_after(|c| {
                let d = dev(c, "ain2");
                d.address = Some("10.0.0.1:502".into());
                d.connect_timeout_s = Some(1.0);
                d.serial_path = None;
                d.baud = Some(300);
                d.stop_bits = Some(3);
            }),
            [
                "devices.ain2.serial_path",
                "devices.ain2.address",
                "devices.ain2.connect_timeout_s",
                "devices.ain2.baud",
                "devices.ain2.stop_bits",
            ]
        );
        assert_eq!(
            problems_after(|c| dev(c, "ain1").address = Some("plc:5o2".into())),
            ["devices.ain1.address"]
        );
    }

    #[test]
    fn unit_ids_and_times() {
        assert_eq!(
            problems_after(|c| {
                let d = dev(c, "ain1");
                d.unit_id = Some(248);
                d.timeout_s = 0.0;
                d.poll_interval_s = -1.0;
                d.backoff_initial_s = 5.0;
                d.backoff_max_s = 1.0;
                d.degrade_after_cycles = 0;
                dev(c, "ain2").unit_id = Some(0);
                c.gateway.status_interval_s = f64::NAN;
                c.nc_modules.get_mut("nc_x").expect("nc").job_timeout_s = 0.0;
            }),
            [
                "gateway.status_interval_s",
                "devices.ain1.unit_id",
                "devices.ain1.timeout_s",
                "devices.ain1.poll_interval_s",
                "devices.ain1.backoff_max_s",
                "devices.ain1.degrade_after_cycles",
                "devices.ain2.unit_id",
                "nc_modules.nc_x.job_timeout_s",
            ]
        );
    }

    #[test]
    fn shared_serial_line() {
        let keys = problems_after(|c| {
            let mut other = c.devices["ain2"].clone();
            other.baud = Some(9600);
            other.parity = Some(Parity::None);
            other.stop_bits = None; // 2 without parity
            c.devices.insert("ain3".into(), other);
        });
        assert_eq!(
            keys,
            [
                "devices.ain3.baud",
                "devices.ain3.parity",
                "devices.ain3.stop_bits",
                "devices.ain3.unit_id",
            ]
        );
        // Defaults count: an explicit 19200/even/1 equals the defaults.
        assert_eq!(
            problems_after(|c| {
                let mut other = c.devices["ain2"].clone();
                other.baud = None;
                other.parity = None;
                other.stop_bits = None;
                other.unit_id = Some(8);
                c.devices.insert("ain3".into(), other);
            }),
            Vec::<String>::new()
        );
    }

    #[test]
    fn registers_and_scaling() {
        assert_eq!(
            problems_after(|c| {
                let t = ch(c, "T_ambient");
                t.address = Some(65535);
                t.scaling = Scaling::Direct(DirectScaling {
                    gain: 0.0,
                    offset_degc: f64::INFINITY,
                });
            }),
            [
                "channels.T_ambient.address",
                "channels.T_ambient.scaling.gain",
                "channels.T_ambient.scaling.offset_degc",
            ]
        );
        assert_eq!(
            problems_after(|c| {
                let t = ch(c, "T_bed");
                t.data_type = DataType::I16;
                t.scaling = Scaling::Transmitter(TransmitterScaling {
                    adc_full_scale_counts: 40_000,
                    adc_full_scale_ma: 16.0,
                    current_range: CurrentRange::Ma4To20,
                    range_min_degc: 100.0,
                    range_max_degc: 0.0,
                });
                ch(c, "T_screw").data_type = DataType::F32;
            }),
            [
                "channels.T_bed.scaling.adc_full_scale_counts",
                "channels.T_bed.scaling.adc_full_scale_ma",
                "channels.T_bed.scaling.range_max_degc",
            ],
            "f32 counts are fine"
        );
        // The same register read twice is fine.
        assert_eq!(
            problems_after(|c| ch(c, "T_screw").address = Some(0)),
            Vec::<String>::new()
        );
    }

    #[test]
    fn filter_ranges() {
        assert_eq!(
            problems_after(|c| {
                let f = &mut ch(c, "T_bed").filter;
                f.median_samples = 4;
                f.lowpass_tau_s = -1.0;
                f.max_rate_degc_per_s = -0.1;
                f.max_rejected_samples = 0;
                f.stale_after_s = -5.0;
                f.valid_min_degc = 50.0;
                f.valid_max_degc = 50.0;
                ch(c, "T_screw").filter.median_samples = 0;
            }),
            [
                "channels.T_bed.filter.median_samples",
                "channels.T_bed.filter.lowpass_tau_s",
                "channels.T_bed.filter.max_rate_degc_per_s",
                "channels.T_bed.filter.max_rejected_samples",
                "channels.T_bed.filter.stale_after_s",
                "channels.T_bed.filter.valid_max_degc",
                "channels.T_screw.filter.median_samples",
            ]
        );
    }

    #[test]
    fn references() {
        assert_eq!(
            problems_after(|c| {
                ch(c, "T_bed").device = "nope".into();
                x(c).tan_beta.terms[0].channel = "T_nope".into();
                let dup = x(c).k0.terms[0].clone();
                x(c).k0.terms.push(dup);
                let mut y = c.axes["X"].clone();
                y.k0 = K0Model::default();
                y.tan_beta = TanBetaModel::default();
                c.axes.insert("Y".into(), y);
            }),
            [
                "channels.T_bed.device",
                "axes.X.k0.terms[2].channel",
                "axes.X.tan_beta.terms[0].channel",
                "axes.Y.nc_module",
            ]
        );
        assert_eq!(
            problems_after(|c| x(c).nc_module = "nc_y".into()),
            ["axes.X.nc_module"]
        );
    }

    #[test]
    fn axis_limits_and_md32750() {
        assert_eq!(
            problems_after(|c| {
                let a = x(c);
                a.max_abs_tan_beta = 0.2;
                a.max_abs_k0_mm = 0.0;
                a.deadband_k0_mm = -0.1;
                a.max_step_tan_beta = 0.0;
                a.ramp_k0_mm_per_s = 0.0;
                a.update_interval_s = 0.0;
            }),
            [
                "axes.X.update_interval_s",
                "axes.X.deadband_k0_mm",
                "axes.X.max_abs_k0_mm",
                "axes.X.max_abs_tan_beta",
                "axes.X.max_step_tan_beta",
                "axes.X.ramp_k0_mm_per_s",
            ]
        );
        assert_eq!(problems_after(|c| x(c).md32750 = 8), ["axes.X.md32750"]);
        assert_eq!(problems_after(|c| x(c).md32750 = 2), ["axes.X.k0"]);
        assert_eq!(problems_after(|c| x(c).md32750 = 1), ["axes.X.tan_beta"]);
        assert_eq!(
            problems_after(|c| {
                x(c).on_bad_input = OnBadInput::Hold;
                x(c).ramp_k0_mm_per_s = 0.0;
            }),
            Vec::<String>::new(),
            "ramp rates may be 0 with hold"
        );
    }

    #[test]
    fn names() {
        assert_eq!(
            problems_after(|c| {
                let t = c.channels["T_bed"].clone();
                c.channels.insert("t_bed".into(), t.clone());
                c.channels.insert("T bed".into(), t.clone());
                c.channels.insert("T__bed".into(), t.clone());
                c.channels.insert("".into(), t.clone());
                c.channels.insert("T".repeat(65), t);
            }),
            [
                "channels.\"\"",
                "channels.\"T bed\"",
                format!("channels.{}", "T".repeat(65)).as_str(),
                "channels.T__bed",
                "channels.t_bed",
            ]
        );
    }

    #[test]
    fn sim_section() {
        assert_eq!(
            problems_after(|c| {
                let mut sim = SimConfig::default();
                sim.channels.insert(
                    "T_bed".into(),
                    SimChannelConfig {
                        profile: SimProfile::Sine,
                        amplitude_degc: -1.0,
                        period_s: 0.0,
                        noise_degc: -0.1,
                        ..SimChannelConfig::default()
                    },
                );
                sim.channels
                    .insert("T_nope".into(), SimChannelConfig::default());
                sim.nc_modules.insert(
                    "nc_x".into(),
                    SimNcModuleConfig {
                        md32750: 9,
                        motion_min_mm: 10.0,
                        motion_max_mm: 0.0,
                        motion_speed_mm_per_s: -1.0,
                        ..SimNcModuleConfig::default()
                    },
                );
                sim.nc_modules
                    .insert("nc_nope".into(), SimNcModuleConfig::default());
                c.sim = Some(sim);
            }),
            [
                "sim.channels.T_bed.amplitude_degc",
                "sim.channels.T_bed.period_s",
                "sim.channels.T_bed.noise_degc",
                "sim.channels.T_nope",
                "sim.nc_modules.nc_nope",
                "sim.nc_modules.nc_x.md32750",
                "sim.nc_modules.nc_x.motion_max_mm",
                "sim.nc_modules.nc_x.motion_speed_mm_per_s",
            ]
        );
    }
}
