//! The simplified-Newton (chord) test of convergence for one-block windows.
//!
//! A window solve usually converges in two Gauss-Newton iterations: the first step
//! from the prediction, and a second one, orders of magnitude below the tolerance,
//! that only confirms it. The second needs the full linearization at the new point
//! (the dynamics' Jacobians, the hard equations' QR): most of a step's cost. The
//! chord step asks the same question with what is at hand: the residuals at the new
//! point, and the reduced Jacobians, null space and factored H of the last
//! linearization. Newton's method converges quadratically and the chord step differs
//! from Newton's by O(|first step| · |chord step|), so where it is below the
//! tolerance the solve has converged; where it is not, the solve linearizes and goes
//! on as if the test had not been made.

use super::observer::Iteration;
use super::prior::LinearPrior;
use super::structure::{factor_of, Span};
use super::WindowSolver;
use crate::convergence::{SolveReport, Termination};
use crate::error::{Error, Result};
use crate::graph::ChainGraph;

/// What the chord test made of an undamped step.
pub(super) enum ChordOutcome {
    /// The chord step met the tolerance: the solve has converged.
    Converged(SolveReport),
    /// The correction after the chord step failed to evaluate, at this cost.
    Failed(Error, f64),
    /// No convergence shown: the trial point linearized as every iteration does (its
    /// cost, or why it could not be evaluated).
    Trial(Result<f64>),
}

/// A chord step that met the tolerance and was applied.
pub(super) struct ChordStep {
    /// The decrease the linear model predicts for it.
    pub predicted: f64,
    /// max |δᵢ| / (1 + |xᵢ|).
    pub largest: f64,
}

impl WindowSolver {
    /// After the undamped step `step` (its record, before the trial's cost is known)
    /// of the window `span` to `values`, corrected onto the hard equations: the trial's cost without a
    /// linearization, and where it is lower the chord step; the solve converges when
    /// that is below the tolerance, else the trial is linearized as usual.
    pub(super) fn chord_test(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        span: Span,
        step: Iteration,
    ) -> ChordOutcome {
        let Span { k0, k1, prior, .. } = span;
        let held = span.held();
        let cost = match self.evaluate(graph, values, span, false) {
            Ok(c) if c <= step.cost => c,
            _ => return ChordOutcome::Trial(self.evaluate(graph, values, span, true)),
        };
        let Some(chord) = self.chord_step(graph, values, k0, prior) else {
            return ChordOutcome::Trial(self.evaluate(graph, values, span, true));
        };
        // Back onto the hard equations to round-off: the chord step's part p comes
        // from the old C.
        if let Err(e) = self.correct(graph, values, k0, k1) {
            return ChordOutcome::Failed(e, cost);
        }
        if let Some(observer) = self.observer.as_mut() {
            let first = Iteration {
                trial: Some(cost),
                ..step
            };
            observer.iteration(&first);
            observer.iteration(&Iteration {
                iteration: step.iteration + 1,
                cost,
                trial: None,
                predicted: chord.predicted,
                largest_step: chord.largest,
                small: true,
                restored: true,
                chord: true,
                ..first
            });
        }
        if !held {
            self.keep_for_marginal(values, k0, k1);
        }
        ChordOutcome::Converged(SolveReport::new(
            Termination::Converged,
            step.iteration + 1,
            cost - chord.predicted,
        ))
    }

    /// Whether a solve of steps k0..k1 may stop on a chord step: the last
    /// linearization recorded what one needs (the reduced rows of a one-block
    /// window's soft factors), and nothing is marginalized from that linearization
    /// afterwards. A solve with the step before held is not marginalized from; a
    /// conditioned past re-evaluates the factors it keeps. A marginal prior is
    /// made from the window's linearization of its first step, and one made a step
    /// before the optimum moves a dependent-coordinate run's least-squares
    /// compromise (the four-bar at 1 ms by 10 % of its error, the double pendulum's
    /// chaos by 40 % after 5 s): such solves linearize again.
    pub(super) fn chord_ready(&self, k0: usize, k1: usize, held: bool) -> bool {
        self.settings.chord_test
            && k1 == k0 + 1
            && self.kept.width.is_some()
            && (held || self.past_conditioned())
    }

    /// At `values` (block k0, just evaluated without linearizing, so that its soft
    /// factors' whitened residuals are in their buffers and its hard equations' −c in
    /// `hard_rhs`): the chord step −H⁻¹g with g = (JN)ᵀr from the recorded rows and
    /// the factored H of the last linearization. Applied to `values` and returned when
    /// it is below the step tolerance and keeps the hard equations; otherwise `None`,
    /// with `values` unchanged.
    ///
    /// The residuals are not shifted by J p (p: the particular step restoring the hard
    /// equations, at round-off after the correction that precedes the evaluation);
    /// p itself is part of the step and of the tolerance test.
    pub(super) fn chord_step(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        prior: Option<&LinearPrior>,
    ) -> Option<ChordStep> {
        let s = self.s;
        let d = self.kept.width?;
        let tolerance = self.settings.step_tolerance;
        // p: the least-norm step onto the hard equations with the last C.
        let hard_rows = self.lin.hard[0].rows;
        if hard_rows > 0 {
            self.lin.hard[0]
                .reduction
                .solve(&self.lin.hard_rhs[..hard_rows], &mut self.correction);
        } else {
            self.correction.fill(0.0);
        }
        let x = &values[k0 * s..(k0 + 1) * s];
        let at_round_off = self.lin.hard[0].at_round_off;
        let restored = x
            .iter()
            .zip(&self.correction)
            .all(|(xi, p)| at_round_off || p.abs() <= tolerance * (1.0 + xi.abs()));
        if !restored {
            return None;
        }
        // g = Σ (JN)ᵀ r over the recorded rows, in the order they were recorded.
        let g = &mut self.normal.g[..s];
        g.fill(0.0);
        let mut at = 0;
        for &i in &self.kept.instances {
            let inst = self.structure.instances[i];
            let dim = factor_of(graph, inst).dim();
            let buf = self.lin.buffers.of(inst);
            for &r in &buf.r[..dim] {
                let row = &self.kept.rows[at * (d + 1)..at * (d + 1) + d];
                for (ga, ja) in g[..d].iter_mut().zip(row) {
                    *ga += ja * r;
                }
                at += 1;
            }
        }
        if let Some(p) = prior {
            // The prior's gradient Λ(x − x̄) + η, reduced by N₀ᵀ.
            let red = &self.lin.hard[0].reduction;
            let (diff, rest) = self.scratch.split_at_mut(s);
            let (grad, work) = rest.split_at_mut(s);
            p.gradient(x, diff, grad, work);
            for (k, gk) in grad.iter().enumerate() {
                let (start, nrow) = red.row(k);
                for (ga, na) in g[start..].iter_mut().zip(nrow) {
                    *ga += na * gk;
                }
            }
        }
        if !g[..d].iter().all(|v| v.is_finite()) {
            return None;
        }
        self.normal.solve(s);
        // δ = p + N y, into `correction` (which held p); tested before it is applied.
        let red = &self.lin.hard[0].reduction;
        let y = &self.normal.delta[..s];
        let mut largest = 0.0f64;
        super::iterate::step_scales(
            x,
            self.settings
                .step_per_variable
                .then_some(&self.variables[..]),
            &mut self.step_scale,
        );
        for (i, scale) in self.step_scale.iter().enumerate() {
            let (start, nrow) = red.row(i);
            let step = self.correction[i]
                + nrow
                    .iter()
                    .zip(&y[start..])
                    .map(|(a, b)| a * b)
                    .sum::<f64>();
            self.correction[i] = step;
            largest = largest.max(step.abs() / scale);
        }
        if !(largest <= tolerance) {
            return None;
        }
        for (xi, step) in values[k0 * s..(k0 + 1) * s]
            .iter_mut()
            .zip(&self.correction)
        {
            *xi += step;
        }
        // The gradient at the new point is g + H y (`marginalize_last` reads both).
        let predicted = self.normal.predicted_decrease(s);
        Some(ChordStep { predicted, largest })
    }
}
