//! The command line, and how its commands write to standard output and error.

use std::fmt::Display;
use std::io::{self, Write};
use std::path::PathBuf;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

/// compgate: thermal compensation gateway for CNC machine tools.
///
/// Without a command it runs the gateway against an embedded simulated plant (field
/// I/O module and NC axis module on loopback), as a demonstration.
#[derive(Debug, Parser)]
#[command(version = env!("COMPGATE_BUILD"), about, long_about = None)]
pub struct Cli {
    /// Log filter (tracing EnvFilter syntax), e.g. "info" or "compgate=debug".
    /// Defaults to RUST_LOG, else "info" ("warn" for the demo, to keep the status line clean)
    /// with tokio-modbus' and the OPC UA client's session warnings off (the gateway reports
    /// those faults itself).
    #[arg(long, global = true)]
    pub log: Option<String>,
    /// What to do; the demo when omitted.
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the gateway against the devices the config names.
    Run {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: PathBuf,
        /// Shadow mode for every axis: compute, record and publish what would be
        /// written, never write the NC (as `gateway.shadow = true`; kept on reload).
        #[arg(long)]
        shadow: bool,
    },
    /// Check a configuration and print every problem with its key and file.
    Validate {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: PathBuf,
    },
    /// Read or write an axis's compensation values on its NC target (first dry-run).
    Nc(crate::nc::NcArgs),
    /// Poll every channel once and show registers, byte orders, mA, degC and quality.
    Probe(crate::probe::ProbeArgs),
    /// Print the annotated example configuration or the JSON Schema of the config.
    #[command(subcommand)]
    Config(ConfigCommand),
    /// Write recorded operation as the measurement CSV that calibrate and diagnose read.
    Export(compgate_service::record::export::ExportArgs),
    /// Fit K0(T) and tan(beta)(T) to measured error curves and write the axis model.
    Calibrate(compgate_commission::calibrate::CalibrateArgs),
    /// Find where model and measurement disagree, name the missing effect, add it.
    Diagnose(compgate_commission::diagnose::command::DiagnoseArgs),
    /// ISO 230-2 evaluation (A, B, R, E, M) of bidirectional runs in a measurement CSV.
    Iso230(compgate_commission::iso230::Iso230Args),
    /// Measure reversal backlash of a full-closed-loop axis from encoder vs scale trace.
    Backlash(compgate_commission::backlash::BacklashArgs),
    /// Evaluate volumetric compensation of a 5-axis AC-head machine over a workspace grid.
    Volumetric(compgate_commission::volumetric::VolumetricArgs),
    /// Thermal test of the simulated machine with the gateway in the loop, off vs on.
    #[cfg(feature = "sim")]
    Scenario(crate::scenario::ScenarioArgs),
    /// Run the gateway against the embedded simulated plant (the default).
    #[cfg(feature = "sim")]
    Demo(DemoArgs),
    /// Run only the simulated plant on the addresses the config names.
    #[cfg(feature = "sim")]
    Sim {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: PathBuf,
    },
}

/// `compgate config ...`.
#[derive(Debug, Subcommand)]
pub enum ConfigCommand {
    /// Print the example configuration with every key of its sections, annotated with
    /// its documentation (the doc comments of the config structs): `config/annotated.toml`.
    Example,
    /// Print the JSON Schema (draft 2020-12) of the configuration, for TOML editors'
    /// completion and checking.
    Schema,
}

/// `compgate demo`.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Where the live status page (and `/metrics`) listens, IP:PORT; port 0 takes a
    /// free port, `off` serves none. A busy port is reported and the demo runs without
    /// the page.
    #[arg(long, default_value = "127.0.0.1:9464", value_parser = http_bind)]
    pub http: String,
    /// Shadow mode: compute and show what would be written, never write the NC.
    #[arg(long)]
    pub shadow: bool,
}

/// `--http`: `off` or a socket address, as `metrics.bind` takes it. A typo is the
/// command line's error (exit 2, naming the flag), not a page that quietly is not
/// served; a busy port is found only when binding, and the demo runs on without it.
fn http_bind(text: &str) -> Result<String, String> {
    if text == "off" {
        return Ok(text.to_string());
    }
    text.parse::<std::net::SocketAddr>()
        .map(|_| text.to_string())
        .map_err(|e| format!("{e}: give IP:PORT (e.g. 127.0.0.1:9464) or `off`"))
}

impl Default for DemoArgs {
    fn default() -> Self {
        DemoArgs {
            http: "127.0.0.1:9464".into(),
            shadow: false,
        }
    }
}

/// The groups `compgate --help` lists the commands in.
const GROUPS: [(&str, &[&str]); 3] = [
    ("Service", &["run", "validate", "config", "export"]),
    (
        "Commissioning",
        &[
            "nc",
            "probe",
            "calibrate",
            "diagnose",
            "iso230",
            "backlash",
            "volumetric",
            "scenario",
        ],
    ),
    ("Tools", &["demo", "sim"]),
];

/// The clap command with the subcommands listed by group in the help.
pub fn command() -> clap::Command {
    let cmd = Cli::command();
    let mut listing = String::new();
    for (group, names) in GROUPS {
        let subs: Vec<&clap::Command> = names
            .iter()
            .filter_map(|n| cmd.get_subcommands().find(|s| s.get_name() == *n))
            .collect();
        if subs.is_empty() {
            continue;
        }
        listing.push_str(&format!("{group}:\n"));
        for s in subs {
            let about = s.get_about().map(|a| a.to_string()).unwrap_or_default();
            listing.push_str(&format!("  {:<11} {about}\n", s.get_name()));
        }
        listing.push('\n');
    }
    cmd.help_template(format!(
        "{{before-help}}{{about-with-newline}}\n{{usage-heading}} {{usage}}\n\n{listing}Options:\n{{options}}{{after-help}}"
    ))
}

/// Parses the process's arguments (clap exits on `--help` and on errors).
pub fn parse() -> Cli {
    let matches = command().get_matches();
    Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit())
}

/// Exit status after a write to a closed pipe (`compgate config schema | head -1`):
/// 128 + SIGPIPE, what a shell reports for a C tool the signal ended, so a `set -o
/// pipefail` script sees the same as with `cat`. Rust ignores SIGPIPE and restoring
/// its default takes `unsafe`, so the write fails with EPIPE instead: see [`print()`].
pub const EXIT_BROKEN_PIPE: u8 = 141;

/// A command's output could not be written.
#[derive(Debug, thiserror::Error)]
#[error("cannot write to standard {stream}: {source}")]
pub struct OutputError {
    /// "output" or "error".
    stream: &'static str,
    #[source]
    source: io::Error,
}

impl OutputError {
    /// The reader went away: the program ends quietly with [`EXIT_BROKEN_PIPE`]
    /// (nobody is left to read a message); any other error is reported, status 1.
    pub fn is_broken_pipe(&self) -> bool {
        self.source.kind() == io::ErrorKind::BrokenPipe
    }

    /// A write error of standard output.
    pub fn stdout(source: io::Error) -> Self {
        OutputError {
            stream: "output",
            source,
        }
    }
}

/// Writes `text` to standard output, flushed: `print!` without its panic when the
/// write fails.
pub fn print(text: impl Display) -> Result<(), OutputError> {
    let mut out = io::stdout().lock();
    write!(out, "{text}")
        .and_then(|()| out.flush())
        .map_err(OutputError::stdout)
}

/// Writes `text` and a newline to standard error: `eprintln!` without its panic.
pub fn eprintln(text: impl Display) -> Result<(), OutputError> {
    writeln!(io::stderr().lock(), "{text}").map_err(|source| OutputError {
        stream: "error",
        source,
    })
}

#[cfg(test)]
mod tests {
    use std::any::TypeId;

    /// Every flag that takes a number takes a negative one (`--p0-mm -100`): without
    /// `allow_negative_numbers`, clap reads `-100` as an unknown flag and says
    /// "unexpected argument '-1' found", which names neither the flag nor the value.
    #[test]
    fn every_numeric_flag_takes_a_negative_number() {
        let numeric = [
            TypeId::of::<f64>(),
            TypeId::of::<u8>(),
            TypeId::of::<u16>(),
            TypeId::of::<u32>(),
            TypeId::of::<u64>(),
            TypeId::of::<i64>(),
            TypeId::of::<usize>(),
        ];
        fn walk(cmd: &clap::Command, path: &str, numeric: &[TypeId], bad: &mut Vec<String>) {
            for a in cmd.get_arguments() {
                let ty = a.get_value_parser().type_id();
                if numeric.iter().any(|t| ty == *t)
                    && !a.is_allow_negative_numbers_set()
                    && !a.is_allow_hyphen_values_set()
                {
                    bad.push(format!("{path} --{}", a.get_id()));
                }
            }
            for s in cmd.get_subcommands() {
                walk(s, &format!("{path} {}", s.get_name()), numeric, bad);
            }
        }
        let mut bad = Vec::new();
        walk(&super::command(), "compgate", &numeric, &mut bad);
        assert!(bad.is_empty(), "no allow_negative_numbers: {bad:?}");
    }
}
