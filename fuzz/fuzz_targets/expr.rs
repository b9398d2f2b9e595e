//! Expression text → `Expr::parse` → `eval`, `bind`, `names` and `derivative`, on a thread with a
//! 256 kB stack: no input may panic or overflow it, and every error is one short line.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbfg::expr::Expr;

fn check(text: &str) {
    let lookup = |name: &str| match name {
        "t" => Some(0.5),
        "L" => Some(2.0),
        "mass" => Some(3.0),
        "zero" => Some(0.0),
        _ if name.len().is_multiple_of(3) => Some(name.len() as f64),
        _ => None,
    };
    let short = |e: &mbfg::expr::ExprError| {
        let msg = e.to_string();
        assert!(!msg.contains('\n'), "message spans lines: {msg}");
        assert!(msg.chars().count() <= 300, "message too long: {msg}");
    };
    let expr = match Expr::parse(text) {
        Ok(expr) => expr,
        Err(e) => return short(&e),
    };
    if let Err(e) = expr.eval(&lookup) {
        short(&e);
    }
    let _ = expr.names();
    match expr.bind(&|n| n == "t", &lookup) {
        Ok(bound) => {
            if let Err(e) = bound.eval(&|n| (n == "t").then_some(0.25)) {
                short(&e);
            }
            // The symbolic derivative of any expression evaluates like the expression.
            match bound.derivative("t") {
                Ok(d) => {
                    if let Err(e) = d.eval(&|n| (n == "t").then_some(0.25)) {
                        short(&e);
                    }
                }
                Err(e) => short(&e),
            }
        }
        Err(e) => short(&e),
    }
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let text = text.to_string();
    // A small stack proves the depth limits, not the default 8 MB.
    std::thread::Builder::new()
        .stack_size(256 * 1024)
        .spawn(move || check(&text))
        .expect("spawn")
        .join()
        .unwrap_or_else(|e| std::panic::resume_unwind(e));
});
