//! Priors: f_prior on a whole variable ([`Prior`]) and on some of its components
//! ([`ComponentPrior`]).

use super::shared::{identity, key_accessor};
use crate::error::Result;
use crate::graph::{Factor, Key, VarKind, Workspace};

/// f_prior: e = x − x₀ on one variable.
pub struct Prior {
    name: String,
    keys: [Key; 1],
    target: Vec<f64>,
}

impl Prior {
    pub fn new(kind: VarKind, target: Vec<f64>) -> Self {
        Prior {
            name: format!("f_prior({})", kind.symbol()),
            keys: [Key::now(kind)],
            target,
        }
    }
}

impl Factor for Prior {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.target.len()
    }
    fn dim(&self) -> usize {
        self.target.len()
    }
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        true
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = x[0][i] - self.target[i];
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim(), 1.0);
        }
        Ok(())
    }
}

/// f_prior on some components of a variable: e = x[idx] − x₀. Fixes the generalized
/// forces where no actuator acts (x₀ = 0), or the prescribed coordinates' initial
/// velocity and acceleration.
pub struct ComponentPrior {
    name: String,
    keys: [Key; 1],
    /// The size of the variable the components are of.
    size: usize,
    indices: Vec<usize>,
    target: Vec<f64>,
}

impl ComponentPrior {
    /// On components `indices` of the variable `kind`, of `size` entries.
    pub fn new(kind: VarKind, size: usize, indices: Vec<usize>, target: Vec<f64>) -> Self {
        assert_eq!(indices.len(), target.len(), "one target per component");
        ComponentPrior {
            name: format!("f_prior({}[…])", kind.symbol()),
            keys: [Key::now(kind)],
            size,
            indices,
            target,
        }
    }
}

impl Factor for ComponentPrior {
    fn name(&self) -> &str {
        &self.name
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
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        for (ri, (&i, &t)) in r.iter_mut().zip(self.indices.iter().zip(&self.target)) {
            *ri = x[0][i] - t;
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
