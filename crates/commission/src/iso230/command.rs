//! `compgate iso230` on the command line: the measurements in, the report out.

use std::path::PathBuf;

use compgate_core::measure::{MeasureError, Measurements};

use crate::args::check_f64;

use super::{evaluate_lines, report, Grouping, Iso230Error};

/// `compgate iso230` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct Iso230Args {
    /// Measured-error CSV (t_s,pos_mm,dir,err_um,T_...; dir required: +1 approached
    /// upwards, -1 downwards).
    #[arg(long)]
    pub data: PathBuf,
    /// The nominal target positions, mm, comma-separated; each row is taken by the
    /// nearest within the tolerance. Default: targets found by clustering.
    // Hyphen values, not only negative numbers: `-500,0,500` is no number to clap.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub targets: Vec<f64>,
    /// How far a recorded position may lie from its target (with --targets) or from
    /// its neighbour in the same cluster (without), mm.
    #[arg(long, allow_negative_numbers = true, default_value_t = super::DEFAULT_TOLERANCE_MM)]
    pub target_tolerance_mm: f64,
}

/// Runs the command.
pub fn run(args: &Iso230Args) -> Result<String, Iso230Error> {
    // Checked before the file is read: a bad flag is the user's first fix.
    let grouping = Grouping {
        targets_mm: args
            .targets
            .iter()
            .map(|&t| check_f64("--targets", t, -1e9, 1e9, "mm"))
            .collect::<Result<_, _>>()?,
        tolerance_mm: check_f64(
            "--target-tolerance-mm",
            args.target_tolerance_mm,
            1e-9,
            1e3,
            "mm",
        )?,
    };
    let (m, lines) = Measurements::read_positions_path(&args.data).map_err(|e| match e {
        // The reader's own error names the file already.
        MeasureError::Io { path, source } => Iso230Error::Io { path, source },
        e => Iso230Error::Data(args.data.display().to_string(), e),
    })?;
    Ok(report(&evaluate_lines(
        &m.pos_mm, &m.dir, &m.err_um, &grouping, &lines,
    )?))
}
