//! The tables of the reports: Markdown, as the guide shows them, and plain text in
//! fixed-width columns for the terminal.

use std::fmt::Write as _;

/// A Markdown table: a header row, the `|---|` rule, then the rows.
#[derive(Debug, Clone, Default)]
pub struct Markdown {
    header: Vec<String>,
    rows: Vec<Vec<String>>,
}

impl Markdown {
    /// A table with these column headers.
    pub fn new<S: Into<String>>(header: impl IntoIterator<Item = S>) -> Self {
        Self {
            header: header.into_iter().map(Into::into).collect(),
            rows: Vec::new(),
        }
    }

    /// Appends a row; an empty cell stays empty (`| |`).
    pub fn row<S: Into<String>>(&mut self, cells: impl IntoIterator<Item = S>) -> &mut Self {
        self.rows.push(cells.into_iter().map(Into::into).collect());
        self
    }

    /// The table, every line ending in a newline.
    pub fn render(&self) -> String {
        let mut s = line(&self.header);
        s.push('|');
        s.push_str(&"---|".repeat(self.header.len()));
        s.push('\n');
        for row in &self.rows {
            s.push_str(&line(row));
        }
        s
    }
}

fn line(cells: &[String]) -> String {
    let mut s = String::from("|");
    for c in cells {
        if c.is_empty() {
            s.push_str(" |");
        } else {
            let _ = write!(s, " {c} |");
        }
    }
    s.push('\n');
    s
}

/// Alignment of a plain-text column.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Align {
    /// Padded on the right.
    Left,
    /// Padded on the left (numbers).
    Right,
}

/// One plain-text column: the spaces before it, its width and alignment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Column {
    /// Spaces before the column.
    pub gap: usize,
    /// Width the cell is padded to (a longer cell is kept whole).
    pub width: usize,
    /// Which side is padded.
    pub align: Align,
}

impl Column {
    /// A left-aligned column.
    pub const fn left(gap: usize, width: usize) -> Self {
        Self {
            gap,
            width,
            align: Align::Left,
        }
    }

    /// A right-aligned column.
    pub const fn right(gap: usize, width: usize) -> Self {
        Self {
            gap,
            width,
            align: Align::Right,
        }
    }
}

/// A line of plain-text columns (no newline); cells beyond the columns are dropped.
pub fn plain_line<S: AsRef<str>>(columns: &[Column], cells: impl IntoIterator<Item = S>) -> String {
    let mut s = String::new();
    for (col, cell) in columns.iter().zip(cells) {
        let cell = cell.as_ref();
        s.push_str(&" ".repeat(col.gap));
        let _ = match col.align {
            Align::Left => write!(s, "{cell:<w$}", w = col.width),
            Align::Right => write!(s, "{cell:>w$}", w = col.width),
        };
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markdown_as_the_reports_print_it() {
        let mut t = Markdown::new(["axis", "+ (up)", "bidirectional"]);
        t.row(["A accuracy", "4.000", "11.000"]);
        t.row(["M mean", "", "5.500"]);
        assert_eq!(
            t.render(),
            "| axis | + (up) | bidirectional |\n|---|---|---|\n\
             | A accuracy | 4.000 | 11.000 |\n| M mean | | 5.500 |\n"
        );
    }

    #[test]
    fn plain_columns_pad_like_format_widths() {
        let cols = [Column::left(2, 6), Column::right(1, 7), Column::left(2, 0)];
        let x = 1.23456;
        assert_eq!(
            plain_line(&cols, ["lag", &format!("{x:.3}"), "ok"]),
            format!("  {:<6} {x:>7.3}  ok", "lag")
        );
    }
}
