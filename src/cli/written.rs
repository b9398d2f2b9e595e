//! The options for what a CSV holds beyond the standard columns and which rows, and
//! those columns and rows computed for a trajectory.

use super::failure::{plain, Failure};
use mbfg::forward;
use mbfg::Model;

/// What the CSV holds beyond the standard columns, and which rows.
#[derive(clap::Args)]
pub struct WrittenArgs {
    /// Write the rows at t = 0, S, 2S, … only (and the last); S must be a whole
    /// number of time steps. The solve is unchanged.
    #[arg(long = "sample-dt", value_name = "S")]
    sample_dt: Option<f64>,
    /// Optional columns after the standard ones, comma-separated: `bodies` (angle,
    /// centre of mass position and velocity of every body), `energy` (kinetic,
    /// potential, work of every non-conservative effect, energy_balance), `joints`
    /// (the force every joint and slider transmits, on each body at each point),
    /// `constraints` (the force each of the scene's constraints carries: a distance's
    /// tension, a slider's normal force).
    #[arg(long, value_name = "LIST")]
    columns: Option<String>,
}

/// [`WrittenArgs`] checked: the sample stride in steps and the column groups.
pub struct Written {
    stride: usize,
    groups: Vec<mbfg::derived::Group>,
    rule: mbfg::derived::WorkRule,
}

impl WrittenArgs {
    /// `--sample-dt`, as given.
    pub fn sample_dt(&self) -> Option<f64> {
        self.sample_dt
    }
}

impl Written {
    /// Checks the options against the time step; errors are bad input. `rule`
    /// integrates the work columns (that of the run's integrator).
    pub fn new(args: &WrittenArgs, dt: f64, rule: mbfg::derived::WorkRule) -> Result<Self, String> {
        let stride = match args.sample_dt {
            Some(s) => mbfg::io::sample_stride(dt, s)?,
            None => 1,
        };
        let groups = match &args.columns {
            Some(list) => mbfg::derived::Group::parse_list(list)?,
            None => Vec::new(),
        };
        Ok(Written {
            stride,
            groups,
            rule,
        })
    }

    /// Whether the rows can be written as the run's steps become final: the
    /// optional columns need every step first.
    pub fn streams(&self) -> bool {
        self.groups.is_empty()
    }

    /// Rows written: every `stride()`-th (and the last).
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// The rows a run handed on, and their optional columns computed over every step
    /// it took (a refined run's between them too).
    pub fn prepare_steps(
        &self,
        model: &Model,
        steps: mbfg::derived::Steps,
    ) -> Result<(forward::Trajectory, Prepared), Failure> {
        let prepared = self.prepared(steps.len(), |groups| {
            steps.columns(model, groups, self.rule)
        })?;
        Ok((steps.into_rows(), prepared))
    }

    /// The optional columns over every step (the work integrals need them all), and
    /// the rows to write.
    pub fn prepare(
        &self,
        model: &Model,
        trajectory: &forward::Trajectory,
        actuators: Option<&[f64]>,
    ) -> Result<Prepared, Failure> {
        self.prepared(trajectory.len(), |groups| {
            mbfg::derived::columns(model, trajectory, groups, actuators, self.rule)
        })
    }

    /// The columns `columns` makes of the groups asked (none: not called) and the
    /// rows to write of `len`.
    fn prepared(
        &self,
        len: usize,
        columns: impl FnOnce(&[mbfg::derived::Group]) -> mbfg::Result<mbfg::derived::Columns>,
    ) -> Result<Prepared, Failure> {
        let extra = match self.groups.is_empty() {
            true => None,
            false => Some(columns(&self.groups).map_err(|e| Failure::Run(plain(e)))?),
        };
        let rows = (self.stride > 1).then(|| mbfg::io::sampled_rows(len, self.stride));
        Ok(Prepared { extra, rows })
    }
}

/// The optional columns and rows of one trajectory, ready to write.
pub struct Prepared {
    extra: Option<mbfg::derived::Columns>,
    rows: Option<Vec<usize>>,
}

impl Prepared {
    /// Puts `columns` (row-major steps × names, every step) before the optional
    /// ones: the standard deviations of an estimate.
    pub fn with_leading(mut self, columns: mbfg::derived::Columns) -> Self {
        let steps = if columns.names.is_empty() {
            0
        } else {
            columns.values.len() / columns.names.len()
        };
        self.extra = Some(match self.extra.take() {
            None => columns,
            Some(rest) => {
                let (a, b) = (columns.names.len(), rest.names.len());
                let mut values = Vec::with_capacity(steps * (a + b));
                for k in 0..steps {
                    values.extend_from_slice(&columns.values[k * a..(k + 1) * a]);
                    values.extend_from_slice(&rest.values[k * b..(k + 1) * b]);
                }
                let mut names = columns.names;
                names.extend(rest.names);
                mbfg::derived::Columns { names, values }
            }
        });
        self
    }

    pub fn csv<'a>(&'a self, forces: Option<&'a [f64]>) -> mbfg::io::CsvOptions<'a> {
        mbfg::io::CsvOptions {
            forces,
            extra: self
                .extra
                .as_ref()
                .map(|c| (c.names.as_slice(), c.values.as_slice())),
            rows: self.rows.as_deref(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_and_column_options_are_checked() {
        let args = |sample_dt, columns: Option<&str>| WrittenArgs {
            sample_dt,
            columns: columns.map(str::to_string),
        };
        let w = Written::new(&args(Some(0.01), Some("energy")), 0.001, Default::default()).unwrap();
        assert_eq!(w.stride, 10);
        assert_eq!(w.groups, [mbfg::derived::Group::Energy]);
        assert!(Written::new(&args(Some(0.0015), None), 0.001, Default::default()).is_err());
        assert!(Written::new(&args(None, Some("nope")), 0.001, Default::default()).is_err());
    }
}
