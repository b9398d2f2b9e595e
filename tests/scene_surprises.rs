//! What a scene file does that its author may not have meant is said, not silently
//! done: drawing hints the reader ignores, a mechanism that nothing moves, a length
//! that contradicts the drawing, an expression cut at a comma.

use std::path::{Path, PathBuf};
use std::process::Output;

fn check(path: &Path) -> Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .arg("check")
        .arg(path)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run mbfg")
}

fn temp_scene(name: &str, text: &str) -> PathBuf {
    let p = std::env::temp_dir().join(format!("mbfg-surprise-{}-{name}", std::process::id()));
    std::fs::write(&p, text).unwrap();
    p
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn visual_hints_of_mbse_files_are_accepted_with_a_note() {
    let out = check(Path::new("tests/data/mbse/plate-visual.yaml"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = stdout(&out);
    assert!(text.contains("m = 4 constraints"), "{text}");
    for body in ["planar_bodies[0]", "planar_bodies[1]"] {
        assert!(
            text.contains(&format!(
                "note: tests/data/mbse/plate-visual.yaml: {body}.visual is a drawing hint: ignored"
            )),
            "{text}"
        );
    }
    // On its own an MBSE file has nothing acting on it: said too.
    assert!(
        text.contains("warning: ") && text.contains("nothing moves the mechanism"),
        "{text}"
    );
}

#[test]
fn a_length_that_contradicts_the_drawing_is_named_with_the_distance() {
    let fourbar = std::fs::read_to_string("scenes/fourbar.yaml").unwrap();
    let bad = temp_scene(
        "fourbar.yaml",
        &fourbar.replace("length: sqrt(13)}", "length: 1}"),
    );
    let text = stdout(&check(&bad));
    std::fs::remove_file(&bad).ok();
    assert!(
        text.contains("warning: assembling the constraints moved P2 by 2.828e0 m"),
        "{text}"
    );
    // The suite's own scenes assemble where they are drawn.
    let text = stdout(&check(Path::new("scenes/fourbar.yaml")));
    assert!(!text.contains("warning"), "{text}");
}

#[test]
fn an_expression_cut_at_a_comma_says_to_quote_it() {
    let mut text = std::fs::read_to_string("scenes/pendulum.yaml").unwrap();
    text += "  - {type: torque, coordinate: theta, value: 20*min(1, t)}\n";
    let scene = temp_scene("comma.yaml", &text);
    let out = check(&scene);
    std::fs::remove_file(&scene).ok();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("malformed expression '20*min(1'") && err.contains("quote an expression"),
        "{err}"
    );
    assert!(err.trim_end().chars().count() <= 300, "{err}");
}

#[test]
fn a_point_that_moves_without_mass_is_named() {
    // P2 hangs on a massless rod from the bob: its swing about P1 has no inertia.
    let scene = temp_scene(
        "massless.yaml",
        "name: massless-end\n\
         points:\n  - {name: A, x: 0, y: 0, fixed: true}\n  \
         - {name: P1, x: 0.7, y: -0.7, mass: 1}\n  - {name: P2, x: 1.4, y: -0.7}\n\
         constraints:\n  - {name: rod1, type: distance, points: [A, P1]}\n  \
         - {name: rod2, type: distance, points: [P1, P2]}\n\
         effects:\n  - {type: gravity, vector: [0, -9.81]}\n",
    );
    let text = stdout(&check(&scene));
    std::fs::remove_file(&scene).ok();
    assert!(
        text.contains("warning: 1 of the 2 motions the constraints allow carry no inertia (moving without mass: P2)"),
        "{text}"
    );
    // A point without mass whose every motion moves a mass (the knee between two
    // rods, the tip carrying the mass) is no such case.
    let knee = temp_scene(
        "knee.yaml",
        "name: knee\n\
         points:\n  - {name: A, x: 0, y: 0, fixed: true}\n  \
         - {name: P1, x: 0.7, y: -0.7}\n  - {name: P2, x: 1.4, y: -0.7, mass: 1}\n\
         constraints:\n  - {name: rod1, type: distance, points: [A, P1]}\n  \
         - {name: rod2, type: distance, points: [P1, P2]}\n\
         effects:\n  - {type: gravity, vector: [0, -9.81]}\n",
    );
    let text = stdout(&check(&knee));
    std::fs::remove_file(&knee).ok();
    assert!(!text.contains("no inertia"), "{text}");
}

/// A spring's `rest_length` takes `auto` inside an expression as a distance's `length`
/// does (it read "undefined name 'auto'"): 0.5*auto is half the placed distance.
#[test]
fn a_rest_length_may_scale_the_placed_distance() {
    let text = "name: half-rest
points:
  - {name: O, x: 0, y: 0, fixed: true}
  - {name: P, x: 0, y: -2}
bodies:
  - {name: bob, points: [O, P], mass: 1}
effects:
  - {name: spring, type: spring_damper, points: [O, P], stiffness: 10, rest_length: 0.5*auto}
";
    let scene = mbfg::Scene::from_str(text, Path::new("half-rest.yaml")).unwrap();
    let rest = scene.effects.iter().find_map(|e| match e {
        mbfg::scene::Effect::SpringDamper { rest_length, .. } => Some(*rest_length),
        _ => None,
    });
    assert_eq!(rest, Some(1.0));
}
