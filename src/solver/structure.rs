//! The window's structure: which factor instances a window holds, in step order.

use super::*;

/// Which factors a linearization takes.
#[derive(Clone, Copy)]
pub(super) enum Scope {
    /// Every factor inside the window [k0, k1).
    Window,
    /// Only the factors touching step k0 (for its marginalization; k1 = k0 + 2).
    Oldest,
}

/// One factor at one step: `initial` factors come from `graph.initial_factors`.
#[derive(Clone, Copy)]
pub(super) struct Instance {
    pub(super) initial: bool,
    pub(super) index: usize,
    pub(super) step: usize,
}

pub(super) fn factor_of(graph: &ChainGraph, inst: Instance) -> &dyn Factor {
    if inst.initial {
        graph.initial_factors[inst.index].as_ref()
    } else {
        graph.step_factors[inst.index].as_ref()
    }
}

pub(super) fn is_hard(f: &dyn Factor) -> bool {
    matches!(f.noise(), Noise::Hard)
}

impl WindowSolver {
    /// Lists the factor instances of a scope.
    pub(super) fn collect_instances(
        &mut self,
        graph: &ChainGraph,
        k0: usize,
        k1: usize,
        scope: Scope,
    ) {
        self.instances.clear();
        if k0 == 0 {
            for index in 0..graph.initial_factors.len() {
                self.instances.push(Instance {
                    initial: true,
                    index,
                    step: 0,
                });
            }
        }
        for (index, factor) in graph.step_factors.iter().enumerate() {
            let keys = factor.keys();
            let max_lag = keys.iter().map(|k| k.lag).max().unwrap_or(0);
            // Conditional solves hold the step before the window fixed and keep the
            // factors that reach back to it.
            let first = if self.conditional {
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
        self.hard_cost.clear();
        self.hard_cost.resize(inst.len(), 0.0);
    }
}
