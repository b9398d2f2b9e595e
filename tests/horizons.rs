//! Long horizons: `mbfg simulate --out` writes each row as its step becomes final,
//! to the same bytes as the run held whole (standard output); the fixed-lag
//! smoother's memory does not grow with the number of steps, the batch's does; and
//! the summary line reports the peak memory, measured.

mod common;
use common::{mbfg, stderr};

/// A fresh directory of this test's own.
fn scratch(name: &str) -> std::path::PathBuf {
    common::scratch("horizons", name)
}

/// `mbfg simulate args…` twice: streamed to a file, and held, to standard output.
/// Returns the file's bytes and standard output's.
fn streamed_and_held(name: &str, args: &[&str]) -> (Vec<u8>, Vec<u8>) {
    let out = scratch(name).join("run.csv");
    let mut streamed = vec!["simulate"];
    streamed.extend(args);
    let held = streamed.clone();
    streamed.extend(["--out", out.to_str().unwrap()]);
    let run = mbfg(&streamed);
    assert!(run.status.success(), "{name}: {}", stderr(&run));
    let run_held = mbfg(&held);
    assert!(run_held.status.success(), "{name}: {}", stderr(&run_held));
    (std::fs::read(&out).unwrap(), run_held.stdout)
}

#[test]
fn the_streamed_csv_is_the_held_one_byte_for_byte() {
    let cases: [(&str, &[&str]); 6] = [
        // 5001 steps: the smoother's buffer is compacted on the way.
        (
            "dc-window",
            &["scenes/fourbar.yaml", "--dt", "0.001", "--t-end", "5"],
        ),
        (
            "ic-window5",
            &[
                "scenes/fourbar-theta.yaml",
                "--coords",
                "ic",
                "--window",
                "5",
                "--dt",
                "0.001",
                "--t-end",
                "4.5",
            ],
        ),
        (
            "dc-batch",
            &[
                "scenes/fourbar.yaml",
                "--batch",
                "--dt",
                "0.001",
                "--t-end",
                "1",
            ],
        ),
        (
            "ic-batch",
            &[
                "scenes/fourbar-theta.yaml",
                "--coords",
                "ic",
                "--batch",
                "--dt",
                "0.001",
                "--t-end",
                "1",
            ],
        ),
        (
            "sampled",
            &[
                "scenes/double-pendulum.yaml",
                "--dt",
                "0.001",
                "--t-end",
                "1",
                "--sample-dt",
                "0.007",
            ],
        ),
        // Made again at a finer step (the file starts over), every 3rd state written.
        (
            "refined",
            &[
                "scenes/benchmarks/andrews-squeezer.yaml",
                "--dt",
                "0.001",
                "--t-end",
                "0.015",
            ],
        ),
    ];
    for (name, args) in cases {
        let (file, held) = streamed_and_held(name, args);
        assert!(file.len() > 1000, "{name}: {} bytes", file.len());
        assert!(
            file == held,
            "{name}: the streamed file ({} bytes) differs from the held output ({} bytes)",
            file.len(),
            held.len()
        );
    }
}

/// The peak memory (bytes) the summary line of `mbfg simulate … --out` reports.
fn peak_memory(name: &str, args: &[&str]) -> f64 {
    let out = scratch(name).join("run.csv");
    let mut all = vec!["simulate"];
    all.extend(args);
    all.extend(["--out", out.to_str().unwrap()]);
    let run = mbfg(&all);
    assert!(run.status.success(), "{name}: {}", stderr(&run));
    let summary = String::from_utf8_lossy(&run.stdout).to_string();
    let mib: f64 = summary
        .split("; peak memory ")
        .nth(1)
        .and_then(|rest| rest.split(" MiB").next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{name}: no peak memory in {summary:?}"));
    mib * 1024.0 * 1024.0
}

#[test]
fn the_smoothers_memory_does_not_grow_with_the_horizon_the_batchs_does() {
    // The four-bar (n = 4): a run held whole keeps at least t, q, q̇, q̈ of every
    // step, 13 numbers, and the smoother's variables of every step besides.
    let held_per_step = 13.0 * 8.0;
    let fourbar = |t_end: &'static str| -> Vec<&'static str> {
        vec!["scenes/fourbar.yaml", "--dt", "0.001", "--t-end", t_end]
    };
    let short = peak_memory("smoother-2k", &fourbar("2"));
    let long = peak_memory("smoother-40k", &fourbar("40"));
    let grown = long - short;
    let held = 38_000.0 * held_per_step;
    assert!(
        grown < held / 3.0,
        "the smoother's peak memory grew by {:.2} MiB from 2k to 40k steps (holding the \
         trajectory alone would add {:.2} MiB)",
        grown / 1048576.0,
        held / 1048576.0
    );
    // The measure sees memory that does grow: a batch through the general solver
    // (the paper's integrator factors: its steps are not square) holds every step's
    // variables and the linear system of the whole horizon, at least q, q̇, q̈ of
    // every step (96 bytes) and its block row of the normal equations (12 × 12
    // doubles): over 4k steps 4.9 MiB, well above the peak's run-to-run spread.
    let batch = |name, t_end| {
        let mut a = fourbar(t_end);
        a.extend(["--batch", "--dc-integrators", "full"]);
        peak_memory(name, &a)
    };
    let batch_short = batch("batch-1k", "1");
    let batch_long = batch("batch-5k", "5");
    let held = 4_000.0 * (12.0 + 144.0) * 8.0;
    assert!(
        batch_long - batch_short > 0.5 * held,
        "the batch's peak memory grew by {:.2} MiB only from 1k to 5k steps (its \
         variables and normal equations alone are {:.2} MiB)",
        (batch_long - batch_short) / 1048576.0,
        held / 1048576.0
    );
}

#[test]
fn a_run_streamed_to_a_file_needs_no_memory_for_its_rows() {
    // 20 001 steps of the four-bar: the smoother keeps a few thousand steps' variables
    // (under 1 MB) whatever the horizon; the rows held for standard output add about
    // 4 MB. Under a 2 MB limit the streamed run goes, the held one is refused.
    let out = scratch("limit").join("run.csv");
    let args = [
        "simulate",
        "scenes/fourbar.yaml",
        "--dt",
        "0.001",
        "--t-end",
        "20",
    ];
    let limit = [("MBFG_MEMORY_LIMIT", "2e6")];
    let mut streamed = args.to_vec();
    streamed.extend(["--out", out.to_str().unwrap()]);
    let run = common::mbfg_env(&streamed, &limit);
    assert!(run.status.success(), "{}", stderr(&run));
    let held = common::mbfg_env(&args, &limit);
    assert_eq!(held.status.code(), Some(2), "{}", stderr(&held));
    assert!(stderr(&held).contains("needs about"), "{}", stderr(&held));
}
