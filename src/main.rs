//! The `compgate` binary: command line -> tracing -> command.

#[cfg(feature = "sim")]
mod demo;

use std::io::{self, Write};
use std::process::ExitCode;

use compgate::cli::{self, Command, ConfigCommand, OutputError, EXIT_BROKEN_PIPE};
use compgate::nc::NcError;
#[cfg(feature = "sim")]
use compgate::scenario;
use compgate_commission::{backlash, calibrate, diagnose, iso230, volumetric};
use compgate_gateway::config;
use compgate_service::record::{self, export};

/// Why a command failed.
#[derive(Debug, thiserror::Error)]
enum CommandError {
    /// The command's own error, worded by its layer.
    #[error("{0}")]
    Failed(String),
    /// Its output could not be written.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// Stopped by the signal named before it was done; nothing was written.
    #[cfg(feature = "sim")]
    #[error("stopped by {0}; nothing was written, the files that were there are as before")]
    Interrupted(&'static str),
}

/// The command's error, as the operator reads it.
fn failed(e: impl std::fmt::Display) -> CommandError {
    CommandError::Failed(e.to_string())
}

/// The exit status of a command's `result`, its error reported on stderr. A closed
/// pipe, on stdout or stderr, ends quietly with [`EXIT_BROKEN_PIPE`] (see
/// [`OutputError::is_broken_pipe`]); every other failure is status 1.
fn exit_code(result: Result<(), CommandError>) -> ExitCode {
    let e = match result {
        Ok(()) => return ExitCode::SUCCESS,
        Err(CommandError::Output(e)) if e.is_broken_pipe() => {
            return ExitCode::from(EXIT_BROKEN_PIPE)
        }
        Err(e) => e,
    };
    // 128 + SIGINT, as a shell reports a tool that Ctrl-C ended.
    let code = match e {
        #[cfg(feature = "sim")]
        CommandError::Interrupted(_) => ExitCode::from(130),
        _ => ExitCode::FAILURE,
    };
    match cli::eprintln(format_args!("error: {e}")) {
        Err(e) if e.is_broken_pipe() => ExitCode::from(EXIT_BROKEN_PIPE),
        _ => code,
    }
}

/// A writer that keeps its first error: `Measurements::write` words a CSV
/// writer's error as text, which would hide a closed pipe.
struct KeepError<W> {
    inner: W,
    error: Option<io::Error>,
}

impl<W: Write> Write for KeepError<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.inner.write(buf).map_err(|e| self.keep(e))
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush().map_err(|e| self.keep(e))
    }
}

impl<W> KeepError<W> {
    fn keep(&mut self, e: io::Error) -> io::Error {
        let kind = e.kind();
        self.error.get_or_insert(e);
        kind.into()
    }
}

/// `compgate export`. To stdout it writes the CSV here, not in `export::run`, so
/// that a closed pipe or a full disk are told apart from the export's own errors.
fn run_export(args: &export::ExportArgs) -> Result<(), CommandError> {
    let summary = if args.out.is_some() {
        export::run(args).map_err(failed)?
    } else {
        let mut out = KeepError {
            inner: io::stdout().lock(),
            error: None,
        };
        match export::write_csv(args, &mut out) {
            Ok(summary) => summary,
            Err(e) => {
                return Err(match out.error {
                    Some(io) => OutputError::stdout(io).into(),
                    None => failed(e),
                })
            }
        }
    };
    for n in &summary.notes {
        cli::eprintln(format_args!("note: {n}"))?;
    }
    cli::eprintln(format_args!(
        "{} rows, channels: {}",
        summary.rows,
        summary.channels.join(", ")
    ))?;
    Ok(())
}

/// `compgate backlash`: on `--nc`, or with `--sim` on an in-process simulated axis.
async fn run_backlash(args: &backlash::BacklashArgs) -> Result<String, backlash::BacklashError> {
    if !args.sim {
        return backlash::run(args).await;
    }
    #[cfg(feature = "sim")]
    return demo::backlash(args).await;
    #[cfg(not(feature = "sim"))]
    Err(backlash::BacklashError::Invalid(vec![
        "--sim: this build has no simulator (built without the `sim` feature)".into(),
    ]))
}

fn main() -> ExitCode {
    let cli = cli::parse();
    #[cfg(feature = "sim")]
    let command = cli
        .command
        .unwrap_or(Command::Demo(cli::DemoArgs::default()));
    #[cfg(not(feature = "sim"))]
    let Some(command) = cli.command
    else {
        return exit_code(Err(failed(
            "give a command (see --help); this build has no simulated plant for the demo",
        )));
    };
    let mut runtime = tokio::runtime::Builder::new_multi_thread();
    if matches!(command, Command::Run { .. }) {
        // Both settings stay because the scale benchmark showed a gain at its load
        // points (docs/benchmarks.md, "The runtime settings, measured"): one worker
        // took 2.67-2.77 % of one core at 100k points/s where a worker per core took
        // 3.25-3.29 %; one malloc arena (set before any thread exists) kept RSS about
        // 5 MB lower at 100k and stops the soak's RSS creep
        // (`compgate_service::heap::use_one_arena`).
        runtime.worker_threads(1);
        compgate_service::heap::use_one_arena();
    }
    match runtime.enable_all().build() {
        Ok(rt) => exit_code(rt.block_on(run(cli.log, command))),
        Err(e) => exit_code(Err(failed(format_args!(
            "cannot start the async runtime: {e}"
        )))),
    }
}

async fn run(log: Option<String>, command: Command) -> Result<(), CommandError> {
    #[cfg(feature = "sim")]
    let default_log = if matches!(command, Command::Demo(_)) {
        "warn"
    } else {
        "info"
    };
    #[cfg(not(feature = "sim"))]
    let default_log = "info";
    compgate_service::init_tracing(log.as_deref(), default_log);

    match command {
        #[cfg(feature = "sim")]
        Command::Demo(args) => demo::demo(&args).await,
        Command::Run {
            config: path,
            shadow,
        } => {
            tracing::info!(
                build = env!("COMPGATE_BUILD"),
                config = %path.display(),
                "compgate starting"
            );
            let (cfg, overrides) = config::load_listing_overrides(&path).map_err(failed)?;
            // What the file does not show; names only, as a value may be a password.
            for o in &overrides {
                tracing::info!("environment override: {o}");
            }
            for w in config::warnings(&cfg, &path.display().to_string()) {
                tracing::warn!(file = %w.file, key = %w.key, "{}", w.message);
            }
            compgate_service::run(&path, cfg, compgate_service::RunOptions { shadow })
                .await
                .map_err(failed)
        }
        Command::Nc(args) => compgate::nc::run(&args).await.map_err(|e| match e {
            NcError::Output(e) => e.into(),
            e => failed(e),
        }),
        Command::Validate { config: path } => {
            let (cfg, overrides) = config::load_listing_overrides(&path).map_err(failed)?;
            // What `run` needs of the file system, so that ExecStartPre catches it;
            // the warnings are printed whether it passes or not.
            let mut path_checked = Ok(());
            if let Some(r) = &cfg.recorder {
                let db = record::resolve_path(&r.path);
                path_checked = record::check_path(&db)
                    .map_err(|e| failed(format_args!("{}: {e}", path.display())));
                if let Some(w) = record::outside_state_directory(&db) {
                    cli::eprintln(format_args!(
                        "warning: {}: recorder.path: {w}",
                        path.display()
                    ))?;
                }
            }
            for w in config::warnings(&cfg, &path.display().to_string()) {
                cli::eprintln(format_args!("warning: {w}"))?;
            }
            path_checked?;
            cli::print(format_args!("{}: OK\n", path.display()))?;
            // Names only: a value may be a password.
            for o in &overrides {
                cli::print(format_args!("environment override: {o}\n"))?;
            }
            Ok(())
        }
        #[cfg(feature = "sim")]
        Command::Sim { config: path } => demo::sim(&path).await,
        Command::Probe(args) => {
            let report = compgate::probe::run(&args).await.map_err(failed)?;
            for w in &report.warnings {
                cli::eprintln(format_args!("warning: {w}"))?;
            }
            cli::print(&report.text)?;
            match report.bad.len() {
                0 => Ok(()),
                n => Err(failed(format_args!(
                    "{n} channel{} bad: {}",
                    if n == 1 { "" } else { "s" },
                    report.bad.join(", ")
                ))),
            }
        }
        Command::Config(ConfigCommand::Example) => Ok(cli::print(
            config::example::annotated_example().map_err(failed)?,
        )?),
        Command::Config(ConfigCommand::Schema) => {
            let text = serde_json::to_string_pretty(&config::json_schema()).map_err(failed)?;
            Ok(cli::print(format_args!("{text}\n"))?)
        }
        Command::Backlash(args) => Ok(cli::print(run_backlash(&args).await.map_err(failed)?)?),
        Command::Volumetric(args) => {
            let evaluated = volumetric::run(&args).map_err(failed)?;
            cli::print(&evaluated.report)?;
            evaluated.accepted().map_err(failed)
        }
        Command::Calibrate(args) => {
            let calibrated = calibrate::run(&args).map_err(failed)?;
            cli::print(calibrated.report())?;
            for w in calibrated.warnings() {
                cli::eprintln(format_args!("warning: {w}"))?;
            }
            Ok(cli::print(calibrated.write().map_err(failed)?)?)
        }
        #[cfg(feature = "sim")]
        Command::Scenario(args) => {
            // A run takes minutes. A signal drops it, and with it the staged outputs'
            // temporary files (named after the pid, so left over for good otherwise).
            let mut stop = compgate_gateway::nc::StopSignals::register();
            let made_out = !args.out.exists();
            let report = tokio::select! {
                report = scenario::run(&args) => report.map_err(failed)?,
                signal = stop.recv() => {
                    if made_out {
                        // Empty by now, as it was not there before.
                        let _ = std::fs::remove_dir(&args.out);
                    }
                    return Err(CommandError::Interrupted(signal));
                }
            };
            Ok(cli::print(format_args!(
                "{}written to {}\n",
                report.text(),
                args.out.display()
            ))?)
        }
        Command::Iso230(args) => Ok(cli::print(iso230::run(&args).map_err(failed)?)?),
        Command::Export(args) => run_export(&args),
        Command::Diagnose(args) => {
            let diagnosed = diagnose::command::run(&args).map_err(failed)?;
            cli::print(diagnosed.report())?;
            for p in diagnosed.write_out().map_err(failed)? {
                cli::print(format_args!("wrote {}\n", p.display()))?;
            }
            diagnosed.write_json().map_err(failed)
        }
    }
}
