//! Rows of measured-error data that look like bad readings, and whether they move the
//! fit (pure, no I/O). `calibrate` names them by line and refuses a model they move;
//! `diagnose` names them before its verdict.

use compgate_core::measure::{Excursion, Frozen, Measurements};

use super::{calibrate, Fit};

/// A row whose residual is more than this many times the typical residual is far
/// off ([`crate::stats::far_off`]): a -999 written for a missing value, an
/// interferometer's glitch.
pub const OUTLIER_FACTOR: f64 = 10.0;

/// A row counts as far off only this far at least, um: below an interferometer's
/// noise a factor means nothing.
pub const OUTLIER_MIN_UM: f64 = 1.0;

/// Far-off rows count only in runs of at most this many: a run of rows off together
/// is the machine (a cold start's transient), not a bad reading.
const ISOLATED_ROWS: usize = 2;

/// Bad readings move the fit when leaving them out changes the fitted error by more
/// than this, um, or than the typical residual.
pub const PULL_MIN_UM: f64 = 1.0;

/// What looks like bad readings in the data of a fit.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BadReadings {
    /// Temperature excursions of the fit's sensors
    /// ([`Measurements::temperature_excursions`]).
    pub excursions: Vec<Excursion>,
    /// Readings of the fit's sensors held at one value
    /// ([`Measurements::frozen_readings`]), only where leaving them out moves the fit:
    /// a sensor far from the heat, logged coarsely, holds its value too.
    pub frozen: Vec<Frozen>,
    /// Rows far off the fit, alone or in pairs, farthest first.
    pub far_off: Vec<usize>,
    /// The typical residual, um ([`crate::stats::far_off`]).
    pub typical_um: f64,
    /// Largest change of the fitted error over the data when the rows above are left
    /// out, um (infinite when the rest cannot be fitted).
    pub pull_um: f64,
}

impl BadReadings {
    /// Nothing looks bad.
    pub fn is_empty(&self) -> bool {
        self.excursions.is_empty() && self.frozen.is_empty() && self.far_off.is_empty()
    }

    /// Every row named, in row order.
    pub fn rows(&self) -> Vec<usize> {
        ascending(
            self.excursions
                .iter()
                .flat_map(|e| e.rows.clone())
                .chain(self.frozen.iter().flat_map(|f| f.rows.clone()))
                .chain(self.far_off.iter().copied()),
        )
    }

    /// They move the fit ([`PULL_MIN_UM`]): the model is not to be used as it is.
    pub fn pull(&self) -> bool {
        !self.is_empty() && self.pull_um > PULL_MIN_UM.max(self.typical_um)
    }
}

/// The bad readings of `m` against the fit `f` of `sensors` to it.
pub fn bad_readings(m: &Measurements, sensors: &[String], f: &Fit) -> BadReadings {
    let excursions: Vec<Excursion> = m
        .temperature_excursions()
        .into_iter()
        .filter(|e| f.terms.iter().any(|t| t.name == e.sensor))
        .collect();
    let (far, typical_um) = crate::stats::far_off(&f.residuals_um, OUTLIER_FACTOR, OUTLIER_MIN_UM);
    let mut sorted = far.clone();
    sorted.sort_unstable();
    let far_off: Vec<usize> = far
        .iter()
        .copied()
        .filter(|&i| {
            // The run of far-off rows around i.
            let is_far = |j: usize| sorted.binary_search(&j).is_ok();
            let before = (0..i)
                .rev()
                .take(ISOLATED_ROWS)
                .take_while(|&j| is_far(j))
                .count();
            let after = (i + 1..m.len())
                .take(ISOLATED_ROWS)
                .take_while(|&j| is_far(j))
                .count();
            before + 1 + after <= ISOLATED_ROWS
        })
        .collect();
    let mut frozen: Vec<Frozen> = m
        .frozen_readings()
        .into_iter()
        .filter(|z| f.terms.iter().any(|t| t.name == z.sensor))
        .collect();
    if !frozen.is_empty() {
        let rows = ascending(frozen.iter().flat_map(|z| z.rows.clone()));
        if pull_um(m, sensors, f, &rows) <= PULL_MIN_UM.max(typical_um) {
            frozen.clear();
        }
    }
    let mut bad = BadReadings {
        excursions,
        frozen,
        far_off,
        typical_um,
        pull_um: 0.0,
    };
    if !bad.is_empty() {
        bad.pull_um = pull_um(m, sensors, f, &bad.rows());
    }
    bad
}

/// Row indices, ascending, each once.
fn ascending(rows: impl Iterator<Item = usize>) -> Vec<usize> {
    let mut rows: Vec<usize> = rows.collect();
    rows.sort_unstable();
    rows.dedup();
    rows
}

/// How far the fitted error moves when `rows` are left out, um.
fn pull_um(m: &Measurements, sensors: &[String], f: &Fit, rows: &[usize]) -> f64 {
    let keep = |i: &usize| rows.binary_search(i).is_err();
    let pick = |v: &[f64]| -> Vec<f64> { (0..v.len()).filter(keep).map(|i| v[i]).collect() };
    let rest = Measurements {
        t_s: pick(&m.t_s),
        pos_mm: pick(&m.pos_mm),
        err_um: pick(&m.err_um),
        dir: (0..m.dir.len()).filter(keep).map(|i| m.dir[i]).collect(),
        travel_mm: pick(&m.travel_mm),
        temps: m
            .temps
            .iter()
            .map(|c| compgate_core::measure::TempColumn {
                name: c.name.clone(),
                degc: pick(&c.degc),
            })
            .collect(),
        ignored_columns: Vec::new(),
    };
    let Ok(g) = calibrate(&rest, sensors, Some(f.p0_mm)) else {
        return f64::INFINITY;
    };
    // Over the rows kept: the rows left out are where the two fits differ by design.
    (0..m.len())
        .filter(keep)
        .map(|i| {
            let temps: Vec<f64> = f
                .terms
                .iter()
                .map(|t| m.temp(&t.name).map_or(f64::NAN, |c| c[i]))
                .collect();
            (f.predict_um(m.pos_mm[i], &temps) - g.predict_um(m.pos_mm[i], &temps)).abs()
        })
        .fold(0.0, f64::max)
}
