//! Measured error data: the CSV format `calibrate` and `diagnose` read and `export`
//! writes, so that recorded operation and laser measurements feed commissioning alike.
//!
//! One header row, comma separated with a decimal point (a header split on `;` or
//! tabs, a spreadsheet's decimal-comma export, is refused as such), one row per
//! measurement in time order:
//!
//! | column      | unit | required | plausible range      | meaning                                          |
//! |-------------|------|----------|----------------------|--------------------------------------------------|
//! | `t_s`       | s    | yes      | 0..=315576000 (10 a) | time since the start, non-decreasing             |
//! | `pos_mm`    | mm   | yes      | -100000..=100000     | axis position of the measurement                 |
//! | `err_um`    | um   | yes      | -100000..=100000     | positioning error, actual minus commanded        |
//! | `T_<name>`  | degC | >= 1     | -100..=500           | a temperature sensor; `<name>` is its channel: 1..=64 of `A-Z a-z 0-9 _ -`, no `__`, not ending in `_` |
//! | `dir`       | -    | no       | +1 or -1             | direction of the last move; else the sign of the last non-zero position change |
//! | `travel_mm` | mm   | no       | 0..=1e9 (1000 km)    | distance travelled since the previous row; else abs(delta pos_mm) |
//!
//! Every value must be a finite number within its plausible range (the bounds are
//! the `*_MIN`/`*_MAX` constants of this module): a value outside is refused with
//! its line and column, never fed to a fit.
//!
//! Any other column is reported in [`Measurements::ignored_columns`] and skipped.
//! A column without a name must be empty in every row (a spreadsheet's trailing
//! `,,`) and is left out; a row of empty cells is a blank line, a line starting with
//! `#` a comment. Lines end in LF, CRLF or a lone CR. The text must be
//! UTF-8: a byte that is not, or a UTF-16 file, is refused with the hint to save
//! the file as CSV UTF-8.

use std::io::{Read, Write};
use std::path::Path;

use thiserror::Error;

/// Plausible `t_s`: 0 ..= 10 years (of 365.25 days) in seconds.
pub const T_S_MAX: f64 = 315_576_000.0;
/// Plausible |`pos_mm`|: 100 m, longer than any machine axis.
pub const POS_MM_MAX: f64 = 100_000.0;
/// Plausible |`err_um`|: 100 mm of positioning error.
pub const ERR_UM_MAX: f64 = 100_000.0;
/// Lowest plausible temperature, degC.
pub const TEMP_DEGC_MIN: f64 = -100.0;
/// Highest plausible temperature, degC.
pub const TEMP_DEGC_MAX: f64 = 500.0;
/// Plausible `travel_mm` of one row: 0 ..= 1000 km (the machine may run for hours
/// between two rows).
pub const TRAVEL_MM_MAX: f64 = 1e9;

/// Errors reading or writing measurement CSV. Lines are 1-based file lines (the header
/// is line 1), columns are header names.
#[derive(Debug, Error)]
pub enum MeasureError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("line {line}: {message}")]
    Csv { line: u64, message: String },
    #[error(
        "line 1: required column `{name}` is missing{}",
        column_hint(name, found)
    )]
    MissingColumn {
        name: &'static str,
        /// A header that is the name with something after it (`err_um [um]`), or
        /// in other case (`POS_MM`).
        found: Option<String>,
    },
    /// A data line that is the header again: two files joined into one.
    #[error(
        "line {line} repeats the header of line {header_line}: two files joined into one? \
         Give each its own file, or delete the line if the rows go on in order"
    )]
    RepeatedHeader { line: u64, header_line: u64 },
    /// The header splits on another delimiter: an export of a spreadsheet set to a
    /// locale with decimal commas, which would otherwise read as one odd column.
    #[error(
        "line {line}: the header is separated by {delimiter}: compgate reads comma-separated \
         files with a decimal point"
    )]
    Delimiter {
        line: u64,
        /// `';'` or `tabs`.
        delimiter: &'static str,
    },
    #[error("the file is empty: expected a header line {expected}")]
    EmptyFile {
        /// The header the format starts with.
        expected: &'static str,
    },
    #[error("line 1: no temperature column (a column named T_<name>)")]
    NoTemperature,
    #[error("line 1: column `{0}` appears twice")]
    DuplicateColumn(String),
    /// A sensor name the gateway refuses as a channel name (it becomes the model's
    /// channel): units in the header, `T_column [degC]`, are the usual cause.
    #[error(
        "line {line}, column {column} `{header}`: {reason} (the name after `T_` becomes the \
         model's channel name; temperatures are degC): rename the header{hint} or delete \
         the column"
    )]
    SensorName {
        line: u64,
        /// 1-based.
        column: usize,
        header: String,
        reason: String,
        /// `, e.g. `T_column`,` when a usable name starts the header.
        hint: String,
    },
    /// A cell under a header without a name: the column's name is missing.
    #[error(
        "line {line}, column {column}: {value:?} under a header with no name: name the column \
         in the header or delete it"
    )]
    UnnamedValue {
        line: u64,
        /// 1-based.
        column: usize,
        value: String,
    },
    /// Bytes that are not UTF-8: a file saved in a legacy code page (Latin-1 `°`).
    #[error(
        "line {line}, column {column}{name}: not UTF-8 text: save the file as CSV in UTF-8 (a \
         spreadsheet's \"CSV UTF-8 (comma delimited)\")"
    )]
    Encoding {
        line: u64,
        /// 1-based.
        column: usize,
        /// ` (`name`)`, the column's header name (as far as it reads), or empty.
        name: String,
    },
    /// A UTF-16 byte order mark: a spreadsheet's "Unicode text" export.
    #[error(
        "the file is UTF-16 text (a spreadsheet's \"Unicode text\" export): save it as CSV in \
         UTF-8 (\"CSV UTF-8 (comma delimited)\")"
    )]
    Utf16,
    #[error("line {line}, column `{column}`: {reason} (value {value:?})")]
    Field {
        line: u64,
        column: String,
        value: String,
        reason: &'static str,
    },
    #[error(
        "line {line}, column `t_s`: time goes backwards ({t_s} s after {prev_s} s): rows in \
         time order; two runs in one file? give each a file of its own"
    )]
    TimeBackwards { line: u64, t_s: f64, prev_s: f64 },
    #[error("no data rows")]
    Empty,
}

/// Comma-separated text with a header row, read the way the measurement files are
/// (also a backlash servo trace): cells trimmed, every row as long as the header,
/// each row with its file line. The csv crate's positions point before the blank
/// lines that precede a row (and count a CRLF file's lines oddly), so the lines come
/// from the bytes read instead.
///
/// What a spreadsheet adds is taken as it means: columns without a name that are
/// empty in every row (trailing `,,`) are left out of the header and the rows, and
/// rows whose cells are all empty are blank lines.
pub struct CsvInput<R> {
    rdr: csv::Reader<LineIndex<std::io::BufReader<R>>>,
    lines: std::rc::Rc<std::cell::RefCell<std::collections::VecDeque<(u64, u64)>>>,
    /// The header row, named columns only.
    pub header: csv::StringRecord,
    /// The header's file line (blank lines may come first).
    pub header_line: u64,
    /// The file column (0-based) of every entry of `header`.
    columns: Vec<usize>,
    /// File columns (0-based) without a name; every cell of theirs must be empty.
    unnamed: Vec<usize>,
    /// The header's cells as far as they read (lossy UTF-8), by file column.
    raw_names: Vec<String>,
    raw: csv::StringRecord,
}

impl<R: Read> CsvInput<R> {
    /// Opens `reader` and reads its header. Refuses an empty file, naming the header
    /// the format starts with (`expected`), and a header split on ';' or tabs (a
    /// spreadsheet's decimal-comma export) that has no column `key`, which "`key` is
    /// missing" would not explain.
    pub fn open(reader: R, key: &str, expected: &'static str) -> Result<Self, MeasureError> {
        let mut reader = std::io::BufReader::new(reader);
        // UTF-16 would read as one column of odd names, or as bytes that are not UTF-8.
        let start = std::io::BufRead::fill_buf(&mut reader).map_err(|e| MeasureError::Csv {
            line: 1,
            message: e.to_string(),
        })?;
        if is_utf16(start) {
            return Err(MeasureError::Utf16);
        }
        let index = LineIndex::new(reader);
        let lines = index.lines.clone();
        let rdr = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            .flexible(false)
            .comment(Some(b'#'))
            .from_reader(index);
        let mut input = CsvInput {
            rdr,
            lines,
            header: csv::StringRecord::new(),
            header_line: 1,
            columns: Vec::new(),
            unnamed: Vec::new(),
            raw_names: Vec::new(),
            raw: csv::StringRecord::new(),
        };
        match input.rdr.byte_headers() {
            Ok(h) => {
                input.raw_names = h
                    .iter()
                    .map(|c| String::from_utf8_lossy(c).into_owned())
                    .collect()
            }
            Err(e) => return Err(input.error(e)),
        }
        let raw_header = match input.rdr.headers() {
            Ok(h) => h.clone(),
            Err(e) => return Err(input.error(e)),
        };
        if raw_header.is_empty() {
            return Err(MeasureError::EmptyFile { expected });
        }
        input.header_line = input.line_at(raw_header.position());
        let mut header = csv::StringRecord::new();
        for (i, name) in raw_header.iter().enumerate() {
            if name.is_empty() {
                input.unnamed.push(i);
            } else {
                input.columns.push(i);
                header.push_field(name);
            }
        }
        if !header.iter().any(|h| h == key) {
            for (sep, delimiter) in [(';', "';'"), ('\t', "tabs")] {
                if header.iter().any(|h| h.contains(sep)) {
                    return Err(MeasureError::Delimiter {
                        line: input.header_line,
                        delimiter,
                    });
                }
            }
        }
        input.header = header;
        Ok(input)
    }

    /// Reads the next row into `record` (the named columns, as `header`); its file
    /// line, or `None` at the end. A row of empty cells is skipped as a blank line.
    pub fn next(&mut self, record: &mut csv::StringRecord) -> Result<Option<u64>, MeasureError> {
        loop {
            match self.rdr.read_record(&mut self.raw) {
                Ok(true) => {}
                Ok(false) => return Ok(None),
                Err(e) => return Err(self.error(e)),
            }
            let line = self.line_at(self.raw.position());
            if self.raw.iter().all(str::is_empty) {
                continue;
            }
            if let Some(&i) = self.unnamed.iter().find(|&&i| !self.raw[i].is_empty()) {
                return Err(MeasureError::UnnamedValue {
                    line,
                    column: i + 1,
                    value: self.raw[i].to_string(),
                });
            }
            if self.unnamed.is_empty() {
                std::mem::swap(record, &mut self.raw);
            } else {
                record.clear();
                for &i in &self.columns {
                    record.push_field(&self.raw[i]);
                }
            }
            return Ok(Some(line));
        }
    }

    /// The line of the first non-blank line at or after the csv crate's `position`.
    fn line_at(&self, position: Option<&csv::Position>) -> u64 {
        let Some(p) = position else { return 0 };
        let mut lines = self.lines.borrow_mut();
        // Rows come in file order: what lies before this one is never asked again.
        while lines.front().is_some_and(|&(start, _)| start < p.byte()) {
            lines.pop_front();
        }
        lines.front().map_or(p.line(), |&(_, line)| line)
    }

    /// A CSV error with its line; more cells than the header names get the hint
    /// that decimal commas split every number in two.
    fn error(&self, e: csv::Error) -> MeasureError {
        let line = self.line_at(e.position()).max(1);
        if let csv::ErrorKind::Utf8 { err, .. } = e.kind() {
            let field = err.field();
            let name = self
                .raw_names
                .get(field)
                .filter(|n| !n.is_empty())
                .map_or_else(String::new, |n| format!(" (`{n}`)"));
            return MeasureError::Encoding {
                line,
                column: field + 1,
                name,
            };
        }
        // The crate's own text names a record number and another line; ours the line.
        let message = match *e.kind() {
            csv::ErrorKind::UnequalLengths {
                expected_len, len, ..
            } if len > expected_len => format!(
                "{len} cells where the header has {expected_len}: a decimal comma splits a \
                 number in two (compgate reads numbers with a decimal point), or a column \
                 has no name in the header"
            ),
            csv::ErrorKind::UnequalLengths {
                expected_len, len, ..
            } => format!(
                "{len} cells where the header has {expected_len}: an empty cell still needs \
                 its comma"
            ),
            _ => e.to_string(),
        };
        MeasureError::Csv { line, message }
    }
}

/// A reader that notes where every line with data starts, (byte offset, line), as
/// the bytes pass to the CSV parser; [`CsvInput`] drops what it has passed. Lines end
/// as the parser ends them: at `\n`, `\r\n` or a lone `\r` (an old Mac export);
/// blank lines and comments (`#` first) hold no row.
struct LineIndex<R> {
    inner: R,
    lines: std::rc::Rc<std::cell::RefCell<std::collections::VecDeque<(u64, u64)>>>,
    offset: u64,
    line: u64,
    line_start: u64,
    /// Nothing on the line so far.
    blank: bool,
    /// The line starts with `#`.
    comment: bool,
    /// The last byte was a `\r`, so a `\n` now ends no further line.
    after_cr: bool,
}

impl<R> LineIndex<R> {
    fn new(inner: R) -> Self {
        LineIndex {
            inner,
            lines: Default::default(),
            offset: 0,
            line: 1,
            line_start: 0,
            blank: true,
            comment: false,
            after_cr: false,
        }
    }

    fn end_line(&mut self) {
        if !self.blank && !self.comment {
            self.lines
                .borrow_mut()
                .push_back((self.line_start, self.line));
        }
    }
}

impl<R: Read> Read for LineIndex<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        if n == 0 {
            self.end_line();
            self.blank = true;
        }
        for &b in &buf[..n] {
            match b {
                b'\n' if self.after_cr => self.line_start = self.offset + 1,
                b'\n' | b'\r' => {
                    self.end_line();
                    self.line += 1;
                    self.line_start = self.offset + 1;
                    self.blank = true;
                    self.comment = false;
                }
                b'#' if self.blank => {
                    self.comment = true;
                    self.blank = false;
                }
                _ => self.blank = false,
            }
            self.after_cr = b == b'\r';
            self.offset += 1;
        }
        Ok(n)
    }
}

/// Longest channel name the gateway takes, characters.
pub const MAX_CHANNEL_NAME_LEN: usize = 64;

/// Whether text starts with a UTF-16 byte order mark (a spreadsheet's "Unicode text"
/// export, Windows Notepad's "Unicode"), which would otherwise read as bytes that are
/// not UTF-8. The CSV reader and the configuration loader share it.
pub fn is_utf16(start: &[u8]) -> bool {
    start.starts_with(&[0xff, 0xfe]) || start.starts_with(&[0xfe, 0xff])
}

/// Why `name` cannot name a channel, device or axis of the gateway, or `None`:
/// 1..=64 characters of `A-Z a-z 0-9 _ -`, without `__` (the level separator of
/// environment overrides) and not ending in `_` (`COMPGATE__CHANNELS__T___ADDRESS`
/// would split as `T` and `_ADDRESS`). The gateway's config and the sensor columns
/// `T_<name>` of a measurement CSV (they name a model's channels) share it.
pub fn channel_name_problem(name: &str) -> Option<String> {
    let len = name.chars().count();
    if name.is_empty() {
        Some("name must not be empty".into())
    } else if len > MAX_CHANNEL_NAME_LEN {
        Some(format!(
            "name of {len} characters, longer than {MAX_CHANNEL_NAME_LEN}"
        ))
    } else if !name
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        Some("name may contain only A-Z, a-z, 0-9, `_` and `-`".into())
    } else if name.contains("__") {
        Some("name must not contain `__`, the level separator of environment overrides".into())
    } else if name.ends_with('_') {
        Some(
            "name must not end in `_`: in an environment override it would run into the \
             `__` after it (`T_` + `__ADDRESS` reads as `T` and `_ADDRESS`)"
                .into(),
        )
    } else {
        None
    }
}

/// A measurement file, buffered; an error names it.
fn open(path: &Path) -> Result<std::io::BufReader<std::fs::File>, MeasureError> {
    open_file(path)
        .map(std::io::BufReader::new)
        .map_err(|source| MeasureError::Io {
            path: path.display().to_string(),
            source,
        })
}

/// Opens a file to read, refusing a directory at once: opening one succeeds, and the
/// first read failed as "line 1: Is a directory".
pub fn open_file(path: &Path) -> std::io::Result<std::fs::File> {
    let file = std::fs::File::open(path)?;
    if file.metadata()?.is_dir() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::IsADirectory,
            "a directory, not a file",
        ));
    }
    Ok(file)
}

/// The columns a reader reads beside `pos_mm`, `err_um` and the optional ones.
#[derive(Debug, Clone, Copy)]
enum Wanted<'a> {
    /// `t_s` and the `T_` columns: every one (`None`, at least one required) or these
    /// sensors' (names without `T_`).
    Thermal(Option<&'a [&'a str]>),
    /// Neither: `t_s` is read if there, `T_` columns are not.
    Positions,
}

impl Wanted<'_> {
    /// Whether the `T_<sensor>` column is read.
    fn reads(&self, sensor: &str) -> bool {
        match self {
            Wanted::Thermal(None) => true,
            Wanted::Thermal(Some(names)) => names.contains(&sensor),
            Wanted::Positions => false,
        }
    }
}

/// One temperature column.
#[derive(Debug, Clone, PartialEq)]
pub struct TempColumn {
    /// Sensor name without the `T_` prefix.
    pub name: String,
    /// One value per row.
    pub degc: Vec<f64>,
}

/// The hint of [`MeasureError::MissingColumn`] when a header carries the name and
/// more, or the name in other case.
fn column_hint(name: &str, found: &Option<String>) -> String {
    match found {
        Some(h) if h.eq_ignore_ascii_case(name) => {
            format!(" (there is a column `{h}`: names are lower case, `{name}`)")
        }
        Some(h) => {
            format!(" (there is a column `{h}`: the header holds the name alone, without units)")
        }
        None => String::new(),
    }
}

/// See [`Measurements::temperature_excursions`], K.
pub const EXCURSION_K: f64 = 5.0;
/// See [`Measurements::temperature_excursions`]: a step must be this many times the
/// sensor's median change from row to row too.
pub const EXCURSION_TYPICAL_STEPS: f64 = 10.0;
/// See [`Measurements::temperature_excursions`], K: the spread of a fault value's
/// rows (a constant written for a missing reading).
pub const EXCURSION_FLAT_K: f64 = 0.1;

/// See [`Measurements::frozen_readings`], s: a live reading flickers in its last
/// digit well within half an hour while another part of the machine warms.
pub const FROZEN_MIN_S: f64 = 1800.0;
/// See [`Measurements::frozen_readings`], K.
pub const FROZEN_OTHERS_K: f64 = 2.0;
/// See [`Measurements::frozen_readings`]: fewer rows than this say too little.
const FROZEN_MIN_ROWS: usize = 10;

/// A reading held at one value ([`Measurements::frozen_readings`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Frozen {
    /// Sensor name without `T_`.
    pub sensor: String,
    /// Its rows (0-based).
    pub rows: std::ops::Range<usize>,
    /// The value it holds, degC.
    pub degc: f64,
    /// The sensor that moved most meanwhile, without `T_`.
    pub other: String,
    /// How far that one moved meanwhile (its range), K.
    pub other_moved_k: f64,
}

/// A temperature excursion ([`Measurements::temperature_excursions`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Excursion {
    /// Sensor name without `T_`.
    pub sensor: String,
    /// Its rows (0-based).
    pub rows: std::ops::Range<usize>,
    /// The reading before it, degC.
    pub before_degc: f64,
    /// The reading during it (its first row), degC.
    pub during_degc: f64,
}

/// A measurement series, column-wise.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Measurements {
    pub t_s: Vec<f64>,
    pub pos_mm: Vec<f64>,
    pub err_um: Vec<f64>,
    /// +1/-1; 0 while the direction is unknown (no move yet and no `dir` column).
    pub dir: Vec<i8>,
    pub travel_mm: Vec<f64>,
    pub temps: Vec<TempColumn>,
    /// Header names that are not part of the format, in file order.
    pub ignored_columns: Vec<String>,
}

impl Measurements {
    /// Number of rows.
    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    /// True when there are no rows.
    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }

    /// The temperature column of a sensor: `name` is the column's name without `T_`,
    /// or, failing that, with it. A gateway channel named `T_bed` is exported as the
    /// column `T_bed`, sensor `bed`: a model of the running config, whose terms name
    /// `T_bed`, reads that column.
    pub fn temp(&self, name: &str) -> Option<&[f64]> {
        let find = |n: &str| self.temps.iter().find(|c| c.name == n);
        find(name)
            .or_else(|| name.strip_prefix("T_").and_then(find))
            .map(|c| c.degc.as_slice())
    }

    /// Reads a file; errors name the file.
    pub fn read_path(path: &Path) -> Result<Self, MeasureError> {
        Self::read_path_with_lines(path).map(|(m, _)| m)
    }

    /// [`Measurements::read_path`], with the 1-based file line of every row (blank
    /// lines are skipped, so a row's index does not give its line).
    pub fn read_path_with_lines(path: &Path) -> Result<(Self, Vec<u64>), MeasureError> {
        Self::read_with_lines(open(path)?)
    }

    /// Reads CSV from any reader.
    pub fn read<R: Read>(reader: R) -> Result<Self, MeasureError> {
        Self::read_with_lines(reader).map(|(m, _)| m)
    }

    /// [`Measurements::read`], with the file line of every row.
    pub fn read_with_lines<R: Read>(reader: R) -> Result<(Self, Vec<u64>), MeasureError> {
        Self::read_rows(reader, Wanted::Thermal(None))
    }

    /// [`Measurements::read_path_with_lines`] for a fit of some sensors only: the `T_`
    /// columns of the others (names without `T_`) are listed in `ignored_columns`
    /// unread, so a bad cell of a sensor the fit leaves out does not stop it.
    pub fn read_path_sensors(
        path: &Path,
        sensors: &[&str],
    ) -> Result<(Self, Vec<u64>), MeasureError> {
        Self::read_rows(open(path)?, Wanted::Thermal(Some(sensors)))
    }

    /// Readings that leave a sensor's level by more than [`EXCURSION_K`] (and
    /// [`EXCURSION_TYPICAL_STEPS`] times its median step) from one row to the next,
    /// hold one value (within [`EXCURSION_FLAT_K`]) and come back to
    /// within 1 K (or a fifth of the step) of that level: a sensor that dropped out,
    /// a 0 or a fault value written for a missing reading. A sensor that heats or
    /// cools fast (a motor winding) moves through its values and does not come back
    /// at once, however far apart the rows.
    pub fn temperature_excursions(&self) -> Vec<Excursion> {
        let mut found = Vec::new();
        for c in &self.temps {
            let v = &c.degc;
            // Rows hours apart change by kelvins as the machine does: a step counts
            // only far beyond the sensor's own typical change from row to row.
            let mut steps: Vec<f64> = v.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
            steps.sort_by(f64::total_cmp);
            let typical = steps.get(steps.len() / 2).copied().unwrap_or(0.0);
            let least = EXCURSION_K.max(EXCURSION_TYPICAL_STEPS * typical);
            let mut i = 1;
            while i < v.len() {
                let (before, step) = (v[i - 1], v[i] - v[i - 1]);
                if step.abs() <= least {
                    i += 1;
                    continue;
                }
                let mut k = i;
                while k < v.len()
                    && (v[k] - before).abs() > EXCURSION_K
                    && (v[k] - v[i]).abs() <= EXCURSION_FLAT_K
                {
                    k += 1;
                }
                if k < v.len() && (v[k] - before).abs() <= (0.2 * step.abs()).max(1.0) {
                    found.push(Excursion {
                        sensor: c.name.clone(),
                        rows: i..k,
                        before_degc: before,
                        during_degc: v[i],
                    });
                    i = k + 1;
                } else {
                    i += 1;
                }
            }
        }
        found.sort_by_key(|e| e.rows.start);
        found
    }

    /// Readings that hold exactly one value for [`FROZEN_MIN_S`] at least while another
    /// sensor of the file moves by more than [`FROZEN_OTHERS_K`]: a frozen transmitter,
    /// or a last value held for a sensor that went silent. A sensor at a steady level
    /// still flickers in its last digit; one far from the heat may not, so these are
    /// doubts to weigh, not faults.
    pub fn frozen_readings(&self) -> Vec<Frozen> {
        let mut found = Vec::new();
        for c in &self.temps {
            let v = &c.degc;
            let mut start = 0;
            while start < v.len() {
                // At least one row: a NaN equals nothing, itself neither.
                let end = start
                    + v[start..]
                        .iter()
                        .take_while(|&&x| x == v[start])
                        .count()
                        .max(1);
                let held = end - start >= FROZEN_MIN_ROWS
                    && self.t_s[end - 1] - self.t_s[start] >= FROZEN_MIN_S;
                if held {
                    let moved = self
                        .temps
                        .iter()
                        .filter(|o| o.name != c.name)
                        .map(|o| {
                            let (lo, hi) = o.degc[start..end]
                                .iter()
                                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
                                    (lo.min(x), hi.max(x))
                                });
                            (o, hi - lo)
                        })
                        .max_by(|a, b| a.1.total_cmp(&b.1));
                    if let Some((o, k)) = moved.filter(|(_, k)| *k > FROZEN_OTHERS_K) {
                        found.push(Frozen {
                            sensor: c.name.clone(),
                            rows: start..end,
                            degc: v[start],
                            other: o.name.clone(),
                            other_moved_k: k,
                        });
                    }
                }
                start = end;
            }
        }
        found.sort_by_key(|f| f.rows.start);
        found
    }

    /// The positions alone, for an evaluation that needs no time or temperature (ISO
    /// 230-2 from a laser's file): `t_s` and `T_<name>` may be missing, and `T_`
    /// cells are not read (a sensor's bad cell does not stop it); a row without
    /// `t_s` has time 0, and `t_s` may restart (two sessions in one file). With the
    /// file line of every row; errors name the file.
    pub fn read_positions_path(path: &Path) -> Result<(Self, Vec<u64>), MeasureError> {
        Self::read_rows(open(path)?, Wanted::Positions)
    }

    /// The reader, of the columns `wanted`.
    fn read_rows<R: Read>(reader: R, wanted: Wanted<'_>) -> Result<(Self, Vec<u64>), MeasureError> {
        let thermal = matches!(wanted, Wanted::Thermal(_));
        let (key, expected) = if thermal {
            ("t_s", "t_s,pos_mm,err_um,T_<name>")
        } else {
            ("pos_mm", "pos_mm,dir,err_um")
        };
        let mut input = CsvInput::open(reader, key, expected)?;
        let header = input.header.clone();
        let mut lines = Vec::new();

        let mut seen = std::collections::HashSet::new();
        let (mut i_t, mut i_pos, mut i_err, mut i_dir, mut i_travel) =
            (None, None, None, None, None);
        let mut temp_idx = Vec::new();
        let mut out = Measurements::default();
        for (i, name) in header.iter().enumerate() {
            if !seen.insert(name.to_string()) {
                return Err(MeasureError::DuplicateColumn(name.to_string()));
            }
            match name {
                "t_s" => i_t = Some(i),
                "pos_mm" => i_pos = Some(i),
                "err_um" => i_err = Some(i),
                "dir" => i_dir = Some(i),
                "travel_mm" => i_travel = Some(i),
                _ => match name.strip_prefix("T_") {
                    Some(sensor) if !sensor.is_empty() && wanted.reads(sensor) => {
                        if let Some(reason) = channel_name_problem(sensor) {
                            let usable: String = sensor
                                .chars()
                                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_' || *c == '-')
                                .collect();
                            let usable = usable.trim_end_matches(['_', '-']);
                            return Err(MeasureError::SensorName {
                                line: input.header_line,
                                column: input.columns[i] + 1,
                                header: name.to_string(),
                                reason,
                                hint: if usable.is_empty() || usable == sensor {
                                    String::new()
                                } else {
                                    format!(", e.g. `T_{usable}`,")
                                },
                            });
                        }
                        temp_idx.push(i);
                        out.temps.push(TempColumn {
                            name: sensor.to_string(),
                            degc: Vec::new(),
                        });
                    }
                    _ => out.ignored_columns.push(name.to_string()),
                },
            }
        }
        let missing = |name: &'static str| MeasureError::MissingColumn {
            name,
            found: header
                .iter()
                .find(|h| {
                    (h.len() > name.len() && h.starts_with(name)) || h.eq_ignore_ascii_case(name)
                })
                .map(str::to_string),
        };
        let i_t = match i_t {
            None if thermal => return Err(missing("t_s")),
            i_t => i_t,
        };
        let i_pos = i_pos.ok_or_else(|| missing("pos_mm"))?;
        let i_err = i_err.ok_or_else(|| missing("err_um"))?;
        // Sensors left out (`Wanted::Thermal(Some)`) count: the fit names a missing one.
        if thermal && !header.iter().any(|h| h.len() > 2 && h.starts_with("T_")) {
            return Err(MeasureError::NoTemperature);
        }

        let mut record = csv::StringRecord::new();
        let mut last_dir: i8 = 0;
        while let Some(line) = input.next(&mut record)? {
            if header
                .iter()
                .enumerate()
                .all(|(i, h)| record[i].trim() == h)
            {
                return Err(MeasureError::RepeatedHeader {
                    line,
                    header_line: input.header_line,
                });
            }
            let bad = |i: usize, reason| MeasureError::Field {
                line,
                column: header[i].to_string(),
                value: record[i].to_string(),
                reason,
            };
            let num = |i: usize| -> Result<f64, MeasureError> {
                let v: f64 = record[i].parse().map_err(|_| {
                    let cell = record[i].trim();
                    bad(
                        i,
                        if cell.is_empty() {
                            "an empty cell: every row needs a value in every column (logged \
                             less often than the error? give each row the last reading before \
                             it)"
                        } else if cell.replacen(',', ".", 1).parse::<f64>().is_ok() {
                            "not a number: a decimal comma? compgate reads numbers with a \
                             decimal point"
                        } else {
                            "not a number"
                        },
                    )
                })?;
                if v.is_finite() {
                    Ok(v)
                } else {
                    Err(bad(i, "not a finite number"))
                }
            };
            // A finite number within `lo..=hi`; `reason` states the range.
            let within = |i: usize, lo: f64, hi: f64, reason| -> Result<f64, MeasureError> {
                let v = num(i)?;
                if (lo..=hi).contains(&v) {
                    Ok(v)
                } else {
                    Err(bad(i, reason))
                }
            };
            let t_s = match i_t {
                Some(i) => within(
                    i,
                    0.0,
                    T_S_MAX,
                    "outside the plausible range 0..=315576000 s (10 years)",
                )?,
                None => 0.0,
            };
            // Positions alone (ISO 230-2) take the file's order as the run order, and a
            // laser's export of two sessions restarts its clock.
            if let (true, Some(&prev_s)) = (thermal, out.t_s.last()) {
                if t_s < prev_s {
                    return Err(MeasureError::TimeBackwards { line, t_s, prev_s });
                }
            }
            let pos_mm = within(
                i_pos,
                -POS_MM_MAX,
                POS_MM_MAX,
                "outside the plausible range -100000..=100000 mm",
            )?;
            let delta_mm = out.pos_mm.last().map_or(0.0, |p| pos_mm - p);
            let dir = match i_dir {
                // A "+" or "up" was "not a number", which said nothing of the values.
                Some(i) => match record[i].trim().parse::<f64>() {
                    Ok(1.0) => 1,
                    Ok(-1.0) => -1,
                    _ => {
                        return Err(MeasureError::Field {
                            line,
                            column: "dir".into(),
                            value: record[i].to_string(),
                            reason: "must be +1 (approached upwards) or -1 (downwards)",
                        })
                    }
                },
                None => {
                    if delta_mm > 0.0 {
                        last_dir = 1;
                    } else if delta_mm < 0.0 {
                        last_dir = -1;
                    }
                    last_dir
                }
            };
            let travel_mm = match i_travel {
                Some(i) => {
                    let v = num(i)?;
                    if v < 0.0 {
                        return Err(bad(i, "must not be negative"));
                    }
                    within(
                        i,
                        0.0,
                        TRAVEL_MM_MAX,
                        "outside the plausible range 0..=1e9 mm (1000 km)",
                    )?
                }
                None => delta_mm.abs(),
            };
            out.err_um.push(within(
                i_err,
                -ERR_UM_MAX,
                ERR_UM_MAX,
                "outside the plausible range -100000..=100000 um",
            )?);
            for (col, &i) in out.temps.iter_mut().zip(&temp_idx) {
                col.degc.push(within(
                    i,
                    TEMP_DEGC_MIN,
                    TEMP_DEGC_MAX,
                    "outside the plausible range -100..=500 degC",
                )?);
            }
            out.t_s.push(t_s);
            out.pos_mm.push(pos_mm);
            out.dir.push(dir);
            out.travel_mm.push(travel_mm);
            lines.push(line);
        }
        if out.is_empty() {
            return Err(MeasureError::Empty);
        }
        Ok((out, lines))
    }

    /// Writes the series in the same format (with `dir` and `travel_mm`), so that
    /// `read(write(m)) == m` up to float formatting (Rust's shortest round-trip form).
    pub fn write<W: Write>(&self, writer: W) -> Result<(), MeasureError> {
        let mut w = RowWriter::new(writer, self.temps.iter().map(|c| c.name.as_str()))?;
        for i in 0..self.len() {
            w.row(
                Row {
                    t_s: self.t_s[i],
                    pos_mm: self.pos_mm[i],
                    dir: self.dir[i],
                    travel_mm: self.travel_mm[i],
                    err_um: self.err_um[i],
                },
                self.temps.iter().map(|c| c.degc[i]),
            )?;
        }
        w.finish()
    }

    /// Appends `row` and its temperatures, one per column of `temps`.
    pub fn push(&mut self, row: Row, degc: impl IntoIterator<Item = f64>) {
        self.t_s.push(row.t_s);
        self.pos_mm.push(row.pos_mm);
        self.dir.push(row.dir);
        self.travel_mm.push(row.travel_mm);
        self.err_um.push(row.err_um);
        for (c, v) in self.temps.iter_mut().zip(degc) {
            c.degc.push(v);
        }
    }
}

/// One measurement row but its temperatures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Row {
    pub t_s: f64,
    pub pos_mm: f64,
    /// +1/-1; 0 unknown (written as +1: the format has no "unknown").
    pub dir: i8,
    pub travel_mm: f64,
    pub err_um: f64,
}

/// Writes the measurement CSV a row at a time, so that a long export never holds
/// its rows in memory.
pub struct RowWriter<W: Write> {
    w: csv::Writer<W>,
    row: Vec<String>,
}

fn csv_err(e: csv::Error) -> MeasureError {
    MeasureError::Csv {
        line: 0,
        message: e.to_string(),
    }
}

impl<W: Write> RowWriter<W> {
    /// Writes the header, with a column `T_<name>` for each of `temps`.
    pub fn new<'a>(
        writer: W,
        temps: impl IntoIterator<Item = &'a str>,
    ) -> Result<Self, MeasureError> {
        let mut w = csv::Writer::from_writer(writer);
        let mut header = vec![
            "t_s".to_string(),
            "pos_mm".into(),
            "dir".into(),
            "travel_mm".into(),
            "err_um".into(),
        ];
        header.extend(temps.into_iter().map(|n| format!("T_{n}")));
        w.write_record(&header).map_err(csv_err)?;
        Ok(RowWriter {
            w,
            row: Vec::with_capacity(header.len()),
        })
    }

    /// Writes one row.
    pub fn row(&mut self, r: Row, degc: impl IntoIterator<Item = f64>) -> Result<(), MeasureError> {
        self.row.clear();
        self.row.push(r.t_s.to_string());
        self.row.push(r.pos_mm.to_string());
        self.row.push(if r.dir < 0 { "-1" } else { "1" }.into());
        self.row.push(r.travel_mm.to_string());
        self.row.push(r.err_um.to_string());
        self.row.extend(degc.into_iter().map(|v| v.to_string()));
        self.w.write_record(&self.row).map_err(csv_err)
    }

    /// Flushes what is written.
    pub fn finish(mut self) -> Result<(), MeasureError> {
        self.w.flush().map_err(|source| MeasureError::Io {
            path: "output".into(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(s: &str) -> Result<Measurements, MeasureError> {
        Measurements::read(s.as_bytes())
    }

    #[test]
    fn derives_dir_and_travel_and_reports_other_columns() {
        let m = read(
            "t_s,pos_mm,err_um,T_bed,note,T_screw\n\
             0,0,1.0,20,a,21\n\
             1,100,2.0,20.5,b,22\n\
             2,100,2.5,20.6,c,22.5\n\
             3,50,1.5,20.7,d,23\n",
        )
        .unwrap();
        assert_eq!(m.len(), 4);
        assert_eq!(m.dir, vec![0, 1, 1, -1]);
        assert_eq!(m.travel_mm, vec![0.0, 100.0, 0.0, 50.0]);
        assert_eq!(m.ignored_columns, vec!["note".to_string()]);
        assert_eq!(m.temp("screw").unwrap(), &[21.0, 22.0, 22.5, 23.0]);
        assert_eq!(m.temps[0].name, "bed");
    }

    /// iso230 named line 19 for a value on line 21 of a file with two blank lines:
    /// it counted rows from the header. The reader gives every row's line.
    #[test]
    fn rows_keep_their_file_lines_across_blank_lines() {
        for (text, want) in [
            (
                "t_s,pos_mm,err_um,T_a\n0,0,1,20\n\n\n1,10,2,21\n2,20,3,22",
                [2, 5, 6],
            ),
            (
                "\u{feff}t_s,pos_mm,err_um,T_a\r\n0,0,1,20\r\n\r\n\r\n1,10,2,21\r\n2,20,3,22\r\n",
                [2, 5, 6],
            ),
            // An old Mac export ends its lines with a lone CR.
            (
                "t_s,pos_mm,err_um,T_a\r0,0,1,20\r\r\r1,10,2,21\r2,20,3,22\r",
                [2, 5, 6],
            ),
            // Comment lines (`#` first), before the header too, hold no row.
            (
                "# XL-80 run 3\nt_s,pos_mm,err_um,T_a\n0,0,1,20\n# paused\n\n1,10,2,21\n2,20,3,22\n",
                [3, 6, 7],
            ),
        ] {
            let (m, lines) = Measurements::read_with_lines(text.as_bytes()).unwrap();
            assert_eq!(m.len(), 3);
            assert_eq!(lines, want, "{text:?}");
        }
        // And the errors: a field, and a row of another length, after blank lines.
        let e = read("t_s,pos_mm,err_um,T_a\r\n0,0,1,20\r\n\r\n\r\n1,x,2,21\r\n").unwrap_err();
        assert!(e.to_string().starts_with("line 5, column `pos_mm`"), "{e}");
        let e = read("t_s,pos_mm,err_um,T_a\n0,0,1,20\n\n\n1,1,2,5,21\n").unwrap_err();
        assert!(e.to_string().starts_with("line 5: "), "{e}");
        let e = read("t_s,pos_mm,err_um,T_a\r0,0,1,20\r4,100,1,NaN\r").unwrap_err();
        assert!(e.to_string().starts_with("line 3, column `T_a`"), "{e}");
    }

    #[test]
    fn round_trips_through_write() {
        let m = read(
            "t_s,pos_mm,dir,travel_mm,err_um,T_a\n\
             0.5,10.25,-1,3.5,-0.125,20.1\n\
             0.75,11,1,0.75,0.3333333333333333,20.2\n",
        )
        .unwrap();
        let mut buf = Vec::new();
        m.write(&mut buf).unwrap();
        assert_eq!(read(std::str::from_utf8(&buf).unwrap()).unwrap(), m);
    }

    /// A dropout to 0 is found whatever the rows' spacing (a check of rows at most
    /// 60 s apart missed it in a log every 120 s, named the row where the sensor came
    /// back, and refused a motor sensor heating 6.5 K a minute: field review).
    #[test]
    fn a_dropout_is_an_excursion_and_a_fast_sensor_is_not() {
        let series = |degc: Vec<f64>| Measurements {
            t_s: (0..degc.len()).map(|i| 120.0 * i as f64).collect(),
            pos_mm: vec![0.0; degc.len()],
            err_um: vec![0.0; degc.len()],
            dir: vec![1; degc.len()],
            travel_mm: vec![0.0; degc.len()],
            temps: vec![TempColumn {
                name: "a".into(),
                degc,
            }],
            ignored_columns: Vec::new(),
        };
        // 23.6 degC warming slowly, 0 on rows 10..15, a one-row -999 at 30.
        let mut v: Vec<f64> = (0..40).map(|i| 23.6 + 0.01 * i as f64).collect();
        v[10..15].fill(0.0);
        v[30] = -999.0;
        let e = series(v).temperature_excursions();
        assert_eq!(e.len(), 2, "{e:?}");
        assert_eq!((e[0].rows.clone(), e[0].during_degc), (10..15, 0.0));
        assert!((e[0].before_degc - 23.69).abs() < 1e-9, "{e:?}");
        assert_eq!(e[1].rows, 30..31);
        // A motor sensor: 25 K up with a 200 s time constant, rows 60 s apart, then
        // down again; and the same logged every 600 s with its noise.
        let motor: Vec<f64> = (0..120)
            .map(|i| {
                let t = 60.0 * i as f64;
                let on = |t: f64| 25.0 * (1.0 - (-(t / 200.0)).exp());
                20.0 + if t < 3600.0 {
                    on(t)
                } else {
                    on(3600.0) * (-((t - 3600.0) / 200.0)).exp()
                }
            })
            .collect();
        assert!(series(motor.clone()).temperature_excursions().is_empty());
        let coarse: Vec<f64> = motor
            .iter()
            .step_by(10)
            .enumerate()
            .map(|(i, v)| v + 0.03 * ((i * 7) % 5) as f64)
            .collect();
        assert!(series(coarse).temperature_excursions().is_empty());
    }

    /// A transmitter frozen at a plausible value went unnoticed (field review R5-D).
    #[test]
    fn a_reading_held_while_the_machine_warms_is_frozen() {
        // Rows 120 s apart over 4 h; the screw warms 9 K, the column 2 K.
        let n = 120;
        let t_s: Vec<f64> = (0..n).map(|i| 120.0 * i as f64).collect();
        let warm = |k: f64| -> Vec<f64> {
            (0..n)
                .map(|i| {
                    20.0 + k * (1.0 - (-(i as f64) / 80.0).exp()) + 0.013 * ((i * 7) % 3) as f64
                })
                .collect()
        };
        let mut column = warm(2.5);
        // Frozen from row 60 on (2 h).
        let held = column[60];
        column[60..].fill(held);
        // The ambient, logged to 0.1 K, holds 20.0 for 20 min (too short) and then
        // 20.1 while the screw warms: held as a frozen one is, which only the fit
        // can weigh (`calibrate::bad_readings`).
        let ambient: Vec<f64> = (0..n).map(|i| if i < 10 { 20.0 } else { 20.1 }).collect();
        let m = Measurements {
            t_s,
            pos_mm: vec![0.0; n],
            err_um: vec![0.0; n],
            dir: vec![1; n],
            travel_mm: vec![0.0; n],
            temps: vec![
                TempColumn {
                    name: "column".into(),
                    degc: column,
                },
                TempColumn {
                    name: "screw".into(),
                    degc: warm(12.0),
                },
                TempColumn {
                    name: "ambient".into(),
                    degc: ambient,
                },
            ],
            ignored_columns: Vec::new(),
        };
        let f = m.frozen_readings();
        assert_eq!(f.len(), 2, "{f:?}");
        assert_eq!(
            (f[0].sensor.as_str(), f[0].rows.clone()),
            ("ambient", 10..n)
        );
        assert_eq!(
            (f[1].sensor.as_str(), f[1].rows.clone(), f[1].degc),
            ("column", 60..n, held)
        );
        assert_eq!(f[1].other, "screw");
        assert!(f[1].other_moved_k > FROZEN_OTHERS_K, "{f:?}");
        // A live reading, flickering in its last digit, is not frozen.
        let mut live = m.clone();
        live.temps.truncate(2);
        live.temps[0].degc = warm(2.5);
        assert!(live.frozen_readings().is_empty());
    }

    /// Temperatures logged at another rate (empty cells), a quoted decimal comma,
    /// units in a header and two runs in one file were refused without a word of
    /// what to do (field review).
    #[test]
    fn refusals_say_what_to_do() {
        for (text, want) in [
            (
                "t_s,pos_mm,err_um,T_a\n0,0,1,20\n1,5,2,\n",
                "line 3, column `T_a`: an empty cell: every row needs a value in every column \
                 (logged less often than the error? give each row the last reading before it) \
                 (value \"\")",
            ),
            (
                "t_s,pos_mm,dir,err_um,T_a\n0,0,up,1,20\n",
                "line 2, column `dir`: must be +1 (approached upwards) or -1 (downwards) \
                 (value \"up\")",
            ),
            (
                "t_s,pos_mm,err_um,T_a\n0,0,\"1,5\",20\n",
                "line 2, column `err_um`: not a number: a decimal comma? compgate reads \
                 numbers with a decimal point (value \"1,5\")",
            ),
            (
                "t_s,pos_mm,err_um [um],T_a\n0,0,1,20\n",
                "line 1: required column `err_um` is missing (there is a column `err_um \
                 [um]`: the header holds the name alone, without units)",
            ),
            (
                "t_s,pos_mm,err_um,T_a\n0,0,1,20\n600,0,1,20\n0,0,1,20\n",
                "line 4, column `t_s`: time goes backwards (0 s after 600 s): rows in time \
                 order; two runs in one file? give each a file of its own",
            ),
            (
                "T_S,POS_MM,ERR_UM,T_BED\n0,0,1,20\n",
                "line 1: required column `t_s` is missing (there is a column `T_S`: names \
                 are lower case, `t_s`)",
            ),
            (
                "t_s,pos_mm,err_um,T_a\n0,0,1,20\n# second file\nt_s,pos_mm,err_um,T_a\n0,0,1,20\n",
                "line 4 repeats the header of line 1: two files joined into one? Give each \
                 its own file, or delete the line if the rows go on in order",
            ),
        ] {
            assert_eq!(read(text).unwrap_err().to_string(), want, "{text:?}");
        }
        // The positions alone: time is not read for its order.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("two_sessions.csv");
        std::fs::write(
            &path,
            "t_s,pos_mm,dir,err_um\n0,0,1,1\n600,0,-1,1\n0,0,1,1\n",
        )
        .unwrap();
        let (m, lines) = Measurements::read_positions_path(&path).unwrap();
        assert_eq!((m.len(), lines), (3, vec![2, 3, 4]));
    }

    #[test]
    fn errors_name_line_and_column() {
        // A directory read as a file failed as "line 1: Is a directory".
        let dir = std::env::temp_dir();
        let e = Measurements::read_path(&dir).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("{}: a directory, not a file", dir.display())
        );
        let e = read("t_s,pos_mm,err_um,T_a\n0,0,1,20\n1,x,1,20\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 3, column `pos_mm`: not a number (value \"x\")"
        );
        let e = read("t_s,pos_mm,err_um,T_a\n5,0,1,20\n4,0,1,20\n").unwrap_err();
        assert!(e.to_string().starts_with("line 3, column `t_s`"), "{e}");
        let e = read("t_s,pos_mm,err_um,T_a,dir\n5,0,1,20,0\n").unwrap_err();
        assert!(e.to_string().contains("column `dir`"), "{e}");
        let e = read("t_s,pos_mm,err_um,T_a\n5,0,1,20\n6,0,1\n").unwrap_err();
        assert!(e.to_string().starts_with("line 3:"), "{e}");
        let e = read("t_s,pos_mm,T_a\n5,0,20\n").unwrap_err();
        assert!(e.to_string().contains("`err_um` is missing"), "{e}");
        assert!(matches!(
            read("t_s,pos_mm,err_um\n0,0,0\n"),
            Err(MeasureError::NoTemperature)
        ));
        assert!(matches!(
            read("t_s,pos_mm,err_um,T_a\n"),
            Err(MeasureError::Empty)
        ));
        assert!(matches!(
            read("t_s,pos_mm,err_um,T_a,T_a\n0,0,0,1,1\n"),
            Err(MeasureError::DuplicateColumn(_))
        ));
        let e = read("t_s,pos_mm,err_um,T_a\n0,0,NaN,20\n").unwrap_err();
        assert!(e.to_string().contains("not a finite number"), "{e}");
    }

    /// A semicolon or tab separated file (a spreadsheet export in a decimal-comma
    /// locale) said "required column `t_s` is missing"; an empty file said so too.
    #[test]
    fn other_delimiters_and_an_empty_file_are_named() {
        let want = "line 1: the header is separated by ';': compgate reads comma-separated \
                    files with a decimal point";
        for text in [
            "t_s;pos_mm;err_um;T_a\n0;0;1;20\n",
            // German decimal commas: the header is what gives it away.
            "t_s;pos_mm;err_um;T_a\n0;0;1,5;20,25\n",
            "\u{feff}t_s;pos_mm;err_um;T_a\r\n0;0;1;20\r\n",
        ] {
            assert_eq!(read(text).unwrap_err().to_string(), want, "{text:?}");
        }
        let e = read("t_s\tpos_mm\terr_um\tT_a\n0\t0\t1\t20\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 1: the header is separated by tabs: compgate reads comma-separated files \
             with a decimal point"
        );
        for text in ["", "\n", "\r\n\n"] {
            let e = read(text).unwrap_err();
            assert!(matches!(e, MeasureError::EmptyFile { .. }), "{text:?}: {e}");
            assert!(e.to_string().starts_with("the file is empty"), "{e}");
        }
        // A comma header whose other names hold a ';' is not misread as one.
        let e = read("t_s,pos_mm,a;b,T_a\n0,0,x,20\n").unwrap_err();
        assert!(e.to_string().contains("`err_um` is missing"), "{e}");
        // Decimal commas under a comma header: more cells than names.
        let e = read("t_s,pos_mm,err_um,T_a\n0,0,1,5,20,25\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 2: 6 cells where the header has 4: a decimal comma splits a number in two \
             (compgate reads numbers with a decimal point), or a column has no name in the \
             header"
        );
        // Fewer cells is no decimal comma.
        let e = read("t_s,pos_mm,err_um,T_a\n0,0,1\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 2: 3 cells where the header has 4: an empty cell still needs its comma"
        );
        // Blank lines first: the header's own line.
        let e = read("\n\r\nt_s;pos_mm;err_um;T_a\n").unwrap_err();
        assert!(e.to_string().starts_with("line 3: "), "{e}");
    }

    /// `T_column [degC]` gave a model with channel `column [degC]`, which validate
    /// refuses: the header is refused here, naming its line and column.
    #[test]
    fn sensor_names_the_gateway_refuses_are_refused_with_their_column() {
        let e = read("t_s,pos_mm,err_um,T_bed,T_column [degC]\n0,0,1,20,21\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 1, column 5 `T_column [degC]`: name may contain only A-Z, a-z, \
             0-9, `_` and `-` (the name after `T_` becomes the model's channel name; \
             temperatures are degC): rename the header, e.g. `T_column`, or delete the \
             column"
        );
        // Blank lines first, and an unnamed column before it: the file's own line and column.
        let e = read("\nt_s,,pos_mm,err_um,T_a°C\n0,,0,1,20\n").unwrap_err();
        assert!(
            e.to_string().starts_with("line 2, column 5 `T_a°C`: "),
            "{e}"
        );
        for bad in ["T_a__b", &format!("T_{}", "a".repeat(65))] {
            let e = read(&format!("t_s,pos_mm,err_um,{bad}\n0,0,1,20\n")).unwrap_err();
            assert!(matches!(e, MeasureError::SensorName { .. }), "{bad}: {e}");
        }
        assert!(read("t_s,pos_mm,err_um,T_bed-top_2\n0,0,1,20\n").is_ok());
    }

    /// A spreadsheet's artefacts: trailing empty columns (`,,`) were refused as
    /// "column `` appears twice", one trailing comma made an ignored column with no
    /// name, and rows of commas below the data were "not a number".
    #[test]
    fn empty_unnamed_columns_and_rows_of_empty_cells_are_ignored() {
        let plain = read("t_s,pos_mm,err_um,T_a\n0,0,1,20\n1,10,2,21\n").unwrap();
        for text in [
            "t_s,pos_mm,err_um,T_a,\n0,0,1,20,\n1,10,2,21,\n",
            "t_s,pos_mm,err_um,T_a,,\n0,0,1,20,,\n1,10,2,21,,\n,,,,,\n,,,,,\n",
            "t_s,,pos_mm,err_um,T_a\n0,,0,1,20\n,,,,\n1,,10,2,21\n",
        ] {
            let (m, lines) = Measurements::read_with_lines(text.as_bytes()).unwrap();
            assert_eq!(m, plain, "{text:?}");
            assert!(m.ignored_columns.is_empty(), "{text:?}");
            assert_eq!(lines.len(), 2);
        }
        // The line numbers stay the file's.
        let e = read("t_s,pos_mm,err_um,T_a,\n0,0,1,20,\n,,,,\n1,x,2,21,\n").unwrap_err();
        assert!(e.to_string().starts_with("line 4, column `pos_mm`"), "{e}");
        // A value under no name is a column whose name is missing.
        let e = read("t_s,pos_mm,err_um,T_a,\n0,0,1,20,\n1,10,2,21,7\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 3, column 5: \"7\" under a header with no name: name the column in the \
             header or delete it"
        );
    }

    /// A Latin-1 `°` and a UTF-16 "Unicode text" export gave the csv crate's message
    /// with a 0-based field and no column name.
    #[test]
    fn text_that_is_not_utf8_is_named_with_its_line_and_column() {
        let read_bytes = |b: &[u8]| Measurements::read(b).unwrap_err().to_string();
        let e = read_bytes(b"t_s,pos_mm,err_um,T_Motor\xb0C\n0,0,1,20\n");
        assert_eq!(
            e,
            "line 1, column 4 (`T_Motor\u{fffd}C`): not UTF-8 text: save the file as CSV in \
             UTF-8 (a spreadsheet's \"CSV UTF-8 (comma delimited)\")"
        );
        let e = read_bytes(b"t_s,pos_mm,err_um,T_a\n0,0,1,20\n1,0,1,2\xb00\n");
        assert!(
            e.starts_with("line 3, column 4 (`T_a`): not UTF-8 text: save the file"),
            "{e}"
        );
        let utf16: Vec<u8> = "\u{feff}t_s\tpos_mm\terr_um\tT_a\r\n0\t0\t1\t20\r\n"
            .encode_utf16()
            .flat_map(u16::to_le_bytes)
            .collect();
        let e = read_bytes(&utf16);
        assert!(e.starts_with("the file is UTF-16 text"), "{e}");
        let be: Vec<u8> = "\u{feff}t_s"
            .encode_utf16()
            .flat_map(u16::to_be_bytes)
            .collect();
        assert!(matches!(
            Measurements::read(&be[..]),
            Err(MeasureError::Utf16)
        ));
    }

    /// The error of a file whose third line has `row` (header and a good line
    /// before it).
    fn third_line(row: &str) -> String {
        let text = format!("t_s,pos_mm,dir,travel_mm,err_um,T_a\n0,0,1,0,1,20\n{row}\n");
        read(&text).unwrap_err().to_string()
    }

    #[test]
    fn implausible_values_are_refused_with_line_and_column() {
        for (row, want) in [
            (
                "1,1e308,1,0,1,20",
                "line 3, column `pos_mm`: outside the plausible range -100000..=100000 mm \
                 (value \"1e308\")",
            ),
            (
                "1,0,1,0,-1e308,20",
                "line 3, column `err_um`: outside the plausible range -100000..=100000 um \
                 (value \"-1e308\")",
            ),
            (
                "1,0,1,0,1,1e300",
                "line 3, column `T_a`: outside the plausible range -100..=500 degC \
                 (value \"1e300\")",
            ),
            (
                "1e308,0,1,0,1,20",
                "line 3, column `t_s`: outside the plausible range 0..=315576000 s (10 years) \
                 (value \"1e308\")",
            ),
            (
                "1,0,1,1e308,1,20",
                "line 3, column `travel_mm`: outside the plausible range 0..=1e9 mm (1000 km) \
                 (value \"1e308\")",
            ),
            (
                "1,0,1,-1,1,20",
                "line 3, column `travel_mm`: must not be negative (value \"-1\")",
            ),
        ] {
            assert_eq!(third_line(row), want);
        }
        // Just past a bound.
        assert!(third_line("1,-100000.5,1,0,1,20").starts_with("line 3, column `pos_mm`"));
        assert!(third_line("1,0,1,0,1,-100.1").starts_with("line 3, column `T_a`"));
        let e = read("t_s,pos_mm,err_um,T_a\n-1,0,1,20\n").unwrap_err();
        assert!(
            e.to_string()
                .starts_with("line 2, column `t_s`: outside the plausible range"),
            "{e}"
        );
        // The bounds themselves are plausible.
        for text in [
            "t_s,pos_mm,err_um,T_a\n0,-100000,0,20\n0,100000,0,20\n",
            "t_s,pos_mm,err_um,T_a\n0,0,-100000,20\n0,0,100000,20\n",
            "t_s,pos_mm,err_um,T_a\n0,0,0,-100\n0,0,0,500\n",
            "t_s,pos_mm,err_um,T_a\n0,0,0,20\n315576000,0,0,20\n",
            "t_s,pos_mm,dir,travel_mm,err_um,T_a\n0,0,1,1e9,0,20\n",
        ] {
            assert!(read(text).is_ok(), "{text}");
        }
    }
}
