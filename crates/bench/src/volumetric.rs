//! The volumetric compensator's speed: compensations per second on one core, the
//! figure `cycle` sets against a servo cycle.

use std::time::Instant;

use compgate_commission::volumetric::{synthetic_model, VolumetricCompensator};

/// Result of [`bench_per_s`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bench {
    /// Compensations ([`VolumetricCompensator::feedback`]) per second on one core.
    pub per_s: f64,
    /// Time of one compensation, ns.
    pub ns_each: f64,
}

/// Measures [`VolumetricCompensator::feedback`] on the synthetic model over a
/// pseudo-random sweep of poses for about `seconds`, on the calling thread.
pub fn bench_per_s(seconds: f64) -> Bench {
    let comp = VolumetricCompensator::new(synthetic_model(1.0));
    let t = comp.model().travel;
    let mut poses = [[0.0; 5]; 256];
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    for p in poses.iter_mut() {
        for (i, v) in p.iter_mut().enumerate() {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let s = (state >> 11) as f64 / (1u64 << 53) as f64;
            *v = t[i].0 + s * (t[i].1 - t[i].0);
        }
    }
    let start = Instant::now();
    let mut n = 0u64;
    let mut sink = 0.0;
    loop {
        for p in &poses {
            let f = comp.feedback(std::hint::black_box(p));
            sink += f[0];
        }
        n += poses.len() as u64;
        if start.elapsed().as_secs_f64() >= seconds {
            break;
        }
    }
    std::hint::black_box(sink);
    let el = start.elapsed().as_secs_f64();
    Bench {
        per_s: n as f64 / el,
        ns_each: el * 1e9 / n as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bench_runs() {
        let seconds = std::env::var("COMPGATE_BENCH_S")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(0.05);
        let b = bench_per_s(seconds);
        println!(
            "{:.0} compensations/s, {:.1} ns each; {:.0} per 125 us cycle, {:.0} per 500 us",
            b.per_s,
            b.ns_each,
            125e3 / b.ns_each,
            500e3 / b.ns_each
        );
        assert!(b.per_s > 1000.0, "{b:?}");
    }
}
