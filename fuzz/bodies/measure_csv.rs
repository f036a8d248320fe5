//! Fuzz body: the measurement CSV reader on arbitrary bytes.

use compgate_core::measure::Measurements;

/// Reads `data` as measurement CSV. What the reader accepts must be consistent (one
/// value per column and row, all finite) and survive its own writer: `read(write(m))`
/// gives the same series back.
pub fn run(data: &[u8]) {
    let Ok(m) = Measurements::read(data) else {
        return;
    };
    let n = m.len();
    assert!(n > 0, "an accepted file has rows");
    for series in [&m.t_s, &m.pos_mm, &m.err_um, &m.travel_mm] {
        assert_eq!(series.len(), n);
        assert!(series.iter().all(|v| v.is_finite()));
    }
    assert_eq!(m.dir.len(), n);
    for c in &m.temps {
        assert_eq!(c.degc.len(), n);
        assert!(c.degc.iter().all(|v| v.is_finite()));
    }
    let mut out = Vec::new();
    if let Err(e) = m.write(&mut out) {
        panic!("writing an accepted series failed: {e}");
    }
    let back = match Measurements::read(out.as_slice()) {
        Ok(back) => back,
        Err(e) => panic!("the writer's output does not read back: {e}"),
    };
    assert_eq!(back.t_s, m.t_s);
    assert_eq!(back.pos_mm, m.pos_mm);
    assert_eq!(back.err_um, m.err_um);
    assert_eq!(back.temps, m.temps);
}
