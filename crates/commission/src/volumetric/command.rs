//! `compgate volumetric` on the command line: arguments, the grid specification, the
//! error file in and the report and maps out.

use std::fmt::Write as _;
use std::path::PathBuf;

use clap::builder::PossibleValue;

use super::evaluation::evaluate_pole;
use super::kinematics::{Pole, PoleMode, VolumetricCompensator};
use super::report::{report, write_poses_csv, write_svgs, SVG_FILES};
use super::{parse, VolumetricError, AXES, MAX_ONLINE_C_CORRECTION_DEG};

/// `--pole hold|swing`; implemented here so that the kinematics stay free of clap.
impl clap::ValueEnum for PoleMode {
    fn value_variants<'a>() -> &'a [Self] {
        &[PoleMode::Hold, PoleMode::Swing]
    }

    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(match self {
            PoleMode::Hold => PossibleValue::new("hold").help("C is not corrected at the pole"),
            PoleMode::Swing => PossibleValue::new("swing")
                .help("C swings within its travel to the least orientation error"),
        })
    }
}

/// Arguments of `compgate volumetric`.
#[derive(Debug, Clone, clap::Args)]
pub struct VolumetricArgs {
    /// Error parameter file (format: `compgate-volumetric-errors 1`).
    #[arg(long, value_name = "FILE")]
    pub errors: PathBuf,
    /// Evaluation grid: a count of points per axis over its travel (e.g. `4`, at least
    /// 2), or
    /// per-axis ranges `X=0:1000:5,A=-90:90:4` (start:end:count, a count of 1 with
    /// start = end; axes not named get 3 points over their travel). At most 2000000 poses (the product of the five
    /// counts, e.g. `--grid 18`): larger grids are refused.
    #[arg(long, default_value = "4")]
    pub grid: String,
    /// Directory for the SVG error maps (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// What to do in the pole band near A = 0; the help text is `pole_help`, which
    /// states the band from the constants the kinematics use.
    #[arg(long, value_enum, default_value_t = PoleMode::Swing, help = pole_help())]
    pub pole: PoleMode,
    /// Largest C move a pole swing may make, deg (the C travel bounds it too; beyond
    /// it Hold is kept). Set it from C's speed and the time the path spends at the
    /// pole.
    #[arg(
        long = "max-c-swing",
        value_name = "DEG",
        allow_negative_numbers = true,
        default_value_t = 720.0
    )]
    pub max_c_swing_deg: f64,
    /// Per-pose CSV: commanded X Y Z A C, the drive positions, iterations, residual
    /// and uncompensated tip and orientation errors, pole band and floor.
    #[arg(long, value_name = "FILE.csv")]
    pub csv: Option<PathBuf>,
}

/// `--pole`'s help: the band as [`VolumetricCompensator::feedback_at_pole`] draws it,
/// from [`MAX_ONLINE_C_CORRECTION_DEG`].
fn pole_help() -> String {
    format!(
        "In the pole band near A = 0 (where step 1 would move C by more than {} deg; the \
         per-cycle feedback blends towards holding C there and holds it beyond {} deg): \
         `swing` (default) solves for the drive positions that reach the nominal tool \
         axis, or the least error the head allows, with C within its travel; `hold` \
         leaves C alone",
        MAX_ONLINE_C_CORRECTION_DEG / 2.0,
        MAX_ONLINE_C_CORRECTION_DEG
    )
}

/// Largest number of poses (the product of the five axes' point counts) a grid may
/// have. Memory and time grow with the pose count (about 150 bytes and 2 us per pose
/// in a release build on two cores): `--grid 1000` (10^15 poses) grew to 22.7 GB
/// before the kernel killed it. At this limit a run takes a few seconds and about
/// 300 MB.
pub const MAX_GRID_POSES: u64 = 2_000_000;

/// Grid axes: the values of each of the five axes; refuses a grid of more than
/// `MAX_GRID_POSES` (2000000) poses and an axis named twice.
pub fn parse_grid(spec: &str, travel: &[(f64, f64); 5]) -> Result<[Vec<f64>; 5], VolumetricError> {
    let grid = parse_grid_axes(spec, travel)?;
    // u64: five counts of at most 1000 multiply to at most 10^15.
    let poses: u64 = grid.iter().map(|a| a.len() as u64).product();
    if poses > MAX_GRID_POSES {
        return Err(VolumetricError::Grid(format!(
            "--grid {}: {poses} poses exceed the limit of {MAX_GRID_POSES} (the product of \
             the five axes' point counts); use fewer points per axis",
            spec.trim()
        )));
    }
    Ok(grid)
}

fn parse_grid_axes(spec: &str, travel: &[(f64, f64); 5]) -> Result<[Vec<f64>; 5], VolumetricError> {
    // To the nanometre (or 1e-9 deg): -0.5:-0.1:5 gave -0.19999999999999996.
    let lin = |lo: f64, hi: f64, n: usize| -> Vec<f64> {
        if n == 1 {
            vec![(lo + hi) / 2.0]
        } else {
            (0..n)
                .map(|i| {
                    let v = lo + (hi - lo) * i as f64 / (n - 1) as f64;
                    (v * 1e9).round() / 1e9
                })
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
        if n == 1 {
            // The middle of every travel: a pose nobody asked for.
            return Err(VolumetricError::Grid(
                "--grid 1: one point per axis would be the middle of every travel; give the \
                 pose as ranges (e.g. X=500:500:1,Y=400:400:1,Z=300:300:1,A=0:0:1,C=0:0:1)"
                    .into(),
            ));
        }
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
        if out[i].is_some() {
            // The second range silently replaced the first one before.
            return Err(VolumetricError::Grid(format!(
                "--grid: axis {} given twice",
                AXES[i]
            )));
        }
        let (lo, hi, n) = (num(f[0])?, num(f[1])?, count(f[2])?);
        if n == 1 && lo != hi {
            // It evaluated the middle, a position nobody asked for.
            return Err(VolumetricError::Grid(format!(
                "{name}: one point over {lo}..{hi}: give the point as start and end (e.g. \
                 {name}={lo}:{lo}:1)"
            )));
        }
        let (tlo, thi) = travel[i];
        if lo > hi {
            return Err(VolumetricError::Grid(format!(
                "{name}: {lo}..{hi} is reversed: give start <= end"
            )));
        }
        if lo < tlo || hi > thi {
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

/// What `compgate volumetric` evaluated: the report, and whether every pose met the
/// acceptance.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluated {
    /// The report, with the files written.
    pub report: String,
    /// Poses outside the acceptance, and every pose.
    pub failed: (usize, usize),
}

impl Evaluated {
    /// An error when a pose failed the acceptance (the report names them): the
    /// command exits 1 after printing the report.
    pub fn accepted(&self) -> Result<(), VolumetricError> {
        match self.failed {
            (0, _) => Ok(()),
            (failed, total) => Err(VolumetricError::Acceptance { failed, total }),
        }
    }
}

/// `compgate volumetric`: reads the error file, evaluates the grid uncompensated and
/// compensated, writes the SVG maps with `--out` and the CSV with `--csv`, and
/// returns the report.
pub fn run(args: &VolumetricArgs) -> Result<Evaluated, VolumetricError> {
    // Checked before the file is read: a bad flag is the user's first fix. Beyond two
    // turns (more than any C travel) the limit means nothing; a huge value is a typo.
    crate::args::check_f64("--max-c-swing", args.max_c_swing_deg, 0.0, 720.0, "deg")?;
    let mut outputs: Vec<PathBuf> = args.csv.iter().cloned().collect();
    if let Some(dir) = &args.out {
        compgate_core::outputs::make_dir("--out", dir)?;
        outputs.extend(SVG_FILES.iter().map(|f| dir.join(f)));
    }
    compgate_core::outputs::check(
        &[&args.errors],
        &outputs.iter().map(PathBuf::as_path).collect::<Vec<_>>(),
    )?;
    let bytes = std::fs::read(&args.errors)
        .map_err(|e| VolumetricError::Io(format!("{}: {e}", args.errors.display())))?;
    let model = super::format::decode(&bytes)
        .and_then(parse)
        .map_err(|e| match e {
            e @ VolumetricError::Parse { .. } => VolumetricError::InFile {
                path: args.errors.display().to_string(),
                source: Box::new(e),
            },
            other => other,
        })?;
    let grid = parse_grid(&args.grid, &model.travel)?;
    // Allowed by the format, but a measurement export that dropped a table looks like
    // a valid result without this line.
    let missing: Vec<&str> = AXES
        .iter()
        .zip(&model.tables)
        .filter(|(_, t)| t.pos.is_empty())
        .map(|(a, _)| *a)
        .collect();
    let comp = VolumetricCompensator::new(model);
    let pole = Pole {
        mode: args.pole,
        max_c_swing_deg: args.max_c_swing_deg,
    };
    let ev = evaluate_pole(&comp, &grid, &pole);
    let acc = ev.acceptance();
    let mut s = String::new();
    if !missing.is_empty() {
        let _ = writeln!(
            s,
            "{}: no table for {}: {} component errors are taken as zero (write a table of \
             zeros over the travel to say so)",
            args.errors.display(),
            missing.join(", "),
            if missing.len() == 1 { "its" } else { "their" }
        );
    }
    s.push_str(&report(&ev));
    if let Some(path) = &args.csv {
        write_poses_csv(path, &ev)?;
        let _ = writeln!(s, "wrote {}", path.display());
    }
    if let Some(dir) = &args.out {
        for p in write_svgs(dir, &ev)? {
            let _ = writeln!(s, "wrote {}", p.display());
        }
    }
    Ok(Evaluated {
        report: s,
        failed: (acc.failed.len(), acc.total),
    })
}
