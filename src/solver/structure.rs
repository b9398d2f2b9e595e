//! The window's structure: which factor instances a window holds, in step order.
//! It depends on the window's shape only (its length, its scope, whether it starts
//! at step 0), so it is resolved once per shape and shifted along the run.

use crate::graph::{ChainGraph, Factor, Term};

use super::LinearPrior;

/// Which factors a linearization takes.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) enum Scope {
    /// Every factor inside the window [k0, k1); with `held`, the step before the
    /// window is held at its value and the factors reaching back to it stay (a
    /// conditional solve).
    Window { held: bool },
    /// Only the factors touching step k0 (for its marginalization; k1 = k0 + 2).
    Oldest,
}

/// What one evaluation of a window reads: its steps k0..k1, the prior on step k0 and
/// the factors it takes. The solve's linearizations, trials and Hessians all share it.
#[derive(Clone, Copy)]
pub(super) struct Span<'a> {
    pub(super) k0: usize,
    pub(super) k1: usize,
    pub(super) prior: Option<&'a LinearPrior>,
    pub(super) scope: Scope,
}

impl Span<'_> {
    /// Whether the step before the window is held at its value (a conditional solve).
    pub(super) fn held(&self) -> bool {
        self.scope == Scope::Window { held: true }
    }
}

/// Which of a graph's lists a factor instance comes from.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) enum Source {
    /// `graph.step_terms()`.
    Step,
    /// `graph.initial_terms()`.
    Initial,
    /// `graph.sparse_terms()` (a factor of one chosen run step).
    At,
}

/// One factor at one step of the values, `index` into its `source` list.
#[derive(Clone, Copy)]
pub(super) struct Instance {
    pub(super) source: Source,
    pub(super) index: usize,
    pub(super) step: usize,
}

/// What a window's instance list depends on besides its first step.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) struct Shape {
    at_start: bool,
    blocks: usize,
    scope: Scope,
}

/// The shape the solver's instance list was last built for, and the first step it
/// was built at.
#[derive(Clone, Copy, Debug)]
pub(super) struct Resolved {
    shape: Shape,
    k0: usize,
    /// Whether the list holds factors of chosen steps: such a list is never
    /// shifted (the graph may have gained or dropped some since, see
    /// `ChainGraph::add_soft_at`).
    sparse: bool,
}

/// An instance list of another shape, parked while the solver uses its current one
/// (a fixed-lag run alternates between a few: the window, its conditional start,
/// the oldest step's marginalization).
pub(super) struct Listing {
    resolved: Resolved,
    instances: Vec<Instance>,
    by_step: Vec<usize>,
    block_start: Vec<usize>,
}

/// Shapes kept parked at most.
const PARKED: usize = 4;

pub(super) fn term_of(graph: &ChainGraph, inst: Instance) -> &Term {
    match inst.source {
        Source::Step => &graph.step_terms()[inst.index],
        Source::Initial => &graph.initial_terms()[inst.index],
        Source::At => &graph.sparse_terms()[inst.index].1,
    }
}

pub(super) fn factor_of(graph: &ChainGraph, inst: Instance) -> &dyn Factor {
    term_of(graph, inst).factor()
}

/// Whether an instance is of a constraint (a hard factor, eliminated per step).
pub(super) fn is_hard(graph: &ChainGraph, inst: Instance) -> bool {
    term_of(graph, inst).is_constraint()
}

/// The structure stage's state: the factor instances of the current window, in
/// `instances` order and by step, the lists of other shapes parked beside them, and
/// where the values' step 0 sits in the run.
pub(super) struct Structure {
    /// The run step of the values' step 0 (a streaming run moves its values
    /// toward the start of their buffer, [`super::WindowSolver::shift_steps`]): a step's
    /// time, and the factors of chosen run steps, are placed by it.
    pub(super) base: usize,
    pub(super) instances: Vec<Instance>,
    /// What `instances` was built for, and the lists of other shapes.
    resolved: Option<Resolved>,
    parked: Vec<Listing>,
    /// The instances in step order (indices into `instances`), and where each block's
    /// begin in it (one more entry than blocks).
    pub(super) by_step: Vec<usize>,
    pub(super) block_start: Vec<usize>,
    next_slot: Vec<usize>,
}

impl Structure {
    /// Room for the instances of a window of up to `capacity` steps of `graph`.
    pub(super) fn new(graph: &ChainGraph, capacity: usize) -> Self {
        let per_window = capacity * graph.step_terms().len() + graph.initial_terms().len();
        Structure {
            base: 0,
            instances: Vec::with_capacity(per_window),
            resolved: None,
            parked: Vec::new(),
            by_step: Vec::with_capacity(per_window),
            block_start: Vec::with_capacity(capacity + 1),
            next_slot: Vec::with_capacity(capacity),
        }
    }

    /// The run step of step `step` of the values: the one place that maps the
    /// values' steps to the run's (a streaming run moves its values, `base`).
    pub(super) fn run_step(&self, step: usize) -> usize {
        self.base + step
    }

    /// The step of the values that run step `run` sits at, if it is at or after
    /// the values' step 0.
    pub(super) fn local_step(&self, run: usize) -> Option<usize> {
        run.checked_sub(self.base)
    }

    /// Lists the factor instances of a scope, in `instances` and (by step) in
    /// `by_step` and `block_start`: built when the window's shape changes, shifted
    /// to k0 otherwise.
    pub(super) fn collect_instances(
        &mut self,
        graph: &ChainGraph,
        k0: usize,
        k1: usize,
        scope: Scope,
    ) {
        let shape = Shape {
            at_start: k0 == 0,
            blocks: k1 - k0,
            scope,
        };
        if self.resolved.is_some_and(|r| r.shape != shape) {
            self.park();
            if let Some(at) = self.parked.iter().position(|l| l.resolved.shape == shape) {
                let listing = self.parked.swap_remove(at);
                self.resolved = Some(listing.resolved);
                self.instances = listing.instances;
                self.by_step = listing.by_step;
                self.block_start = listing.block_start;
            }
        }
        match self.resolved {
            // Factors of chosen steps are not where a shifted list would put them.
            Some(r) if r.shape == shape && !r.sparse && graph.sparse_terms().is_empty() => {
                if r.k0 != k0 {
                    for inst in &mut self.instances {
                        inst.step = inst.step - r.k0 + k0;
                    }
                }
            }
            _ => self.build_instances(graph, k0, k1, scope),
        }
        let sparse = !graph.sparse_terms().is_empty()
            && self.instances.iter().any(|i| i.source == Source::At);
        self.resolved = Some(Resolved { shape, k0, sparse });
    }

    /// Parks the current instance list (the oldest parked one goes when full).
    fn park(&mut self) {
        let Some(resolved) = self.resolved.take() else {
            return;
        };
        if self.parked.len() == PARKED {
            self.parked.remove(0);
        }
        self.parked.push(Listing {
            resolved,
            instances: std::mem::take(&mut self.instances),
            by_step: std::mem::take(&mut self.by_step),
            block_start: std::mem::take(&mut self.block_start),
        });
    }

    fn build_instances(&mut self, graph: &ChainGraph, k0: usize, k1: usize, scope: Scope) {
        self.instances.clear();
        if k0 == 0 {
            for index in 0..graph.initial_terms().len() {
                self.instances.push(Instance {
                    source: Source::Initial,
                    index,
                    step: 0,
                });
            }
        }
        for (index, term) in graph.step_terms().iter().enumerate() {
            let keys = term.factor().keys();
            let max_lag = keys.iter().map(|k| k.lag).max().unwrap_or(0);
            // Conditional solves hold the step before the window fixed and keep the
            // factors that reach back to it.
            let first = if scope == (Scope::Window { held: true }) {
                k0.max(max_lag)
            } else {
                k0 + max_lag
            };
            for step in first..k1 {
                if let Scope::Oldest = scope {
                    if !keys.iter().any(|k| step - k.lag == k0) {
                        continue;
                    }
                }
                self.instances.push(Instance {
                    source: Source::Step,
                    index,
                    step,
                });
            }
        }
        if !graph.sparse_terms().is_empty() {
            self.sparse_instances(graph, k0, k1, scope);
        }
        // Step order, `instances` order within a step (initial factors first, those
        // of chosen steps last): a counting sort by step.
        let inst = &self.instances;
        let blocks = k1 - k0;
        self.block_start.clear();
        self.block_start.resize(blocks + 1, 0);
        for i in inst {
            self.block_start[i.step - k0 + 1] += 1;
        }
        for b in 0..blocks {
            self.block_start[b + 1] += self.block_start[b];
        }
        self.by_step.clear();
        self.by_step.resize(inst.len(), 0);
        self.next_slot.clear();
        self.next_slot
            .extend_from_slice(&self.block_start[..blocks]);
        for (i, it) in inst.iter().enumerate() {
            let slot = &mut self.next_slot[it.step - k0];
            self.by_step[*slot] = i;
            *slot += 1;
        }
    }

    /// Adds the instances of the factors of chosen run steps that fall in the
    /// window [k0, k1) of the values, under the same rules as the step factors:
    /// every variable inside the window (or, held, the step before it), and for
    /// `Oldest` touching step k0.
    fn sparse_instances(&mut self, graph: &ChainGraph, k0: usize, k1: usize, scope: Scope) {
        let range = graph.sparse_range(self.run_step(k0), self.run_step(k1));
        for index in range {
            let (run, term) = &graph.sparse_terms()[index];
            let Some(step) = self.local_step(*run) else {
                continue;
            };
            let keys = term.factor().keys();
            let max_lag = keys.iter().map(|k| k.lag).max().unwrap_or(0);
            let inside = match scope {
                Scope::Window { held: true } => step >= max_lag,
                Scope::Window { held: false } => step >= k0 + max_lag,
                Scope::Oldest => step >= k0 + max_lag && keys.iter().any(|k| step - k.lag == k0),
            };
            if inside {
                self.instances.push(Instance {
                    source: Source::At,
                    index,
                    step,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{Prior, Trapezoidal};
    use crate::graph::{Layout, Noise, VarKind};

    /// q, q̇ of size 1: a trapezoidal integrator at every step (reaching back one
    /// step), a prior on q at every step, one on step 0, and one at run step 3.
    fn graph() -> ChainGraph {
        let layout = Layout::new(&[(VarKind::Q, 1), (VarKind::Dq, 1)]);
        let dt = 0.1;
        ChainGraph::builder(layout, dt, 0.0)
            .step_soft(
                Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, 1, dt)),
                Noise::Isotropic(0.1),
            )
            .step_soft(
                Box::new(Prior::new(VarKind::Q, vec![0.0])),
                Noise::Isotropic(1.0),
            )
            .initial_soft(
                Box::new(Prior::new(VarKind::Q, vec![0.0])),
                Noise::Isotropic(1.0),
            )
            .soft_at(
                3,
                Box::new(Prior::new(VarKind::Q, vec![1.0])),
                Noise::Isotropic(1.0),
            )
            .build()
            .unwrap()
    }

    /// An instance as (source, index, step).
    type Listed = (Source, usize, usize);

    /// The instance list, and the instances block by block.
    fn listing(st: &Structure) -> (Vec<Listed>, Vec<Vec<usize>>) {
        let list = st
            .instances
            .iter()
            .map(|i| (i.source, i.index, i.step))
            .collect();
        let blocks = st
            .block_start
            .windows(2)
            .map(|w| st.by_step[w[0]..w[1]].to_vec())
            .collect();
        (list, blocks)
    }

    #[test]
    fn a_window_lists_its_factors_in_step_order() {
        use Source::{At, Initial, Step};
        let graph = graph();
        let mut st = Structure::new(&graph, 4);
        // From step 0: the initial factor, no integrator into step 0; the factor of
        // run step 3 is outside.
        st.collect_instances(&graph, 0, 3, Scope::Window { held: false });
        let (list, blocks) = listing(&st);
        let want = [(Initial, 0, 0), (Step, 0, 1), (Step, 0, 2)];
        assert_eq!(list[..3], want);
        assert_eq!(list[3..], [(Step, 1, 0), (Step, 1, 1), (Step, 1, 2)]);
        assert_eq!(blocks, [vec![0, 3], vec![1, 4], vec![2, 5]]);

        // Steps 1..4: the integrator into step 1 reaches outside, run step 3's factor
        // is in, last in its block.
        st.collect_instances(&graph, 1, 4, Scope::Window { held: false });
        let (list, blocks) = listing(&st);
        let want = [(Step, 0, 2), (Step, 0, 3), (Step, 1, 1), (Step, 1, 2)];
        assert_eq!(list[..4], want);
        assert_eq!(list[4..], [(Step, 1, 3), (At, 0, 3)]);
        assert_eq!(blocks, [vec![2], vec![0, 3], vec![1, 4, 5]]);
        // Held: the integrator into step 1 stays.
        st.collect_instances(&graph, 1, 4, Scope::Window { held: true });
        assert_eq!(listing(&st).0[0], (Step, 0, 1));

        // The values moved one step: run step 3 is their step 2.
        st.base = 1;
        st.collect_instances(&graph, 1, 3, Scope::Window { held: false });
        let (list, blocks) = listing(&st);
        assert_eq!(list, [(Step, 0, 2), (Step, 1, 1), (Step, 1, 2), (At, 0, 2)]);
        assert_eq!(blocks, [vec![1], vec![0, 2, 3]]);

        // The oldest step's factors: those touching step 1.
        st.collect_instances(&graph, 1, 3, Scope::Oldest);
        assert_eq!(listing(&st).0, [(Step, 0, 2), (Step, 1, 1)]);
    }

    #[test]
    fn a_shape_seen_before_is_shifted_not_rebuilt() {
        // Without factors of chosen steps a list of a known shape is shifted.
        let layout = Layout::new(&[(VarKind::Q, 1), (VarKind::Dq, 1)]);
        let graph = ChainGraph::builder(layout, 0.1, 0.0)
            .step_soft(
                Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, 1, 0.1)),
                Noise::Isotropic(0.1),
            )
            .build()
            .unwrap();
        let mut st = Structure::new(&graph, 4);
        let mut fresh = Structure::new(&graph, 4);
        for (k0, scope) in [
            (1, Scope::Window { held: false }),
            (1, Scope::Oldest),
            (2, Scope::Window { held: false }),
            (4, Scope::Oldest),
            (5, Scope::Window { held: true }),
        ] {
            st.collect_instances(&graph, k0, k0 + 2, scope);
            fresh.build_instances(&graph, k0, k0 + 2, scope);
            assert_eq!(listing(&st), listing(&fresh), "k0 = {k0}, {scope:?}");
        }
    }
}
