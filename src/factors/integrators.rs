//! The factors between consecutive steps: the soft link f_eq ([`Equality`]) and the
//! integrators f_ei ([`Euler`]) and f_ti ([`Trapezoidal`]).

use super::shared::{identity, key_accessor};
use crate::error::Result;
use crate::graph::{Factor, Key, VarKind, Workspace};

/// f_eq: e = x_t − x_{t−1}, a soft link between consecutive steps.
pub struct Equality {
    name: String,
    keys: [Key; 2],
    dim: usize,
}

impl Equality {
    pub fn new(kind: VarKind, dim: usize) -> Self {
        Equality {
            name: format!("f_eq({})", kind.symbol()),
            keys: [Key::before(kind), Key::now(kind)],
            dim,
        }
    }
}

impl Factor for Equality {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.dim
    }
    fn dim(&self) -> usize {
        self.dim
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
            *ri = x[1][i] - x[0][i];
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim, -1.0);
            identity(&mut j[1], self.dim, 1.0);
        }
        Ok(())
    }
}

/// f_ei: e = x_t − x_{t−1} − Δt ẋ_{t−1}.
pub struct Euler {
    name: String,
    keys: [Key; 3],
    dim: usize,
    dt: f64,
}

impl Euler {
    pub fn new(x: VarKind, dx: VarKind, dim: usize, dt: f64) -> Self {
        Euler {
            name: format!("f_ei({})", x.symbol()),
            keys: [Key::before(x), Key::now(x), Key::before(dx)],
            dim,
            dt,
        }
    }
}

impl Factor for Euler {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.dim
    }
    fn dim(&self) -> usize {
        self.dim
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
            *ri = x[1][i] - x[0][i] - self.dt * x[2][i];
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim, -1.0);
            identity(&mut j[1], self.dim, 1.0);
            identity(&mut j[2], self.dim, -self.dt);
        }
        Ok(())
    }
}

/// f_ti: e = x_t − x_{t−1} − Δt/2 (ẋ_{t−1} + ẋ_t).
pub struct Trapezoidal {
    name: String,
    keys: [Key; 4],
    dim: usize,
    dt: f64,
}

impl Trapezoidal {
    pub fn new(x: VarKind, dx: VarKind, dim: usize, dt: f64) -> Self {
        Trapezoidal {
            name: format!("f_ti({})", x.symbol()),
            keys: [Key::before(x), Key::now(x), Key::before(dx), Key::now(dx)],
            dim,
            dt,
        }
    }
}

impl Factor for Trapezoidal {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.dim
    }
    fn dim(&self) -> usize {
        self.dim
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
        let h = 0.5 * self.dt;
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = x[1][i] - x[0][i] - h * (x[2][i] + x[3][i]);
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim, -1.0);
            identity(&mut j[1], self.dim, 1.0);
            identity(&mut j[2], self.dim, -h);
            identity(&mut j[3], self.dim, -h);
        }
        Ok(())
    }
}
