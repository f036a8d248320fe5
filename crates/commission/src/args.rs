//! Checks of numeric command-line arguments shared by the tools: clap parses `nan`
//! and `inf` as valid `f64`, and a non-finite or absurd value reaching a fit or a
//! simulation makes it hang or produce garbage, so every numeric flag is checked
//! against a plausible range before any work, and the message names the flag.
//! `--sensors`, which calibrate, diagnose and scenario share, is read here too, and
//! so is a list's repeated item.

use thiserror::Error;

/// A numeric command-line argument that cannot be used.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ArgError {
    /// NaN or infinite.
    #[error("{flag} {value:?}: not a finite number")]
    NotFinite {
        /// The flag, e.g. `--p0-mm`.
        flag: &'static str,
        /// The value given.
        value: f64,
    },
    /// Finite but outside what the flag can mean.
    #[error("{flag} {value:?}: outside the plausible range {min}..={max} {unit}")]
    OutOfRange {
        /// The flag, e.g. `--p0-mm`.
        flag: &'static str,
        /// The value given.
        value: f64,
        /// Smallest accepted value.
        min: f64,
        /// Largest accepted value.
        max: f64,
        /// Unit of the range, for the message.
        unit: &'static str,
    },
    /// A list names one item twice (`--sensors column,T_column`).
    #[error("{flag}: {item} named twice")]
    Twice {
        /// The flag, e.g. `--sensors`.
        flag: &'static str,
        /// The item as the tools name it, e.g. `T_column`.
        item: String,
    },
    /// A list that must name something is empty (`--sensors ""`).
    #[error("{flag}: the list is empty: name at least one, or leave {flag} out")]
    Empty {
        /// The flag, e.g. `--sensors`.
        flag: &'static str,
    },
    /// A list has an empty item (`--sensors a,,b`, `--sensors a,`).
    #[error("{flag}: an empty name in the list (a comma too many?)")]
    EmptyItem {
        /// The flag, e.g. `--sensors`.
        flag: &'static str,
    },
}

/// `value` if it is finite and within `min..=max`, else the error naming `flag`.
pub fn check_f64(
    flag: &'static str,
    value: f64,
    min: f64,
    max: f64,
    unit: &'static str,
) -> Result<f64, ArgError> {
    if !value.is_finite() {
        return Err(ArgError::NotFinite { flag, value });
    }
    if !(min..=max).contains(&value) {
        return Err(ArgError::OutOfRange {
            flag,
            value,
            min,
            max,
            unit,
        });
    }
    Ok(value)
}

/// The sensors `--sensors` names, without `T_` (either spelling names the column
/// `T_<name>`); a sensor named twice is refused: it would make the fit's columns
/// linearly dependent, which the fit can only word as a property of the data. An
/// empty list or name is refused too: it would be reported as a missing column `T_`.
pub fn sensor_names(wanted: &[String]) -> Result<Vec<&str>, ArgError> {
    const FLAG: &str = "--sensors";
    if wanted.iter().all(|w| w.trim().is_empty()) {
        return Err(ArgError::Empty { flag: FLAG });
    }
    let names: Vec<&str> = wanted
        .iter()
        .map(|w| {
            let name = w.trim();
            name.strip_prefix("T_").unwrap_or(name)
        })
        .collect();
    if names.contains(&"") {
        return Err(ArgError::EmptyItem { flag: FLAG });
    }
    once(FLAG, names.iter().map(|n| format!("T_{n}")))?;
    Ok(names)
}

/// Refuses an item that `flag`'s list names twice (`--effects reversal,reversal`),
/// naming it: a repeat is more likely a typo for another item than a request.
pub fn once<S: AsRef<str>>(
    flag: &'static str,
    items: impl IntoIterator<Item = S>,
) -> Result<(), ArgError> {
    let mut seen: Vec<String> = Vec::new();
    for item in items {
        let item = item.as_ref().trim();
        if seen.iter().any(|s| s == item) {
            return Err(ArgError::Twice {
                flag,
                item: item.to_string(),
            });
        }
        seen.push(item.to_string());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_the_flag() {
        let e = check_f64("--p0-mm", f64::NAN, -1.0, 1.0, "mm").unwrap_err();
        assert_eq!(e.to_string(), "--p0-mm NaN: not a finite number");
        let e = check_f64("--p0-mm", 2.0, -1.0, 1.0, "mm").unwrap_err();
        assert_eq!(
            e.to_string(),
            "--p0-mm 2.0: outside the plausible range -1..=1 mm"
        );
        assert_eq!(check_f64("--p0-mm", 1.0, -1.0, 1.0, "mm"), Ok(1.0));
    }

    #[test]
    fn a_sensor_named_twice_is_refused_in_either_spelling() {
        let list = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert_eq!(
            sensor_names(&list(&["column", " T_screw"])),
            Ok(vec!["column", "screw"])
        );
        for twice in [&["column", "column"][..], &["column", "T_column"]] {
            let e = sensor_names(&list(twice)).unwrap_err();
            assert_eq!(e.to_string(), "--sensors: T_column named twice");
        }
    }

    #[test]
    fn an_empty_sensor_list_or_name_is_refused_as_such() {
        let list = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        for empty in [&[""][..], &[" "], &["", ""]] {
            let e = sensor_names(&list(empty)).unwrap_err();
            assert_eq!(e, ArgError::Empty { flag: "--sensors" });
            assert!(e.to_string().contains("the list is empty"), "{e}");
        }
        for gap in [&["a", ""][..], &["a", "", "b"], &["T_"]] {
            let e = sensor_names(&list(gap)).unwrap_err();
            assert_eq!(e, ArgError::EmptyItem { flag: "--sensors" }, "{gap:?}");
        }
    }

    #[test]
    fn an_item_named_twice_is_named() {
        assert_eq!(once("--effects", ["reversal", "thermal_lag"]), Ok(()));
        let e = once("--effects", ["reversal", " reversal"]).unwrap_err();
        assert_eq!(e.to_string(), "--effects: reversal named twice");
    }
}
