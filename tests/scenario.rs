//! The structured fuzz target's oracle (`mbfg::scenario`), run on seeded inputs: the
//! generated scenes pass it, and it catches a wrong load derivative that this test
//! injects itself.

use mbfg::model::forces::Force;
use mbfg::scenario::{closed_form, judge, judge_with};

mod common;

/// Deterministic bytes for input `seed`.
fn input(seed: u64, len: usize) -> Vec<u8> {
    let mut rng = common::Rng(seed.wrapping_mul(7919) + 1);
    (0..len)
        .map(|_| (rng.uniform().abs() * 256.0) as u8)
        .collect()
}

#[test]
fn seeded_generated_scenes_pass_the_oracle() {
    for seed in 0..60 {
        let bytes = input(seed, 48);
        if let Some(bad) = judge(&bytes) {
            panic!("seed {seed}: {bad}");
        }
    }
}

#[test]
fn inputs_the_fuzz_target_failed_on_pass_now() {
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/fuzz-regressions/runs");
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let bytes = std::fs::read(&path).unwrap();
        if let Some(bad) = judge(&bytes) {
            panic!("{}: {bad}", path.display());
        }
    }
}

#[test]
fn the_oracle_catches_a_wrong_load_derivative() {
    // ∂Q/∂q̇ of every damped or rate-dependent load off by 10 %, as a slip in a
    // closed form would make it; everything else as the model has it.
    let wrong = |force: &Force,
                 model: &mbfg::Model,
                 state: (&[f64], &[f64], f64),
                 kq: &mut [f64],
                 kv: &mut [f64]| {
        let mut own = vec![0.0; kv.len()];
        closed_form(force, model, state, kq, &mut own)?;
        for (k, v) in kv.iter_mut().zip(&own) {
            *k += 1.1 * v;
        }
        Ok(())
    };
    let mut caught = 0;
    let mut rate_loads = 0;
    for seed in 0..60 {
        let bytes = input(seed, 48);
        let text = mbfg::scenario::scene_text(&mut mbfg::scenario::Choices::new(&bytes));
        let damped = text.contains("damping: ") || text.contains("rate(theta)");
        if let Some(bad) = judge_with(&bytes, &wrong) {
            assert!(bad.contains("finite differences"), "{bad}");
            caught += 1;
        }
        rate_loads += usize::from(damped);
    }
    assert!(
        rate_loads > 10,
        "only {rate_loads} scenes with a rate-dependent load"
    );
    assert!(caught >= rate_loads / 2, "caught {caught} of {rate_loads}");
}
