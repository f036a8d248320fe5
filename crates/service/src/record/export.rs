//! `compgate export`: recorded operation as the measurement CSV that `calibrate` and
//! `diagnose` read ([`compgate_core::measure`]).
//!
//! Rows lie on a grid of `step_s` from `--since`, up to the last reading in the
//! window; each row holds, per channel, the last filtered value measured at or
//! before that time with a usable quality (good or uncertain), so a bad reading
//! never reaches a model fit. A reading without a raw value (the device did not
//! answer: the gateway held the value, reason `comm` and the like) is no
//! measurement either. A NaN raw value is NULL in the database too (SQLite has no
//! NaN), but its reading is bad (`not finite`), which is the same outcome. A value
//! is held across a gap in the record (the recorder's interval, the gateway
//! stopped) for at most `--max-hold-s`, never across a reading that was no
//! measurement: there the record says nobody measured. Rows where a channel has had
//! no usable value yet, whose latest reading was no measurement, or whose value is
//! older than `--max-hold-s` are left out, and counted on stderr. An export without
//! a row is an error, and so is one whose grid is too large to be a typo-free window.
//!
//! - `t_s`: seconds since the first exported row (so an early `--since` does not
//!   push it past what `calibrate` takes).
//! - `T_<name>`: one column per recorded channel (a channel named `T_bed` gives the
//!   column `T_bed`, a channel `bed` gives `T_bed` too).
//! - `pos_mm`: the NC's actual position of `--axis`, as recorded each status tick;
//!   0 without `--axis` (stated on stderr).
//! - `travel_mm`, `dir`: the sum of every recorded position change since the previous
//!   row, and the sign of the last one (so the travel does not depend on `--step-s`).
//! - `err_um`: the filtered value of `--err-channel` (a channel that measures the
//!   error, e.g. a probe or a laser interface, scaled to um); 0 without it (stated
//!   on stderr): the gateway cannot know the error without a sensor for it. On a
//!   machine in service the NC compensates: the sensor measures the error left after
//!   the compensation the NC applied (recorded per status tick as
//!   `nc.applied_comp_mm`), not the machine's error a model must predict. Export
//!   names the span of the window where the axis had compensation applied, and
//!   `--add-applied-comp` writes `err_um + 1000 * applied_comp_mm` (the applied
//!   compensation held to the grid like the position), the error without it.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use rusqlite::{params, Connection, OpenFlags, OptionalExtension};

use compgate_core::measure::{
    Measurements, Row, RowWriter, TempColumn, TEMP_DEGC_MAX, TEMP_DEGC_MIN,
};

/// Arguments of `compgate export`.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// The recorder's database file.
    #[arg(long)]
    pub db: PathBuf,
    /// Start, UTC: `2026-11-22T08:00:00Z`, `2026-11-22 08:00:00` or Unix seconds.
    #[arg(long, allow_negative_numbers = true)]
    pub since: String,
    /// End (exclusive), same forms as --since.
    #[arg(long, allow_negative_numbers = true)]
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
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    pub step_s: f64,
    /// Longest a recorded value (temperature, error, position) is held to fill the
    /// grid, s; raise it for a recorder that records less often (`recorder.interval_s`).
    #[arg(long, allow_negative_numbers = true, default_value_t = 60.0)]
    pub max_hold_s: f64,
    /// Add the NC's recorded applied compensation of --axis to err_um (err_um + 1000 *
    /// applied_comp_mm at that instant): on a recording made with compensation on,
    /// the error without compensation, which is what calibrate and diagnose fit.
    #[arg(long)]
    pub add_applied_comp: bool,
}

/// Applied compensation smaller than this (mm, 0.5 um) is none: the NC's
/// compensation rounded, not a compensated recording.
pub const APPLIED_COMP_MIN_MM: f64 = 0.0005;

/// Grid rows an export may span: a week at 0.1 s. More is a mistyped step (and hours
/// of work before the first row).
pub const MAX_GRID_ROWS: i64 = 6_048_000;

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
    /// The database cannot be read.
    #[error("--db {path}: {message}")]
    Db {
        /// The database file.
        path: String,
        /// What failed.
        message: String,
    },
    /// Writing the CSV failed, or its file would be the database.
    #[error("{0}")]
    Write(String),
    /// No row could be exported; nothing was written.
    #[error("no row to export between --since and --until: {0}")]
    Empty(String),
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

/// `text` as Unix milliseconds. `clock` is a connection of its own (in memory), for
/// SQLite's date parser: on the recorder's database, the first query would report
/// a database it cannot read as this flag's fault.
fn parse_time(clock: &Connection, flag: &'static str, text: &str) -> Result<i64, ExportError> {
    if let Ok(s) = text.trim().parse::<f64>() {
        if s.is_finite() {
            return Ok((s * 1000.0).round() as i64);
        }
    }
    // SQLite's date parser: ISO 8601 forms, UTC.
    let ms: Option<f64> = clock
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

/// The filtered value of a recorded reading if it is a measurement of its cycle: a
/// usable quality (good or uncertain) and a raw value. Without one the device did not
/// answer and the gateway held its last value: a gap, not a measurement.
fn measured(value_degc: Option<f64>, quality: u8, sampled: bool) -> Option<f64> {
    value_degc.filter(|v| sampled && quality < 2 && v.is_finite())
}

/// Reads the record between `since` and `until` into a measurement series.
pub fn measurements(args: &ExportArgs) -> Result<(Measurements, ExportSummary), ExportError> {
    let mut m = Measurements::default();
    let summary = export(args, |names, row, degc| {
        if m.temps.is_empty() {
            m.temps = names
                .iter()
                .map(|n| TempColumn {
                    name: n.clone(),
                    degc: Vec::new(),
                })
                .collect();
        }
        m.push(row, degc.iter().copied());
        Ok(())
    })?;
    Ok((m, summary))
}

/// Writes the measurement CSV of the record between `since` and `until` to `out`, a
/// row at a time; nothing at all when there is no row (an error).
pub fn write_csv<W: std::io::Write>(
    args: &ExportArgs,
    out: W,
) -> Result<ExportSummary, ExportError> {
    let mut out = Some(out);
    let mut w: Option<RowWriter<W>> = None;
    let write_err = |e: compgate_core::measure::MeasureError| ExportError::Write(e.to_string());
    let summary = export(args, |names, row, degc| {
        let w = match &mut w {
            Some(w) => w,
            None => {
                let writer = out
                    .take()
                    .ok_or_else(|| ExportError::Write("no output".into()))?;
                w.insert(
                    RowWriter::new(writer, names.iter().map(String::as_str)).map_err(write_err)?,
                )
            }
        };
        w.row(row, degc.iter().copied()).map_err(write_err)
    })?;
    if let Some(w) = w {
        w.finish().map_err(write_err)?;
    }
    Ok(summary)
}

/// Per channel, what the record holds of it in the window.
struct ChannelSpan {
    first_ms: i64,
    last_ms: i64,
    /// The lowest and highest measured value (good or uncertain, with a raw value).
    measured_degc: Option<(f64, f64)>,
}

/// The export, row by row: `emit` gets the temperature columns' names (without
/// `T_`), a row and its temperatures, in time order. The readings are read as they
/// are needed, never all at once: a month of 64 channels took 3 GB.
pub fn export(
    args: &ExportArgs,
    mut emit: impl FnMut(&[String], Row, &[f64]) -> Result<(), ExportError>,
) -> Result<ExportSummary, ExportError> {
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
    if !(args.max_hold_s.is_finite() && args.max_hold_s > 0.0) {
        return Err(ExportError::Arg {
            flag: "max-hold-s",
            message: format!("{} must be > 0", args.max_hold_s),
        });
    }
    // The grid is in whole milliseconds, the record's resolution: another step would
    // be rounded to one the user did not ask for.
    let step_ms = (args.step_s * 1000.0).round();
    if step_ms < 1.0 || (args.step_s * 1000.0 - step_ms).abs() > 1e-6 {
        return Err(ExportError::Arg {
            flag: "step-s",
            message: format!(
                "{} s is not a whole number of milliseconds of at least 0.001 s (the record's resolution)",
                args.step_s
            ),
        });
    }
    let step_ms = step_ms as i64;
    let clock = Connection::open_in_memory().map_err(|e| ExportError::Arg {
        flag: "since",
        message: format!("SQLite's date parser: {e}"),
    })?;
    let since = parse_time(&clock, "since", &args.since)?;
    let until = parse_time(&clock, "until", &args.until)?;
    if until <= since {
        return Err(ExportError::Arg {
            flag: "until",
            message: format!("`{}` is not after --since `{}`", args.until, args.since),
        });
    }
    let conn = open_database(&args.db)?;
    let hold_ms = (args.max_hold_s * 1000.0).round() as i64;
    let names: BTreeMap<i64, String> = conn
        .prepare("SELECT id, name FROM channels")
        .and_then(|mut s| {
            s.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
                .collect::<Result<_, _>>()
        })
        .map_err(db)?;
    let name_of = |id: &i64| {
        names
            .get(id)
            .cloned()
            .unwrap_or_else(|| format!("channel{id}"))
    };
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
        if args.add_applied_comp {
            return Err(ExportError::Arg {
                flag: "add-applied-comp",
                message: "needs --axis: the applied compensation is recorded per NC axis".into(),
            });
        }
        notes.push("pos_mm is 0: no --axis given".to_string());
    }
    if args.add_applied_comp && err_id.is_none() {
        return Err(ExportError::Arg {
            flag: "add-applied-comp",
            message: "needs --err-channel: without a measured error err_um would be the applied compensation alone".into(),
        });
    }

    // What each channel holds in the window, in one pass that keeps nothing per reading.
    let spans: BTreeMap<i64, ChannelSpan> = conn
        .prepare(
            "SELECT channel, min(t_unix_ms), max(t_unix_ms), \
             min(CASE WHEN quality < 2 AND raw IS NOT NULL AND value_degc BETWEEN -1e308 AND 1e308 THEN value_degc END), \
             max(CASE WHEN quality < 2 AND raw IS NOT NULL AND value_degc BETWEEN -1e308 AND 1e308 THEN value_degc END) \
             FROM readings WHERE t_unix_ms >= ?1 AND t_unix_ms < ?2 GROUP BY channel",
        )
        .and_then(|mut s| {
            s.query_map(params![since, until], |r| {
                let lo: Option<f64> = r.get(3)?;
                let hi: Option<f64> = r.get(4)?;
                Ok((
                    r.get(0)?,
                    ChannelSpan {
                        first_ms: r.get(1)?,
                        last_ms: r.get(2)?,
                        measured_degc: lo.zip(hi),
                    },
                ))
            })?
            .collect::<Result<_, _>>()
        })
        .map_err(db)?;
    let (Some(first_ms), Some(last_ms)) = (
        spans.values().map(|c| c.first_ms).min(),
        spans.values().map(|c| c.last_ms).max(),
    ) else {
        return Err(ExportError::Empty(
            "the record holds no reading in the window".into(),
        ));
    };
    // The grid spans the record within the window, not the window: one wider than the
    // record (a mistyped year, or "everything") costs nothing beyond it.
    let grid_start = since + (first_ms - since) / step_ms * step_ms;
    // No row after the last reading: past it the gateway recorded nothing.
    let grid_end = until.min(last_ms + 1);
    let grid_rows = (grid_end - grid_start) / step_ms;
    if grid_rows > MAX_GRID_ROWS {
        return Err(ExportError::Arg {
            flag: "step-s",
            message: format!(
                "the record in the window spans {grid_rows} rows of {} s; at most {MAX_GRID_ROWS} (narrow --since and --until, or raise --step-s)",
                args.step_s
            ),
        });
    }

    // Temperature channels: every channel with a reading in the window, but the error
    // channel. A channel that reads no temperature (a laser or probe channel not given
    // as --err-channel) would make calibrate refuse the whole file: it is left out,
    // and said. Its most extreme usable value names it.
    let mut temp_ids: Vec<i64> = Vec::new();
    for (id, span) in &spans {
        if Some(*id) == err_id {
            continue;
        }
        let out_of_range = span.measured_degc.and_then(|(lo, hi)| {
            let range = TEMP_DEGC_MIN..=TEMP_DEGC_MAX;
            [lo, hi]
                .into_iter()
                .filter(|v| !range.contains(v))
                .max_by(|a, b| a.abs().total_cmp(&b.abs()))
        });
        match out_of_range {
            Some(v) => notes.push(format!(
                "channel `{}` left out: it reads {v}, no temperature ({TEMP_DEGC_MIN}..={TEMP_DEGC_MAX} degC); give it as --err-channel if it measures the error",
                name_of(id)
            )),
            None => temp_ids.push(*id),
        }
    }
    // A channel renamed, added or removed inside the window has no value on one side
    // of the change: those rows cannot be exported, and the rest of the gap would be
    // blamed on the record.
    let partial: Vec<String> = temp_ids
        .iter()
        .chain(err_id.iter())
        .filter_map(|id| {
            let span = spans.get(id)?;
            let starts = span.first_ms - first_ms > hold_ms;
            let ends = last_ms - span.last_ms > hold_ms;
            (starts || ends).then(|| {
                format!(
                    "`{}` ({})",
                    name_of(id),
                    match (starts, ends) {
                        (true, true) => "starts and ends inside the window",
                        (true, false) => "starts inside the window",
                        _ => "ends inside the window",
                    }
                )
            })
        })
        .collect();
    let col: BTreeMap<i64, usize> = temp_ids
        .iter()
        .enumerate()
        .map(|(i, id)| (*id, i))
        .collect();
    let columns: Vec<String> = temp_ids
        .iter()
        .map(|id| {
            let n = name_of(id);
            n.strip_prefix("T_").map(str::to_string).unwrap_or(n)
        })
        .collect();

    // The NC positions, each with the compensation the NC applied in that status
    // tick, from the last one before the grid on, after the last change before that
    // (which gives the direction): not the axis' whole history.
    // Only reads that carry a position: a target that reports none (OPC UA, ADS)
    // records NULL, and a standing axis at 0 is not what the machine did.
    let mut applied_found = false;
    let positions: Vec<(i64, f64, Option<f64>)> = match &args.axis {
        Some(axis) => {
            let query = |sql: &str,
                         p: &[&dyn rusqlite::ToSql]|
             -> Result<Vec<(i64, f64, Option<f64>)>, ExportError> {
                conn.prepare(sql)
                    .and_then(|mut s| {
                        s.query_map(p, |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?
                            .collect::<Result<_, _>>()
                    })
                    .map_err(db)
            };
            let before = query(
                "SELECT t_unix_ms, position_mm, applied_comp_mm FROM nc WHERE axis = ?1 AND t_unix_ms <= ?2 AND position_mm IS NOT NULL ORDER BY t_unix_ms DESC LIMIT 1",
                &[axis, &grid_start],
            )?;
            let mut v = Vec::new();
            let from = match before.first() {
                Some(&(t0, p0, _)) => {
                    v = query(
                        "SELECT t_unix_ms, position_mm, applied_comp_mm FROM nc WHERE axis = ?1 AND t_unix_ms < ?2 AND position_mm != ?3 ORDER BY t_unix_ms DESC LIMIT 1",
                        &[axis, &t0, &p0],
                    )?;
                    t0
                }
                None => grid_start,
            };
            v.extend(query(
                "SELECT t_unix_ms, position_mm, applied_comp_mm FROM nc WHERE axis = ?1 AND t_unix_ms >= ?2 AND t_unix_ms < ?3 AND position_mm IS NOT NULL ORDER BY t_unix_ms",
                &[axis, &from, &until],
            )?);
            if v.is_empty() {
                let unreported: bool = conn
                    .query_row(
                        "SELECT COUNT(*) > 0 FROM nc WHERE axis = ?1 AND t_unix_ms < ?2 AND position_mm IS NULL",
                        params![axis, until],
                        |r| r.get(0),
                    )
                    .map_err(db)?;
                let message = if unreported {
                    format!("the NC target of axis `{axis}` reports no position (an OPC UA or ADS target reads the setting data only): pos_mm cannot be exported from this record; leave --axis out to export the temperatures and the error alone (pos_mm 0), and measure the error over positions for calibrate (a laser run's CSV with pos_mm)")
                } else {
                    format!("no recorded NC position of axis `{axis}` before --until")
                };
                return Err(ExportError::Arg {
                    flag: "axis",
                    message,
                });
            }
            if args.add_applied_comp && v.iter().any(|(_, _, applied)| applied.is_none()) {
                return Err(ExportError::Arg {
                    flag: "add-applied-comp",
                    message: format!("the NC target of axis `{axis}` reported no applied compensation in the window"),
                });
            }
            // Whether the record holds compensation applied to --axis in the window.
            let (note, applied) = applied_comp_note(&conn, axis, since, until, args)?;
            notes.extend(note);
            applied_found = applied;
            v
        }
        None => Vec::new(),
    };

    // Without --axis, or where the record holds no applied compensation for it (a
    // target that reports none: OPC UA, ADS, the S7 block; or zeros a build before
    // stored for them): what the NC held and compgate wrote is the record that the
    // error was measured with compensation on.
    if err_id.is_some() && !applied_found {
        notes.extend(comp_on_nc_notes(
            &conn,
            args.axis.as_deref(),
            since,
            until,
            args,
        )?);
    }

    // Readings in the window, in time order, read as the grid reaches them. The value
    // only when it was measured in that cycle with a usable quality.
    let mut stmt = conn
        .prepare("SELECT t_unix_ms, channel, value_degc, quality, raw IS NOT NULL FROM readings WHERE t_unix_ms >= ?1 AND t_unix_ms < ?2 ORDER BY t_unix_ms")
        .map_err(db)?;
    let mut readings = stmt
        .query_map(params![since, until], |r| {
            let (v, q, sampled): (Option<f64>, u8, bool) = (r.get(2)?, r.get(3)?, r.get(4)?);
            Ok((
                r.get::<_, i64>(0)?,
                r.get::<_, i64>(1)?,
                measured(v, q, sampled),
            ))
        })
        .map_err(db)?
        .peekable();

    // Each with the time it was recorded, to leave out rows it is too old for.
    let mut last: Vec<Option<(i64, f64)>> = vec![None; temp_ids.len()];
    let mut last_err: Option<(i64, f64)> = None;
    let mut last_pos: Option<(i64, f64)> = None;
    // The compensation the NC applied at `last_pos`, mm: recorded in the same row.
    let mut last_applied_mm: Option<f64> = None;
    // Whether the channel's latest reading was no measurement: its last value is not
    // held across it (the outage is known, not a gap between recorded samples).
    let mut cut = vec![false; temp_ids.len()];
    let mut err_cut = false;
    let mut stale_rows = 0usize;
    let mut unmeasured_rows = 0usize;
    let mut unseen_rows = 0usize;
    let mut moved_mm = 0.0;
    let mut rows = 0usize;
    let mut degc = vec![f64::NAN; temp_ids.len()];

    let mut pi = 0;
    let mut grid = grid_start;
    let mut dir: i8 = 0;
    let mut first_row: Option<i64> = None;
    while grid < grid_end {
        loop {
            match readings.peek() {
                Some(Ok((t, _, _))) if *t > grid => break,
                None => break,
                Some(_) => {}
            }
            let Some(next) = readings.next() else { break };
            let (t, ch, v) = next.map_err(db)?;
            if Some(ch) == err_id {
                last_err = v.map(|v| (t, v)).or(last_err);
                err_cut = v.is_none();
            } else if let Some(&c) = col.get(&ch) {
                last[c] = v.map(|v| (t, v)).or(last[c]);
                cut[c] = v.is_none();
            }
        }
        while let Some(&(t, p, applied_mm)) = positions.get(pi) {
            if t > grid {
                break;
            }
            if let Some((_, prev)) = last_pos {
                moved_mm += (p - prev).abs();
                if p > prev {
                    dir = 1;
                } else if p < prev {
                    dir = -1;
                }
            }
            last_pos = Some((t, p));
            last_applied_mm = applied_mm;
            pi += 1;
        }
        let fresh = |v: &Option<(i64, f64)>| v.is_some_and(|(t, _)| grid - t <= hold_ms);
        let seen = !last.is_empty()
            && last.iter().all(Option::is_some)
            && (err_id.is_none() || last_err.is_some())
            && (args.axis.is_none() || last_pos.is_some());
        let unmeasured = cut.contains(&true) || err_cut;
        let ready = seen
            && !unmeasured
            && last.iter().all(fresh)
            && (err_id.is_none() || fresh(&last_err))
            && (args.axis.is_none() || fresh(&last_pos));
        if seen && !ready {
            if unmeasured {
                unmeasured_rows += 1;
            } else {
                stale_rows += 1;
            }
        } else if !seen && last.iter().any(Option::is_some) {
            unseen_rows += 1;
        }
        if ready {
            // The first row starts the count: what moved before it is no travel of
            // the exported window.
            let travel = if rows == 0 { 0.0 } else { moved_mm };
            moved_mm = 0.0;
            let t0 = *first_row.get_or_insert(grid);
            for (d, v) in degc.iter_mut().zip(&last) {
                *d = v.map_or(f64::NAN, |(_, v)| v);
            }
            emit(
                &columns,
                Row {
                    t_s: (grid - t0) as f64 / 1000.0,
                    pos_mm: last_pos.map_or(0.0, |(_, p)| p),
                    dir,
                    travel_mm: travel,
                    err_um: last_err.map_or(0.0, |(_, v)| v)
                        + if args.add_applied_comp {
                            // The sensor read the error minus what the NC applied
                            // (the simulated plant's `measure - applied`): added back,
                            // the error without compensation.
                            1000.0 * last_applied_mm.unwrap_or(0.0)
                        } else {
                            0.0
                        },
                },
                &degc,
            )?;
            rows += 1;
        }
        grid += step_ms;
    }
    if !partial.is_empty() {
        notes.push(format!(
            "{} rows left out or cut short: channel {} (renamed, added or removed?); a row needs every channel, so export the spans before and after apart",
            unseen_rows + stale_rows,
            partial.join(", ")
        ));
    } else if stale_rows > 0 {
        notes.push(format!(
            "{stale_rows} rows left out: a value in them was older than --max-hold-s {} s (a gap in the record)",
            args.max_hold_s
        ));
    }
    if unmeasured_rows > 0 {
        notes.push(format!(
            "{unmeasured_rows} rows left out: a channel's latest reading in them was no measurement (its device did not answer, or the value was bad), and no value is held across one"
        ));
    }
    if rows == 0 {
        let never: Vec<String> = temp_ids
            .iter()
            .zip(&last)
            .filter(|(_, v)| v.is_none())
            .map(|(id, _)| name_of(id))
            .chain(
                (err_id.is_some() && last_err.is_none())
                    .then(|| args.err_channel.clone().unwrap_or_default()),
            )
            .collect();
        let why = if temp_ids.is_empty() {
            "no temperature channel has a reading in the window".to_string()
        } else if !never.is_empty() {
            format!(
                "no measured value of usable quality (good or uncertain) of {} in the window",
                never.join(", ")
            )
        } else if stale_rows > 0 || unmeasured_rows > 0 {
            format!(
                "in every row a value was older than --max-hold-s {} s or a channel's latest reading was no measurement",
                args.max_hold_s
            )
        } else {
            "no recorded NC position of --axis in the window".to_string()
        };
        return Err(ExportError::Empty(why));
    }
    Ok(ExportSummary {
        rows,
        channels: temp_ids
            .iter()
            .filter_map(|id| names.get(id).cloned())
            .collect(),
        notes,
    })
}

/// How far before the window export looks for the NC's last read (the gateway reads
/// it at least every status interval while it runs), ms.
const READ_BEFORE_MS: i64 = 86_400_000;

/// Per axis (`axis`, or every axis), a note when compensation was on the NC in the
/// window or left on it before: the NC was read to hold, or a verified job wrote, a
/// value beyond [`APPLIED_COMP_MIN_MM`] (SD43900) or a slope. A job that landed but
/// was not verified (a read-back too slow) shows in the NC's reads.
fn comp_on_nc_notes(
    conn: &Connection,
    axis: Option<&str>,
    since: i64,
    until: i64,
    args: &ExportArgs,
) -> Result<Vec<String>, ExportError> {
    let db = |e: rusqlite::Error| ExportError::Db {
        path: args.db.display().to_string(),
        message: e.to_string(),
    };
    let axes: Vec<String> = match axis {
        Some(a) => vec![a.to_string()],
        // No index on the axis: the jobs table is small, and the nc rows of the window
        // are an index range.
        None => conn
            .prepare(
                "SELECT axis FROM jobs WHERE ok = 1 AND t_unix_ms < ?2 UNION \
                 SELECT axis FROM nc WHERE t_unix_ms >= ?1 AND t_unix_ms < ?2 ORDER BY axis",
            )
            .map_err(db)?
            .query_map(params![since, until], |r| r.get(0))
            .map_err(db)?
            .collect::<Result<_, _>>()
            .map_err(db)?,
    };
    let mut notes = Vec::new();
    for axis in axes {
        // The NC's reads in the window; the applied compensation recorded in it (how
        // many rows hold one, the largest).
        let (held_k0, held_tan, applied_rows, applied_max): (Option<f64>, Option<f64>, i64, Option<f64>) = conn
            .query_row(
                "SELECT max(abs(sd43900_mm)), max(abs(sd43910)), COUNT(applied_comp_mm), max(abs(applied_comp_mm)) \
                 FROM nc WHERE axis = ?1 AND t_unix_ms >= ?2 AND t_unix_ms < ?3",
                params![axis, since, until],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
            )
            .map_err(db)?;
        // The verified jobs in the window, and the last one before it.
        let (in_window, job_k0, job_tan): (i64, Option<f64>, Option<f64>) = conn
            .query_row(
                "SELECT COUNT(*), max(abs(sd43900_mm)), max(abs(sd43910)) FROM jobs \
                 WHERE ok = 1 AND axis = ?1 AND t_unix_ms >= ?2 AND t_unix_ms < ?3",
                params![axis, since, until],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
            )
            .map_err(db)?;
        let job_before: Option<(i64, f64, f64)> = conn
            .query_row(
                "SELECT t_unix_ms, abs(sd43900_mm), abs(sd43910) FROM jobs \
                 WHERE ok = 1 AND axis = ?1 AND t_unix_ms < ?2 ORDER BY t_unix_ms DESC LIMIT 1",
                params![axis, since],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
            )
            .optional()
            .map_err(db)?;
        // What the NC held at the start: its last read before the window, unless a
        // verified job came after it; looked for over a bounded span (the index is
        // on time only, and an axis without reads would be looked for back to the
        // first row).
        let read_from = job_before.map_or(since - READ_BEFORE_MS, |(t, _, _)| {
            t.max(since - READ_BEFORE_MS)
        });
        let read_before: Option<(f64, f64)> = conn
            .query_row(
                "SELECT abs(sd43900_mm), abs(sd43910) FROM nc WHERE axis = ?1 AND t_unix_ms >= ?2 \
                 AND t_unix_ms < ?3 ORDER BY t_unix_ms DESC LIMIT 1",
                params![axis, read_from, since],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .optional()
            .map_err(db)?;
        let at_start = read_before.or(job_before.map(|(_, k0, tan)| (k0, tan)));
        let largest = |xs: [Option<f64>; 3]| xs.into_iter().flatten().fold(0.0, f64::max);
        let k0_mm = largest([held_k0, at_start.map(|b| b.0), job_k0]);
        let tan_beta = largest([held_tan, at_start.map(|b| b.1), job_tan]);
        let shadow = "measure with the axis in shadow mode (`shadow = true`) for calibrate";
        if let Some(applied) = applied_max.filter(|a| *a > APPLIED_COMP_MIN_MM) {
            notes.push(format!(
                "the NC applied compensation to axis `{axis}` in the window (up to {:.1} um): \
                 err_um is the error left after it; give --axis {axis} --add-applied-comp to \
                 add it back, or {shadow}",
                applied * 1000.0
            ));
            continue;
        }
        if k0_mm <= APPLIED_COMP_MIN_MM && tan_beta == 0.0 {
            continue;
        }
        let slope = if tan_beta > 0.0 {
            format!(", |SD43910| up to {tan_beta:.3e}")
        } else {
            String::new()
        };
        let on_nc = format!(
            "compgate compensated axis `{axis}` in the window ({in_window} verified jobs in it, \
             SD43900 up to {:.1} um on the NC{slope})",
            k0_mm * 1000.0
        );
        notes.push(if applied_rows > 0 {
            format!(
                "{on_nc}, yet the record says the NC applied none: an axis not referenced, or \
                 with its compensation off, applies none, and builds before this one recorded \
                 0 for a target that reports no applied compensation (OPC UA, ADS, S7); if \
                 it applied, err_um is the error left after it and a model fitted on it is not \
                 the machine's: {shadow}"
            )
        } else {
            format!(
                "{on_nc}, and the record holds no applied compensation to add back: err_um is \
                 the error left after it, and a model fitted on it is not the machine's; {shadow}"
            )
        });
    }
    Ok(notes)
}

/// The note on the compensation the NC applied to `axis` in the window, if any: a
/// recording made with compensation on measures the error left after it; and whether
/// the record holds some applied in the window.
fn applied_comp_note(
    conn: &Connection,
    axis: &str,
    since: i64,
    until: i64,
    args: &ExportArgs,
) -> Result<(Option<String>, bool), ExportError> {
    let span: Option<(String, String, f64)> = conn
        .query_row(
            "SELECT strftime('%Y-%m-%dT%H:%M:%fZ', min(t_unix_ms) / 1000.0, 'unixepoch'), \
             strftime('%Y-%m-%dT%H:%M:%fZ', max(t_unix_ms) / 1000.0, 'unixepoch'), \
             max(abs(applied_comp_mm)) \
             FROM nc WHERE axis = ?1 AND t_unix_ms >= ?2 AND t_unix_ms < ?3 AND abs(applied_comp_mm) > ?4",
            params![axis, since, until, APPLIED_COMP_MIN_MM],
            |r| {
                let first: Option<String> = r.get(0)?;
                let last: Option<String> = r.get(1)?;
                let max_mm: Option<f64> = r.get(2)?;
                Ok(first.zip(last).zip(max_mm).map(|((a, b), m)| (a, b, m)))
            },
        )
        .map_err(|e| ExportError::Db {
            path: args.db.display().to_string(),
            message: e.to_string(),
        })?;
    let Some((first, last, max_mm)) = span else {
        let note = args.add_applied_comp.then(|| {
            format!("--add-applied-comp: the record holds no applied compensation of axis `{axis}` in the window; nothing was added")
        });
        return Ok((note, false));
    };
    let applied = format!(
        "the NC applied compensation to axis `{axis}` from {first} to {last} (up to {:.1} um)",
        max_mm * 1000.0
    );
    let note = if args.add_applied_comp {
        format!("{applied}; err_um is the measured error plus the applied compensation at that instant (--add-applied-comp): the error without compensation")
    } else {
        format!("{applied}: there err_um is the error left after the NC's compensation, and a model fitted on it is not the machine's model; give --add-applied-comp to write the error without compensation (err_um + the applied compensation at that instant), or export a window with compensation off")
    };
    Ok((Some(note), true))
}

/// `compgate export --out FILE`: writes the CSV to `args.out`. Standard output is the
/// command line's to write (it tells a closed pipe from the export's own errors), so
/// a missing `--out` is an error, told after the export's own (`record::tests`
/// reaches those through here without `--out`).
pub fn run(args: &ExportArgs) -> Result<ExportSummary, ExportError> {
    if let Some(out) = &args.out {
        refuse_database_files(&args.db, out)?;
        compgate_core::outputs::check(&[&args.db], &[out])
            .map_err(|e| ExportError::Write(e.to_string()))?;
    }
    let Some(out) = &args.out else {
        export(args, |_, _, _| Ok(()))?;
        return Err(ExportError::Arg {
            flag: "out",
            message: "required: the CSV is written to a file".into(),
        });
    };
    let io = |e: std::io::Error| ExportError::Write(format!("{}: {e}", out.display()));
    // Written beside it and renamed over it when complete: an error leaves the old file.
    let mut staged = compgate_core::outputs::Staged::new();
    let file = std::fs::File::create(staged.path_for(out)).map_err(io)?;
    let summary = write_csv(args, std::io::BufWriter::new(file))?;
    staged.commit().map_err(|(_, e)| io(e))?;
    Ok(summary)
}

/// Files SQLite and the recorder keep beside the database: written over while a
/// gateway records, the WAL's committed transactions would be lost.
const DATABASE_SUFFIXES: [&str; 5] = ["", "-wal", "-shm", "-journal", ".lock"];

/// Refuses an `out` that names the database or one of its companion files, however
/// spelled (`./db/../db/g.db-wal`): the directories are compared canonicalized, the
/// file names as given. The companions may not exist yet when the export runs, so
/// comparing files (as `outputs::check` does) does not catch them.
fn refuse_database_files(db: &Path, out: &Path) -> Result<(), ExportError> {
    let split = |p: &Path| -> Option<(PathBuf, std::ffi::OsString)> {
        let dir = match p.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        Some((dir.canonicalize().ok()?, p.file_name()?.to_owned()))
    };
    let (Some((db_dir, db_name)), Some((out_dir, out_name))) = (split(db), split(out)) else {
        return Ok(());
    };
    if db_dir != out_dir {
        return Ok(());
    }
    for suffix in DATABASE_SUFFIXES {
        let mut name = db_name.clone();
        name.push(suffix);
        if name == out_name {
            return Err(ExportError::Write(format!(
                "--out {}: is the recorder database {}{suffix}; refusing to overwrite it",
                out.display(),
                db.display()
            )));
        }
    }
    Ok(())
}

/// Opens the recorder's database `path` read-only and reads its schema, so that a
/// path that is no database, or a database SQLite cannot read here, is reported as
/// such, naming `--db`.
fn open_database(path: &Path) -> Result<Connection, ExportError> {
    let err = |message: String| ExportError::Db {
        path: path.display().to_string(),
        message,
    };
    let meta = std::fs::metadata(path).map_err(|e| err(e.to_string()))?;
    if meta.is_dir() {
        return Err(err(
            "is a directory; give the recorder's database file (recorder.path)".into(),
        ));
    }
    // Bytes 18 and 19 of an SQLite header are 2 in WAL mode, the recorder's.
    let mut header = Vec::with_capacity(20);
    std::fs::File::open(path)
        .and_then(|f| f.take(20).read_to_end(&mut header))
        .map_err(|e| err(e.to_string()))?;
    let wal = header.get(18..20).is_some_and(|v| v.contains(&2));
    let conn = open_read_only(path).map_err(|e| err(e.to_string()))?;
    let tables = conn.query_row(
        "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name IN ('channels', 'readings')",
        [],
        |r| r.get::<_, i64>(0),
    );
    match tables {
        Ok(2) => Ok(conn),
        Ok(_) => Err(err(
            "holds no recorded readings (no tables `channels` and `readings`): give the \
             recorder's database file (recorder.path)"
                .into(),
        )),
        Err(e) if wal && e.sqlite_error_code() == Some(rusqlite::ErrorCode::CannotOpen) => {
            let dir = match path.parent() {
                Some(d) if !d.as_os_str().is_empty() => d,
                _ => Path::new("."),
            };
            Err(err(format!(
                "cannot be opened read-only here: it is in WAL mode, and SQLite reads such a \
                 database only with its -wal and -shm files beside it, which it could neither \
                 open nor create in {} (a read-only directory?); copy the database with its \
                 -wal file to a writable directory ({e})",
                dir.display()
            )))
        }
        Err(e) => Err(err(e.to_string())),
    }
}

/// Opens `path` read-only, for tests and tools.
pub fn open_read_only(path: &Path) -> Result<Connection, rusqlite::Error> {
    Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY)
}
