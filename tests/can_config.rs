//! CAN devices and channels in the config: what loads, and what validation reports
//! (by key and file) for each kind of mistake.

use compgate_gateway::config::{self, ConfigError, Transport};

fn example() -> String {
    std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/can-example.toml"
    ))
    .expect("can-example.toml")
}

/// The problems of `text` as `key: message` lines, empty if it loads.
fn problems(text: &str) -> Vec<String> {
    match config::load_str(text, "can.toml") {
        Ok(_) => Vec::new(),
        Err(ConfigError::Invalid(p)) => p
            .iter()
            .map(|p| {
                assert_eq!(p.file, "can.toml");
                format!("{}: {}", p.key, p.message)
            })
            .collect(),
        Err(e) => vec![e.to_string()],
    }
}

fn has(p: &[String], key: &str, words: &str) -> bool {
    p.iter()
        .any(|l| l.starts_with(&format!("{key}: ")) && l.contains(words))
}

#[test]
fn the_can_example_loads() {
    let cfg = config::load_str(&example(), "can.toml").expect("valid");
    let dev = &cfg.devices["can_ain"];
    assert_eq!(dev.transport(), Transport::Can);
    assert_eq!(dev.can().map(|c| c.node_id), Some(5));
    assert_eq!(dev.can().map(|c| c.interface.as_str()), Some("vcan0"));
    let params = |c: &config::Config| {
        let can = c.devices["can_ain"].can().expect("can").clone();
        can.params(std::time::Duration::from_millis(500))
    };
    assert_eq!(params(&cfg).tpdo_max_age, None, "synchronous");
    let event = example().replace("# tpdo_max_age_s = 0.3", "tpdo_max_age_s = 0.3");
    let event = config::load_str(&event, "can.toml").expect("valid");
    assert_eq!(
        params(&event).tpdo_max_age,
        Some(std::time::Duration::from_millis(300)),
        "event-driven"
    );
    let can = cfg.channels["T_screw"].can.expect("can table");
    assert_eq!((can.pdo, can.offset_bytes), (Some(1), Some(2)));
    let sdo = cfg.channels["T_col"].can.expect("can table");
    assert_eq!((sdo.sdo_index, sdo.sdo_subindex), (Some(0x9130), Some(3)));
    // And the gateway builds from it without touching the bus.
    compgate_gateway::runtime::build(&cfg).expect("builds");
}

#[test]
fn node_id_interface_and_modbus_keys() {
    let p = problems(&example().replace("node_id = 5", "node_id = 128"));
    assert!(has(&p, "devices.can_ain.node_id", "1..=127"), "{p:#?}");
    let p = problems(&example().replace("node_id = 5", "node_id = 0"));
    assert!(
        has(
            &p,
            "devices.can_ain.node_id",
            "integer `0`, expected an integer 1..=127"
        ),
        "{p:#?}"
    );
    let p = problems(&example().replace("node_id = 5\n", ""));
    assert!(has(&p, "devices.can_ain.node_id", "required"), "{p:#?}");
    let p = problems(&example().replace("interface = \"vcan0\"\n", ""));
    assert!(has(&p, "devices.can_ain.interface", "required"), "{p:#?}");
    let p = problems(&example().replace("interface = \"vcan0\"", "interface = \"/dev/can0\""));
    assert!(
        has(&p, "devices.can_ain.interface", "not a network interface"),
        "{p:#?}"
    );
    // Linux refuses these names: validate must too, not `run` with "No such device".
    for bad in ["can 0", "can0:1", " can0", "."] {
        let p = problems(
            &example().replace("interface = \"vcan0\"", &format!("interface = \"{bad}\"")),
        );
        assert!(
            has(&p, "devices.can_ain.interface", "not a network interface"),
            "{bad:?}: {p:#?}"
        );
    }
    let p = problems(&example().replace("node_id = 5", "node_id = 5\nunit_id = 1\nbaud = 9600"));
    assert!(
        has(
            &p,
            "devices.can_ain.unit_id",
            "not used by transport = \"can\""
        ),
        "{p:#?}"
    );
    assert!(has(&p, "devices.can_ain.baud", "not used"), "{p:#?}");
    let p = problems(&example().replace("heartbeat_timeout_s = 1.5", "heartbeat_timeout_s = -1.0"));
    assert!(
        has(
            &p,
            "devices.can_ain.heartbeat_timeout_s",
            "`-1`, expected a number 0..=3600"
        ),
        "{p:#?}"
    );
    let p = problems(&example().replace(
        "heartbeat_timeout_s = 1.5",
        "heartbeat_timeout_s = 1.5\ntpdo_max_age_s = 0.0",
    ));
    assert!(
        has(
            &p,
            "devices.can_ain.tpdo_max_age_s",
            "`0`, expected a number 0.001..=3600"
        ),
        "{p:#?}"
    );
}

#[test]
fn two_nodes_with_one_id_on_one_interface() {
    let second = "\n[devices.can_b]\ntransport = \"can\"\ninterface = \"vcan0\"\nnode_id = 5\n";
    let p = problems(&format!("{}{second}", example()));
    assert!(
        has(
            &p,
            "devices.can_b.node_id",
            "already used by `can_ain` on interface vcan0"
        ),
        "{p:#?}"
    );
    // The same id on another interface is another bus.
    let p = problems(&format!(
        "{}{}",
        example(),
        second.replace("vcan0", "vcan1")
    ));
    assert!(p.is_empty(), "{p:#?}");
}

#[test]
fn one_poll_interval_and_one_sync_producer_per_interface() {
    // can_ain polls every 0.5 s; a second node on vcan0 must too (one SYNC period).
    let second = "\n[devices.can_b]\ntransport = \"can\"\ninterface = \"vcan0\"\nnode_id = 6\n";
    let p = problems(&format!("{}{second}poll_interval_s = 0.2\n", example()));
    assert!(
        has(
            &p,
            "devices.can_b.poll_interval_s",
            "interface vcan0 is shared with `can_ain`, which uses poll_interval_s = 0.5"
        ),
        "{p:#?}"
    );
    assert_eq!(p.len(), 1, "{p:#?}");
    // The default (1.0 s) differs as well.
    let p = problems(&format!("{}{second}", example()));
    assert!(
        has(&p, "devices.can_b.poll_interval_s", "one SYNC"),
        "{p:#?}"
    );

    // Same interval on vcan0, another on vcan1: one producer each, at its interval.
    let third = "\n[devices.can_c]\ntransport = \"can\"\ninterface = \"vcan1\"\nnode_id = 5\npoll_interval_s = 0.25\n";
    let text = format!("{}{second}poll_interval_s = 0.5\n{third}", example());
    let cfg = config::load_str(&text, "can.toml").expect("valid");
    let built = compgate_gateway::runtime::build(&cfg).expect("builds");
    let producers: Vec<(String, f64)> = built
        .sync_producers
        .iter()
        .map(|p| (p.interface.clone(), p.period.as_secs_f64()))
        .collect();
    assert_eq!(
        producers,
        vec![("vcan0".to_string(), 0.5), ("vcan1".to_string(), 0.25)]
    );
    // vcan1's node sends its TPDOs event-driven: no SYNC there.
    let text = text.replace(
        "poll_interval_s = 0.25\n",
        "poll_interval_s = 0.25\ntpdo_max_age_s = 0.75\n",
    );
    let cfg = config::load_str(&text, "can.toml").expect("valid");
    let built = compgate_gateway::runtime::build(&cfg).expect("builds");
    let interfaces: Vec<&str> = built
        .sync_producers
        .iter()
        .map(|p| p.interface.as_str())
        .collect();
    assert_eq!(interfaces, ["vcan0"]);
}

#[test]
fn channel_mappings() {
    let p = problems(&example().replace("pdo = 1, offset_bytes = 2", "pdo = 5, offset_bytes = 2"));
    assert!(has(&p, "channels.T_screw.can.pdo", "1..=4"), "{p:#?}");
    let p = problems(&example().replace("pdo = 1, offset_bytes = 2", "pdo = 1, offset_bytes = 7"));
    assert!(
        has(
            &p,
            "channels.T_screw.can.offset_bytes",
            "past the 8 bytes of a PDO; expected offset_bytes <= 6"
        ),
        "{p:#?}"
    );
    let p = problems(&example().replace("pdo = 1, offset_bytes = 2", "pdo = 1"));
    assert!(
        has(&p, "channels.T_screw.can.offset_bytes", "required"),
        "{p:#?}"
    );
    let p = problems(&example().replace(
        "sdo_index = 0x9130, sdo_subindex = 3",
        "sdo_index = 0x9130, sdo_subindex = 3, pdo = 1",
    ));
    assert!(has(&p, "channels.T_col.can", "not both"), "{p:#?}");
    let p =
        problems(&example().replace("sdo_index = 0x9130, sdo_subindex = 3", "sdo_index = 0x9130"));
    assert!(
        has(&p, "channels.T_col.can.sdo_subindex", "required"),
        "{p:#?}"
    );
    let p = problems(&example().replace(
        "can = { pdo = 1, offset_bytes = 0 }",
        "register = \"input\"\naddress = 0",
    ));
    assert!(
        has(&p, "channels.T_bed.register", "not used on the CAN device"),
        "{p:#?}"
    );
    assert!(has(&p, "channels.T_bed.can", "required"), "{p:#?}");
    let p = problems(&example().replace(
        "pdo = 1, offset_bytes = 0",
        "pdo = 1, offset_bytes = 0, bogus = 1",
    ));
    assert!(p.iter().any(|l| l.contains("bogus")), "{p:#?}");
}

#[test]
fn can_table_on_a_modbus_channel() {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/minimal.toml"))
        .expect("minimal.toml")
        .replace(
            "address = 0\n",
            "address = 0\ncan = { pdo = 1, offset_bytes = 0 }\n",
        );
    let p = problems(&text);
    assert!(
        has(
            &p,
            "channels.T_screw.can",
            "only for a channel on a CAN device"
        ),
        "{p:#?}"
    );
}
