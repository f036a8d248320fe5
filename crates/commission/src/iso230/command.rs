//! `compgate iso230` on the command line: the measurements in, the report out.

use std::path::PathBuf;

use compgate_core::measure::Measurements;

use super::{evaluate, report, Iso230Error};

/// `compgate iso230` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct Iso230Args {
    /// Measured-error CSV (t_s,pos_mm,err_um,T_...; dir recommended).
    #[arg(long)]
    pub data: PathBuf,
}

/// Runs the command.
pub fn run(args: &Iso230Args) -> Result<String, Iso230Error> {
    let m = Measurements::read_path(&args.data)
        .map_err(|e| Iso230Error::Data(args.data.display().to_string(), e))?;
    Ok(report(&evaluate(&m.pos_mm, &m.dir, &m.err_um)?))
}
