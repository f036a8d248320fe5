//! `--trace FILE.csv`: a servo trace recorded on a real control, read for offline
//! analysis.
//!
//! One header row, comma separated, one row per sample in time order:
//!
//! | column       | unit | required | meaning                                        |
//! |--------------|------|----------|------------------------------------------------|
//! | `t_s`        | s    | yes      | sample time, increasing at a fixed period      |
//! | `encoder_mm` | mm   | yes      | motor encoder actual position                  |
//! | `scale_mm`   | mm   | yes      | linear scale actual position                   |
//! | `command_mm` | mm   | no       | position command; where present it marks the dwells |
//!
//! The trace CSV that `--out` writes has this form. Other columns are ignored. Every
//! value must be a finite number (positions within +-100 m); the sample period must
//! not change by more than [`PERIOD_TOLERANCE`] from the first step; no column may
//! appear twice. Each refusal names the file, the line and the column. The file is
//! read as the measurement files are ([`compgate_core::measure::CsvInput`]): an
//! empty file, a header split on ';' or tabs and decimal commas are named as such.

use std::path::Path;

use compgate_core::measure::{CsvInput, MeasureError};

use super::math::Trace;
use super::BacklashError;

/// Largest |position| in a trace file, mm.
const POSITION_MAX_MM: f64 = 100_000.0;
/// A time step may differ from the first one by this fraction.
pub const PERIOD_TOLERANCE: f64 = 0.01;

/// Reads a trace file; errors name the file, line and column.
pub fn read_trace(path: &Path) -> Result<Trace, BacklashError> {
    let file_err = |line: u64, column: &str, message: String| BacklashError::TraceFile {
        path: path.display().to_string(),
        line,
        column: column.to_string(),
        message,
    };
    let file = compgate_core::measure::open_file(path)
        .map_err(|e| BacklashError::Io(format!("{}: {e}", path.display())))?;
    // The measurement files' reader: the same words for an empty file, a header
    // split on ';' or tabs, and decimal commas.
    let format_err = |e: MeasureError| BacklashError::TraceFormat {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let mut input = CsvInput::open(
        std::io::BufReader::new(file),
        "t_s",
        "t_s,encoder_mm,scale_mm[,command_mm]",
    )
    .map_err(format_err)?;
    let header = input.header.clone();
    let header_line = input.header_line;
    // A duplicated column was read from its first copy only: which of two
    // `encoder_mm` columns is the encoder is not ours to guess.
    for (i, name) in header.iter().enumerate() {
        if let Some(first) = header.iter().take(i).position(|h| h == name) {
            return Err(file_err(
                header_line,
                name,
                format!("column appears twice (columns {} and {})", first + 1, i + 1),
            ));
        }
    }
    let find = |name: &str| header.iter().position(|h| h == name);
    let mut columns = [0usize; 3];
    for (slot, name) in columns.iter_mut().zip(["t_s", "encoder_mm", "scale_mm"]) {
        *slot = find(name)
            .ok_or_else(|| file_err(header_line, name, "required column is missing".to_string()))?;
    }
    let command = find("command_mm");
    let mut trace = Trace::default();
    let mut times: Vec<f64> = Vec::new();
    let mut record = csv::StringRecord::new();
    while let Some(line) = input.next(&mut record).map_err(format_err)? {
        let num = |i: usize, max: f64| -> Result<f64, BacklashError> {
            let cell = &record[i];
            let v: f64 = cell
                .parse()
                .map_err(|_| file_err(line, &header[i], format!("{cell:?} is not a number")))?;
            if !v.is_finite() || v.abs() > max {
                return Err(file_err(
                    line,
                    &header[i],
                    format!("{cell:?} is not a finite number within +-{max}"),
                ));
            }
            Ok(v)
        };
        let t_s = num(columns[0], 1e9)?;
        if let Some(&prev) = times.last() {
            let step = t_s - prev;
            if step <= 0.0 {
                return Err(file_err(
                    line,
                    "t_s",
                    format!("time does not increase ({t_s} s after {prev} s)"),
                ));
            }
            if times.len() >= 2 {
                let period = times[1] - times[0];
                if (step - period).abs() > PERIOD_TOLERANCE * period {
                    return Err(file_err(
                        line,
                        "t_s",
                        format!(
                            "time step {step} s differs from the trace period {period} s (the first step): a servo trace is sampled at a fixed period"
                        ),
                    ));
                }
            }
        }
        times.push(t_s);
        trace.encoder_mm.push(num(columns[1], POSITION_MAX_MM)?);
        trace.scale_mm.push(num(columns[2], POSITION_MAX_MM)?);
        if let Some(i) = command {
            trace.command_mm.push(num(i, POSITION_MAX_MM)?);
        }
    }
    if times.len() < 2 {
        return Err(file_err(
            2,
            "t_s",
            format!("{} samples: a trace needs at least two", times.len()),
        ));
    }
    // The mean step: rounding of the written times does not bias the period.
    trace.period_s = (times[times.len() - 1] - times[0]) / (times.len() - 1) as f64;
    Ok(trace)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A second `encoder_mm` column was ignored silently (the first one was read).
    #[test]
    fn a_duplicated_column_is_refused_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dup.csv");
        let rows = "0,10,10,11\n0.002,10,10,11\n0.004,10,10,11\n";
        std::fs::write(&path, format!("t_s,encoder_mm,scale_mm,encoder_mm\n{rows}")).unwrap();
        let e = read_trace(&path).unwrap_err().to_string();
        assert!(
            e.ends_with(
                "dup.csv: line 1, column `encoder_mm`: column appears twice (columns 2 and 4)"
            ),
            "{e}"
        );
        // The same rows with distinct names are read.
        std::fs::write(&path, format!("t_s,encoder_mm,scale_mm,other\n{rows}")).unwrap();
        assert_eq!(read_trace(&path).unwrap().encoder_mm, vec![10.0; 3]);
    }

    /// A spreadsheet's export said "column `-`: found record with 6 fields" (decimal
    /// commas) and "`t_s` is missing" (';' separated, or an empty file), as the
    /// measurement reader no longer does.
    #[test]
    fn spreadsheet_exports_and_an_empty_file_are_named_as_such() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.csv");
        for (text, want) in [
            (
                "t_s,encoder_mm,scale_mm\n0,10,10\n0,002,10,10\n",
                "line 3: 4 cells where the header has 3: a decimal comma splits a number in \
                 two (compgate reads numbers with a decimal point), or a column has no name in \
                 the header",
            ),
            (
                "t_s;encoder_mm;scale_mm\n0;10;10\n",
                "line 1: the header is separated by ';': compgate reads \
                 comma-separated files with a decimal point",
            ),
            (
                "",
                "the file is empty: expected a header line \
                 t_s,encoder_mm,scale_mm[,command_mm]",
            ),
        ] {
            std::fs::write(&path, text).unwrap();
            let e = read_trace(&path).unwrap_err().to_string();
            let want = format!("{}: {want}", path.display());
            assert!(e.starts_with(&want), "{text:?}: {e}");
        }
        // Blank lines, comments and any line end do not shift the line named.
        for text in [
            "t_s,encoder_mm,scale_mm\n0,1,1\n\n0.002,1,x\n",
            "# XL-80\nt_s,encoder_mm,scale_mm\n0,1,1\n0.002,1,x\n",
            "t_s,encoder_mm,scale_mm\r0,1,1\r\r0.002,1,x\r",
            "t_s,encoder_mm,scale_mm\r\n0,1,1\r\n# moved\r\n0.002,1,x\r\n",
        ] {
            std::fs::write(&path, text).unwrap();
            let e = read_trace(&path).unwrap_err().to_string();
            assert!(
                e.ends_with("line 4, column `scale_mm`: \"x\" is not a number"),
                "{text:?}: {e}"
            );
        }
    }
}
