//! `compgate config example` and `compgate config schema` from the real binary: the
//! annotated example is the file shipped in `config/`, and it is a valid config.

use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_compgate");
const ANNOTATED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/config/annotated.toml");

fn stdout_of(args: &[&str]) -> String {
    let out = Command::new(BIN)
        .args(args)
        .output()
        .expect("compgate runs");
    assert!(
        out.status.success(),
        "compgate {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("UTF-8 output")
}

#[test]
fn config_example_is_the_shipped_annotated_file_and_validates() {
    let printed = stdout_of(&["config", "example"]);
    let shipped = std::fs::read_to_string(ANNOTATED).unwrap();
    assert!(
        printed == shipped,
        "config/annotated.toml differs from `compgate config example` (the config structs' \
         doc comments or config/example.toml changed); regenerate it with\n  \
         cargo run -- config example > config/annotated.toml"
    );
    assert!(
        printed.contains("# Seconds between poll cycles."),
        "{printed}"
    );
    let ok = stdout_of(&["validate", "--config", ANNOTATED]);
    assert!(ok.contains("OK"), "{ok}");
}

#[test]
fn config_schema_is_the_json_schema_with_every_key_documented() {
    let text = stdout_of(&["config", "schema"]);
    let schema: serde_json::Value = serde_json::from_str(&text).expect("JSON");
    assert_eq!(
        schema["$schema"],
        "https://json-schema.org/draft/2020-12/schema"
    );
    for section in ["gateway", "devices", "channels", "axes"] {
        assert!(
            schema["properties"][section]["description"].is_string(),
            "{section}"
        );
    }
    let timeout = &schema["$defs"]["DeviceConfig"]["oneOf"][0]["properties"]["timeout_s"];
    assert_eq!(timeout["default"], 1.0);
    assert!(timeout["description"]
        .as_str()
        .is_some_and(|d| d.contains("poll cycle")));
    // An editor checking against the schema flags an even median, as validate does.
    let median = &schema["$defs"]["FilterConfig"]["properties"]["median_samples"];
    assert_eq!(median["not"]["multipleOf"], 2, "{median}");
}

/// The annotated example was said to hold "every key" while it left out whole
/// sections and keys; its header (and example.toml's) now names what it leaves out,
/// and this keeps the list whole when a key or section is added.
#[test]
fn the_example_names_every_section_and_key_it_leaves_out() {
    let annotated = std::fs::read_to_string(ANNOTATED).unwrap();
    let example =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/example.toml"))
            .unwrap();
    let header = |text: &str| -> String {
        text.lines()
            .take_while(|l| l.starts_with('#'))
            .map(|l| l.trim_start_matches('#').trim())
            .collect::<Vec<_>>()
            .join(" ")
    };
    let headers = [header(&annotated), header(&example)];
    let schema = compgate_gateway::config::json_schema();
    let shown = |key: &str| {
        annotated.lines().any(|l| {
            l.starts_with(&format!("{key} = "))
                || l.starts_with(&format!("[{key}"))
                || l.contains(&format!(".{key}]"))
        })
    };
    let mut left_out: Vec<String> = Vec::new();
    for section in schema["properties"].as_object().unwrap().keys() {
        if !shown(section) {
            left_out.push(format!("[{section}]"));
        }
    }
    // The tables the example has: every key of theirs is shown or named. (A channel's
    // `can` comes with the CAN devices.)
    for def in [
        "GatewayConfig",
        "ChannelConfig",
        "FilterConfig",
        "AxisConfig",
        "K0Term",
        "TanBetaTerm",
    ] {
        let props = schema["$defs"][def]["properties"].as_object().unwrap();
        for key in props.keys().filter(|k| *k != "can") {
            if !shown(key) {
                left_out.push(key.clone());
            }
        }
    }
    assert!(left_out.contains(&"[mqtt]".to_string()), "{left_out:?}");
    assert!(left_out.contains(&"lag_tau_s".to_string()), "{left_out:?}");
    for h in &headers {
        for missing in &left_out {
            assert!(
                h.contains(missing.as_str()),
                "`{missing}` not named in: {h}"
            );
        }
        assert!(h.contains("CAN devices"), "{h}");
    }
}
