//! Parser and writer of the error parameter file (format in the module doc of
//! [`crate::volumetric`]).

use std::fmt::Write as _;

use super::{
    ErrorModel, Geometry, Table, VolumetricError, AXES, COLUMNS, MM_PER_UM, RAD_PER_ARCSEC,
};

/// First token of the header line.
pub const MAGIC: &str = "compgate-volumetric-errors";
/// The one format version this build reads and writes.
pub const VERSION: u32 = 1;

/// Names of the squareness errors, in file order.
pub const SQUARENESS: [&str; 3] = ["EC0Y", "EB0Z", "EA0Z"];
/// Names of the C-axis location errors (two translations in um, two tilts in arcsec).
pub const LOCATION_C: [&str; 4] = ["XOC", "YOC", "AOC", "BOC"];
/// Names of the A-axis location errors (two translations in um, two tilts in arcsec).
pub const LOCATION_A: [&str; 4] = ["YOA", "ZOA", "BOA", "COA"];

fn err(line: usize, field: &str, message: impl Into<String>) -> VolumetricError {
    VolumetricError::Parse {
        line,
        field: field.to_string(),
        message: message.into(),
    }
}

fn number(line: usize, field: &str, token: Option<&str>) -> Result<f64, VolumetricError> {
    let t = token.ok_or_else(|| err(line, field, "missing value"))?;
    let v: f64 = t.parse().map_err(|_| {
        let hint = if t.replacen(',', ".", 1).parse::<f64>().is_ok() {
            " (a decimal comma? compgate reads numbers with a decimal point)"
        } else if t.contains(';') {
            " (fields are separated by spaces, not semicolons)"
        } else if t
            .trim_end_matches(|c: char| c.is_ascii_alphabetic() || "\"'°".contains(c))
            .parse::<f64>()
            .is_ok()
        {
            UNITS_FIXED
        } else {
            ""
        };
        err(line, field, format!("not a number: {t:?}{hint}"))
    })?;
    if !v.is_finite() {
        return Err(err(line, field, format!("not finite: {t:?}")));
    }
    // Wider than any machine's travel in mm or error in um or arcsec, and small
    // enough that the kinematics stay finite.
    if v.abs() > PLAUSIBLE_ABS {
        return Err(err(
            line,
            field,
            format!("{t:?} outside the plausible range -1e6..=1e6"),
        ));
    }
    Ok(v)
}

/// The hint for a unit written in the file.
const UNITS_FIXED: &str = " (the units are fixed: um, arc-seconds, mm for X, Y, Z and deg \
                           for A, C; write names and numbers only)";

/// The keywords that start a line outside a table.
const KEYWORDS: [&str; 6] = [
    "travel",
    "pivot_mm",
    "tool_length_mm",
    "squareness",
    "location",
    "table",
];

/// Largest magnitude of any number in an error file.
const PLAUSIBLE_ABS: f64 = 1e6;

fn axis_index(line: usize, field: &str, token: Option<&str>) -> Result<usize, VolumetricError> {
    let t = token.ok_or_else(|| err(line, field, "missing axis name"))?;
    AXES.iter()
        .position(|a| *a == t)
        .ok_or_else(|| err(line, field, format!("unknown axis {t:?} (X, Y, Z, A or C)")))
}

fn no_more<'a>(
    line: usize,
    mut tokens: impl Iterator<Item = &'a str>,
) -> Result<(), VolumetricError> {
    match tokens.next() {
        Some(t) if t.starts_with(|c: char| c.is_ascii_alphabetic()) => Err(err(
            line,
            "end of line",
            format!("unexpected {t:?}{UNITS_FIXED}"),
        )),
        Some(t) => Err(err(line, "end of line", format!("unexpected {t:?}"))),
        None => Ok(()),
    }
}

/// Decodes the bytes of an error file as UTF-8; the error names the first line that
/// is not, so that a stray Latin-1 byte can be found.
pub fn decode(bytes: &[u8]) -> Result<&str, VolumetricError> {
    std::str::from_utf8(bytes).map_err(|e| {
        let line = bytes[..e.valid_up_to()]
            .iter()
            .filter(|b| **b == b'\n')
            .count()
            + 1;
        err(line, "text", "not valid UTF-8")
    })
}

/// Parses an error parameter file. Every error names the 1-based line and the field.
pub fn parse(text: &str) -> Result<ErrorModel, VolumetricError> {
    // A byte order mark (Windows editors write one) is not part of the header; the
    // measurement CSV reader skips it too.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.split('#').next().unwrap_or("").trim()))
        .filter(|(_, l)| !l.is_empty());

    let (n, header) = lines.next().ok_or_else(|| {
        err(
            1,
            "header",
            format!("empty file; expected \"{MAGIC} {VERSION}\""),
        )
    })?;
    let mut h = header.split_whitespace();
    if h.next() != Some(MAGIC) {
        return Err(err(n, "header", format!("expected \"{MAGIC} {VERSION}\"")));
    }
    let version = h
        .next()
        .ok_or_else(|| err(n, "version", "missing version"))?;
    if version != VERSION.to_string() {
        return Err(err(
            n,
            "version",
            format!("unsupported version {version:?}; this build reads {VERSION}"),
        ));
    }
    no_more(n, h)?;

    let mut travel: [Option<(f64, f64)>; 5] = [None; 5];
    let mut travel_line = [0usize; 5];
    // With the line each came from: a second line silently replaced the first.
    let mut pivot_mm: Option<([f64; 3], usize)> = None;
    let mut tool_length_mm: Option<(f64, usize)> = None;
    let mut squareness_rad = [0.0; 3];
    let mut loc_c = [0.0; 4];
    let mut loc_a = [0.0; 4];
    let mut tables: [Option<(usize, Table)>; 5] = Default::default();
    // Line of each squareness/location error already read: a second line for the same
    // name silently replaced the first before.
    let mut named_seen: std::collections::BTreeMap<String, usize> = Default::default();

    while let Some((n, l)) = lines.next() {
        let mut t = l.split_whitespace();
        let key = t.next().unwrap_or("");
        match key {
            "travel" => {
                let i = axis_index(n, "axis", t.next())?;
                let unit = if i < 3 { "mm" } else { "deg" };
                let lo = number(n, &format!("{} min ({unit})", AXES[i]), t.next())?;
                let hi = number(n, &format!("{} max ({unit})", AXES[i]), t.next())?;
                no_more(n, t)?;
                if lo >= hi {
                    return Err(err(n, "max", format!("travel max {hi} not above min {lo}")));
                }
                if travel[i].is_some() {
                    return Err(err(n, "axis", format!("travel of {} given twice", AXES[i])));
                }
                travel[i] = Some((lo, hi));
                travel_line[i] = n;
            }
            "pivot_mm" => {
                let v = [
                    number(n, "pivot x (mm)", t.next())?,
                    number(n, "pivot y (mm)", t.next())?,
                    number(n, "pivot z (mm)", t.next())?,
                ];
                no_more(n, t)?;
                if let Some((_, first)) = pivot_mm {
                    return Err(err(
                        n,
                        "pivot_mm",
                        format!("pivot_mm given twice (first on line {first})"),
                    ));
                }
                pivot_mm = Some((v, n));
            }
            "tool_length_mm" => {
                let v = number(n, "tool length (mm)", t.next())?;
                no_more(n, t)?;
                if v < 0.0 {
                    return Err(err(n, "tool length (mm)", "negative"));
                }
                if let Some((_, first)) = tool_length_mm {
                    return Err(err(
                        n,
                        "tool_length_mm",
                        format!("tool_length_mm given twice (first on line {first})"),
                    ));
                }
                tool_length_mm = Some((v, n));
            }
            "squareness" | "location" => {
                let name = t
                    .next()
                    .ok_or_else(|| err(n, "name", "missing error name"))?;
                let (names, slot, units): (&[&str], &mut [f64], &[f64]) = match key {
                    "squareness" => (
                        &SQUARENESS,
                        &mut squareness_rad,
                        &[RAD_PER_ARCSEC, RAD_PER_ARCSEC, RAD_PER_ARCSEC],
                    ),
                    _ if name.ends_with("OC") => (
                        &LOCATION_C,
                        &mut loc_c,
                        &[MM_PER_UM, MM_PER_UM, RAD_PER_ARCSEC, RAD_PER_ARCSEC],
                    ),
                    _ => (
                        &LOCATION_A,
                        &mut loc_a,
                        &[MM_PER_UM, MM_PER_UM, RAD_PER_ARCSEC, RAD_PER_ARCSEC],
                    ),
                };
                let k = names.iter().position(|x| *x == name).ok_or_else(|| {
                    err(
                        n,
                        "name",
                        format!("unknown {key} error {name:?} (one of {})", names.join(", ")),
                    )
                })?;
                if let Some(first) = named_seen.insert(name.to_string(), n) {
                    return Err(err(
                        n,
                        "name",
                        format!("{key} {name} given twice (first on line {first})"),
                    ));
                }
                slot[k] = number(n, name, t.next())? * units[k];
                no_more(n, t)?;
            }
            "table" => {
                let i = axis_index(n, "axis", t.next())?;
                for (c, want) in COLUMNS[i].iter().enumerate() {
                    match t.next() {
                        Some(got) if got == *want => {}
                        Some(got) => {
                            let hint = if got.starts_with(want) {
                                UNITS_FIXED
                            } else {
                                ""
                            };
                            return Err(err(
                                n,
                                &format!("column {}", c + 2),
                                format!("expected {want}, found {got:?}{hint}"),
                            ));
                        }
                        None => {
                            return Err(err(
                                n,
                                &format!("column {}", c + 2),
                                format!("missing {want}"),
                            ))
                        }
                    }
                }
                no_more(n, t)?;
                if tables[i].is_some() {
                    return Err(err(n, "axis", format!("second table for {}", AXES[i])));
                }
                let start = n;
                let (tu, ru) = (MM_PER_UM, RAD_PER_ARCSEC);
                let mut table = Table::default();
                let mut closed = false;
                for (n, l) in lines.by_ref() {
                    if l == "end" {
                        closed = true;
                        break;
                    }
                    let mut t = l.split_whitespace();
                    let first = l.split_whitespace().next().unwrap_or("");
                    if first.eq_ignore_ascii_case("end") || KEYWORDS.contains(&first) {
                        return Err(err(
                            n,
                            "end",
                            format!(
                                "table {} of line {start} is not closed by a line \"end\" \
                                 before {first:?}",
                                AXES[i]
                            ),
                        ));
                    }
                    let pos_name = if i < 3 {
                        "position (mm)"
                    } else {
                        "angle (deg)"
                    };
                    let p = number(n, pos_name, t.next())?;
                    if let Some(&last) = table.pos.last() {
                        if p <= last {
                            return Err(err(
                                n,
                                pos_name,
                                format!("{p} not above the previous row's {last}"),
                            ));
                        }
                    }
                    let mut row = [0.0; 6];
                    for (c, v) in row.iter_mut().enumerate() {
                        *v = number(n, COLUMNS[i][c], t.next())? * if c < 3 { tu } else { ru };
                    }
                    if let Some(extra) = t.next() {
                        return Err(err(
                            n,
                            "end of line",
                            format!(
                                "unexpected {extra:?}: a row is the {pos_name} and the six \
                                 values {}",
                                COLUMNS[i].join(" ")
                            ),
                        ));
                    }
                    table.pos.push(p);
                    table.val.push(row);
                }
                if !closed {
                    return Err(err(start, "end", "table not closed by a line \"end\""));
                }
                if table.pos.len() < 2 {
                    return Err(err(start, "rows", "a table needs at least two rows"));
                }
                tables[i] = Some((start, table));
            }
            other => {
                return Err(err(
                    n,
                    "keyword",
                    format!("unknown keyword {other:?} ({})", KEYWORDS.join(", ")),
                ))
            }
        }
    }

    let end_line = text.lines().count().max(1);
    let mut tr = [(0.0, 0.0); 5];
    for i in 0..5 {
        tr[i] = travel[i].ok_or_else(|| {
            err(
                end_line,
                "travel",
                format!("no travel line for {}", AXES[i]),
            )
        })?;
    }
    let mut out_tables: [Table; 5] = Default::default();
    for (i, slot) in tables.into_iter().enumerate() {
        if let Some((line, table)) = slot {
            let (lo, hi) = tr[i];
            let (first, last) = (table.pos[0], table.pos[table.pos.len() - 1]);
            if first > lo || last < hi {
                // A C table measured over 0..360 for a travel of -200..200 spans enough
                // but is numbered otherwise.
                let wrap = if i >= 3 && last - first >= hi - lo.max(hi - 360.0) {
                    "; a rotary table is not wrapped: number its angles as the travel does \
                     (rows beyond it shifted by 360 deg)"
                } else {
                    ""
                };
                return Err(err(
                    line,
                    AXES[i],
                    format!(
                        "table covers {first}..{last} but the travel (line {}) is {lo}..{hi}; \
                         tables are not extrapolated{wrap}",
                        travel_line[i]
                    ),
                ));
            }
            out_tables[i] = table;
        }
    }
    Ok(ErrorModel::new(
        Geometry {
            pivot_mm: pivot_mm
                .ok_or_else(|| err(end_line, "pivot_mm", "missing pivot_mm line"))?
                .0,
            tool_length_mm: tool_length_mm
                .ok_or_else(|| err(end_line, "tool_length_mm", "missing tool_length_mm line"))?
                .0,
        },
        tr,
        out_tables,
        squareness_rad,
        loc_c,
        loc_a,
    ))
}

/// Writes a model in the file format (values in um and arcsec, shortest round-trip
/// decimal form).
pub fn write(model: &ErrorModel) -> String {
    let mut s = format!(
        "{MAGIC} {VERSION}\n\
         # Volumetric error parameters (format: compgate::volumetric module doc).\n\
         # Translations in um, rotations in arc-seconds; X, Y, Z in mm; A, C in deg.\n"
    );
    let g = &model.geometry;
    let _ = writeln!(
        s,
        "pivot_mm {} {} {}\ntool_length_mm {}",
        g.pivot_mm[0], g.pivot_mm[1], g.pivot_mm[2], g.tool_length_mm
    );
    for (i, (lo, hi)) in model.travel.iter().enumerate() {
        let _ = writeln!(s, "travel {} {lo} {hi}", AXES[i]);
    }
    for (k, name) in SQUARENESS.iter().enumerate() {
        let _ = writeln!(
            s,
            "squareness {name} {:.4}",
            model.squareness_rad[k] / RAD_PER_ARCSEC
        );
    }
    for (names, vals) in [(LOCATION_C, model.loc_c), (LOCATION_A, model.loc_a)] {
        for (k, name) in names.iter().enumerate() {
            let unit = if k < 2 { MM_PER_UM } else { RAD_PER_ARCSEC };
            let _ = writeln!(s, "location {name} {:.4}", vals[k] / unit);
        }
    }
    for (i, table) in model.tables.iter().enumerate() {
        if table.pos.is_empty() {
            continue;
        }
        let _ = writeln!(s, "table {} {}", AXES[i], COLUMNS[i].join(" "));
        for (p, row) in table.pos.iter().zip(&table.val) {
            let _ = write!(s, "{p}");
            for (c, v) in row.iter().enumerate() {
                let unit = if c < 3 { MM_PER_UM } else { RAD_PER_ARCSEC };
                let _ = write!(s, " {:.4}", v / unit);
            }
            s.push('\n');
        }
        s.push_str("end\n");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volumetric::synthetic_model;

    fn text() -> String {
        write(&synthetic_model(1.0))
    }

    /// A file saved with a byte order mark failed with `header: expected
    /// "compgate-volumetric-errors 1"`.
    #[test]
    fn a_byte_order_mark_is_skipped() {
        let plain = parse(&text()).unwrap();
        let with_bom = parse(&format!("\u{feff}{}", text())).unwrap();
        assert_eq!(write(&with_bom), write(&plain));
        // Only at the start: elsewhere it is an unknown keyword, named with its line.
        let inside = text().replacen("pivot_mm", "\u{feff}pivot_mm", 1);
        let e = parse(&inside).unwrap_err().to_string();
        assert!(e.starts_with("line 4, keyword: unknown keyword"), "{e}");
    }

    /// A second pivot_mm or tool_length_mm line silently replaced the first, while a
    /// second travel, squareness, location or table line is refused.
    #[test]
    fn duplicate_geometry_lines_are_refused_naming_both_lines() {
        let t = text();
        assert!(t.lines().nth(3).unwrap().starts_with("pivot_mm"), "{t}");
        assert!(
            t.lines().nth(4).unwrap().starts_with("tool_length_mm"),
            "{t}"
        );
        for (extra, want) in [
            (
                "pivot_mm 1 2 3",
                "pivot_mm: pivot_mm given twice (first on line 4)",
            ),
            (
                "tool_length_mm 100",
                "tool_length_mm: tool_length_mm given twice (first on line 5)",
            ),
        ] {
            let doubled = format!("{t}{extra}\n");
            let line = doubled.lines().count();
            let e = parse(&doubled).unwrap_err().to_string();
            assert_eq!(e, format!("line {line}, {want}"));
        }
    }
}
