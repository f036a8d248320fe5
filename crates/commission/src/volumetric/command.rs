//! `compgate volumetric` on the command line: arguments, the grid specification, the
//! error file in and the report and maps out.

use std::fmt::Write as _;
use std::path::PathBuf;

use clap::builder::PossibleValue;

use super::evaluation::evaluate_pole;
use super::kinematics::{Pole, PoleMode, VolumetricCompensator};
use super::report::{report, write_svgs};
use super::{parse, VolumetricError, AXES};

/// `--pole hold|swing`; implemented here so that the kinematics stay free of clap.
impl clap::ValueEnum for PoleMode {
    fn value_variants<'a>() -> &'a [Self] {
        &[PoleMode::Hold, PoleMode::Swing]
    }

    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(match self {
            PoleMode::Hold => {
                PossibleValue::new("hold").help("C is not corrected near A = 0 (safe online)")
            }
            PoleMode::Swing => PossibleValue::new("swing")
                .help("solve for the drive positions even if C must swing"),
        })
    }
}

/// Arguments of `compgate volumetric`.
#[derive(Debug, Clone, clap::Args)]
pub struct VolumetricArgs {
    /// Error parameter file (format: `compgate-volumetric-errors 1`).
    #[arg(long, value_name = "FILE")]
    pub errors: PathBuf,
    /// Evaluation grid: a count of points per axis over its travel (e.g. `4`), or
    /// per-axis ranges `X=0:1000:5,A=-90:90:4` (start:end:count; axes not named get 3
    /// points over their travel).
    #[arg(long, default_value = "4")]
    pub grid: String,
    /// Directory for the SVG error maps (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Within 1 deg of A = 0 (the pole): `hold` leaves C alone (safe online), `swing`
    /// solves for the drive positions even if C must swing.
    #[arg(long, value_enum, default_value_t = PoleMode::Hold)]
    pub pole: PoleMode,
    /// Largest C move a pole swing may make, deg (beyond it Hold is kept).
    #[arg(long = "max-c-swing", value_name = "DEG", default_value_t = 180.0)]
    pub max_c_swing_deg: f64,
}

/// Grid axes: the values of each of the five axes.
pub fn parse_grid(spec: &str, travel: &[(f64, f64); 5]) -> Result<[Vec<f64>; 5], VolumetricError> {
    let lin = |lo: f64, hi: f64, n: usize| -> Vec<f64> {
        if n == 1 {
            vec![(lo + hi) / 2.0]
        } else {
            (0..n)
                .map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64)
                .collect()
        }
    };
    let count = |s: &str| -> Result<usize, VolumetricError> {
        match s.trim().parse::<usize>() {
            Ok(n) if (1..=1000).contains(&n) => Ok(n),
            _ => Err(VolumetricError::Grid(format!("bad count {s:?} (1..=1000)"))),
        }
    };
    let spec = spec.trim();
    if !spec.contains('=') {
        let n = count(spec)?;
        return Ok(std::array::from_fn(|i| lin(travel[i].0, travel[i].1, n)));
    }
    let mut out: [Option<Vec<f64>>; 5] = Default::default();
    for part in spec.split(',') {
        let (name, range) = part.split_once('=').ok_or_else(|| {
            VolumetricError::Grid(format!("expected AXIS=start:end:count, got {part:?}"))
        })?;
        let i = AXES
            .iter()
            .position(|a| a.eq_ignore_ascii_case(name.trim()))
            .ok_or_else(|| VolumetricError::Grid(format!("unknown axis {name:?}")))?;
        let f: Vec<&str> = range.split(':').collect();
        if f.len() != 3 {
            return Err(VolumetricError::Grid(format!(
                "{name}: expected start:end:count, got {range:?}"
            )));
        }
        let num = |s: &str| {
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| VolumetricError::Grid(format!("{name}: not a number {s:?}")))
        };
        let (lo, hi, n) = (num(f[0])?, num(f[1])?, count(f[2])?);
        let (tlo, thi) = travel[i];
        if lo < tlo || hi > thi || lo > hi {
            return Err(VolumetricError::Grid(format!(
                "{name}: {lo}..{hi} outside the travel {tlo}..{thi}"
            )));
        }
        out[i] = Some(lin(lo, hi, n));
    }
    Ok(std::array::from_fn(|i| {
        out[i]
            .take()
            .unwrap_or_else(|| lin(travel[i].0, travel[i].1, 3))
    }))
}

/// `compgate volumetric`: reads the error file, evaluates the grid uncompensated and
/// compensated, writes the SVG maps with `--out`, and returns the report.
pub fn run(args: &VolumetricArgs) -> Result<String, VolumetricError> {
    let text = std::fs::read_to_string(&args.errors)
        .map_err(|e| VolumetricError::Io(format!("{}: {e}", args.errors.display())))?;
    let model = parse(&text).map_err(|e| match e {
        VolumetricError::Parse {
            line,
            field,
            message,
        } => VolumetricError::Parse {
            line,
            field: format!("{}: {field}", args.errors.display()),
            message,
        },
        other => other,
    })?;
    let grid = parse_grid(&args.grid, &model.travel)?;
    let comp = VolumetricCompensator::new(model);
    let pole = Pole {
        mode: args.pole,
        max_c_swing_deg: args.max_c_swing_deg,
    };
    if !(pole.max_c_swing_deg >= 0.0 && pole.max_c_swing_deg.is_finite()) {
        return Err(VolumetricError::Grid(format!(
            "--max-c-swing: {} deg is not a finite angle >= 0",
            pole.max_c_swing_deg
        )));
    }
    let ev = evaluate_pole(&comp, &grid, &pole);
    let mut s = report(&ev);
    if let Some(dir) = &args.out {
        for p in write_svgs(dir, &ev)? {
            let _ = writeln!(s, "wrote {}", p.display());
        }
    }
    Ok(s)
}
