//! `mbfg check` on bad scene files: every error ends the program with exit code 2 and
//! one line on stderr, `error: FILE[:LINE]: [KEY: ]MESSAGE`, naming the file, the line
//! when the parser knows it, and the key or name at fault. Also the good cases: the
//! suite's scenes and the MBSE files under `tests/data/mbse/` assemble to the expected
//! n, m and degrees of freedom.
//!
//! The binary runs in the crate's directory on paths relative to it, so the messages
//! read as a user would see them (`tests/data/bad/unknown-point.yaml:9: ...`).

use std::path::PathBuf;
use std::process::Output;

fn manifest_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Runs `mbfg check <rel>` in the crate's directory.
fn check(rel: &str) -> Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .arg("check")
        .arg(rel)
        .current_dir(manifest_dir())
        .output()
        .expect("run mbfg")
}

fn bad(name: &str) -> String {
    format!("tests/data/bad/{name}")
}

/// Runs `mbfg check` on a file that must fail; checks exit code 2, one line on
/// stderr starting with `error: ` and naming the file, nothing on stdout. Returns
/// that line.
fn failure(rel: &str) -> String {
    let out = check(rel);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        !stderr.contains("panicked") && out.status.code() != Some(101),
        "{rel}: mbfg panicked: {stderr}"
    );
    assert_eq!(
        out.status.code(),
        Some(2),
        "{rel}: expected exit code 2, got {:?}; stderr: {stderr}",
        out.status
    );
    assert!(stdout.is_empty(), "{rel}: unexpected stdout: {stdout}");
    let text = stderr.strip_suffix('\n').unwrap_or(&stderr);
    assert!(
        !text.is_empty() && !text.contains('\n'),
        "{rel}: stderr must be exactly one line, got:\n{stderr}"
    );
    assert!(
        text.starts_with("error: "),
        "{rel}: stderr must start with 'error: ': {text}"
    );
    assert!(
        text.contains(rel),
        "{rel}: the message must name the file: {text}"
    );
    text.to_string()
}

/// A bad file whose error the parser locates: the line must be exactly
/// `error: FILE:LINE: KEY: ...` and contain every one of `fragments`.
fn assert_error(name: &str, line: u64, key: &str, fragments: &[&str]) {
    let rel = bad(name);
    let text = failure(&rel);
    let prefix = if key.is_empty() {
        format!("error: {rel}:{line}: ")
    } else {
        format!("error: {rel}:{line}: {key}: ")
    };
    assert!(
        text.starts_with(&prefix),
        "{name}: expected the message to start with '{prefix}', got: {text}"
    );
    for f in fragments {
        assert!(text.contains(f), "{name}: expected '{f}' in: {text}");
    }
}

// ---------------------------------------------------------------------------------
// YAML

#[test]
fn yaml_syntax_error() {
    // `points: [A, P` is never closed; the parser notices on the next line, the
    // message names the line that opened it.
    assert_error(
        "yaml-syntax.yaml",
        8,
        "",
        &["YAML syntax error", "`[` opened on this line is not closed"],
    );
}

#[test]
fn yaml_unclosed_brace_is_named_at_its_line() {
    assert_error(
        "yaml-unclosed-brace.yaml",
        4,
        "",
        &["`{` opened on this line is not closed"],
    );
}

#[test]
fn yaml_value_that_is_not_a_number_names_its_key() {
    let text = failure(&bad("yaml-nan.yaml"));
    assert_error(
        "yaml-nan.yaml",
        9,
        "mass",
        &["`.nan` is not a finite number"],
    );
    assert!(!text.contains("syntax"), "{text}");
}

#[test]
fn empty_file_is_called_empty() {
    let rel = bad("empty.yaml");
    let text = failure(&rel);
    assert!(
        text.starts_with(&format!("error: {rel}: the file is empty")),
        "{text}"
    );
}

#[test]
fn yaml_duplicate_key() {
    let rel = bad("yaml-duplicate-key.yaml");
    assert_error(
        "yaml-duplicate-key.yaml",
        10,
        "",
        &["YAML syntax error", "duplicate", "mass"],
    );
    // The parser's advice on its own API is not for users.
    let text = failure(&rel);
    assert!(!text.contains("DuplicateKeyPolicy"), "{text}");
}

#[test]
fn missing_file() {
    let rel = bad("does-not-exist.yaml");
    assert!(!manifest_dir().join(&rel).exists());
    let text = failure(&rel);
    assert!(
        text.starts_with(&format!("error: {rel}: ")),
        "no line for a file that cannot be read: {text}"
    );
}

// ---------------------------------------------------------------------------------
// Points and bodies

#[test]
fn unknown_point_in_body() {
    assert_error(
        "unknown-point.yaml",
        9,
        "bodies[1].points",
        &["unknown point 'P3'"],
    );
}

/// Warnings of `mbfg check` on a scene that assembles (exit 0).
fn warnings(rel: &str) -> Vec<String> {
    let out = check(rel);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{rel}: {stderr}");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .chain(stderr.lines())
        .filter(|l| l.trim_start().starts_with("warning: "))
        .map(str::to_string)
        .collect()
}

#[test]
fn units_that_slip_through_are_warned_of() {
    let mm = warnings("tests/data/units/millimetres.yaml");
    assert!(
        mm.iter()
            .any(|w| w.contains("effect 'knee': rest_angle 97 is beyond 2π")
                && w.contains("1.6930 rad")),
        "{mm:?}"
    );
    assert!(
        mm.iter()
            .any(|w| w.contains("body 'crank' is 120.000 m long") && w.contains("millimetres")),
        "{mm:?}"
    );
    let grams = warnings("tests/data/units/grams.yaml");
    assert!(
        grams
            .iter()
            .any(|w| w.contains("body 'crank' weighs 250.000 kg") && w.contains("grams")),
        "{grams:?}"
    );
    // The suite's scenes, a 5 mm crank included, are in metres and kilograms.
    for scene in [
        "scenes/fourbar.yaml",
        "scenes/driven/slider-crank-mm.yaml",
        "scenes/driven/six-bar-press.yaml",
        "scenes/pick-and-place.yaml",
    ] {
        let w = warnings(scene);
        assert!(
            !w.iter()
                .any(|w| w.contains("millimetres") || w.contains("grams") || w.contains("2π")),
            "{scene}: {w:?}"
        );
    }
}

#[test]
fn a_locked_mechanism_is_warned_of_without_independent_coordinates() {
    let dir = std::env::temp_dir().join(format!("mbfg-locked-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let text = std::fs::read_to_string(manifest_dir().join(bad("locked-independent.yaml")))
        .unwrap()
        .replace("independent: [theta]\n", "");
    let scene = dir.join("locked.yaml");
    std::fs::write(&scene, text).unwrap();
    let w = warnings(scene.to_str().unwrap());
    assert!(
        w.iter().any(|w| w.contains("the mechanism cannot move")
            && w.contains("constraint 'brace: distance(A,C)'")),
        "{w:?}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn duplicate_point_name() {
    assert_error(
        "duplicate-point.yaml",
        6,
        "points[2].name",
        &["duplicate name 'P'"],
    );
}

#[test]
fn duplicate_body_name() {
    // The second body gives its name on the line after its points: the line is the
    // name's.
    assert_error(
        "duplicate-body.yaml",
        12,
        "bodies[1].name",
        &["duplicate name 'link'"],
    );
}

#[test]
fn body_with_one_point() {
    assert_error(
        "body-one-point.yaml",
        9,
        "bodies[0].points",
        &["'rod'", "needs 2 or more points, has 1"],
    );
}

#[test]
fn body_with_coincident_points() {
    assert_error(
        "body-coincident-points.yaml",
        7,
        "bodies[0]",
        &["'rod'", "'A'", "'P'", "coincide"],
    );
}

#[test]
fn body_naming_a_point_twice() {
    assert_error(
        "body-same-point-twice.yaml",
        8,
        "bodies[0]",
        &["'plate'", "point 'P' twice"],
    );
}

#[test]
fn body_with_zero_mass() {
    assert_error(
        "mass-nonpositive.yaml",
        9,
        "bodies[0].mass",
        &["must be positive", "got 0"],
    );
}

#[test]
fn body_with_negative_inertia() {
    assert_error(
        "inertia-negative.yaml",
        10,
        "bodies[0].inertia",
        &["must be positive", "-0.1"],
    );
}

#[test]
fn body_with_zero_inertia() {
    assert_error(
        "inertia-zero.yaml",
        10,
        "bodies[0].inertia",
        &["must be positive", "got 0"],
    );
}

#[test]
fn i0_below_mass_times_cog_squared() {
    // I0 = 0.25 about the first point, m |cog|² = 2 · 0.5² = 0.5: the line is I0's.
    assert_error(
        "i0-below-steiner.yaml",
        11,
        "bodies[0].I0",
        &["0.25", "0.5", "centre of mass"],
    );
}

#[test]
fn unknown_key_in_body() {
    assert_error(
        "unknown-body-key.yaml",
        10,
        "bodies[0].colour",
        &["unknown key 'colour'", "inertia", "I0"],
    );
}

// ---------------------------------------------------------------------------------
// Expressions

#[test]
fn malformed_expression() {
    assert_error(
        "malformed-expression.yaml",
        12,
        "bodies[0].inertia",
        &["malformed expression", "'2*(L'"],
    );
}

#[test]
fn malformed_expression_over_two_lines_is_one_line() {
    // A block scalar keeps its line breaks; the message shows them escaped.
    assert_error(
        "expression-multiline.yaml",
        12,
        "bodies[0].inertia",
        &["malformed expression", "2*(L\\n+ 1"],
    );
}

#[test]
fn undefined_name_in_expression() {
    assert_error(
        "undefined-name.yaml",
        8,
        "points[1].x",
        &["undefined name", "'L2'"],
    );
}

// ---------------------------------------------------------------------------------
// Types of effects, constraints and coordinates

#[test]
fn unknown_effect_type() {
    assert_error(
        "unknown-effect-type.yaml",
        10,
        "effects[1].type",
        &["unknown effect type 'drag'", "spring_damper"],
    );
}

#[test]
fn unknown_constraint_type() {
    // The entry starts on line 10 with its name; `type: gear` is on line 11.
    assert_error(
        "unknown-constraint-type.yaml",
        11,
        "constraints[0].type",
        &["unknown constraint type 'gear'", "fixed_slider"],
    );
}

#[test]
fn unknown_coordinate_type() {
    assert_error(
        "unknown-coordinate-type.yaml",
        10,
        "coordinates[1].type",
        &["unknown coordinate type 'curvature'", "relative_angle"],
    );
}

// ---------------------------------------------------------------------------------
// Independent coordinates and the initial state

#[test]
fn unknown_independent_coordinate() {
    assert_error(
        "unknown-independent.yaml",
        11,
        "independent",
        &["unknown coordinate 'thetta'", "did you mean 'theta'?"],
    );
}

#[test]
fn unknown_effect_coordinate_suggests_the_closest() {
    assert_error(
        "unknown-effect-coordinate.yaml",
        11,
        "effects[0].coordinate",
        &["unknown coordinate 'pis'", "did you mean 'psi'?"],
    );
}

#[test]
fn a_mechanism_that_cannot_move_names_the_constraint_that_locks_it() {
    assert_error(
        "locked-independent.yaml",
        16,
        "independent",
        &[
            "the mechanism cannot move",
            "0 degrees of freedom",
            "constraint 'brace: distance(A,C)' takes its last degree of freedom",
        ],
    );
}

#[test]
fn a_point_on_no_body_is_named_when_independent_coordinates_are_declared() {
    assert_error(
        "massless-independent.yaml",
        12,
        "independent",
        &[
            "the mechanism has 3 degree(s) of freedom",
            "point(s) P on no body",
            "name 3",
        ],
    );
}

#[test]
fn initial_velocity_of_a_dependent_coordinate() {
    assert_error(
        "velocity-not-independent.yaml",
        14,
        "initial.velocities.P.y",
        &["independent"],
    );
}

#[test]
fn position_problem_that_cannot_close() {
    // Crank 1, coupler 1, rocker 1 between pivots 10 m apart: no line to point at,
    // but the message names the constraints left violated.
    let rel = bad("fourbar-cannot-close.yaml");
    let text = failure(&rel);
    assert!(text.starts_with(&format!("error: {rel}: ")), "{text}");
    assert!(text.contains("position problem"), "{text}");
    for c in [
        "crank: distance(A,P1)",
        "coupler: distance(P1,P2)",
        "rocker: distance(P2,B)",
    ] {
        assert!(
            text.contains(c),
            "expected '{c}' among the violated: {text}"
        );
    }
}

// ---------------------------------------------------------------------------------
// Mechanism files

#[test]
fn mechanism_naming_itself() {
    // Only an MBSE file can be a mechanism: a scene naming itself must not recurse.
    assert_error(
        "mechanism-self.yaml",
        3,
        "mechanism",
        &["not an MBSE mechanism file", "mechanism-self.yaml"],
    );
}

#[test]
fn mechanism_file_missing() {
    assert_error(
        "mechanism-missing.yaml",
        3,
        "mechanism",
        &["cannot read", "no-such-mechanism.yaml"],
    );
}

#[test]
fn mbse_point_index_out_of_range() {
    assert_error(
        "mbse-point-out-of-range.yaml",
        8,
        "planar_bodies[1].points",
        &["unknown point 3", "0 to 2"],
    );
}

#[test]
fn mbse_unknown_relative_coordinate_type() {
    assert_error(
        "mbse-unknown-relative-type.yaml",
        10,
        "relative_coordinates[1].type",
        &["'RelativeDistance'", "RelativeAngleAbsoluteDOF"],
    );
}

#[test]
fn mbse_body_without_i0() {
    // MBSE bodies take I0 about the first point; `inertia` is not read.
    assert_error(
        "mbse-unknown-key.yaml",
        9,
        "planar_bodies[0].I0",
        &["missing required key", "body0"],
    );
}

#[test]
fn no_bad_input_panics() {
    let dir = manifest_dir().join("tests/data/bad");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .expect("tests/data/bad")
        .map(|e| {
            e.expect("dir entry")
                .file_name()
                .to_string_lossy()
                .into_owned()
        })
        .filter(|n| n.ends_with(".yaml"))
        .collect();
    names.sort();
    assert!(names.len() >= 20, "too few bad files: {names:?}");
    for name in &names {
        // `failure` rejects a panic, a signal (stack overflow), any exit code but 2
        // and anything but one line.
        failure(&bad(name));
    }
}

// ---------------------------------------------------------------------------------
// Good scenes

/// Runs `mbfg check` on a file that must pass and returns its stdout.
fn success(rel: &str) -> String {
    let out = check(rel);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{rel}: exit {:?}; stderr: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.stderr.is_empty(), "{rel}: unexpected stderr");
    stdout
}

/// n, m, dof and the coordinate names from a `mbfg check` summary.
fn summary(stdout: &str) -> (usize, usize, usize, Vec<String>) {
    let field = |prefix: &str| {
        stdout
            .lines()
            .find_map(|l| l.strip_prefix(prefix))
            .unwrap_or_else(|| panic!("no '{prefix}' line in:\n{stdout}"))
            .to_string()
    };
    let n_line = field("n = ");
    let (n, names) = n_line
        .split_once(" coordinates: ")
        .unwrap_or_else(|| panic!("malformed n line: {n_line}"));
    let m_line = field("m = ");
    let m = m_line.split_whitespace().next().unwrap().to_string();
    let dof = field("degrees of freedom: ");
    (
        n.parse().unwrap(),
        m.parse().unwrap(),
        dof.trim().parse().unwrap(),
        names.split(", ").map(str::to_string).collect(),
    )
}

#[test]
fn fourbar_checks() {
    let out = success("scenes/fourbar.yaml");
    assert!(out.contains("n = 4"), "{out}");
    assert!(out.contains("m = 3"), "{out}");
    assert!(out.contains("degrees of freedom: 1"), "{out}");
    let (n, m, dof, names) = summary(&out);
    assert_eq!((n, m, dof), (4, 3, 1));
    assert_eq!(names, ["P1.x", "P1.y", "P2.x", "P2.y"]);
}

#[test]
fn pick_and_place_in_both_formats() {
    let native = summary(&success("scenes/pick-and-place.yaml"));
    let scene = summary(&success("scenes/pick-and-place-mbse.yaml"));
    let mbse = summary(&success("scenes/mbse/pick-and-place.yaml"));
    for (file, s) in [("native", &native), ("scene", &scene), ("mbse", &mbse)] {
        assert_eq!((s.0, s.1, s.2), (22, 21, 2), "{file}");
        assert_eq!(s.3.len(), 22, "{file}");
    }
    // The scene naming the MBSE file and the MBSE file itself: the same q.
    assert_eq!(scene.3, mbse.3);
    assert_eq!(&mbse.3[20..], ["r0", "r1"]);
    // The native scene names its points as MBSE does (p<index>), so the point
    // coordinates agree; its two motor angles have names of their own.
    assert_eq!(native.3[..20], mbse.3[..20]);
    assert_eq!(&native.3[20..], ["motor1", "motor2"]);
}

#[test]
fn mbse_test_files() {
    let fourbar = summary(&success("tests/data/mbse/fourbar.yaml"));
    assert_eq!((fourbar.0, fourbar.1, fourbar.2), (5, 4, 1));
    assert_eq!(fourbar.3, ["p1.x", "p1.y", "p2.x", "p2.y", "r0"]);

    let plate = summary(&success("tests/data/mbse/pendulum-plate.yaml"));
    assert_eq!((plate.0, plate.1, plate.2), (7, 6, 1));
    assert_eq!(
        plate.3,
        ["p1.x", "p1.y", "p2.x", "p2.y", "p3.x", "p3.y", "r0"]
    );

    // A scene naming the MBSE four-bar, with r0 independent and moving.
    let out = success("tests/data/mbse/fourbar-scene.yaml");
    let scene = summary(&out);
    assert_eq!(scene, fourbar);
    assert!(out.contains("independent coordinates: r0"), "{out}");
    assert!(out.contains("motor: torque on r0"), "{out}");
    assert!(!out.contains("kinetic energy 0.000000 J"), "{out}");
}
