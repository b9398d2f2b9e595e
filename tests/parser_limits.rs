//! No input to the parsers may panic, abort or overflow the stack (issue 16): the
//! size limits of expressions, scenes and tables, the shape of their messages, and
//! the inputs the fuzz targets (fuzz/, docs/fuzzing.md) once crashed on.

use mbfg::expr::{Expr, ExprError, MAX_DEPTH, MAX_NODES};
use mbfg::io::{read_table_from, read_table_with, TableLimits};
use mbfg::Scene;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

/// One line of at most 300 characters, and no Rust Debug text.
fn assert_short(msg: &str) {
    assert!(!msg.contains('\n'), "message spans lines: {msg}");
    assert!(
        msg.chars().count() <= 300,
        "message of {} characters: {msg}",
        msg.chars().count()
    );
    assert!(!msg.contains(" { "), "Debug text in message: {msg}");
}

/// Runs `f` on a thread with a 256 kB stack, far below the default 2 to 8 MB.
fn small_stack<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    std::thread::Builder::new()
        .stack_size(256 * 1024)
        .spawn(f)
        .unwrap()
        .join()
        .unwrap()
}

fn too_large(text: String) -> String {
    small_stack(move || match Expr::parse(&text) {
        Err(e @ ExprError::TooLarge(_)) => e.to_string(),
        other => panic!("expected a size error, got {other:?}"),
    })
}

#[test]
fn deep_parentheses_are_refused() {
    let msg = too_large(format!("{}1{}", "(".repeat(10_000), ")".repeat(10_000)));
    assert!(msg.contains("nested too deeply"), "{msg}");
    assert!(msg.contains(&MAX_DEPTH.to_string()), "{msg}");
    assert_short(&msg);
    let msg = too_large(format!("{}1{}", "abs(".repeat(10_000), ")".repeat(10_000)));
    assert!(msg.contains("nested too deeply"), "{msg}");
    // Unclosed: the limit is met before the end of the text.
    assert_short(&too_large("(".repeat(10_000)));
}

#[test]
fn long_sign_and_power_chains_are_refused() {
    let msg = too_large(format!("{}t", "-".repeat(20_000)));
    assert!(msg.contains("nested too deeply"), "{msg}");
    assert_short(&msg);
    let msg = too_large(format!("{}2", "2^".repeat(20_000)));
    assert!(msg.contains("nested too deeply"), "{msg}");
    assert_short(&msg);
}

#[test]
fn a_long_flat_sum_is_refused() {
    let terms: Vec<String> = (0..70_000).map(|i| format!("{}", i % 10)).collect();
    let msg = too_large(terms.join("+"));
    assert!(msg.contains(&MAX_NODES.to_string()), "{msg}");
    assert_short(&msg);
    let msg = too_large("1".repeat(200_000));
    assert!(msg.contains("too long"), "{msg}");
}

#[test]
fn the_largest_accepted_trees_fit_a_small_stack() {
    small_stack(|| {
        // Every kind of nesting up to the limit, and the widest flat sum.
        let depth = MAX_DEPTH - 2;
        let cases = [
            format!("{}t{}", "(".repeat(depth), ")".repeat(depth)),
            format!("{}t{}", "abs(".repeat(depth), ")".repeat(depth)),
            format!("{}t", "-".repeat(depth)),
            format!("{}t", "1^".repeat(depth)),
            format!(
                "{}t{}",
                "(1+2*-1^max(t,".repeat(depth / 4),
                "))".repeat(depth / 4)
            ),
            vec!["t"; MAX_NODES / 2 - 1].join("+"),
        ];
        for text in cases {
            let e = Expr::parse(&text).unwrap_or_else(|e| panic!("{e}"));
            let lookup = |n: &str| (n == "t").then_some(0.5);
            e.eval(&lookup).unwrap();
            assert_eq!(e.names(), vec!["t".to_string()]);
            let b = e.bind(&|n| n == "t", &lookup).unwrap();
            b.eval(&lookup).unwrap();
            drop((e, b));
        }
    });
}

#[test]
fn huge_quoted_input_is_cut_in_messages() {
    let name = "x".repeat(90_000);
    let e = Expr::parse(&format!("{name}(1)")).unwrap_err().to_string();
    assert_short(&e);
    assert!(e.contains('…'), "{e}");
    let e = Expr::parse(&name).unwrap().eval(&|_| None).unwrap_err();
    assert_short(&e.to_string());
    let e = Expr::parse(&"9".repeat(50_000).replace("99", "9.9.")).unwrap_err();
    assert_short(&e.to_string());
}

fn scene_error(text: &str) -> String {
    let text = text.to_string();
    small_stack(move || {
        let e = Scene::from_str(&text, Path::new("limits.yaml")).unwrap_err();
        e.to_string()
    })
}

const HEAD: &str = "points:\n  - {name: A, x: 0, y: 0, fixed: true}\n  - {name: B, x: 1, y: 0}\nbodies:\n  - {name: crank, points: [A, B], mass: 1}\ncoordinates:\n  - {name: theta, type: angle, points: [A, B]}\n";

#[test]
fn scene_errors_name_file_line_and_key_in_one_short_line() {
    let deep = format!("{}t{}", "(".repeat(10_000), ")".repeat(10_000));
    let msg = scene_error(&format!(
        "{HEAD}effects:\n  - {{type: torque, coordinate: theta, value: \"{deep}\"}}\n"
    ));
    assert!(
        msg.starts_with("limits.yaml:9: effects[0].value: "),
        "{msg}"
    );
    assert!(msg.contains("nested too deeply"), "{msg}");
    assert_short(&msg);

    let sum = vec!["1"; 70_000].join("+");
    let msg = scene_error(&format!("parameters:\n  k: {sum}\n{HEAD}"));
    assert!(msg.starts_with("limits.yaml:2: parameters.k: "), "{msg}");
    assert_short(&msg);

    // A malformed expression of a megabyte is quoted, cut.
    let bad = format!("{})", "t+".repeat(500_000));
    let msg = scene_error(&format!(
        "{HEAD}effects:\n  - {{type: torque, coordinate: theta, value: \"{bad}\"}}\n"
    ));
    assert!(msg.contains("effects[0].value"), "{msg}");
    assert_short(&msg);

    // Names, types and keys quoted from the file are cut too.
    let long = "n".repeat(100_000);
    for text in [
        format!("{HEAD}effects:\n  - {{type: {long}}}\n"),
        format!("{HEAD}independent: [{long}]\n"),
        format!("{HEAD}{long}: 1\n"),
        format!("{HEAD}effects:\n  - {{type: torque, coordinate: {long}, value: 1}}\n"),
        format!("points:\n  - {{name: \"{long}\\n{long}\", x: 0, y: 0}}\n"),
    ] {
        assert_short(&scene_error(&text));
    }
}

#[test]
fn yaml_budget_breaches_are_plain_words() {
    let many = format!("[{}]", vec!["0"; 260_000].join(","));
    let msg = scene_error(&many);
    assert!(msg.contains("too large or too complex"), "{msg}");
    assert!(!msg.contains("Nodes"), "{msg}");
    assert_short(&msg);

    let deep = format!("{}{}", "[".repeat(300), "]".repeat(300));
    let msg = scene_error(&deep);
    assert_short(&msg);

    let long_key = format!("a: 1\n{}: 1\n{}: 2\n", "k".repeat(1_000), "k".repeat(1_000));
    let msg = scene_error(&long_key);
    assert!(msg.to_lowercase().contains("duplicate"), "{msg}");
    assert_short(&msg);
}

#[test]
fn oversized_scenes_and_device_mechanisms_are_refused() {
    let big = format!("{HEAD}# {}\n", "x".repeat(5 << 20));
    let msg = scene_error(&big);
    assert!(msg.contains("too large"), "{msg}");
    if Path::new("/dev/zero").exists() {
        let msg = scene_error("mechanism: /dev/zero\n");
        assert!(msg.contains("not a regular file"), "{msg}");
    }
}

/// Counts the bytes a reader hands out.
struct Counting<R> {
    inner: R,
    read: std::rc::Rc<std::cell::Cell<usize>>,
}

impl<R: Read> Read for Counting<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.read.set(self.read.get() + n);
        Ok(n)
    }
}

fn temp(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("mbfg-limits-{}-{name}", std::process::id()))
}

/// A gzip-compressed CSV `t,theta` of `rows` rows.
fn gz_table(rows: usize) -> Vec<u8> {
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    gz.write_all(b"t,theta\n").unwrap();
    for k in 0..rows {
        writeln!(gz, "{},0", k as f64 * 1e-3).unwrap();
    }
    gz.finish().unwrap()
}

#[test]
fn a_compressed_table_beyond_the_limit_is_refused_as_it_streams() {
    let data = gz_table(1_000_000);
    let limits = TableLimits {
        max_cells: 2_000,
        ..TableLimits::default()
    };
    let read = std::rc::Rc::new(std::cell::Cell::new(0));
    let input = Counting {
        inner: flate2::read::GzDecoder::new(&data[..]),
        read: read.clone(),
    };
    let e = read_table_from(input, "bomb.csv.gz", &limits, &mut |_| Ok(()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("2000"), "{e}");
    assert!(e.contains("bomb.csv.gz:1002"), "{e}");
    assert_short(&e);
    // 1000 rows of about 10 bytes, and the reader's buffer, of some 12 MB.
    assert!(read.get() < 100_000, "{} bytes read", read.get());

    // The same through a file, by name.
    let path = temp("bomb.csv.gz");
    std::fs::write(&path, &data).unwrap();
    let e = read_table_with(&path, &limits, &mut |_| Ok(())).unwrap_err();
    std::fs::remove_file(&path).ok();
    assert!(e.to_string().contains("limit of 2000 values"), "{e}");

    // A byte limit stops a file that is one endless line.
    let limits = TableLimits {
        max_cells: 1_000,
        max_bytes: 10_000,
    };
    let line = vec![b'1'; 1_000_000];
    let e = read_table_from(&line[..], "line.csv", &limits, &mut |_| Ok(()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("10000 bytes"), "{e}");
}

#[test]
fn a_header_check_runs_before_the_rows() {
    let data = gz_table(1_000_000);
    let read = std::rc::Rc::new(std::cell::Cell::new(0));
    let input = Counting {
        inner: flate2::read::GzDecoder::new(&data[..]),
        read: read.clone(),
    };
    let mut seen = Vec::new();
    let e = read_table_from(input, "x.csv", &TableLimits::default(), &mut |cols| {
        seen = cols.to_vec();
        Err(mbfg::Error::data_in(
            "x.csv",
            None,
            "unknown coordinate `theta`",
        ))
    })
    .unwrap_err();
    assert!(e.to_string().contains("unknown coordinate"), "{e}");
    assert_eq!(seen, ["t", "theta"]);
    assert!(read.get() < 100_000, "{} bytes read", read.get());
    // Within the limits the table reads as before.
    let t = read_table_from(
        &b"t,x\n0,1\n1,2\n"[..],
        "ok.csv",
        &TableLimits::default(),
        &mut |_| Ok(()),
    )
    .unwrap();
    assert_eq!((t.rows, t.values.clone()), (2, vec![0.0, 1.0, 1.0, 2.0]));
}

#[test]
fn table_messages_are_short() {
    let long = "c".repeat(100_000);
    for text in [
        format!("t,{long}\n0,1\n"),
        format!("t,x\n0,{long}\n"),
        "t,\"a\nb\"\n0,1\n".to_string(),
        "t,x\n0,\u{1}\n".to_string(),
    ] {
        let e = read_table_from(
            text.as_bytes(),
            "t.csv",
            &TableLimits::default(),
            &mut |_| Ok(()),
        )
        .unwrap_err();
        assert_short(&e.to_string());
    }
    let bad_utf8 = b"t,x\n0,\xff\n";
    let e = read_table_from(&bad_utf8[..], "t.csv", &TableLimits::default(), &mut |_| {
        Ok(())
    })
    .unwrap_err();
    assert_short(&e.to_string());
}

/// Every input a fuzz target once failed on, replayed through the same calls.
#[test]
fn fuzz_regressions_do_not_crash() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/fuzz-regressions");
    let mut count = 0;
    for target in ["scene", "expr", "trajectory"] {
        let Ok(entries) = std::fs::read_dir(dir.join(target)) else {
            continue;
        };
        for entry in entries {
            let path = entry.unwrap().path();
            let data = std::fs::read(&path).unwrap();
            let name = path.display().to_string();
            small_stack(move || replay(target, &data)).unwrap_or_else(|m| panic!("{name}: {m}"));
            count += 1;
        }
    }
    assert!(count > 0, "no regression inputs under {}", dir.display());
}

fn replay(target: &str, data: &[u8]) -> Result<(), String> {
    let check = |msg: String| {
        if msg.contains('\n') || msg.chars().count() > 300 {
            Err(format!("bad message: {msg}"))
        } else {
            Ok(())
        }
    };
    match target {
        "scene" => {
            let Ok(text) = std::str::from_utf8(data) else {
                return Ok(());
            };
            match Scene::from_str(text, Path::new("fuzz.yaml")) {
                Ok(scene) => {
                    let _ = mbfg::Model::new(&scene);
                    Ok(())
                }
                Err(e) => check(e.to_string()),
            }
        }
        "expr" => {
            let Ok(text) = std::str::from_utf8(data) else {
                return Ok(());
            };
            match Expr::parse(text) {
                Ok(e) => {
                    let lookup = |n: &str| (n == "t").then_some(0.5);
                    let _ = e.eval(&lookup);
                    let _ = e.bind(&|n| n == "t", &lookup).map(|b| b.eval(&lookup));
                    Ok(())
                }
                Err(e) => check(e.to_string()),
            }
        }
        _ => {
            let limits = TableLimits {
                max_cells: 100_000,
                max_bytes: 4 << 20,
            };
            let input: Box<dyn Read> = if data.starts_with(&[0x1f, 0x8b]) {
                Box::new(flate2::read::GzDecoder::new(data))
            } else {
                Box::new(data)
            };
            match read_table_from(input, "fuzz.csv", &limits, &mut |_| Ok(())) {
                Ok(table) => {
                    let text = include_str!("../scenes/fourbar-theta.yaml");
                    let scene = Scene::from_str(text, Path::new("fourbar-theta.yaml")).unwrap();
                    let model = mbfg::Model::new(&scene).unwrap();
                    let _ = mbfg::inverse::Prescription::from_table(&model, &table, "fuzz.csv");
                    Ok(())
                }
                Err(e) => check(e.to_string()),
            }
        }
    }
}

/// A malformed table is a typed error that names its file and line.
#[test]
fn a_malformed_row_is_a_data_error_at_its_line() {
    let e = read_table_from(
        &b"t,x\n0,1\n1,oops\n"[..],
        "bad.csv",
        &TableLimits::default(),
        &mut |_| Ok(()),
    )
    .unwrap_err();
    match &e {
        mbfg::Error::Data { file, line, .. } => {
            assert_eq!(file.as_deref(), Some("bad.csv"));
            assert_eq!(*line, Some(3), "{e}");
        }
        other => panic!("not a data error: {other}"),
    }
    assert!(e.to_string().starts_with("bad.csv:3: "), "{e}");
}
