//! A prescribed motion: f_prior on some coordinates following a table of values, one
//! row per time step ([`PrescribedMotion`]).

use super::shared::key_accessor;
use crate::error::{Error, Result};
use crate::graph::{Factor, Key, VarKind, Workspace};
use std::sync::Arc;

/// f_prior on a prescribed motion: e = q[idx] − q_p(t_k), the values read from a
/// table with one row per time step t_k = t₀ + k·Δt.
pub struct PrescribedMotion {
    keys: [Key; 1],
    /// The size of the variable the prescribed components are of.
    size: usize,
    indices: Vec<usize>,
    /// Row-major steps × indices.len().
    table: Arc<Vec<f64>>,
    t0: f64,
    dt: f64,
}

impl PrescribedMotion {
    /// On components `indices` of q, of `size` entries (or of z, with `on`).
    pub fn new(size: usize, indices: Vec<usize>, table: Arc<Vec<f64>>, t0: f64, dt: f64) -> Self {
        Self::on(VarKind::Q, size, indices, table, t0, dt)
    }

    /// On components `indices` of the variable `kind`, of `size` entries.
    pub fn on(
        kind: VarKind,
        size: usize,
        indices: Vec<usize>,
        table: Arc<Vec<f64>>,
        t0: f64,
        dt: f64,
    ) -> Self {
        PrescribedMotion {
            keys: [Key::now(kind)],
            size,
            indices,
            table,
            t0,
            dt,
        }
    }
}

impl Factor for PrescribedMotion {
    fn name(&self) -> &str {
        "f_prior(q prescribed)"
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.size
    }
    fn dim(&self) -> usize {
        self.indices.len()
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let p = self.indices.len();
        let k = ((t - self.t0) / self.dt).round() as usize;
        let row = self.table.get(k * p..(k + 1) * p).ok_or_else(|| {
            Error::InvalidArgument(format!("no prescribed values at t = {t} (step {k})"))
        })?;
        for (ri, (&i, &v)) in r.iter_mut().zip(self.indices.iter().zip(row)) {
            *ri = x[0][i] - v;
        }
        if let Some(j) = jac {
            let d = x[0].len();
            j[0].fill(0.0);
            for (row, &i) in self.indices.iter().enumerate() {
                j[0][row * d + i] = 1.0;
            }
        }
        Ok(())
    }
}
