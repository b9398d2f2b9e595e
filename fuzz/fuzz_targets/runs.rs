//! Past the parsers: bytes → a small valid scene (`mbfg::scenario`) → assembly,
//! forward runs (DC or IC, each integrator, a few steps) and an inverse solve, judged
//! by the oracle: no panic, no non-finite output, one-line errors, a converged run's
//! |Φ| and energy balance plausible or warned of, load derivatives equal to finite
//! differences.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Some(finding) = mbfg::scenario::judge(data) {
        panic!("{finding}");
    }
});
