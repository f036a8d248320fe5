//! The `compgate` binary: command line -> tracing -> command.

#[cfg(feature = "sim")]
mod demo;

use std::process::ExitCode;

use compgate::cli::{self, Command, ConfigCommand};
#[cfg(feature = "sim")]
use compgate::scenario;
use compgate_commission::{backlash, calibrate, iso230, volumetric};
use compgate_gateway::config;

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
        eprintln!(
            "error: give a command (see --help); this build has no simulated plant for the demo"
        );
        return ExitCode::FAILURE;
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
        Ok(rt) => rt.block_on(run(cli.log, command)),
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            ExitCode::FAILURE
        }
    }
}

async fn run(log: Option<String>, command: Command) -> ExitCode {
    #[cfg(feature = "sim")]
    let default_log = if matches!(command, Command::Demo(_)) {
        "warn"
    } else {
        "info"
    };
    #[cfg(not(feature = "sim"))]
    let default_log = "info";
    compgate_service::init_tracing(log.as_deref(), default_log);

    let result = match command {
        #[cfg(feature = "sim")]
        Command::Demo(args) => demo::demo(&args).await,
        Command::Run {
            config: path,
            shadow,
        } => match config::load(&path) {
            Ok(cfg) => {
                for w in config::warnings(&cfg, &path.display().to_string()) {
                    tracing::warn!(file = %w.file, key = %w.key, "{}", w.message);
                }
                compgate_service::run(&path, cfg, compgate_service::RunOptions { shadow })
                    .await
                    .map_err(|e| e.to_string())
            }
            Err(e) => Err(e.to_string()),
        },
        Command::Nc(args) => compgate::nc::run(&args).await,
        Command::Validate { config: path } => match config::load(&path) {
            Ok(cfg) => {
                for w in config::warnings(&cfg, &path.display().to_string()) {
                    eprintln!("warning: {w}");
                }
                println!("{}: OK", path.display());
                Ok(())
            }
            Err(e) => Err(e.to_string()),
        },
        #[cfg(feature = "sim")]
        Command::Sim { config: path } => demo::sim(&path).await,
        Command::Probe(args) => match compgate::probe::run(&args).await {
            Ok(report) => {
                print!("{}", report.text);
                match report.bad.len() {
                    0 => Ok(()),
                    n => Err(format!(
                        "{n} channel{} bad: {}",
                        if n == 1 { "" } else { "s" },
                        report.bad.join(", ")
                    )),
                }
            }
            Err(e) => Err(e),
        },
        Command::Config(ConfigCommand::Example) => config::example::annotated_example()
            .map(|text| print!("{text}"))
            .map_err(|e| e.to_string()),
        Command::Config(ConfigCommand::Schema) => {
            match serde_json::to_string_pretty(&config::json_schema()) {
                Ok(text) => {
                    println!("{text}");
                    Ok(())
                }
                Err(e) => Err(e.to_string()),
            }
        }
        Command::Backlash(args) => match run_backlash(&args).await {
            Ok(report) => {
                print!("{report}");
                Ok(())
            }
            Err(e) => Err(e.to_string()),
        },
        Command::Volumetric(args) => match volumetric::run(&args) {
            Ok(report) => {
                print!("{report}");
                Ok(())
            }
            Err(e) => Err(e.to_string()),
        },
        Command::Calibrate(args) => calibrate::run(&args)
            .map(|report| print!("{report}"))
            .map_err(|e| e.to_string()),
        #[cfg(feature = "sim")]
        Command::Scenario(args) => match scenario::run(&args).await {
            Ok(report) => {
                print!("{}", report.text());
                println!("written to {}", args.out.display());
                Ok(())
            }
            Err(e) => Err(e.to_string()),
        },
        Command::Iso230(args) => iso230::run(&args)
            .map(|report| print!("{report}"))
            .map_err(|e| e.to_string()),
        Command::Export(args) => match compgate_service::record::export::run(&args) {
            Ok(summary) => {
                for n in &summary.notes {
                    eprintln!("note: {n}");
                }
                eprintln!(
                    "{} rows, channels: {}",
                    summary.rows,
                    summary.channels.join(", ")
                );
                Ok(())
            }
            Err(e) => Err(e.to_string()),
        },
        Command::Diagnose(args) => {
            compgate_commission::diagnose::command::run(&args).map_err(|e| e.to_string())
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
