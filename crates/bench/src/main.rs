//! `compgate-bench`: the benchmarks of compgate, kept out of the production binary.
//!
//! - `cycle`: full poll-filter-compute cycles against the bare Modbus request rate.
//! - `soak`: the `compgate` binary as a real process against simulated field modules,
//!   with recording, metrics and MQTT on; CPU and RSS over time.
//! - `nc`: NC job latency per target kind against its peer (p50/p99).
//! - `nc-s7`: job latency of the S7 data-block target against its test peer.

mod cycle;
mod nc;
mod nc_s7;
mod soak;
mod volumetric;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// compgate's benchmarks.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Measure poll-filter-compute cycles against the bare Modbus request rate.
    Cycle {
        /// Channels on the simulated module, read in one request.
        #[arg(long, default_value_t = 64)]
        channels: u16,
        /// Measured cycles per round.
        #[arg(long, default_value_t = 2000)]
        cycles: u32,
        /// Alternating rounds of gateway and bare measurements (many short rounds: the
        /// median then outvotes bursts of load from other processes).
        #[arg(long, default_value_t = 15)]
        rounds: u32,
    },
    /// Soak the real gateway process (8 devices x 64 channels at 10 Hz, recording,
    /// metrics and MQTT on) and report CPU and RSS.
    Soak {
        /// How long, in seconds (at least 10).
        #[arg(long)]
        seconds: f64,
        /// The `compgate` binary to soak; by default the one beside this binary.
        #[arg(long)]
        compgate: Option<PathBuf>,
    },
    /// NC job latency (write + verified read-back) per target kind against its peer.
    Nc {
        /// Measured jobs per kind.
        #[arg(long, default_value_t = 1000)]
        jobs: usize,
        /// Python interpreter of the peers; default target/peers-venv/bin/python.
        #[arg(long)]
        python: Option<PathBuf>,
    },
    /// Job latency (REQ to verified read-back) of the S7 data-block target against
    /// its peer, python-snap7 from target/peers-venv (tests/peers/install.sh).
    NcS7 {
        /// Measured jobs per value type.
        #[arg(long, default_value_t = 200)]
        jobs: u32,
        /// Scan cycle of the simulated PLC program, ms.
        #[arg(long, default_value_t = 1.0)]
        plc_cycle_ms: f64,
    },
}

/// The `compgate` binary that cargo built beside this one.
fn sibling_compgate() -> Result<PathBuf, String> {
    let exe = std::env::current_exe().map_err(|e| format!("own binary: {e}"))?;
    let path = exe.with_file_name("compgate");
    if path.is_file() {
        Ok(path)
    } else {
        Err(format!(
            "no compgate binary at {} (build it first: cargo build --release), or give --compgate",
            path.display()
        ))
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Cycle {
            channels,
            cycles,
            rounds,
        } => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .map_err(|e| format!("cannot start the async runtime: {e}"))
            .and_then(|rt| {
                rt.block_on(cycle::run(channels, cycles, rounds))
                    .map_err(|e| e.to_string())
            })
            .map(|report| {
                print!("{}", report.table());
                println!();
                print!("{}", cycle::volumetric_line(2.0));
            }),
        Command::Soak { seconds, compgate } => compgate
            .map_or_else(sibling_compgate, Ok)
            .and_then(|exe| soak::run(seconds, &exe))
            .map(|report| print!("{report}")),
        Command::Nc { jobs, python } => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .map_err(|e| format!("cannot start the async runtime: {e}"))
            .and_then(|rt| rt.block_on(nc::run(jobs, python)))
            .map(|outcomes| print!("{}", nc::table(&outcomes))),
        Command::NcS7 { jobs, plc_cycle_ms } => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .map_err(|e| format!("cannot start the async runtime: {e}"))
            .and_then(|rt| {
                ["real", "lreal"].into_iter().try_for_each(|t| {
                    rt.block_on(nc_s7::run(jobs, t, plc_cycle_ms))
                        .map(|r| println!("{}", r.line()))
                })
            }),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
