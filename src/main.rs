//! The `compgate` binary: command line -> tracing -> command.

use std::io::IsTerminal;
use std::process::ExitCode;

use clap::Parser;
use compgate::cli::{Cli, Command};
use compgate::plant::{Bind, Plant};
use compgate::{backlash, bench, calibrate, config, gateway, iso230, scenario, status, volumetric};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

/// The demo's configuration, embedded so `cargo run --release` needs no file.
const DEMO_CONFIG: &str = include_str!("../config/demo.toml");

/// Cancels the token on Ctrl-C or SIGTERM.
fn shutdown_on_signals() -> CancellationToken {
    let token = CancellationToken::new();
    let t = token.clone();
    tokio::spawn(async move {
        let ctrl_c = tokio::signal::ctrl_c();
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(s) => s,
                Err(e) => {
                    tracing::error!(error = %e, "cannot watch SIGTERM");
                    let _ = ctrl_c.await;
                    t.cancel();
                    return;
                }
            };
        tokio::select! {
            _ = ctrl_c => tracing::info!("Ctrl-C: stopping"),
            _ = term.recv() => tracing::info!("SIGTERM: stopping"),
        }
        t.cancel();
    });
    token
}

/// Runs the gateway on `cfg` with the status printer until a signal.
async fn run_gateway(cfg: &config::Config) -> Result<(), String> {
    let shutdown = shutdown_on_signals();
    let (tx, rx) = watch::channel(gateway::Status::default());
    let interval = std::time::Duration::from_secs_f64(cfg.gateway.status_interval_s);
    let printer = tokio::spawn(status::print_loop(
        rx,
        interval,
        std::io::stdout().is_terminal(),
        shutdown.clone(),
    ));
    let result = gateway::run(cfg, shutdown.clone(), tx).await;
    shutdown.cancel();
    let _ = printer.await;
    result.map_err(|e| e.to_string())
}

async fn demo() -> Result<(), String> {
    let cfg =
        config::load_str(DEMO_CONFIG, "config/demo.toml (embedded)").map_err(|e| e.to_string())?;
    let plant = Plant::start(&cfg, Bind::Ephemeral)
        .await
        .map_err(|e| e.to_string())?;
    eprintln!(
        "compgate demo: simulated field module and NC axis module on loopback; Ctrl-C stops."
    );
    run_gateway(&plant.config).await
}

async fn sim(path: &std::path::Path) -> Result<(), String> {
    let cfg = config::load(path).map_err(|e| e.to_string())?;
    let plant = Plant::start(&cfg, Bind::AsConfigured)
        .await
        .map_err(|e| e.to_string())?;
    for (name, d) in &plant.config.devices {
        if let (Some(interface), Some(node)) = (&d.interface, d.node_id) {
            println!("CANopen node {name}: {interface} node {node}");
            continue;
        }
        let at = d
            .address
            .as_deref()
            .or(d.serial_path.as_deref())
            .unwrap_or("-");
        println!(
            "field module {name}: {at} (unit {})",
            d.unit_id.unwrap_or_default()
        );
    }
    for (name, m) in &plant.config.nc_modules {
        println!("NC axis module {name}: {}", m.address);
    }
    println!("simulated plant running; Ctrl-C stops.");
    shutdown_on_signals().cancelled().await;
    drop(plant);
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let command = cli.command.unwrap_or(Command::Demo);
    let mut runtime = tokio::runtime::Builder::new_multi_thread();
    if matches!(command, Command::Run { .. }) {
        // The service does little work in many small wake-ups (8 devices at 10 Hz:
        // a timer and a reply each). On one worker they follow each other on one
        // thread; with a worker per core they also wake idle workers to steal work,
        // which cost a fifth of the soak's CPU (1.60 % -> 1.35 % of one core).
        runtime.worker_threads(1);
        // Before any thread exists: per-thread malloc arenas made the service's RSS
        // creep upward with a flat live heap (see `compgate::heap::use_one_arena`).
        compgate::heap::use_one_arena();
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
    let default_log = if matches!(command, Command::Demo) {
        "warn"
    } else {
        "info"
    };
    compgate::service::init_tracing(log.as_deref(), default_log);

    let result = match command {
        Command::Demo => demo().await,
        Command::Run { config: path } => match config::load(&path) {
            Ok(cfg) => compgate::service::run(&path, cfg).await,
            Err(e) => Err(e.to_string()),
        },
        Command::Validate { config: path } => match config::load(&path) {
            Ok(_) => {
                println!("{}: OK", path.display());
                Ok(())
            }
            Err(e) => Err(e.to_string()),
        },
        Command::Sim { config: path } => sim(&path).await,
        Command::Backlash(args) => match backlash::run(&args).await {
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
        Command::Export(args) => match compgate::record::export::run(&args) {
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
            compgate::diagnose::command::run(&args).map_err(|e| e.to_string())
        }
        Command::Bench {
            soak: Some(seconds),
            ..
        } => match tokio::task::spawn_blocking(move || compgate::service::soak::run(seconds)).await
        {
            Ok(Ok(report)) => {
                print!("{report}");
                Ok(())
            }
            Ok(Err(e)) => Err(e),
            Err(e) => Err(e.to_string()),
        },
        Command::Bench {
            channels,
            cycles,
            rounds,
            soak: None,
        } => match bench::run(channels, cycles, rounds).await {
            Ok(report) => {
                print!("{}", report.table());
                println!();
                print!("{}", bench::volumetric_line(2.0));
                Ok(())
            }
            Err(e) => Err(e.to_string()),
        },
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
