//! The ISO 230-2 report: the per-target and the axis tables.

use std::fmt::Write as _;

use super::{Iso230, RUNS_REQUIRED};
use crate::table::Markdown;

/// The report, as printed.
pub fn report(r: &Iso230) -> String {
    let mut s = String::new();
    s.push_str("ISO 230-2 bidirectional evaluation (um)\n\n");
    let um = |v: f64| format!("{v:.3}");
    let mut targets = Markdown::new([
        "target mm",
        "runs +/-",
        "mean +",
        "mean -",
        "s +",
        "s -",
        "B_i",
        "mean bidir",
        "R_i +",
        "R_i -",
        "R_i",
    ]);
    for t in &r.targets {
        targets.row([
            t.pos_mm.to_string(),
            format!("{}/{}", t.runs_up, t.runs_down),
            um(t.mean_up_um),
            um(t.mean_down_um),
            um(t.s_up_um),
            um(t.s_down_um),
            um(t.b_um),
            um(t.mean_um),
            um(t.r_up_um),
            um(t.r_down_um),
            um(t.r_um),
        ]);
    }
    s.push_str(&targets.render());
    let mut axis = Markdown::new(["axis, um", "+ (up)", "- (down)", "bidirectional"]);
    for (name, up, down, both) in [
        ("A accuracy of positioning", r.a_up_um, r.a_down_um, r.a_um),
        (
            "R repeatability of positioning",
            r.r_up_um,
            r.r_down_um,
            r.r_um,
        ),
        (
            "E systematic positioning error",
            r.e_up_um,
            r.e_down_um,
            r.e_um,
        ),
    ] {
        axis.row([name.to_string(), um(up), um(down), um(both)]);
    }
    axis.row([
        "M mean bidirectional positioning error",
        "",
        "",
        &um(r.m_um),
    ]);
    axis.row([
        "B reversal value (mean reversal value)",
        "",
        "",
        &format!("{:.3} ({:.3})", r.b_um, r.b_mean_um),
    ]);
    s.push('\n');
    s.push_str(&axis.render());
    let runs = |keep: &dyn Fn(&super::Target) -> bool| {
        let at: Vec<String> = r
            .targets
            .iter()
            .filter(|t| keep(t))
            .map(|t| format!("{} mm ({}/{})", t.pos_mm, t.runs_up, t.runs_down))
            .collect();
        at.join(", ")
    };
    let few = runs(&|t| t.runs_up < RUNS_REQUIRED || t.runs_down < RUNS_REQUIRED);
    if !few.is_empty() {
        let _ = writeln!(
            s,
            "\nnote: fewer than the {RUNS_REQUIRED} runs each way ISO 230-2 asks for at {few}"
        );
    }
    // The standard's cycle approaches every target as often from each side.
    let unequal = runs(&|t| t.runs_up != t.runs_down);
    if !unequal.is_empty() {
        let _ = writeln!(
            s,
            "\nnote: runs upwards and downwards differ in number at {unequal}: the test \
             cycle approaches every target as often from each side; are rows missing?"
        );
    }
    // A laser's export in mm read as um gave A = 0.015 um without a word.
    let least_um = crate::calibrate::fit::MIN_ERR_SPAN_UM;
    if r.a_um < least_um {
        let _ = writeln!(
            s,
            "\nwarning: A is {:.4} um, below {least_um} um (below any machine's repeatability \
             and any laser's noise): is err_um in mm? The column holds micrometres",
            r.a_um
        );
    }
    s
}
