//! Scene text → `Scene::from_str` → `Model::new` (which solves the position problem).
//! No input may panic, and every parse error is one line of at most 300 characters.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::Path;

/// Scenes larger than this are valid but only slow the search down.
const MAX_PARTS: usize = 40;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let scene = match mbfg::Scene::from_str(text, Path::new("fuzz.yaml")) {
        Ok(scene) => scene,
        Err(e) => {
            let msg = e.to_string();
            assert!(!msg.contains('\n'), "message spans lines: {msg}");
            assert!(msg.chars().count() <= 300, "message too long: {msg}");
            return;
        }
    };
    let parts = scene.points.len()
        + scene.bodies.len()
        + scene.coordinates.len()
        + scene.constraints.len()
        + scene.effects.len();
    if parts > MAX_PARTS {
        return;
    }
    if let Ok(model) = mbfg::Model::new(&scene) {
        // Every time function must evaluate without panicking.
        for e in &scene.effects {
            if let mbfg::scene::Effect::Torque { value, .. } = e {
                let _ = value.at(0.5);
            }
        }
        drop(model);
    }
});
