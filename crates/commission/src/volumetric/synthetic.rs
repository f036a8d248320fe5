//! The synthetic error sets: the source of the example files, the tests' and the
//! benchmark's machine.

use std::f64::consts::PI;

use super::kinematics::{ErrorModel, Geometry, Table};
use super::{MM_PER_UM, RAD_PER_ARCSEC};

/// A synthetic but realistic error set (tens of um, tens of arc-seconds) of a
/// machine with 1000 x 800 x 600 mm travel, A +-100 deg, C +-200 deg; the source of
/// `config/volumetric-example.errors`. `scale` multiplies every error.
pub fn synthetic_model(scale: f64) -> ErrorModel {
    let travel = [
        (0.0, 1000.0),
        (0.0, 800.0),
        (0.0, 600.0),
        (-100.0, 100.0),
        (-200.0, 200.0),
    ];
    // Per axis and column: amplitude (um or arcsec) of a linear and a wave term.
    let amp: [[(f64, f64); 6]; 5] = [
        [
            (18.0, 4.0),
            (-6.0, 3.0),
            (5.0, 2.0),
            (3.0, 2.0),
            (-8.0, 4.0),
            (6.0, 3.0),
        ],
        [
            (-14.0, 5.0),
            (4.0, 2.0),
            (-7.0, 3.0),
            (-5.0, 3.0),
            (4.0, 2.0),
            (7.0, 2.0),
        ],
        [
            (10.0, 3.0),
            (-5.0, 2.0),
            (6.0, 2.0),
            (6.0, 3.0),
            (-4.0, 3.0),
            (3.0, 1.0),
        ],
        [
            (6.0, 4.0),
            (-8.0, 5.0),
            (5.0, 3.0),
            (20.0, 8.0),
            (-10.0, 5.0),
            (8.0, 4.0),
        ],
        [
            (-7.0, 5.0),
            (6.0, 4.0),
            (4.0, 3.0),
            (-9.0, 4.0),
            (7.0, 3.0),
            (25.0, 10.0),
        ],
    ];
    let tables: [Table; 5] = std::array::from_fn(|i| {
        let (lo, hi) = travel[i];
        let n = if i < 3 { 11 } else { 21 };
        let mut pos = Vec::with_capacity(n);
        let mut val = Vec::with_capacity(n);
        for j in 0..n {
            let s = j as f64 / (n - 1) as f64;
            pos.push(lo + s * (hi - lo));
            val.push(std::array::from_fn(|c| {
                let (l, w) = amp[i][c];
                let e = l * (s - 0.5) + w * (2.0 * PI * s * 1.5 + c as f64).sin();
                let unit = if c < 3 { MM_PER_UM } else { RAD_PER_ARCSEC };
                (e * 1e4).round() / 1e4 * unit * scale
            }));
        }
        Table::new(pos, val)
    });
    ErrorModel::new(
        Geometry {
            pivot_mm: [0.0, 0.0, -150.0],
            tool_length_mm: 250.0,
        },
        travel,
        tables,
        [6.0, -4.0, 5.0].map(|v| v * RAD_PER_ARCSEC * scale),
        [
            8.0 * MM_PER_UM,
            -6.0 * MM_PER_UM,
            5.0 * RAD_PER_ARCSEC,
            -7.0 * RAD_PER_ARCSEC,
        ]
        .map(|v| v * scale),
        [
            5.0 * MM_PER_UM,
            9.0 * MM_PER_UM,
            -4.0 * RAD_PER_ARCSEC,
            6.0 * RAD_PER_ARCSEC,
        ]
        .map(|v| v * scale),
    )
}

/// [`synthetic_model`] without the head's out-of-plane errors (EBA, EAC, EBC, BOA,
/// BOC zero; EAC too because C's error motions act in the machine frame, so EAC
/// turns out of the A plane as C turns): the cone the tool sweeps about A then passes
/// through the C axis (cap radius 0, [`ErrorModel::pole_reach`]), so a C move
/// reaches every tool axis at the pole; the source of
/// `config/volumetric-in-plane.errors`.
pub fn synthetic_model_in_plane(scale: f64) -> ErrorModel {
    let m = synthetic_model(scale);
    let mut tables = m.tables.clone();
    for row in &mut tables[3].val {
        row[4] = 0.0;
    }
    for row in &mut tables[4].val {
        row[3] = 0.0;
        row[4] = 0.0;
    }
    let [xoc, yoc, aoc, _] = m.loc_c;
    let [yoa, zoa, _, coa] = m.loc_a;
    ErrorModel::new(
        m.geometry,
        m.travel,
        tables,
        m.squareness_rad,
        [xoc, yoc, aoc, 0.0],
        [yoa, zoa, 0.0, coa],
    )
}
