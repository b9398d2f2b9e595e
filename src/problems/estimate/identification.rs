//! What an estimate tells about the parameters it identifies ([`Identification`]):
//! each one's estimate and σ, their correlations, and whether the readings determine
//! it. A parameter is determined where the readings shrink its prior's σ: in the
//! units of the priors' σ's, the readings' information on the parameters is
//! A = S C⁻¹ S − I (C the posterior covariance, S the priors' σ's), and a direction
//! of A with an eigenvalue below [`DETERMINED_ABOVE`] keeps more than half its prior
//! σ. The parameters along such a direction are named, with the reason: alone, its
//! σ stays near its prior's; with others, only a combination is determined.

use nalgebra::{DMatrix, SymmetricEigen};

/// The information (in units of the prior) a direction needs to count as
/// determined: 3 is a posterior σ of half the prior's.
pub const DETERMINED_ABOVE: f64 = 3.0;
/// A parameter takes part in an undetermined direction where its component is above
/// this (a unit eigenvector).
const TAKES_PART: f64 = 0.3;

/// One identified parameter's estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct ParameterEstimate {
    pub name: String,
    pub estimate: f64,
    pub sigma: f64,
    /// The prior: the scene's value and σ.
    pub prior: f64,
    pub prior_sigma: f64,
    /// Why the readings do not determine it (`None`: they do).
    pub undetermined: Option<String>,
    /// The σ at the process σ a batch lowered to what its dynamics residuals show
    /// (`None`: not lowered): narrower than `sigma`, which holds at the default σ too.
    pub sigma_lowered: Option<f64>,
}

/// The identified parameters at the end of the record, with their correlations.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Identification {
    pub parameters: Vec<ParameterEstimate>,
    /// Row-major P × P.
    pub correlation: Vec<f64>,
}

impl Identification {
    /// From the final estimate `p` and its covariance `c` (row-major P × P), the priors'
    /// means and σ's.
    pub fn new(names: &[String], p: &[f64], c: &[f64], prior: &[f64], prior_sigma: &[f64]) -> Self {
        let np = names.len();
        let sigma: Vec<f64> = (0..np).map(|i| c[i * np + i].max(0.0).sqrt()).collect();
        let correlation = (0..np * np)
            .map(|k| {
                let (i, j) = (k / np, k % np);
                let d = sigma[i] * sigma[j];
                if i == j {
                    1.0
                } else if d > 0.0 {
                    (c[k] / d).clamp(-1.0, 1.0)
                } else {
                    0.0
                }
            })
            .collect();
        let reasons = undetermined(names, c, prior_sigma);
        Identification {
            parameters: (0..np)
                .map(|i| ParameterEstimate {
                    name: names[i].clone(),
                    estimate: p[i],
                    sigma: sigma[i],
                    prior: prior[i],
                    prior_sigma: prior_sigma[i],
                    undetermined: reasons[i].clone(),
                    sigma_lowered: None,
                })
                .collect(),
            correlation,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.parameters.is_empty()
    }

    /// With the parameters' covariance `c` (row-major P × P) at the lowered process σ.
    pub fn with_lowered(mut self, c: &[f64]) -> Self {
        let np = self.parameters.len();
        for (i, p) in self.parameters.iter_mut().enumerate() {
            p.sigma_lowered = Some(c[i * np + i].max(0.0).sqrt());
        }
        self
    }

    /// The CSV of `--parameters-out`: name, estimate, sigma, prior, prior_sigma,
    /// identifiable, reason, the correlation matrix's row (corr:<name>), then
    /// sigma_lowered (empty where the process σ was not lowered).
    pub fn write_csv(&self, w: &mut dyn std::io::Write) -> std::io::Result<()> {
        let np = self.parameters.len();
        write!(
            w,
            "name,estimate,sigma,prior,prior_sigma,identifiable,reason"
        )?;
        for p in &self.parameters {
            write!(w, ",corr:{}", p.name)?;
        }
        writeln!(w, ",sigma_lowered")?;
        for (i, p) in self.parameters.iter().enumerate() {
            let reason = p.undetermined.as_deref().unwrap_or("");
            write!(
                w,
                "{},{},{},{},{},{},\"{}\"",
                p.name,
                crate::io::number(p.estimate),
                crate::io::number(p.sigma),
                crate::io::number(p.prior),
                crate::io::number(p.prior_sigma),
                if p.undetermined.is_none() {
                    "yes"
                } else {
                    "no"
                },
                reason.replace('"', "'")
            )?;
            for j in 0..np {
                write!(w, ",{}", crate::io::number(self.correlation[i * np + j]))?;
            }
            match p.sigma_lowered {
                Some(s) => writeln!(w, ",{}", crate::io::number(s))?,
                None => writeln!(w, ",")?,
            }
        }
        Ok(())
    }
}

/// For each parameter, why the readings leave it undetermined (see the module).
fn undetermined(names: &[String], c: &[f64], prior_sigma: &[f64]) -> Vec<Option<String>> {
    let np = names.len();
    let scaled = DMatrix::from_fn(np, np, |i, j| {
        c[i * np + j] / (prior_sigma[i] * prior_sigma[j])
    });
    let mut out: Vec<Option<String>> = vec![None; np];
    let Some(inverse) = scaled.clone().try_inverse() else {
        return names
            .iter()
            .map(|_| Some("the covariance of the parameters is singular".to_string()))
            .collect();
    };
    let information = (&inverse + inverse.transpose()) * 0.5 - DMatrix::identity(np, np);
    let eig = SymmetricEigen::new(information);
    for (k, &lambda) in eig.eigenvalues.iter().enumerate() {
        if lambda >= DETERMINED_ABOVE {
            continue;
        }
        let mut v = eig.eigenvectors.column(k).into_owned();
        let part: Vec<usize> = (0..np).filter(|&i| v[i].abs() > TAKES_PART).collect();
        // The direction's sign is arbitrary: its first component positive.
        if part.first().is_some_and(|&i| v[i] < 0.0) {
            v.neg_mut();
        }
        // σ along the direction, as a fraction of the prior's.
        let kept = 1.0 / (1.0 + lambda.max(0.0)).sqrt();
        let combo: Vec<String> = part
            .iter()
            .map(|&i| format!("{:+.2} {}", v[i], names[i]))
            .collect();
        for &i in &part {
            if out[i].is_some() {
                continue;
            }
            let others: Vec<String> = part
                .iter()
                .filter(|&&o| o != i)
                .map(|&o| format!("'{}'", names[o]))
                .collect();
            out[i] = Some(if others.is_empty() {
                format!(
                    "the readings barely determine it: its σ stays at {:.0} % of its prior's",
                    100.0 * kept
                )
            } else {
                format!(
                    "it moves together with {}: the readings determine a combination of them, \
                     not each (along {} in units of the priors' σ, {:.0} % of the prior σ is \
                     left)",
                    others.join(", "),
                    combo.join(" "),
                    100.0 * kept
                )
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: &[&str]) -> Vec<String> {
        n.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_shrunk_sigma_is_determined_and_a_kept_one_is_named() {
        let id = Identification::new(
            &names(&["g", "m"]),
            &[9.98, 2.1],
            &[0.01f64.powi(2), 0.0, 0.0, 0.45f64.powi(2)],
            &[9.0, 2.0],
            &[2.0, 0.5],
        );
        assert!(id.parameters[0].undetermined.is_none());
        let why = id.parameters[1].undetermined.as_deref().unwrap();
        assert!(why.contains("90 %"), "{why}");
    }

    #[test]
    fn two_parameters_that_move_together_are_both_named() {
        // The readings determine a + b to 1e-2 of the priors' σ; a − b not at all.
        let (sum, diff) = (1e-4, 1.0);
        let c = [
            0.5 * (sum + diff),
            0.5 * (sum - diff),
            0.5 * (sum - diff),
            0.5 * (sum + diff),
        ];
        let r = c[1] / c[0];
        let id = Identification::new(
            &names(&["a", "b"]),
            &[1.0, 1.0],
            &c,
            &[1.0, 1.0],
            &[1.0, 1.0],
        );
        for p in &id.parameters {
            let why = p.undetermined.as_deref().unwrap_or("");
            assert!(why.contains("combination"), "{}: {why}", p.name);
        }
        assert!(id.parameters[0]
            .undetermined
            .as_deref()
            .unwrap()
            .contains("'b'"));
        assert!(id.parameters[1]
            .undetermined
            .as_deref()
            .unwrap()
            .contains("'a'"));
        assert!((id.correlation[1] - r).abs() < 1e-12);
    }
}
