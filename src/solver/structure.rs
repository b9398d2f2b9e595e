//! The window's structure: which factor instances a window holds, in step order.
//! It depends on the window's shape only (its length, its scope, whether it starts
//! at step 0), so it is resolved once per shape and shifted along the run.

use super::*;

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

/// One factor at one step: `initial` factors come from `graph.initial_terms()`.
#[derive(Clone, Copy)]
pub(super) struct Instance {
    pub(super) initial: bool,
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
    if inst.initial {
        &graph.initial_terms()[inst.index]
    } else {
        &graph.step_terms()[inst.index]
    }
}

pub(super) fn factor_of(graph: &ChainGraph, inst: Instance) -> &dyn Factor {
    term_of(graph, inst).factor()
}

/// Whether an instance is of a constraint (a hard factor, eliminated per step).
pub(super) fn is_hard(graph: &ChainGraph, inst: Instance) -> bool {
    term_of(graph, inst).is_constraint()
}

impl WindowSolver {
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
            Some(r) if r.shape == shape => {
                if r.k0 != k0 {
                    for inst in &mut self.instances {
                        inst.step = inst.step - r.k0 + k0;
                    }
                }
            }
            _ => self.build_instances(graph, k0, k1, scope),
        }
        self.resolved = Some(Resolved { shape, k0 });
        self.hard_cost.clear();
        self.hard_cost.resize(self.instances.len(), 0.0);
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
                    initial: true,
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
                    initial: false,
                    index,
                    step,
                });
            }
        }
        // Step order, `instances` order within a step (initial factors first): a
        // counting sort by step.
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
}
