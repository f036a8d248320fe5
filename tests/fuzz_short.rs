//! The short, deterministic form of the fuzz targets in `fuzz/` (docs/fuzzing.md): each
//! target's body (the same file the cargo-fuzz target includes) runs over its seed
//! corpus in `fuzz/corpus/<target>/` and then over a few thousand mutations of it made
//! by a seeded xorshift generator, within a few seconds. A panic in a body fails the
//! test and prints the input.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::time::{Duration, Instant};

#[path = "../fuzz/bodies/can_frame.rs"]
mod can_frame;
#[path = "../fuzz/bodies/config.rs"]
mod config;
#[path = "../fuzz/bodies/measure_csv.rs"]
mod measure_csv;
#[path = "../fuzz/bodies/modbus_reply.rs"]
mod modbus_reply;
#[path = "../fuzz/bodies/volumetric_errors.rs"]
mod volumetric_errors;

/// Mutations per target (fewer if the time bound runs out first).
const MUTATIONS: usize = 3000;
/// Time bound per target for the mutations (the seeds always all run).
const BUDGET: Duration = Duration::from_secs(4);

/// Byte strings worth inserting: numbers at the edges of f64 and the integer types,
/// the separators of the formats, and input that is long or deeply nested.
fn interesting() -> Vec<Vec<u8>> {
    let mut v: Vec<Vec<u8>> = [
        "1e308",
        "-1e308",
        "1e309",
        "nan",
        "NaN",
        "inf",
        "-inf",
        "-0",
        "0",
        "-1",
        "4294967296",
        "18446744073709551616",
        "1e-320",
        "0x7FF",
        "65535",
        "125",
        "126",
        "\u{0}",
        "\u{feff}",
        "\"",
        "'",
        ",",
        ";",
        "\n",
        "\r\n",
        "#",
        "=",
        "[",
        "]",
        "{",
        "}",
        ".",
        " ",
        "\t",
        "end",
        "table X",
        "travel",
        "T_",
        "t_s",
        "\"\"\"",
        "[[",
    ]
    .iter()
    .map(|s| s.as_bytes().to_vec())
    .collect();
    v.extend([
        vec![0xFF; 4],
        vec![0x00; 8],
        vec![0x80],
        vec![b'a'; 10_000],
        vec![b'['; 2_000],
        vec![b'9'; 400],
        b"x=".iter().chain([b'{'; 1_000].iter()).copied().collect(),
    ]);
    v
}

/// xorshift64*: small, seeded, the same sequence on every machine.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// 0..n (n > 0).
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

/// One to four random edits of `input`; `other` is another seed to splice from.
fn mutate(rng: &mut Rng, input: &[u8], other: &[u8], tokens: &[Vec<u8>]) -> Vec<u8> {
    let mut out = input.to_vec();
    for _ in 0..=rng.below(4) {
        let at = rng.below(out.len() + 1);
        match rng.below(8) {
            0 if !out.is_empty() => {
                let i = at.min(out.len() - 1);
                out[i] ^= 1 << rng.below(8);
            }
            1 if !out.is_empty() => {
                let i = at.min(out.len() - 1);
                out[i] = rng.next() as u8;
            }
            2 => out.truncate(at),
            3 => {
                let end = (at + rng.below(16)).min(out.len());
                out.drain(at..end);
            }
            4 | 5 => {
                let t = &tokens[rng.below(tokens.len())];
                out.splice(at..at, t.iter().copied());
            }
            6 => {
                // Replace the token under `at` (up to a separator) by an interesting one.
                let end = out[at..]
                    .iter()
                    .position(|b| b" ,\n\t=#".contains(b))
                    .map_or(out.len(), |p| at + p);
                let t = &tokens[rng.below(tokens.len())];
                out.splice(at..end, t.iter().copied());
            }
            _ => {
                let from = rng.below(other.len() + 1);
                let end = (from + rng.below(64)).min(other.len());
                out.splice(at..at, other[from..end].iter().copied());
            }
        }
    }
    out
}

/// Runs `body` on `input`; on a panic, fails naming the target and showing the input.
fn check(target: &str, body: fn(&[u8]), input: &[u8]) {
    if catch_unwind(AssertUnwindSafe(|| body(input))).is_err() {
        panic!(
            "fuzz body `{target}` panicked on {} bytes: {:?}",
            input.len(),
            String::from_utf8_lossy(input)
        );
    }
}

/// The seeds of `target`, then mutations of them.
fn exercise(target: &str, body: fn(&[u8]), seed: u64) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/corpus")
        .join(target);
    let mut seeds: Vec<Vec<u8>> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| {
            let path = entry.expect("corpus entry").path();
            std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        })
        .collect();
    // read_dir order is the file system's; the mutations must not depend on it.
    seeds.sort();
    assert!(!seeds.is_empty(), "no seeds in {}", dir.display());
    for s in &seeds {
        check(target, body, s);
    }
    let tokens = interesting();
    let mut rng = Rng(seed);
    let start = Instant::now();
    let mut done = 0;
    while done < MUTATIONS && start.elapsed() < BUDGET {
        let input = &seeds[rng.below(seeds.len())];
        let other = &seeds[rng.below(seeds.len())];
        let mutated = mutate(&mut rng, input, other, &tokens);
        check(target, body, &mutated);
        done += 1;
    }
    assert!(done > 0, "no mutation of `{target}` ran");
}

#[test]
fn fuzz_short_config() {
    exercise("config", config::run, 0x243F_6A88_85A3_08D3);
}

#[test]
fn fuzz_short_measure_csv() {
    exercise("measure_csv", measure_csv::run, 0x1319_8A2E_0370_7344);
}

#[test]
fn fuzz_short_volumetric_errors() {
    exercise(
        "volumetric_errors",
        volumetric_errors::run,
        0xA409_3822_299F_31D0,
    );
}

#[test]
fn fuzz_short_modbus_reply() {
    exercise("modbus_reply", modbus_reply::run, 0x082E_FA98_EC4E_6C89);
}

#[test]
fn fuzz_short_can_frame() {
    exercise("can_frame", can_frame::run, 0x4528_21E6_38D0_1377);
}
