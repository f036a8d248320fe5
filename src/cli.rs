//! The command line.

use std::path::PathBuf;

use clap::{Parser, Subcommand};

/// compgate: thermal compensation gateway for CNC machine tools.
///
/// Without a command it runs the gateway against an embedded simulated plant (field
/// I/O module and NC axis module on loopback), as a demonstration.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
pub struct Cli {
    /// Log filter (tracing EnvFilter syntax), e.g. "info" or "compgate=debug".
    /// Defaults to RUST_LOG, else "info" ("warn" for the demo, to keep the status line clean).
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
    },
    /// Check a configuration and print every problem with its key and file.
    Validate {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: PathBuf,
    },
    /// Run only the simulated plant on the addresses the config names.
    Sim {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: PathBuf,
    },
    /// Run the gateway against the embedded simulated plant (the default).
    Demo,
    /// Measure reversal backlash of a full-closed-loop axis from encoder vs scale trace.
    Backlash(crate::backlash::BacklashArgs),
    /// Evaluate volumetric compensation of a 5-axis AC-head machine over a workspace grid.
    Volumetric(crate::volumetric::VolumetricArgs),
    /// Fit K0(T) and tan(beta)(T) to measured error curves and write the axis model.
    Calibrate(crate::calibrate::CalibrateArgs),
    /// Thermal test of the simulated machine with the gateway in the loop, off vs on.
    Scenario(crate::scenario::ScenarioArgs),
    /// ISO 230-2 evaluation (A, B, R, E, M) of bidirectional runs in a measurement CSV.
    Iso230(crate::iso230::Iso230Args),
    /// Write recorded operation as the measurement CSV that calibrate and diagnose read.
    Export(crate::record::export::ExportArgs),
    /// Find where model and measurement disagree, name the missing effect, add it.
    Diagnose(crate::diagnose::command::DiagnoseArgs),
    /// Measure poll-filter-compute cycles against the bare Modbus request rate.
    Bench {
        /// Channels on the simulated module, read in one request.
        #[arg(long, default_value_t = 64)]
        channels: u16,
        /// Measured cycles per round.
        #[arg(long, default_value_t = 2000)]
        cycles: u32,
        /// Alternating rounds of gateway and bare measurements (many short rounds: the median then outvotes bursts of load from other processes)
        #[arg(long, default_value_t = 15)]
        rounds: u32,
        /// Instead: soak the real gateway process for this many seconds (8 devices x
        /// 64 channels at 10 Hz, recording, metrics and MQTT on) and report CPU and RSS.
        #[arg(long)]
        soak: Option<f64>,
    },
}
