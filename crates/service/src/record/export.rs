//! `compgate export`: recorded operation as the measurement CSV that `calibrate` and
//! `diagnose` read ([`compgate_core::measure`]).
//!
//! Rows lie on a grid of `step_s` from `--since`; each row holds, per channel, the
//! last filtered value recorded at or before that time with a usable quality
//! (good or uncertain), so a bad reading never reaches a model fit. Rows before every
//! channel has had a usable value are left out.
//!
//! - `T_<name>`: one column per recorded channel (a channel named `T_bed` gives the
//!   column `T_bed`, a channel `bed` gives `T_bed` too).
//! - `pos_mm`: the NC's actual position of `--axis`, as recorded each status tick;
//!   0 without `--axis` (stated on stderr).
//! - `travel_mm`, `dir`: the sum of every recorded position change since the previous
//!   row, and the sign of the last one (so the travel does not depend on `--step-s`).
//! - `err_um`: the filtered value of `--err-channel` (a channel that measures the
//!   error, e.g. a probe or a laser interface, scaled to um); 0 without it (stated
//!   on stderr): the gateway cannot know the error without a sensor for it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rusqlite::{params, Connection, OpenFlags};

use compgate_core::measure::{Measurements, TempColumn};

/// Arguments of `compgate export`.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// The recorder's database file.
    #[arg(long)]
    pub db: PathBuf,
    /// Start, UTC: `2026-11-22T08:00:00Z`, `2026-11-22 08:00:00` or Unix seconds.
    #[arg(long)]
    pub since: String,
    /// End (exclusive), same forms as --since.
    #[arg(long)]
    pub until: String,
    /// Write the measurement CSV (t_s,pos_mm,dir,travel_mm,err_um,T_*). The only format.
    #[arg(long, required = true)]
    pub csv: bool,
    /// Output file; standard output when omitted.
    #[arg(long, short)]
    pub out: Option<PathBuf>,
    /// Axis whose recorded NC position becomes pos_mm.
    #[arg(long)]
    pub axis: Option<String>,
    /// Channel whose filtered value is the measured error in um (err_um).
    #[arg(long)]
    pub err_channel: Option<String>,
    /// Seconds between rows.
    #[arg(long, default_value_t = 1.0)]
    pub step_s: f64,
}

/// Errors of `export`, each naming what is at fault.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// An argument is not usable.
    #[error("--{flag}: {message}")]
    Arg {
        /// The flag.
        flag: &'static str,
        /// Why.
        message: String,
    },
    /// The database failed.
    #[error("{path}: {message}")]
    Db {
        /// The database file.
        path: String,
        /// What failed.
        message: String,
    },
    /// Writing the CSV failed.
    #[error("{0}")]
    Write(String),
}

/// What `export` did, for the operator.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportSummary {
    /// Rows written.
    pub rows: usize,
    /// Temperature columns.
    pub channels: Vec<String>,
    /// Notes (zero columns and why).
    pub notes: Vec<String>,
}

fn parse_time(conn: &Connection, flag: &'static str, text: &str) -> Result<i64, ExportError> {
    if let Ok(s) = text.trim().parse::<f64>() {
        if s.is_finite() {
            return Ok((s * 1000.0).round() as i64);
        }
    }
    // SQLite's date parser: ISO 8601 forms, UTC.
    let ms: Option<f64> = conn
        .query_row(
            "SELECT unixepoch(?1, 'subsec') * 1000.0",
            [text.trim()],
            |r| r.get(0),
        )
        .map_err(|e| ExportError::Arg {
            flag,
            message: e.to_string(),
        })?;
    ms.map(|v| v.round() as i64).ok_or_else(|| ExportError::Arg {
        flag,
        message: format!("`{text}` is not a time: use 2026-11-22T08:00:00Z, 2026-11-22 08:00:00 or Unix seconds"),
    })
}

/// Reads the record between `since` and `until` into a measurement series.
pub fn measurements(args: &ExportArgs) -> Result<(Measurements, ExportSummary), ExportError> {
    let path = args.db.display().to_string();
    let db = |e: rusqlite::Error| ExportError::Db {
        path: path.clone(),
        message: e.to_string(),
    };
    if !(args.step_s.is_finite() && args.step_s > 0.0) {
        return Err(ExportError::Arg {
            flag: "step-s",
            message: format!("{} must be > 0", args.step_s),
        });
    }
    let conn =
        Connection::open_with_flags(&args.db, OpenFlags::SQLITE_OPEN_READ_ONLY).map_err(db)?;
    let since = parse_time(&conn, "since", &args.since)?;
    let until = parse_time(&conn, "until", &args.until)?;
    if until <= since {
        return Err(ExportError::Arg {
            flag: "until",
            message: format!("`{}` is not after --since `{}`", args.until, args.since),
        });
    }
    let names: BTreeMap<i64, String> = conn
        .prepare("SELECT id, name FROM channels")
        .and_then(|mut s| {
            s.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
                .collect::<Result<_, _>>()
        })
        .map_err(db)?;
    let err_id = match &args.err_channel {
        Some(n) => Some(
            *names
                .iter()
                .find(|(_, v)| *v == n)
                .ok_or_else(|| ExportError::Arg {
                    flag: "err-channel",
                    message: format!("no channel `{n}` in the record"),
                })?
                .0,
        ),
        None => None,
    };
    let mut notes = Vec::new();
    if err_id.is_none() {
        notes.push("err_um is 0: the record holds no measured error (give --err-channel for a channel that measures it)".to_string());
    }
    if args.axis.is_none() {
        notes.push("pos_mm is 0: no --axis given".to_string());
    }

    // Readings in the window, in time order.
    let mut stmt = conn
        .prepare("SELECT t_unix_ms, channel, value_degc, quality FROM readings WHERE t_unix_ms >= ?1 AND t_unix_ms < ?2 ORDER BY t_unix_ms")
        .map_err(db)?;
    let readings: Vec<(i64, i64, Option<f64>, u8)> = stmt
        .query_map(params![since, until], |r| {
            Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
        })
        .and_then(|rows| rows.collect())
        .map_err(db)?;
    let positions: Vec<(i64, f64)> = match &args.axis {
        Some(axis) => {
            let mut s = conn
                .prepare("SELECT t_unix_ms, position_mm FROM nc WHERE axis = ?1 AND t_unix_ms < ?2 ORDER BY t_unix_ms")
                .map_err(db)?;
            let v: Vec<(i64, f64)> = s
                .query_map(params![axis, until], |r| Ok((r.get(0)?, r.get(1)?)))
                .and_then(|rows| rows.collect())
                .map_err(db)?;
            if v.is_empty() {
                return Err(ExportError::Arg {
                    flag: "axis",
                    message: format!("no recorded NC position of axis `{axis}` before --until"),
                });
            }
            v
        }
        None => Vec::new(),
    };

    // Temperature channels: every channel with a reading in the window, but the error channel.
    let mut temp_ids: Vec<i64> = readings.iter().map(|r| r.1).collect();
    temp_ids.sort_unstable();
    temp_ids.dedup();
    temp_ids.retain(|id| Some(*id) != err_id);
    let col: BTreeMap<i64, usize> = temp_ids
        .iter()
        .enumerate()
        .map(|(i, id)| (*id, i))
        .collect();
    let mut last: Vec<Option<f64>> = vec![None; temp_ids.len()];
    let mut last_err: Option<f64> = None;
    let mut last_pos: Option<f64> = None;
    let mut moved_mm = 0.0;

    let mut m = Measurements {
        temps: temp_ids
            .iter()
            .map(|id| {
                let n = names
                    .get(id)
                    .cloned()
                    .unwrap_or_else(|| format!("channel{id}"));
                TempColumn {
                    name: n.strip_prefix("T_").map(str::to_string).unwrap_or(n),
                    degc: Vec::new(),
                }
            })
            .collect(),
        ..Measurements::default()
    };
    let step_ms = (args.step_s * 1000.0).round().max(1.0) as i64;
    let (mut ri, mut pi) = (0, 0);
    let mut grid = since;
    let mut dir: i8 = 0;
    while grid < until {
        while let Some(&(t, ch, v, q)) = readings.get(ri) {
            if t > grid {
                break;
            }
            let usable = v.filter(|x| q < 2 && x.is_finite());
            if let Some(v) = usable {
                if Some(ch) == err_id {
                    last_err = Some(v);
                } else if let Some(&c) = col.get(&ch) {
                    last[c] = Some(v);
                }
            }
            ri += 1;
        }
        while let Some(&(t, p)) = positions.get(pi) {
            if t > grid {
                break;
            }
            if let Some(prev) = last_pos {
                moved_mm += (p - prev).abs();
                if p > prev {
                    dir = 1;
                } else if p < prev {
                    dir = -1;
                }
            }
            last_pos = Some(p);
            pi += 1;
        }
        let ready = !last.is_empty()
            && last.iter().all(Option::is_some)
            && (err_id.is_none() || last_err.is_some())
            && (args.axis.is_none() || last_pos.is_some());
        if ready {
            let pos = last_pos.unwrap_or(0.0);
            // The first row starts the count: what moved before it is no travel of
            // the exported window.
            let travel = if m.is_empty() { 0.0 } else { moved_mm };
            moved_mm = 0.0;
            m.t_s.push((grid - since) as f64 / 1000.0);
            m.pos_mm.push(pos);
            m.err_um.push(last_err.unwrap_or(0.0));
            m.dir.push(dir);
            m.travel_mm.push(travel);
            for (c, v) in m.temps.iter_mut().zip(&last) {
                c.degc.push(v.unwrap_or(f64::NAN));
            }
        }
        grid += step_ms;
    }
    let summary = ExportSummary {
        rows: m.len(),
        channels: temp_ids
            .iter()
            .filter_map(|id| names.get(id).cloned())
            .collect(),
        notes,
    };
    Ok((m, summary))
}

/// `compgate export`: writes the CSV to `args.out` or standard output.
pub fn run(args: &ExportArgs) -> Result<ExportSummary, ExportError> {
    let (m, summary) = measurements(args)?;
    let werr = |e: compgate_core::measure::MeasureError| ExportError::Write(e.to_string());
    match &args.out {
        Some(p) => {
            let f = std::fs::File::create(p)
                .map_err(|e| ExportError::Write(format!("{}: {e}", p.display())))?;
            m.write(std::io::BufWriter::new(f)).map_err(werr)?;
        }
        None => m.write(std::io::stdout().lock()).map_err(werr)?,
    }
    Ok(summary)
}

/// Opens `path` read-only, for tests and tools.
pub fn open_read_only(path: &Path) -> Result<Connection, rusqlite::Error> {
    Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY)
}
