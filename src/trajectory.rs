//! A motion sampled on a time grid: q, q̇ and q̈ at each time, in model order, as a
//! forward run returns it, the trajectory files hold it and an inverse run reads it.

/// A simulated motion: for each time, q, q̇ and q̈ in model order.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    pub names: Vec<String>,
    pub t: Vec<f64>,
    /// Row-major samples × n.
    pub q: Vec<f64>,
    pub dq: Vec<f64>,
    pub ddq: Vec<f64>,
}

impl Trajectory {
    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    pub fn n(&self) -> usize {
        self.names.len()
    }

    /// Every `stride`-th sample (0, stride, 2·stride, …), on the grid t_j = j·dt.
    pub fn every(&self, stride: usize, dt: f64) -> Trajectory {
        let rows: Vec<usize> = (0..self.len()).step_by(stride.max(1)).collect();
        let mut picked = self.pick(&rows);
        for (j, t) in picked.t.iter_mut().enumerate() {
            *t = j as f64 * dt;
        }
        picked
    }

    /// The samples at `rows`, in that order.
    pub fn pick(&self, rows: &[usize]) -> Trajectory {
        let n = self.n();
        let pick = |v: &[f64]| {
            rows.iter()
                .flat_map(|&r| &v[r * n..(r + 1) * n])
                .copied()
                .collect()
        };
        Trajectory {
            names: self.names.clone(),
            t: rows.iter().map(|&r| self.t[r]).collect(),
            q: pick(&self.q),
            dq: pick(&self.dq),
            ddq: pick(&self.ddq),
        }
    }

    /// Keeps the first `len` samples.
    pub fn truncate(&mut self, len: usize) {
        let n = self.n();
        self.t.truncate(len);
        for v in [&mut self.q, &mut self.dq, &mut self.ddq] {
            v.truncate(len * n);
        }
    }

    pub fn q_at(&self, k: usize) -> &[f64] {
        &self.q[k * self.n()..(k + 1) * self.n()]
    }

    pub fn dq_at(&self, k: usize) -> &[f64] {
        &self.dq[k * self.n()..(k + 1) * self.n()]
    }

    pub fn ddq_at(&self, k: usize) -> &[f64] {
        &self.ddq[k * self.n()..(k + 1) * self.n()]
    }
}

/// A time for messages: t₀ + k·Δt carries round-off (1.2690000000000001).
pub fn round_time(t: f64) -> f64 {
    (t * 1e9).round() / 1e9
}

/// The cubic Hermite basis on [0, 1] at `s`, ([h00, h10, h01, h11]), and its
/// derivatives per unit of s: a value between two states with rates is
/// h00·x₀ + h10·h·ẋ₀ + h01·x₁ + h11·h·ẋ₁ (fourth-order accurate), its rate
/// (d00·x₀ + d01·x₁)/h + d10·ẋ₀ + d11·ẋ₁.
pub fn cubic_hermite(s: f64) -> ([f64; 4], [f64; 4]) {
    let (s2, s3) = (s * s, s * s * s);
    (
        [
            2.0 * s3 - 3.0 * s2 + 1.0,
            s3 - 2.0 * s2 + s,
            -2.0 * s3 + 3.0 * s2,
            s3 - s2,
        ],
        [
            6.0 * s2 - 6.0 * s,
            3.0 * s2 - 4.0 * s + 1.0,
            -6.0 * s2 + 6.0 * s,
            3.0 * s2 - 2.0 * s,
        ],
    )
}
