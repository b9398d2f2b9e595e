//! The estimate as a table ([`Estimates`]): the trajectory CSV contract (t, q:, dq:,
//! ddq:) with the unknown inputs (Q:<c>), the identified parameters (p:<name>) and the
//! standard deviation of every estimate (sd:q:, sd:dq:, sd:ddq:, sd:Q:, sd:p:).

use super::online::StepEstimate;
use crate::error::{Error, Result};
use crate::model::Model;
use std::io::Write;

/// Final estimates, one row a step.
#[derive(Debug, Clone, PartialEq)]
pub struct Estimates {
    pub columns: Vec<String>,
    /// Row-major rows × columns (t first).
    pub values: Vec<f64>,
    pub rows: usize,
    /// Where each estimate column's value sits in a step's block.
    picks: Vec<usize>,
}

impl Estimates {
    /// An empty table of `model`'s coordinates and the unknown inputs on the
    /// coordinates `inputs`, whose values sit in each step's block from `inputs_at`
    /// on (after q, q̇, q̈ in DC; after z, ż, z̈ too in IC).
    pub fn new(model: &Model, inputs: &[usize], inputs_at: usize) -> Self {
        let mut columns = vec!["t".to_string()];
        for p in ["q", "dq", "ddq"] {
            columns.extend(model.names.iter().map(|c| format!("{p}:{c}")));
        }
        columns.extend(inputs.iter().map(|&i| format!("Q:{}", model.names[i])));
        // The identified parameters follow the inputs in the block (DC only).
        let parameters: &[String] = model.parameters.as_ref().map_or(&[], |p| &p.names);
        columns.extend(parameters.iter().map(|p| format!("p:{p}")));
        for p in ["q", "dq", "ddq"] {
            columns.extend(model.names.iter().map(|c| format!("sd:{p}:{c}")));
        }
        columns.extend(inputs.iter().map(|&i| format!("sd:Q:{}", model.names[i])));
        columns.extend(parameters.iter().map(|p| format!("sd:p:{p}")));
        let n = model.n();
        let picks = (0..3 * n)
            .chain(inputs_at..inputs_at + inputs.len() + parameters.len())
            .collect();
        Estimates {
            columns,
            values: Vec::new(),
            rows: 0,
            picks,
        }
    }

    /// The table of an estimate of `model`: its coordinates and its scene's unknown
    /// inputs (estimated in DC, where they follow q, q̇, q̈ in the block).
    pub fn for_model(model: &Model) -> Self {
        let inputs: Vec<usize> = model.estimation.inputs.iter().map(|&(c, _)| c).collect();
        Estimates::new(model, &inputs, 3 * model.n())
    }

    /// Appends a step's estimate (its block: q, q̇, q̈, inputs) and its σ's.
    pub fn push(&mut self, e: &StepEstimate) {
        self.values.push(e.t);
        self.values.extend(self.picks.iter().map(|&i| e.x[i]));
        let sd = e.sd();
        self.values.extend(self.picks.iter().map(|&i| sd[i]));
        self.rows += 1;
    }

    /// The values of column `name`.
    pub fn column(&self, name: &str) -> Option<Vec<f64>> {
        let j = self.columns.iter().position(|c| c == name)?;
        let w = self.columns.len();
        Some((0..self.rows).map(|i| self.values[i * w + j]).collect())
    }

    /// Writes the table as CSV.
    pub fn write_csv(&self, w: &mut dyn Write) -> Result<()> {
        let io = |e: std::io::Error| Error::Io {
            path: "the estimate's CSV".into(),
            source: e,
        };
        writeln!(w, "{}", self.columns.join(",")).map_err(io)?;
        let width = self.columns.len();
        let mut line = String::new();
        for row in self.values.chunks_exact(width) {
            line.clear();
            for (j, v) in row.iter().enumerate() {
                if j > 0 {
                    line.push(',');
                }
                line.push_str(&crate::io::number(*v));
            }
            writeln!(w, "{line}").map_err(io)?;
        }
        Ok(())
    }
}
