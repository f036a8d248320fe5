//! Fuzz body: the volumetric error file parser on arbitrary text.

use compgate_commission::volumetric;

/// Parses `data` as a volumetric error file. An accepted model must survive its own
/// writer (`parse(write(m))` is accepted too) and evaluate at the corners of its travel
/// without panicking.
pub fn run(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(model) = volumetric::parse(text) else {
        return;
    };
    let written = volumetric::write(&model);
    if let Err(e) = volumetric::parse(&written) {
        panic!("the writer's output does not parse back: {e}\n{written}");
    }
    let lo = model.travel.map(|(lo, _)| lo);
    let hi = model.travel.map(|(_, hi)| hi);
    let _ = model.actual_pose(&lo);
    let _ = model.actual_pose(&hi);
}
