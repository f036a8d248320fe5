//! `compgate nc read` and `compgate nc write`: the first look at a real control and the
//! first dry-run write, through the same guarded writer the gateway uses.

use std::io::{BufRead, IsTerminal};
use std::path::{Path, PathBuf};

use clap::{ArgGroup, Args, Subcommand};

use crate::cli::{self, OutputError};
use compgate_gateway::config::{self, Config};
use compgate_gateway::nc::{
    number, shown, shown_mm, thermal_limit, var, var_name, Guarded, Job, NcSnapshot, NcWriter,
    StopSignals,
};

/// `compgate nc`: read or write an axis's compensation values on its target.
#[derive(Debug, Args)]
pub struct NcArgs {
    /// What to do.
    #[command(subcommand)]
    pub command: NcCommand,
}

/// `compgate nc` subcommands.
#[derive(Debug, Subcommand)]
pub enum NcCommand {
    /// Connect and print each axis's SD43900/43910/43920 as the target holds them now.
    Read {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: PathBuf,
        /// Only the axes on this target.
        #[arg(long)]
        target: Option<String>,
    },
    /// Show the change (old -> new) and write it once after confirmation. At least one
    /// of --k0-mm, --tan-beta, --p0-mm; the values not given stay as they are.
    #[command(group(ArgGroup::new("values").required(true).multiple(true)))]
    Write {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: PathBuf,
        /// The axis (a name in `[axes]`).
        #[arg(long)]
        axis: String,
        /// New SD43900 (K0), mm; unchanged when omitted.
        #[arg(long, allow_negative_numbers = true, group = "values")]
        k0_mm: Option<f64>,
        /// New SD43910 (tan(beta)), mm/mm; unchanged when omitted.
        #[arg(long, allow_negative_numbers = true, group = "values")]
        tan_beta: Option<f64>,
        /// New SD43920 (P0), mm; unchanged when omitted.
        #[arg(long, allow_negative_numbers = true, group = "values")]
        p0_mm: Option<f64>,
        /// Write without asking (required when standard input is not a terminal).
        #[arg(long)]
        yes: bool,
    },
}

/// Why `compgate nc` failed.
#[derive(Debug, thiserror::Error)]
pub enum NcError {
    /// The command's own error, worded for the operator.
    #[error("{0}")]
    Failed(String),
    /// Its text could not be written: kept apart so that a closed pipe ends quietly.
    #[error(transparent)]
    Output(#[from] OutputError),
}

impl From<String> for NcError {
    fn from(message: String) -> Self {
        NcError::Failed(message)
    }
}

/// Runs `compgate nc`; the text is printed as it goes.
pub async fn run(args: &NcArgs) -> Result<(), NcError> {
    match &args.command {
        NcCommand::Read { config, target } => read(&load(config)?, target.as_deref()).await,
        NcCommand::Write {
            config,
            axis,
            k0_mm,
            tan_beta,
            p0_mm,
            yes,
        } => {
            let cfg = load(config)?;
            let change = [
                (var::SD43900, *k0_mm),
                (var::SD43910, *tan_beta),
                (var::SD43920, *p0_mm),
            ];
            write(&cfg, axis, &change, *yes).await
        }
    }
}

fn load(path: &Path) -> Result<Config, String> {
    config::load(path).map_err(|e| e.to_string())
}

/// The guarded writer of `axis`, and a line naming it.
fn writer(cfg: &Config, axis: &str) -> Result<(Guarded, String), String> {
    let ax = cfg.axes.get(axis).ok_or_else(|| {
        let names: Vec<&str> = cfg.axes.keys().map(String::as_str).collect();
        format!(
            "no axis `{axis}` in [axes]; there are: {}",
            names.join(", ")
        )
    })?;
    let target = cfg
        .target(&ax.nc_module)
        .ok_or_else(|| format!("axes.{axis}.nc_module: no target `{}`", ax.nc_module))?;
    let w = target
        .build(axis, ax.axis_number.unwrap_or(0))
        .map_err(|e| format!("axes.{axis}: {e}"))?;
    let label = match ax.axis_number {
        Some(n) => format!(
            "axis {axis} (axis {n} on target {}, kind = {})",
            ax.nc_module,
            target.kind().name()
        ),
        None => format!(
            "axis {axis} (target {}, kind = {})",
            ax.nc_module,
            target.kind().name()
        ),
    };
    Ok((
        Guarded::new(w, ax.nc_write_ids(), target.job_timeout()),
        label,
    ))
}

fn values(s: &NcSnapshot) -> String {
    format!(
        "SD43900 = {} mm, SD43910 = {}, SD43920 = {} mm",
        shown_mm(s.sd43900_mm),
        shown(var::SD43910, s.sd43910),
        shown_mm(s.sd43920_mm)
    )
}

async fn read(cfg: &Config, target: Option<&str>) -> Result<(), NcError> {
    if let Some(t) = target {
        if cfg.target(t).is_none() {
            return Err(format!("no target `{t}` in [targets] or [nc_modules]").into());
        }
    }
    let mut failed = 0;
    let mut shown = 0;
    for (name, ax) in &cfg.axes {
        if target.is_some_and(|t| t != ax.nc_module) {
            continue;
        }
        shown += 1;
        let (mut w, label) = writer(cfg, name)?;
        match w.read_snapshot().await {
            Ok(s) => {
                cli::print(format_args!("{label}: {}\n", values(&s)))?;
                // A target that reports the axis state (the NC module, an S7 block)
                // reports all of it.
                if let (Some(md32750), Some(referenced)) = (s.md32750, s.referenced) {
                    cli::print(format_args!(
                        "  MD32750 = {md32750}, referenced = {referenced}, applied compensation = {} mm\n",
                        s.applied_comp_mm.map_or_else(|| "-".to_string(), shown_mm)
                    ))?;
                    // The same facts that hold the gateway and refuse `nc write`.
                    if md32750 != ax.md32750 {
                        cli::print(format_args!(
                            "  warning: axes.{name}.md32750 expects {}: the gateway holds this \
                             axis and `nc write` refuses until MD32750 on the control or the \
                             config is corrected (bit 0: K0, bit 1: slope)\n",
                            ax.md32750
                        ))?;
                    }
                    if !referenced {
                        cli::print(
                            "  warning: the axis is not referenced: the NC applies no \
                             temperature compensation until it is\n",
                        )?;
                    }
                }
                match w.may_write().await {
                    Ok(Some(true)) => cli::print("  this session may write them\n")?,
                    Ok(Some(false)) => cli::print("  this session may NOT write them\n")?,
                    Ok(None) => {}
                    Err(e) => cli::print(format_args!("  write access unknown: {e}\n"))?,
                }
            }
            Err(e) => {
                failed += 1;
                cli::print(format_args!("{label}: {e}\n"))?;
            }
        }
        w.close().await;
    }
    if shown == 0 {
        return Err(String::from("no axis to read").into());
    }
    if failed > 0 {
        return Err(format!("{failed} of {shown} axes could not be read").into());
    }
    Ok(())
}

async fn write(
    cfg: &Config,
    axis: &str,
    change: &[(u16, Option<f64>)],
    yes: bool,
) -> Result<(), NcError> {
    let (mut w, label) = writer(cfg, axis)?;
    let result = write_with(&mut w, &label, cfg, axis, change, yes).await;
    w.close().await;
    result
}

async fn write_with(
    w: &mut Guarded,
    label: &str,
    cfg: &Config,
    axis: &str,
    change: &[(u16, Option<f64>)],
    yes: bool,
) -> Result<(), NcError> {
    let ax = &cfg.axes[axis];
    let mut job = Job { pairs: Vec::new() };
    // The axis's own limits hold for a value typed by hand too; P0 has the range of
    // axes.NAME.p0_mm, which is the NC's own limit of SD43920.
    for &(v, value) in change {
        let Some(x) = value else { continue };
        let (flag, max, unit, whose) = match v {
            var::SD43900 => (
                "--k0-mm",
                ax.max_abs_k0_mm,
                " mm",
                format!("axes.{axis}.max_abs_k0_mm"),
            ),
            var::SD43910 => (
                "--tan-beta",
                ax.max_abs_tan_beta,
                "",
                format!("axes.{axis}.max_abs_tan_beta"),
            ),
            _ => (
                "--p0-mm",
                thermal_limit(var::SD43920).unwrap_or(0.0),
                " mm",
                format!("the range of axes.{axis}.p0_mm and the NC's limit of SD43920"),
            ),
        };
        if !x.is_finite() {
            return Err(format!("{flag} {x}: not a finite number; nothing was written").into());
        }
        if x.abs() > max {
            return Err(format!(
                "{flag} {}: beyond the limit of {}{unit} ({whose}); nothing was written",
                number(x),
                number(max)
            )
            .into());
        }
        job.pairs.push((v, x));
    }
    // The allow-list too, before anything is read or shown as a planned change.
    w.check(&job)
        .map_err(|e| format!("{label}: {e} (axes.{axis}.nc_write)"))?;
    let old = w
        .read_snapshot()
        .await
        .map_err(|e| format!("{label}: {e}"))?;
    if let Some(md32750) = old.md32750.filter(|&m| m != ax.md32750) {
        return Err(format!(
            "{label}: MD32750 is {md32750} on the NC, axes.{axis}.md32750 expects {}: the NC \
             would apply another part of the model than the config computes (bit 0: K0, \
             bit 1: slope); correct MD32750 on the control or axes.{axis}.md32750; nothing \
             was written",
            ax.md32750
        )
        .into());
    }
    if old.referenced == Some(false) {
        cli::eprintln(format_args!(
            "warning: {label}: the axis is not referenced: the NC applies no temperature \
             compensation until it is; a value written now takes effect then"
        ))?;
    }
    let held = |v: u16| match v {
        var::SD43900 => old.sd43900_mm,
        var::SD43910 => old.sd43910,
        _ => old.sd43920_mm,
    };
    cli::print(format_args!("{label}:\n"))?;
    for &(v, x) in &job.pairs {
        cli::print(format_args!(
            "  {}: {} -> {}\n",
            var_name(v),
            shown(v, held(v)),
            // As typed: a value finer than what `shown` keeps is not shown as another.
            number(x)
        ))?;
    }
    if !yes {
        // A script that forgot --yes must not read a "no" into the prompt and succeed.
        if !std::io::stdin().is_terminal() {
            return Err(String::from(
                "standard input is not a terminal, so nobody can answer the question: \
                 pass --yes to write without asking; nothing was written",
            )
            .into());
        }
        cli::print("write? [y/N] ")?;
        let mut answer = String::new();
        std::io::stdin()
            .lock()
            .read_line(&mut answer)
            .map_err(|e| e.to_string())?;
        if !matches!(answer.trim(), "y" | "Y" | "yes") {
            cli::print("nothing written\n")?;
            return Ok(());
        }
    }
    // A signal once the job is under way waits for its outcome (at most the job
    // timeout): ended mid-job, nobody would know whether the values landed.
    let mut stop = StopSignals::register();
    let job_run = w.write_job(&job);
    tokio::pin!(job_run);
    // Biased to the signal: one that came while the job ran is reported even when the
    // job's answer is read in the same turn.
    let result = tokio::select! {
        biased;
        signal = stop.recv() => {
            cli::eprintln(format_args!(
                "{label}: {signal}: the job is under way; stopping once its outcome is known"
            ))?;
            job_run.await
        }
        r = &mut job_run => r,
    };
    let report = result.map_err(|e| format!("{label}: {e}"))?;
    cli::print(format_args!(
        "written and read back in {:.1} ms\n",
        report.elapsed.as_secs_f64() * 1e3
    ))?;
    // Nothing here can see a running gateway: say what it would do with the value.
    cli::print(format_args!(
        "note: a compgate service that compensates axis {axis} takes this as what the NC \
         holds, logs that it changed, and from its next update moves it back to its own \
         value by at most max_step_k0_mm per update_interval_s (a value within \
         deadband_k0_mm of its own stays); stop the service, or give the axis \
         `shadow = true`, to keep it\n"
    ))?;
    Ok(())
}
