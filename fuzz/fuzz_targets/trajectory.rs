//! Trajectory CSV (gzip-compressed when it starts with the gzip magic) →
//! `read_table_from` with small limits → `Prescription::from_table` against the
//! four-bar with its crank angle `theta`. No input may panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbfg::inverse::Prescription;
use mbfg::io::{read_table_from, TableLimits};
use std::io::Read;
use std::path::Path;
use std::sync::OnceLock;

fn model() -> &'static mbfg::Model {
    static MODEL: OnceLock<mbfg::Model> = OnceLock::new();
    MODEL.get_or_init(|| {
        let text = include_str!("../../scenes/fourbar-theta.yaml");
        let scene = mbfg::Scene::from_str(text, Path::new("fourbar-theta.yaml")).unwrap();
        mbfg::Model::new(&scene).unwrap()
    })
}

fuzz_target!(|data: &[u8]| {
    let model = model();
    let limits = TableLimits {
        max_cells: 100_000,
        max_bytes: 4 << 20,
    };
    let input: Box<dyn Read> = if data.starts_with(&[0x1f, 0x8b]) {
        Box::new(flate2::read::GzDecoder::new(data))
    } else {
        Box::new(data)
    };
    let table = match read_table_from(input, "fuzz.csv", &limits, &mut |_| Ok(())) {
        Ok(table) => table,
        Err(e) => {
            let msg = e.to_string();
            assert!(!msg.contains('\n'), "message spans lines: {msg}");
            assert!(msg.chars().count() <= 300, "message too long: {msg}");
            return;
        }
    };
    assert!(table.rows * table.columns.len() <= limits.max_cells);
    assert_eq!(table.values.len(), table.rows * table.columns.len());
    let _ = Prescription::from_table(model, &table, "fuzz.csv");
});
