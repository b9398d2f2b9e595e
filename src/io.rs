//! Trajectory CSV files (the contract of DESIGN.md): header `t`, then `q:<c>` for
//! every coordinate in model order, then `dq:<c>`, then `ddq:<c>`, and `Q:<c>` when
//! generalized forces are known. Numbers are written in Rust's shortest round-trip
//! form, so reading a file back gives the same bits.

use crate::error::{Error, Result};
use crate::forward::Trajectory;
use std::io::Write;
use std::path::Path;

/// The column names of a trajectory with `names` coordinates.
pub fn header(names: &[String], with_forces: bool) -> Vec<String> {
    let mut h = vec!["t".to_string()];
    let prefixes: &[&str] = if with_forces {
        &["q", "dq", "ddq", "Q"]
    } else {
        &["q", "dq", "ddq"]
    };
    for p in prefixes {
        h.extend(names.iter().map(|c| format!("{p}:{c}")));
    }
    h
}

/// Writes a trajectory (and, if given, generalized forces, row-major samples × n).
/// Refuses non-finite values rather than writing them.
pub fn write_trajectory<W: Write>(
    out: W,
    trajectory: &Trajectory,
    forces: Option<&[f64]>,
) -> Result<()> {
    let n = trajectory.n();
    let mut w = csv::Writer::from_writer(out);
    let io = |e: csv::Error| Error::Data(e.to_string());
    w.write_record(header(&trajectory.names, forces.is_some()))
        .map_err(io)?;
    let mut record: Vec<String> = Vec::with_capacity(1 + 4 * n);
    for k in 0..trajectory.len() {
        record.clear();
        let mut push = |v: f64, what: &str| -> Result<()> {
            if !v.is_finite() {
                return Err(Error::Singular(format!(
                    "non-finite {what} at t = {} (sample {k}); nothing written past it",
                    trajectory.t[k]
                )));
            }
            record.push(number(v));
            Ok(())
        };
        push(trajectory.t[k], "time")?;
        for (what, v) in [
            ("position", &trajectory.q),
            ("velocity", &trajectory.dq),
            ("acceleration", &trajectory.ddq),
        ] {
            for &x in &v[k * n..(k + 1) * n] {
                push(x, what)?;
            }
        }
        if let Some(f) = forces {
            for &x in &f[k * n..(k + 1) * n] {
                push(x, "generalized force")?;
            }
        }
        w.write_record(&record).map_err(io)?;
    }
    w.flush().map_err(|e| Error::Data(e.to_string()))?;
    Ok(())
}

/// Shortest round-trip text of a number: plain for moderate magnitudes, scientific
/// otherwise (Rust's plain form would spell 1e-30 with thirty zeros).
fn number(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 || (1e-4..1e7).contains(&a) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// A numeric table read from a CSV file with a header row.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    pub columns: Vec<String>,
    /// Row-major rows × columns.
    pub values: Vec<f64>,
    pub rows: usize,
}

impl Table {
    /// The values of column `name`, if present.
    pub fn column(&self, name: &str) -> Option<Vec<f64>> {
        let j = self.columns.iter().position(|c| c == name)?;
        let w = self.columns.len();
        Some((0..self.rows).map(|i| self.values[i * w + j]).collect())
    }
}

/// Reads a numeric CSV table (gzip-compressed when the name ends in `.gz`, as the
/// committed references are); errors name the file, the line and the column.
pub fn read_table(path: &Path) -> Result<Table> {
    let file = path.display().to_string();
    let raw = std::fs::File::open(path).map_err(|e| Error::Data(format!("{file}: {e}")))?;
    let input: Box<dyn std::io::Read> = if path.extension().is_some_and(|e| e == "gz") {
        Box::new(flate2::read::GzDecoder::new(raw))
    } else {
        Box::new(raw)
    };
    let mut r = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_reader(input);
    let columns: Vec<String> = r
        .headers()
        .map_err(|e| Error::Data(format!("{file}: {e}")))?
        .iter()
        .map(str::to_string)
        .collect();
    if columns.is_empty() || columns.iter().all(|c| c.is_empty()) {
        return Err(Error::Data(format!("{file}: no header row")));
    }
    let mut values = Vec::new();
    let mut rows = 0;
    for (i, record) in r.records().enumerate() {
        let line = i + 2;
        let record = record.map_err(|e| Error::Data(format!("{file}:{line}: {e}")))?;
        if record.len() != columns.len() {
            return Err(Error::InvalidArgument(format!(
                "{file}:{line}: {} fields where the header has {}",
                record.len(),
                columns.len()
            )));
        }
        for (j, field) in record.iter().enumerate() {
            let v: f64 = field.parse().map_err(|_| {
                Error::InvalidArgument(format!(
                    "{file}:{line}: column `{}`: `{field}` is not a number",
                    columns[j]
                ))
            })?;
            if !v.is_finite() {
                return Err(Error::InvalidArgument(format!(
                    "{file}:{line}: column `{}`: {field} is not finite",
                    columns[j]
                )));
            }
            values.push(v);
        }
        rows += 1;
    }
    Ok(Table {
        columns,
        values,
        rows,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn written_trajectory_reads_back_bit_for_bit() {
        let tr = Trajectory {
            names: vec!["P1.x".into(), "theta".into()],
            t: vec![0.0, 0.001],
            q: vec![1.0, 0.1, 0.999_999_5, std::f64::consts::PI],
            dq: vec![0.0, -1e-300, 2.5, 3.0],
            ddq: vec![1.0 / 3.0, 0.0, -9.81, 1e10],
        };
        let mut buf = Vec::new();
        write_trajectory(&mut buf, &tr, None).unwrap();
        let text = String::from_utf8(buf).unwrap();
        assert!(text.starts_with("t,q:P1.x,q:theta,dq:P1.x,dq:theta,ddq:P1.x,ddq:theta\n"));
        let dir = std::env::temp_dir().join(format!("mbfg-io-{}.csv", std::process::id()));
        std::fs::write(&dir, &text).unwrap();
        let table = read_table(&dir).unwrap();
        std::fs::remove_file(&dir).ok();
        assert_eq!(table.rows, 2);
        assert_eq!(table.column("q:theta").unwrap()[1], std::f64::consts::PI);
        assert_eq!(table.column("ddq:P1.x").unwrap()[0], 1.0 / 3.0);
        assert_eq!(table.column("dq:theta").unwrap()[0], -1e-300);
    }

    #[test]
    fn non_finite_values_are_refused() {
        let tr = Trajectory {
            names: vec!["a".into()],
            t: vec![0.0],
            q: vec![f64::NAN],
            dq: vec![0.0],
            ddq: vec![0.0],
        };
        let err = write_trajectory(Vec::new(), &tr, None).unwrap_err();
        assert!(err.to_string().contains("non-finite position"), "{err}");
    }
}
