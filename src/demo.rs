//! The commands that run the simulated plant (feature `sim`): the demo, `sim`, and the
//! simulated axis of `backlash --sim`.

use std::io::IsTerminal;

use compgate::cli;
use compgate::plant::{Bind, Plant};
use compgate_commission::backlash;
use compgate_gateway::config::DeviceConfig;
use compgate_gateway::{config, runtime};
use compgate_service::status;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

use crate::{failed, CommandError};

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

/// Runs the gateway on `cfg` with the status printer, and the status page on `http`
/// (unless `off`), until a signal.
async fn run_gateway(cfg: &config::Config, http: &str) -> Result<(), CommandError> {
    let shutdown = shutdown_on_signals();
    let (tx, rx) = watch::channel(runtime::Status::default());
    let mut hooks = runtime::Hooks::default();
    if http != "off" {
        let m = config::MetricsConfig {
            bind: http.to_string(),
            ..config::MetricsConfig::default()
        };
        match compgate_service::http_listener(&m, &rx, cfg.gateway.status_interval()).await {
            Ok(addr) => {
                cli::eprintln(format_args!(
                    "compgate demo: live status page on http://{addr}/"
                ))?;
                hooks.observer = Box::new(compgate_service::metrics::MetricsObserver::new(None));
            }
            Err(e) => cli::eprintln(format_args!(
                "compgate demo: no status page ({e}); see --http"
            ))?,
        }
    }
    let printer = tokio::spawn(status::print_loop(
        rx,
        std::io::stdout().is_terminal(),
        shutdown.clone(),
    ));
    let result = runtime::run_with(cfg, shutdown.clone(), tx, hooks).await;
    shutdown.cancel();
    let _ = printer.await;
    result.map_err(failed)
}

pub async fn demo(args: &cli::DemoArgs) -> Result<(), CommandError> {
    let mut cfg = config::load_str(DEMO_CONFIG, "config/demo.toml (embedded)").map_err(failed)?;
    cfg.gateway.shadow |= args.shadow;
    let plant = Plant::start(&cfg, Bind::Ephemeral).await.map_err(failed)?;
    cli::eprintln(
        "compgate demo: simulated field module and NC axis module on loopback; Ctrl-C stops.",
    )?;
    run_gateway(&plant.config, &args.http).await
}

pub async fn sim(path: &std::path::Path) -> Result<(), CommandError> {
    let cfg = config::load_for_sim(path).map_err(failed)?;
    let plant = Plant::start(&cfg, Bind::AsConfigured)
        .await
        .map_err(failed)?;
    for (name, d) in &plant.config.devices {
        let (at, unit) = match d {
            DeviceConfig::Can(c) => {
                cli::print(format_args!(
                    "CANopen node {name}: {} node {}\n",
                    c.interface, c.node_id
                ))?;
                continue;
            }
            DeviceConfig::Tcp(t) => (&t.address, t.unit_id),
            DeviceConfig::Rtu(r) => (&r.serial_path, r.unit_id),
        };
        cli::print(format_args!("field module {name}: {at} (unit {unit})\n"))?;
    }
    for (name, m) in &plant.config.modbus_targets() {
        cli::print(format_args!("NC axis module {name}: {}\n", m.address))?;
    }
    cli::print("simulated plant running; Ctrl-C stops.\n")?;
    shutdown_on_signals().cancelled().await;
    drop(plant);
    Ok(())
}

/// `compgate backlash --sim`: the test on an in-process simulated axis.
pub async fn backlash(args: &backlash::BacklashArgs) -> Result<String, backlash::BacklashError> {
    backlash::check_args(args)?;
    let (address, _module, shutdown) = compgate::plant::backlash_axis(args).await?;
    let _stop = shutdown.drop_guard();
    let outcome = backlash::run_on(&address, args).await?;
    let note = format!(
        "simulated: backlash {} um, noise {} um, elasticity {} ms",
        args.sim_backlash_um, args.sim_noise_um, args.sim_elastic_ms
    );
    Ok(backlash::report(&args.axis, &outcome, Some(&note)))
}
