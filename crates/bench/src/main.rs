//! `compgate-bench`: the benchmarks of compgate, kept out of the production binary.
//!
//! - `cycle`: full poll-filter-compute cycles against the bare Modbus request rate.
//! - `soak`: the `compgate` binary as a real process against simulated field modules,
//!   with recording, metrics and MQTT on; CPU and RSS over time.
//! - `nc`: NC job latency per target kind against its peer (p50/p99).
//! - `scale`: points per second per core at 10k, 100k and 1M points/s, against a
//!   bare tokio-modbus client, and the step-to-NC latency.

mod cycle;
mod nc;
mod scale;
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
        /// Channels on the simulated module, read in one request (3..=125: the axis
        /// reads the first three, one read carries at most 125 registers).
        #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u16).range(3..=125))]
        channels: u16,
        /// Measured cycles per round.
        #[arg(long, default_value_t = 2000, value_parser = clap::value_parser!(u32).range(1..))]
        cycles: u32,
        /// Alternating rounds of gateway and bare measurements (many short rounds: the
        /// median then outvotes bursts of load from other processes).
        #[arg(long, default_value_t = 15, value_parser = clap::value_parser!(u32).range(1..))]
        rounds: u32,
    },
    /// Soak the real gateway process (8 devices x 64 channels at 10 Hz, recording,
    /// metrics and MQTT on) and report CPU and RSS.
    Soak {
        /// How long, in seconds (at least 10).
        #[arg(long, allow_negative_numbers = true)]
        seconds: f64,
        /// The `compgate` binary to soak; by default the one beside this binary.
        #[arg(long)]
        compgate: Option<PathBuf>,
    },
    /// NC job latency (write + verified read-back) per target kind against its peer.
    Nc {
        /// Measured jobs per kind (at least 1).
        #[arg(long, default_value_t = 1000, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
        jobs: usize,
        /// Python interpreter of the peers; default target/peers-venv/bin/python.
        #[arg(long)]
        python: Option<PathBuf>,
        /// The kinds to measure, in this order; all by default.
        #[arg(long, value_enum, value_delimiter = ',')]
        kinds: Vec<nc::Kind>,
        /// Value types of the S7 data block, each measured on its own; lreal by default.
        #[arg(long, value_enum, value_delimiter = ',')]
        s7_types: Vec<nc::S7Type>,
        /// Scan cycle of the S7 peer's PLC program, ms (0..=1000).
        #[arg(long, default_value_t = 1.0, allow_negative_numbers = true)]
        plc_cycle_ms: f64,
    },
    /// The gateway process at 10k, 100k and 1M points/s against simulated field
    /// modules, beside a bare tokio-modbus client: CPU, RSS, jitter, points lost and
    /// the step-to-NC latency.
    Scale {
        /// Measured seconds per client and load point, over all rounds (at least 2
        /// per round).
        #[arg(long, default_value_t = 12.0, allow_negative_numbers = true)]
        seconds: f64,
        /// Rounds per load point, each the gateway then the bare client (1..=20).
        #[arg(long, default_value_t = 3)]
        rounds: usize,
        /// Reply delay of every simulated field module, ms (0..=1000).
        #[arg(long, default_value_t = 1.0, allow_negative_numbers = true)]
        delay_ms: f64,
        /// The gateway's `recorder.interval_s`: seconds between the recorded cycles of
        /// a device (0: every poll).
        #[arg(long, default_value_t = 1.0, allow_negative_numbers = true)]
        record_interval_s: f64,
        /// The load points to run, by name (10k, 100k, 1M); all by default.
        #[arg(long, value_delimiter = ',')]
        loads: Vec<String>,
        /// Also write the figures per load point as JSON to this file (replaced only
        /// once the run has succeeded).
        #[arg(long)]
        json: Option<PathBuf>,
        /// The `compgate` binary; by default the one beside this binary.
        #[arg(long)]
        compgate: Option<PathBuf>,
    },
    /// The bare client of `scale` (started by it): polls and discards.
    #[command(hide = true)]
    ScaleBare {
        /// A field module, host:port; repeat for each.
        #[arg(long)]
        address: Vec<String>,
        /// Poll interval, seconds.
        #[arg(long)]
        interval_s: f64,
        /// Registers read per device, from 0, 125 per request.
        #[arg(long)]
        points: u16,
    },
}

/// A temporary file beside `path` that takes the JSON of `--json` and then its name.
fn json_out(path: &std::path::Path) -> Result<tempfile::NamedTempFile, String> {
    if path.is_dir() {
        return Err(format!("--json {}: is a directory", path.display()));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => std::path::Path::new("."),
    };
    if !dir.is_dir() {
        return Err(format!(
            "--json {}: no directory {}",
            path.display(),
            dir.display()
        ));
    }
    let f = tempfile::NamedTempFile::new_in(dir).map_err(|e| {
        format!(
            "--json {}: cannot write into {} ({})",
            path.display(),
            dir.display(),
            e.kind()
        )
    })?;
    // As `fs::write` would create it, not the temporary file's owner-only mode.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt as _;
        f.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))
            .map_err(|e| format!("--json {}: {e}", path.display()))?;
    }
    Ok(f)
}

/// The `compgate` binary: `--compgate` if given (checked before any run starts),
/// else the one cargo built beside this one.
fn compgate_binary(given: Option<PathBuf>) -> Result<PathBuf, String> {
    match given {
        Some(path) if path.is_file() => Ok(path),
        Some(path) => Err(format!(
            "--compgate {}: no such file (the `compgate` binary to run)",
            path.display()
        )),
        None => sibling_compgate(),
    }
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

fn runtime() -> Result<tokio::runtime::Runtime, String> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start the async runtime: {e}"))
}

/// The options of `scale`, with `--loads` names checked (each once).
fn scale_options(
    seconds: f64,
    rounds: usize,
    delay_ms: f64,
    record_interval_s: f64,
    names: &[String],
    compgate: PathBuf,
) -> Result<scale::Options, String> {
    let loads: Vec<scale::Load> = if names.is_empty() {
        scale::LOADS.to_vec()
    } else {
        names
            .iter()
            .map(|n| {
                scale::LOADS
                    .iter()
                    .find(|l| l.name.eq_ignore_ascii_case(n))
                    .copied()
                    .ok_or_else(|| format!("--loads {n}: not one of 10k, 100k, 1M"))
            })
            .collect::<Result<_, _>>()?
    };
    if let Some((i, l)) = loads
        .iter()
        .enumerate()
        .find(|(i, l)| loads[..*i].iter().any(|m| m.name == l.name))
    {
        return Err(format!(
            "--loads: {} given twice (as load point {})",
            l.name,
            i + 1
        ));
    }
    Ok(scale::Options {
        seconds,
        rounds,
        delay_ms,
        compgate,
        loads,
        record_interval_s,
    })
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Cycle {
            channels,
            cycles,
            rounds,
        } => runtime()
            .and_then(|rt| {
                rt.block_on(cycle::run(channels, cycles, rounds))
                    .map_err(|e| e.to_string())
            })
            .map(|report| {
                print!("{}", report.table());
                println!();
                print!("{}", cycle::volumetric_line(2.0));
            }),
        Command::Soak { seconds, compgate } => compgate_binary(compgate)
            .and_then(|exe| soak::run(seconds, &exe))
            .map(|report| print!("{report}")),
        Command::Nc {
            jobs,
            python,
            kinds,
            s7_types,
            plc_cycle_ms,
        } => {
            let mut opts = nc::Options::new(jobs, python);
            if !kinds.is_empty() {
                opts.kinds = kinds;
            }
            if !s7_types.is_empty() {
                opts.s7_types = s7_types;
            }
            opts.plc_cycle_ms = plc_cycle_ms;
            runtime()
                .and_then(|rt| rt.block_on(nc::run(&opts)))
                .map(|outcomes| print!("{}", nc::table(&outcomes, plc_cycle_ms)))
        }
        Command::Scale {
            seconds,
            rounds,
            delay_ms,
            record_interval_s,
            loads,
            json,
            compgate,
        } => compgate_binary(compgate)
            .and_then(|exe| {
                scale_options(seconds, rounds, delay_ms, record_interval_s, &loads, exe)
            })
            .and_then(|opts| {
                // A JSON file that cannot be written fails now, not after the run; the
                // file a run before wrote stays until this one's is complete.
                let out = json
                    .map(|path| json_out(&path).map(|f| (path, f)))
                    .transpose()?;
                let report = runtime()?.block_on(scale::run(&opts))?;
                print!("{}", report.table());
                match out {
                    Some((path, mut f)) => {
                        use std::io::Write as _;
                        writeln!(f, "{:#}", report.json())
                            .map_err(|e| e.to_string())
                            .and_then(|()| {
                                f.persist(&path).map(drop).map_err(|e| e.error.to_string())
                            })
                            .map_err(|e| format!("--json {}: {e}", path.display()))
                    }
                    None => Ok(()),
                }
            }),
        Command::ScaleBare {
            address,
            interval_s,
            points,
        } => tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| format!("cannot start the async runtime: {e}"))
            .and_then(|rt| rt.block_on(scale::bare_client(address, interval_s, points))),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_loads_are_named_once() {
        let names = |n: &[&str]| n.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let opts =
            scale_options(12.0, 3, 1.0, 1.0, &names(&["1m", "10K"]), "compgate".into()).unwrap();
        let loaded: Vec<_> = opts.loads.iter().map(|l| l.name).collect();
        assert_eq!(loaded, ["1M", "10k"]);
        let e = scale_options(
            12.0,
            3,
            1.0,
            1.0,
            &names(&["10k", "1M", "10K"]),
            "compgate".into(),
        )
        .unwrap_err();
        assert_eq!(e, "--loads: 10k given twice (as load point 3)");
        let e = scale_options(12.0, 3, 1.0, 1.0, &names(&["5k"]), "compgate".into()).unwrap_err();
        assert!(e.contains("--loads 5k"), "{e}");
    }

    #[test]
    fn out_of_range_flags_are_refused_by_name() {
        let parse = |args: &[&str]| {
            Cli::try_parse_from(std::iter::once("compgate-bench").chain(args.iter().copied()))
        };
        for args in [
            &["cycle", "--channels", "2"][..],
            &["cycle", "--channels", "126"],
            &["cycle", "--rounds", "0"],
            &["nc", "--jobs", "0"],
        ] {
            let e = parse(args).unwrap_err().to_string();
            assert!(e.contains(args[1]), "{args:?}: {e}");
        }
        // A negative number is a value, for the command's own range check to name.
        let Command::Scale {
            record_interval_s, ..
        } = parse(&["scale", "--record-interval-s", "-1"])
            .unwrap()
            .command
        else {
            panic!("not scale");
        };
        assert_eq!(record_interval_s, -1.0);
    }

    #[test]
    fn a_missing_compgate_binary_is_named_before_the_run() {
        let e = compgate_binary(Some("/no/such/compgate".into())).unwrap_err();
        assert!(
            e.starts_with("--compgate /no/such/compgate: no such file"),
            "{e}"
        );
    }

    #[test]
    fn the_json_file_is_checked_first_and_replaced_only_when_written() {
        let dir = tempfile::tempdir().unwrap();
        let e = json_out(dir.path()).unwrap_err();
        assert!(e.ends_with("is a directory"), "{e}");
        let e = json_out(&dir.path().join("gone/scale.json")).unwrap_err();
        assert!(e.contains("no directory"), "{e}");

        let path = dir.path().join("scale.json");
        std::fs::write(&path, "the run before\n").unwrap();
        let mut f = json_out(&path).unwrap();
        use std::io::Write as _;
        writeln!(f, "{{}}").unwrap();
        // Until the new figures are complete the old ones are what the file holds.
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "the run before\n");
        f.persist(&path).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "{}\n");
    }
}
