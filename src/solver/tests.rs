#[cfg(test)]
mod unit {
    use super::super::structure::Span;
    use super::super::*;
    use crate::forward::{simulate, Coordinates, DcIntegrators, ForwardGraph, ForwardOptions};
    use crate::smoother::Mode;
    use crate::{Model, Scene};
    use std::sync::Arc;

    /// Steps measured per entry, or against their variable's largest entry.
    #[test]
    fn step_scales_per_entry_or_per_variable() {
        let x = [2.0, -0.5, 1e8, 0.25];
        let mut out = [0.0; 4];
        super::super::iterate::step_scales(&x, None, &mut out);
        assert_eq!(out, [3.0, 1.5, 1e8 + 1.0, 1.25]);
        super::super::iterate::step_scales(&x, Some(&[(0, 2), (2, 2)]), &mut out);
        assert_eq!(out, [3.0, 3.0, 1e8 + 1.0, 1e8 + 1.0]);
    }

    /// The DC four-bar at dt = 10 ms (large residuals, so the second-order terms are
    /// far from 0) after 0.5 s, with the paper's integrator factors (tangent ones
    /// leave no marginal prior to make): its graph, values on the constraint manifold,
    /// and the prior of a one-step window on step `k`.
    fn window() -> (ForwardGraph, Vec<f64>, LinearPrior, WindowSolver, usize) {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/fourbar.yaml");
        let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
        let mut opts = ForwardOptions::new(Coordinates::Dependent, 1e-2, 0.5, Mode::FixedLag(1));
        opts.dc_integrators = DcIntegrators::Full;
        let (tr, summary) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
        assert!(summary.failures.is_empty());
        let fg = ForwardGraph::new(model.clone(), &opts).unwrap();
        let s = fg.graph.layout().size();
        let mut values = vec![0.0; tr.len() * s];
        fg.fill_from_trajectory(&model, &tr, &mut values);
        let mut solver = WindowSolver::new(&fg.graph, 2, Settings::default()).unwrap();
        let k = tr.len() - 1;
        let prior = solver.marginalize(&fg.graph, &values, k - 1, None).unwrap();
        (fg, values, prior, solver, k)
    }

    /// Settings that keep Jacobians must keep them within (0, 1).
    #[test]
    fn a_relinearization_threshold_outside_0_1_is_refused() {
        for bad in [0.0, -1e-3, 1.0, f64::NAN, f64::INFINITY] {
            let settings = Settings {
                relinearize_beyond: Some(bad),
                second_order: false,
                ..Settings::default()
            };
            let e = settings.validate().unwrap_err().to_string();
            assert!(e.contains("relinearize_beyond"), "{bad}: {e}");
        }
        let with_newton = Settings {
            relinearize_beyond: Some(0.01),
            ..Settings::default()
        };
        let e = with_newton.validate().unwrap_err().to_string();
        assert!(e.contains("second_order"), "{e}");
    }

    /// Windows of 5 steps slid along a simulated four-bar, each with the marginal of
    /// the step before (every step already solved, so the solves barely move them):
    /// with kept Jacobians each window differentiates only its newest step, and ends
    /// where windows that differentiate everything do.
    #[test]
    fn a_window_keeps_the_jacobians_of_the_steps_that_did_not_move() {
        // The projected integrators: every step's soft equations hold, so kept
        // Jacobians change where the solves end only by their tolerance.
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/fourbar.yaml");
        let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
        let opts = ForwardOptions::new(Coordinates::Dependent, 1e-2, 0.5, Mode::FixedLag(1));
        let (tr, _) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
        let fg = ForwardGraph::new(model.clone(), &opts).unwrap();
        let mut values = vec![0.0; tr.len() * fg.graph.layout().size()];
        fg.fill_from_trajectory(&model, &tr, &mut values);
        let (blocks, last) = (5, tr.len() - 1);
        let run = |beyond: Option<f64>| {
            let settings = Settings {
                relinearize_beyond: beyond,
                second_order: false,
                ..Settings::default()
            };
            let mut solver = WindowSolver::new(&fg.graph, blocks, settings).unwrap();
            let mut v = values.clone();
            let mut prior: Option<LinearPrior> = None;
            for k0 in 1..=last + 1 - blocks {
                let p = solver
                    .marginalize(&fg.graph, &v, k0 - 1, prior.as_ref())
                    .unwrap();
                let report = solver
                    .solve(&fg.graph, &mut v, k0, k0 + blocks, Some(&p))
                    .unwrap();
                prior = Some(p);
                assert_eq!(
                    report.termination,
                    Termination::Converged,
                    "{beyond:?} at {k0}"
                );
            }
            (v, solver.reuse.counts)
        };
        let (fresh, counts) = run(None);
        let (kept, (reused, differentiated)) = run(Some(0.01));
        assert_eq!(counts, (0, 0), "no Jacobian kept without a threshold");
        let windows = last + 1 - blocks;
        // After the first window, only each window's newest step is differentiated.
        assert_eq!(
            (reused, differentiated),
            ((windows - 1) * (blocks - 1), blocks + windows - 1),
            "steps through kept rows and differentiated, over {windows} windows"
        );
        let off = kept
            .iter()
            .zip(&fresh)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs() / (1.0 + b.abs())));
        assert!(off < 1e-8, "kept Jacobians end {off} away");
    }

    /// The one-step window on step `k`, with `prior` on it.
    fn span(k: usize, prior: Option<&LinearPrior>) -> Span<'_> {
        Span {
            k0: k,
            k1: k + 1,
            prior,
            scope: Scope::Window { held: false },
        }
    }

    fn cost_on_manifold(
        solver: &mut WindowSolver,
        fg: &ForwardGraph,
        values: &mut [f64],
        k: usize,
        prior: &LinearPrior,
    ) -> f64 {
        // Projections along the fixed normal space of the linearization: a retraction.
        for _ in 0..6 {
            solver.correct(&fg.graph, values, k, k + 1).unwrap();
        }
        solver
            .evaluate(&fg.graph, values, span(k, Some(prior)), false)
            .unwrap()
    }

    #[test]
    fn exact_hessian_is_the_second_derivative_of_the_cost_on_the_manifold() {
        let (fg, mut values, prior, mut solver, k) = window();
        let s = solver.s;
        let linearize = |solver: &mut WindowSolver, values: &[f64]| {
            solver
                .evaluate(&fg.graph, values, span(k, Some(&prior)), true)
                .unwrap();
        };
        // Away from the optimum (large residuals): a step along the manifold.
        linearize(&mut solver, &values);
        for i in 0..s {
            let (_, row) = solver.lin.hard[0].reduction.row(i);
            values[k * s + i] += 0.2 * row.iter().sum::<f64>();
        }
        cost_on_manifold(&mut solver, &fg, &mut values, k, &prior);
        linearize(&mut solver, &values);
        let gauss_newton = solver.normal.h.diag(0).to_vec();
        solver
            .exact_hessian(&fg.graph, &mut values, span(k, Some(&prior)))
            .unwrap();
        let red = solver.lin.hard[0].reduction.clone();
        let d = red.dim;
        let mut missed = 0.0f64;
        let h: Vec<f64> = solver.normal.h.diag(0)[..d * d].to_vec();
        let x0 = values.clone();
        let mut checked = 0;
        for seed in 0..4 {
            let v: Vec<f64> = (0..d)
                .map(|i| ((i * 7 + seed * 3) % 5) as f64 - 2.0)
                .collect();
            let vhv: f64 = (0..d)
                .map(|i| (0..d).map(|j| v[i] * h[i * d + j] * v[j]).sum::<f64>())
                .sum();
            let mut at = |t: f64| {
                values.copy_from_slice(&x0);
                for i in 0..s {
                    let (start, row) = red.row(i);
                    let step: f64 = row.iter().zip(&v[start..]).map(|(a, b)| a * b).sum();
                    values[k * s + i] += t * step;
                }
                cost_on_manifold(&mut solver, &fg, &mut values, k, &prior)
            };
            let e = 1e-4;
            let second = (at(e) - 2.0 * at(0.0) + at(-e)) / (e * e);
            let gn: f64 = (0..d)
                .map(|i| {
                    (0..d)
                        .map(|j| v[i] * gauss_newton[i * d + j] * v[j])
                        .sum::<f64>()
                })
                .sum();
            missed = missed.max((second - gn).abs() / vhv.abs().max(1.0));
            assert!(
                (second - vhv).abs() <= 1e-4 * vhv.abs().max(1.0),
                "direction {seed}: second difference {second:e}, vᵀHv {vhv:e}"
            );
            checked += 1;
        }
        assert_eq!(checked, 4);
        // What Gauss-Newton leaves out is far above the tolerance here.
        assert!(missed > 1e-2, "Gauss-Newton off by only {missed:e}");
    }

    #[test]
    fn tangent_prior_agrees_with_the_prior_in_value_and_reduced_gradient() {
        let (fg, values, prior, mut solver, k) = window();
        let s = solver.s;
        let mut tangent = prior.clone();
        solver
            .project_prior(&fg.graph, &values, k, &mut tangent)
            .unwrap();
        let red = solver.lin.hard[0].reduction.clone();
        let value = |p: &LinearPrior, x: &[f64]| {
            let dx: Vec<f64> = (0..s).map(|i| x[i] - p.xbar[i]).collect();
            let quad: f64 = (0..s)
                .map(|i| {
                    dx[i]
                        * (0..s)
                            .map(|j| p.dense_information()[i * s + j] * dx[j])
                            .sum::<f64>()
                })
                .sum();
            p.constant + p.eta.iter().zip(&dx).map(|(a, b)| a * b).sum::<f64>() + 0.5 * quad
        };
        let grad = |p: &LinearPrior, x: &[f64]| -> Vec<f64> {
            (0..s)
                .map(|i| {
                    p.eta[i]
                        + (0..s)
                            .map(|j| p.dense_information()[i * s + j] * (x[j] - p.xbar[j]))
                            .sum::<f64>()
                })
                .collect()
        };
        let x = &tangent.xbar;
        let (a, b) = (value(&prior, x), value(&tangent, x));
        assert!((a - b).abs() <= 1e-12 * a.abs().max(1.0), "{a:e} vs {b:e}");
        let (ga, gb) = (grad(&prior, x), grad(&tangent, x));
        for c in 0..red.dim {
            let (mut pa, mut pb) = (0.0, 0.0);
            for i in 0..s {
                let (start, row) = red.row(i);
                if c >= start && c < start + row.len() {
                    pa += row[c - start] * ga[i];
                    pb += row[c - start] * gb[i];
                }
            }
            assert!(
                (pa - pb).abs() <= 1e-9 * pa.abs().max(1.0),
                "Nᵀ∇Q[{c}]: {pa:e} vs {pb:e}"
            );
        }
        // Across the manifold the tangent prior is flat.
        let normal: Vec<f64> = (0..s).map(|i| ga[i] - gb[i]).collect();
        assert!(tangent.dense_information().iter().all(|v| v.is_finite()));
        assert!(
            normal.iter().any(|v| v.abs() > 0.0),
            "the prior pulled across the manifold"
        );
    }

    /// An observer sees every iteration of a solve, numbered from 1, and nothing
    /// else; the report's count agrees.
    #[test]
    fn an_observer_sees_every_iteration() {
        use std::sync::Mutex;
        struct Count(Arc<Mutex<Vec<Iteration>>>);
        impl Observer for Count {
            fn iteration(&mut self, it: &Iteration) {
                self.0.lock().unwrap().push(*it);
            }
        }
        let (fg, mut values, _, mut solver, k) = window();
        let seen = Arc::new(Mutex::new(Vec::new()));
        solver.observe(Box::new(Count(seen.clone())));
        // The newest step after the one before it, as the fixed-lag run starts it.
        let s = fg.graph.layout().size();
        let (done, newest) = values.split_at_mut(k * s);
        newest[..s].copy_from_slice(&done[(k - 1) * s..]);
        let report = solver
            .solve_conditional(&fg.graph, &mut values, k, k + 1)
            .unwrap();
        assert_eq!(report.termination, Termination::Converged);
        let seen = seen.lock().unwrap();
        assert!(!seen.is_empty());
        assert!(seen.len() <= report.iterations);
        assert_eq!(seen.last().unwrap().iteration, report.iterations);
        for (a, b) in seen.iter().zip(seen.iter().skip(1)) {
            assert!(a.iteration < b.iteration);
        }
        for it in seen.iter() {
            assert_eq!((it.k0, it.k1), (k, k + 1));
            assert!(it.cost.is_finite());
        }
    }

    /// Records every iteration it sees.
    struct Record(Arc<std::sync::Mutex<Vec<Iteration>>>);
    impl Observer for Record {
        fn iteration(&mut self, it: &Iteration) {
            self.0.lock().unwrap().push(*it);
        }
    }

    fn recorded(solver: &mut WindowSolver) -> Arc<std::sync::Mutex<Vec<Iteration>>> {
        let seen = Arc::new(std::sync::Mutex::new(Vec::new()));
        solver.observe(Box::new(Record(seen.clone())));
        seen
    }

    /// A held one-step solve stops on a chord step below the tolerance, where the
    /// same solve with every convergence decided on a fresh linearization ends
    /// within the tolerance of the same point, after as many linear solves; a solve
    /// whose linearization a marginal prior is made from never stops on one.
    #[test]
    fn a_chord_step_ends_a_solve_where_a_fresh_linearization_would() {
        let (fg, values, prior, _, k) = window();
        let s = fg.graph.layout().size();
        let mut start = values.clone();
        let (done, newest) = start.split_at_mut(k * s);
        newest[..s].copy_from_slice(&done[(k - 1) * s..]);
        let solve = |chord_test: bool| {
            // Gauss-Newton throughout (the exact Hessian makes no chord steps).
            let settings = Settings {
                chord_test,
                second_order: false,
                ..Settings::default()
            };
            let mut solver = WindowSolver::new(&fg.graph, 2, settings).unwrap();
            let seen = recorded(&mut solver);
            let mut x = start.clone();
            let report = solver
                .solve_conditional(&fg.graph, &mut x, k, k + 1)
                .unwrap();
            assert_eq!(report.termination, Termination::Converged);
            let seen = seen.lock().unwrap().clone();
            (x, report, seen, solver)
        };
        let (x_with, report_with, seen_with, mut solver) = solve(true);
        let (x_without, report_without, seen_without, _) = solve(false);
        let with = &x_with[k * s..(k + 1) * s];
        let without = &x_without[k * s..(k + 1) * s];
        let last = seen_with.last().unwrap();
        assert!(last.chord && last.small, "{last:?}");
        assert!(last.largest_step <= Settings::default().step_tolerance);
        assert!(seen_without.iter().all(|it| !it.chord));
        assert_eq!(report_with.iterations, report_without.iterations);
        for (a, b) in with.iter().zip(without) {
            assert!((a - b).abs() <= 2e-8 * (1.0 + b.abs()), "{a} against {b}");
        }
        // The moved step is back on its hard equations to round-off.
        let mut x = x_with.clone();
        solver.correct(&fg.graph, &mut x, k, k + 1).unwrap();
        for (a, b) in x[k * s..(k + 1) * s].iter().zip(with) {
            assert!((a - b).abs() <= 1e-13 * (1.0 + b.abs()), "{a} against {b}");
        }

        // Marginalized past (the DC graph's tangent priors, as a run makes them):
        // the window's linearization is the marginal's.
        let settings = Settings {
            tangent_priors: true,
            ..Settings::default()
        };
        let mut solver = WindowSolver::new(&fg.graph, 2, settings).unwrap();
        let seen = recorded(&mut solver);
        let mut x = start.clone();
        let mut prior = prior;
        solver.project_prior(&fg.graph, &x, k, &mut prior).unwrap();
        let report = solver
            .solve(&fg.graph, &mut x, k, k + 1, Some(&prior))
            .unwrap();
        assert_eq!(report.termination, Termination::Converged);
        assert!(seen.lock().unwrap().iter().all(|it| !it.chord));
    }

    /// |a − b| ≤ `relative` × max(1, max |a|), entry by entry.
    fn assert_close(a: &[f64], b: &[f64], relative: f64, what: &str) {
        let scale = a.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= relative * scale,
                "{what}[{i}]: {x:e} vs {y:e}"
            );
        }
    }

    /// A projected prior kept as N̄CN̄ᵀ is the one written out s × s: the same Λ, η,
    /// value and gradient, the same reduced normal equations of the window, the same
    /// rows for the least-squares step and the same solve.
    #[test]
    fn the_tangent_form_of_a_prior_is_the_written_out_one() {
        let (fg, values, prior, mut solver, k) = window();
        let s = solver.s;
        let project = |solver: &mut WindowSolver, from: usize| {
            let mut p = prior.clone();
            solver.tangent_form_from = from;
            solver.project_prior(&fg.graph, &values, k, &mut p).unwrap();
            p
        };
        let dense = project(&mut solver, usize::MAX);
        let tangent = project(&mut solver, 0);
        assert!(matches!(dense.information, Information::Dense(_)));
        assert!(matches!(tangent.information, Information::Tangent(_)));
        let close = |a: &[f64], b: &[f64], what: &str| assert_close(a, b, 1e-12, what);
        let lambda = dense.dense_information();
        close(&lambda, &tangent.dense_information(), "Λ");
        close(&dense.eta, &tangent.eta, "η");
        close(&dense.xbar, &tangent.xbar, "x̄");
        close(&[dense.constant], &[tangent.constant], "c");
        // Off the mean, and off the manifold.
        let x: Vec<f64> = (0..s)
            .map(|i| dense.xbar[i] + 1e-3 * ((i * 5 % 7) as f64 - 3.0))
            .collect();
        let (mut delta, mut ga, mut gb) = (vec![0.0; s], vec![0.0; s], vec![0.0; s]);
        let mut work = vec![0.0; 2 * s];
        let va = dense.gradient(&x, &mut delta, &mut ga, &mut work);
        let vb = tangent.gradient(&x, &mut delta, &mut gb, &mut work);
        close(&[va], &[vb], "value");
        close(&ga, &gb, "gradient");
        // The window's reduced normal equations with each.
        let mut moved = values.clone();
        moved[k * s..(k + 1) * s].copy_from_slice(&x);
        let mut normal = |p: &LinearPrior| {
            let cost = solver
                .evaluate(&fg.graph, &moved, span(k, Some(p)), true)
                .unwrap();
            let d = solver.normal.h.dim(0);
            (
                cost,
                solver.normal.h.diag(0)[..d * d].to_vec(),
                solver.normal.g[..d].to_vec(),
            )
        };
        let (ca, ha, gna) = normal(&dense);
        let (cb, hb, gnb) = normal(&tangent);
        close(&[ca], &[cb], "cost");
        close(&ha, &hb, "H");
        close(&gna, &gnb, "g");
        // Its rows: RᵀR = Λ, Rᵀc = η.
        let roots = newton::PriorRoots::of(&tangent, s);
        let rows = roots.eta.len();
        let scale = lambda.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        for i in 0..s {
            for j in 0..s {
                let rtr: f64 = (0..rows)
                    .map(|r| roots.rows[r * s + i] * roots.rows[r * s + j])
                    .sum();
                assert!(
                    (rtr - lambda[i * s + j]).abs() <= 1e-11 * scale,
                    "RᵀR[{i}][{j}]"
                );
            }
            let rtc: f64 = (0..rows)
                .map(|r| roots.rows[r * s + i] * roots.eta[r])
                .sum();
            assert!((rtc - dense.eta[i]).abs() <= 1e-11 * scale, "Rᵀc[{i}]");
        }
        // The same solve of the window, from near its solution.
        let solve = |solver: &mut WindowSolver, p: &LinearPrior| {
            let mut v = values.clone();
            for (i, vi) in v[k * s..(k + 1) * s].iter_mut().enumerate() {
                *vi += 1e-6 * ((i * 3 % 5) as f64 - 2.0);
            }
            let report = solver.solve(&fg.graph, &mut v, k, k + 1, Some(p)).unwrap();
            assert_eq!(report.termination, Termination::Converged);
            v[k * s..(k + 1) * s].to_vec()
        };
        let (xa, xb) = (solve(&mut solver, &dense), solve(&mut solver, &tangent));
        close(&xa, &xb, "solution");
    }

    /// The marginal of a converged one-step window projected as it is formed (from
    /// the joining rows and Y's products with N̄) is the marginal written out and
    /// then projected.
    #[test]
    fn a_marginal_projected_as_it_is_formed_is_the_projected_marginal() {
        let (fg, values, _, _, k) = window();
        let marginal = |from: usize| {
            let mut solver = WindowSolver::new(&fg.graph, 2, Settings::default()).unwrap();
            solver.tangent_form_from = from;
            let mut v = values.clone();
            let report = solver.solve(&fg.graph, &mut v, k - 1, k, None).unwrap();
            assert_eq!(report.termination, Termination::Converged);
            assert!(solver.last.is_some(), "the solve left its linearization");
            // The next step off its constraints: projected through p̄ ≠ 0.
            let s = solver.s;
            for (i, x) in v[k * s..(k + 1) * s].iter_mut().enumerate() {
                *x += 1e-4 * ((i * 3 % 7) as f64 - 3.0);
            }
            let p = solver
                .marginalize_projected(&fg.graph, &v, k - 1, None)
                .unwrap();
            assert_eq!(p.projection.map(|pr| pr.step), Some(k));
            p
        };
        let (dense, tangent) = (marginal(usize::MAX), marginal(0));
        assert!(matches!(dense.information, Information::Dense(_)));
        assert!(matches!(tangent.information, Information::Tangent(_)));
        let close = |a: &[f64], b: &[f64], what: &str| assert_close(a, b, 1e-10, what);
        close(
            &dense.dense_information(),
            &tangent.dense_information(),
            "Λ",
        );
        close(&dense.eta, &tangent.eta, "η");
        close(&dense.xbar, &tangent.xbar, "x̄");
        close(&[dense.constant], &[tangent.constant], "c");
    }

    /// A prior as rows: RᵀR = Λ and Rᵀc = η, for an information of lower rank than
    /// its size (its null direction gets no row).
    #[test]
    fn a_prior_as_rows_has_its_information_and_gradient() {
        let (s, r) = (5, 3);
        // Λ = AᵀA with A r × s, η = Aᵀb: a prior of rank r.
        let a: Vec<f64> = (0..r * s)
            .map(|i| ((i * 7 % 11) as f64 - 5.0) * 0.3)
            .collect();
        let b = [0.7, -1.3, 2.1];
        let mut information = vec![0.0; s * s];
        let mut eta = vec![0.0; s];
        for i in 0..s {
            for j in 0..s {
                information[i * s + j] = (0..r).map(|k| a[k * s + i] * a[k * s + j]).sum();
            }
            eta[i] = (0..r).map(|k| a[k * s + i] * b[k]).sum();
        }
        let prior = LinearPrior {
            information: Information::Dense(information.clone()),
            eta: eta.clone(),
            constant: 0.0,
            xbar: vec![0.0; s],
            projection: None,
        };
        let roots = newton::PriorRoots::of(&prior, s);
        assert_eq!(roots.rows.len(), r * s, "one row per direction informed");
        let rows = roots.rows.len() / s;
        for i in 0..s {
            for j in 0..s {
                let rtr: f64 = (0..rows)
                    .map(|k| roots.rows[k * s + i] * roots.rows[k * s + j])
                    .sum();
                assert!((rtr - information[i * s + j]).abs() <= 1e-12, "Λ[{i}][{j}]");
            }
            let rtc: f64 = (0..rows)
                .map(|k| roots.rows[k * s + i] * roots.eta[k])
                .sum();
            assert!((rtc - eta[i]).abs() <= 1e-12, "η[{i}]");
        }
    }
}
