#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "../bodies/volumetric_errors.rs"]
mod body;

fuzz_target!(|data: &[u8]| body::run(data));
