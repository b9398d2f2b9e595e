mod unit {
    use super::super::*;
    use nalgebra::DMatrix;

    fn pseudo_random(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// C = A B with A rows × rank and B rank × s has rank `rank`.
    fn low_rank(rows: usize, s: usize, rank: usize, seed: &mut u64) -> DMatrix<f64> {
        let a = DMatrix::from_fn(rows, rank, |_, _| pseudo_random(seed));
        let b = DMatrix::from_fn(rank, s, |_, _| pseudo_random(seed));
        a * b
    }

    #[test]
    fn basis_spans_the_null_space_and_particular_solution_is_least_norm() {
        let mut seed = 7;
        for &(rows, s, rank) in &[
            (3, 5, 3),
            (6, 12, 4),
            (8, 6, 6),
            (7, 7, 5),
            (1, 3, 1),
            (5, 9, 0),
        ] {
            let c = low_rank(rows, s, rank, &mut seed);
            let x_true = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let b = &c * &x_true; // consistent right-hand side
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, b.as_slice(), rows);
            assert_eq!(ns.rank, rank, "rank of a {rows}×{s} matrix");
            assert_eq!(ns.dim, s - rank);
            let n = DMatrix::from_row_slice(s, ns.dim, &ns.basis());
            let p = DMatrix::from_column_slice(s, 1, &ns.particular);
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
            for i in 0..s {
                let (start, row) = ns.row(i);
                for j in 0..ns.dim {
                    let inside = j >= start && j < start + row.len();
                    let v = if inside { row[j - start] } else { 0.0 };
                    assert_eq!(
                        v,
                        ns.basis()[i * ns.dim + j],
                        "row {i} of N outside its span"
                    );
                }
            }
            let ntn = n.transpose() * &n;
            assert!(
                (ntn - DMatrix::identity(ns.dim, ns.dim)).amax() < 1e-12,
                "NᵀN = I"
            );
            assert!((&c * &p - &b).amax() < 1e-10, "C p = b");
            assert!((n.transpose() * &p).amax() < 1e-12, "p ⟂ null(C)");
            let b2 = &c * DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let mut x = vec![0.0; s];
            ns.solve(b2.as_slice(), &mut x);
            let x = DMatrix::from_column_slice(s, 1, &x);
            assert!((&c * &x - &b2).amax() < 1e-10, "C x = b for another b");
        }
    }

    /// A reduction copied into another one that held a different system (of other
    /// sizes) is the original, field for field, and solves as it does.
    #[test]
    fn a_copied_reduction_is_the_original() {
        let mut seed = 5;
        let (rows, s) = (4, 9);
        let mut original = NullSpace::new(s, rows);
        let c = low_rank(rows, s, 3, &mut seed);
        let row_major: Vec<f64> = c.transpose().iter().copied().collect();
        let b: Vec<f64> = (0..rows).map(|_| pseudo_random(&mut seed)).collect();
        original.set_segments(&[0, 0, 0, 1, 1, 1, 2, 2, 2]);
        original.reduce(&row_major, &b, rows);
        let mut copy = NullSpace::new(s, rows);
        let other = low_rank(2, s, 2, &mut seed);
        let other: Vec<f64> = other.transpose().iter().copied().collect();
        copy.reduce(&other, &[1.0, -1.0], 2);
        copy.copy_from(&original);
        assert_eq!(format!("{copy:?}"), format!("{original:?}"));
        let (mut x, mut y) = (vec![0.0; s], vec![0.0; s]);
        original.solve(&b, &mut x);
        copy.solve(&b, &mut y);
        assert_eq!(x, y);
    }

    #[test]
    fn unit_equations_fix_their_unknowns_and_the_rest_reduce_as_before() {
        let mut seed = 11;
        let (s, rows) = (9, 7);
        for trial in 0..5 {
            // Rows 0..3 unit rows on unknowns 2, 5, 5 (a redundant duplicate), the
            // rest dense and rank-deficient.
            let mut c = DMatrix::zeros(rows, s);
            c[(0, 2)] = 2.0;
            c[(1, 5)] = -0.5;
            c[(2, 5)] = 1.5;
            let dense = low_rank(rows - 3, s, 2 + trial % 2, &mut seed);
            c.view_mut((3, 0), (rows - 3, s)).copy_from(&dense);
            let x_true = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let b = &c * &x_true;
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, b.as_slice(), rows);
            let rank = c.clone().svd(false, false).rank(1e-9);
            assert_eq!(ns.rank, rank, "trial {trial}");
            let n = DMatrix::from_row_slice(s, ns.dim, &ns.basis());
            let p = DMatrix::from_column_slice(s, 1, &ns.particular);
            assert!((&c * &n).amax() < 1e-12);
            assert!((n.transpose() * &n - DMatrix::identity(ns.dim, ns.dim)).amax() < 1e-12);
            assert!((&c * &p - &b).amax() < 1e-10);
            assert!((p[2] - x_true[2]).abs() < 1e-14 && (p[5] - x_true[5]).abs() < 1e-14);
            assert!(n.row(2).amax() == 0.0 && n.row(5).amax() == 0.0);
        }
    }

    /// A kept equation whose pivot is far below the largest (RANK_TOLERANCE <
    /// R/R₀ < CORRECTION_TOLERANCE) is corrected with a damped step: the least-norm
    /// solution stays below b/μ instead of b/R, the equation pivoted first still
    /// holds, and well above μ the solution is the exact one.
    #[test]
    fn nearly_dependent_equations_get_a_damped_correction() {
        // Rows (1, 1, 0) and (1, 1 + δ, 0): the second pivot is about δ/2 of the first.
        for (delta, damped) in [(1e-9, true), (1e-3, false)] {
            let c = [1.0, 1.0, 0.0, 1.0, 1.0 + delta, 0.0];
            let b = [0.0, 1e-12];
            let mut ns = NullSpace::new(3, 2);
            ns.reduce(&c, &b, 2);
            assert_eq!(ns.rank, 2, "δ = {delta}: the equation is kept");
            assert_eq!(ns.dim, 1);
            let p = &ns.particular;
            let (r0, r1) = (p[0] + p[1], p[0] + (1.0 + delta) * p[1] - 1e-12);
            assert!(
                r0.abs().min(r1.abs()) < 1e-15 && r0.abs().max(r1.abs()) <= 1e-12,
                "δ = {delta}: the equation pivoted first holds, the other is left at most \
                 its residual (residuals {r0:e}, {r1:e})"
            );
            if damped {
                let mu = NullSpace::CORRECTION_TOLERANCE;
                assert!(
                    p[1].abs() <= 1e-12 / mu,
                    "δ = {delta}: correction {:e} not damped",
                    p[1]
                );
            } else {
                let exact = 1e-12 / delta;
                assert!(
                    (p[1] - exact).abs() <= 1e-12 * exact,
                    "δ = {delta}: {:e} instead of the exact {exact:e}",
                    p[1]
                );
            }
            assert_eq!(
                ns.basis()[2 * ns.dim],
                1.0,
                "the untouched unknown stays free"
            );
        }
    }

    /// The damping is for round-off only: a nearly dependent equation whose residual
    /// stands far above the round-off its noise declares is corrected exactly (damped,
    /// it stalls the solves: `docs/dc-stall.md`, "6. Equations of very different
    /// sizes"), one at its round-off is still damped, and without declared noise every
    /// one is.
    #[test]
    fn a_residual_above_its_round_off_is_corrected_exactly() {
        let delta = 1e-7;
        let c = [1.0, 1.0, 0.0, 1.0, 1.0 + delta, 0.0];
        let exact = |b: f64| b / delta;
        for (b1, noise, exact_expected) in [
            (1e-8, Some(1e-16), true),
            (1e-14, Some(1e-16), false),
            (1e-8, None, false),
        ] {
            let mut ns = NullSpace::new(3, 2);
            if let Some(e) = noise {
                ns.set_noise(&[e, e]);
            }
            ns.reduce(&c, &[0.0, b1], 2);
            let p1 = ns.particular[1];
            if exact_expected {
                assert!(
                    (p1 - exact(b1)).abs() <= 1e-6 * exact(b1),
                    "b = {b1:e}: {p1:e} instead of {:e}",
                    exact(b1)
                );
            } else {
                assert!(
                    p1.abs() <= b1 / NullSpace::CORRECTION_TOLERANCE,
                    "b = {b1:e}, noise {noise:?}: correction {p1:e} not damped"
                );
            }
        }
    }

    /// Equations of very different sizes are independent all the same: the
    /// reduction's rank, particular solution and multipliers do not change when one
    /// equation is scaled by 1e-8 (as the damping would, were the pivots compared
    /// with the largest equation's).
    #[test]
    fn equations_of_very_different_sizes_are_solved_exactly() {
        let c = [2.0, 1.0, 0.0, 0.0, 1.0, 3.0];
        let b = [1.0, 2.0];
        let mut plain = NullSpace::new(3, 2);
        plain.reduce(&c, &b, 2);
        for scale in [1e-8, 1e8] {
            let cs = [2.0, 1.0, 0.0, 0.0, scale, 3.0 * scale];
            let bs = [1.0, 2.0 * scale];
            let mut ns = NullSpace::new(3, 2);
            ns.reduce(&cs, &bs, 2);
            assert_eq!(ns.rank, 2, "scale {scale:e}");
            for (p, q) in ns.particular.iter().zip(&plain.particular) {
                assert!(
                    (p - q).abs() <= 1e-12,
                    "scale {scale:e}: {p:e} against {q:e}"
                );
            }
            let g = [0.3, -0.7, 1.1];
            let (mut l, mut lp) = ([0.0; 2], [0.0; 2]);
            ns.multipliers(&g, &mut l);
            plain.multipliers(&g, &mut lp);
            assert!(
                (l[0] - lp[0]).abs() <= 1e-12
                    && (l[1] * scale - lp[1]).abs() <= 1e-9 * lp[1].abs().max(1.0),
                "scale {scale:e}: multipliers {l:?} against {lp:?}"
            );
        }
    }

    #[test]
    fn transposed_solve_is_exact_for_consistent_systems() {
        let mut seed = 23;
        let (s, rows) = (8, 9);
        for trial in 0..4 {
            // Unit rows on unknowns 1 and 6, the rest dense (rank-deficient on odd
            // trials, so some equations are dependent).
            let mut c = DMatrix::zeros(rows, s);
            c[(0, 1)] = 1.5;
            c[(1, 6)] = -2.0;
            let dense = low_rank(rows - 2, s, 5 + trial % 2, &mut seed);
            c.view_mut((2, 0), (rows - 2, s)).copy_from(&dense);
            let mu_true = DMatrix::from_fn(rows, 1, |_, _| pseudo_random(&mut seed));
            let r = c.transpose() * &mu_true; // consistent
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, &vec![0.0; rows], rows);
            let mut mu = vec![0.0; rows];
            ns.solve_transpose(r.as_slice(), &mut mu);
            let back = c.transpose() * DMatrix::from_column_slice(rows, 1, &mu);
            assert!((back - &r).amax() < 1e-10, "trial {trial}: Cᵀμ = r");
        }
    }

    #[test]
    fn segments_give_the_same_reduction_and_zeros_where_earlier_ones_fix() {
        // Block-triangular equations on (x, v, a), 4 unknowns each: A x = ·,
        // B x + A v = ·, with A rank 3 (one redundant row in each block), one unit
        // row on x; a untouched.
        let mut seed = 5;
        let (s, rows) = (12, 9);
        for trial in 0..4 {
            let a = low_rank(4, 4, 3, &mut seed);
            let b = DMatrix::from_fn(4, 4, |_, _| pseudo_random(&mut seed));
            let mut c = DMatrix::zeros(rows, s);
            c.view_mut((0, 0), (4, 4)).copy_from(&a);
            c.view_mut((4, 0), (4, 4)).copy_from(&b);
            c.view_mut((4, 4), (4, 4)).copy_from(&a);
            c[(8, trial % 4)] = 1.0;
            let x_true = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let rhs = &c * &x_true;
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut plain = NullSpace::new(s, rows);
            plain.reduce(&row_major, rhs.as_slice(), rows);
            let mut seg = NullSpace::new(s, rows);
            seg.set_segments(&[0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]);
            seg.reduce(&row_major, rhs.as_slice(), rows);
            assert_eq!(
                (seg.rank, seg.dim),
                (plain.rank, plain.dim),
                "trial {trial}"
            );
            let n = DMatrix::from_row_slice(s, seg.dim, &seg.basis());
            let n0 = DMatrix::from_row_slice(s, plain.dim, &plain.basis());
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
            assert!((n.transpose() * &n - DMatrix::identity(seg.dim, seg.dim)).amax() < 1e-12);
            // The same space: N₀ N₀ᵀ N = N.
            assert!((&n0 * (n0.transpose() * &n) - &n).amax() < 1e-12);
            for i in 0..s {
                assert!((seg.particular[i] - plain.particular[i]).abs() < 1e-12);
                let (start, row) = seg.row(i);
                for j in 0..seg.dim {
                    let inside = j >= start && j < start + row.len();
                    let v = if inside { row[j - start] } else { 0.0 };
                    assert_eq!(
                        v,
                        seg.basis()[i * seg.dim + j],
                        "row {i} of N outside its span"
                    );
                }
            }
            let b2 = &c * DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let (mut x1, mut x2) = (vec![0.0; s], vec![0.0; s]);
            plain.solve(b2.as_slice(), &mut x1);
            seg.solve(b2.as_slice(), &mut x2);
            assert!(x1.iter().zip(&x2).all(|(a, b)| (a - b).abs() < 1e-12));
            let mu_true = DMatrix::from_fn(rows, 1, |_, _| pseudo_random(&mut seed));
            let r = c.transpose() * &mu_true;
            let mut mu = vec![0.0; rows];
            seg.solve_transpose(r.as_slice(), &mut mu);
            let back = c.transpose() * DMatrix::from_column_slice(rows, 1, &mu);
            assert!((back - &r).amax() < 1e-10, "Cᵀμ = r");
        }
        // x fully fixed (A regular): the basis is exactly 0 on x.
        let a = DMatrix::from_fn(4, 4, |_, _| pseudo_random(&mut seed));
        let b = DMatrix::from_fn(3, 4, |_, _| pseudo_random(&mut seed));
        let mut c = DMatrix::zeros(7, 12);
        c.view_mut((0, 0), (4, 4)).copy_from(&a);
        c.view_mut((4, 0), (3, 4)).copy_from(&b);
        c.view_mut((4, 4), (3, 4)).copy_from(&a.rows(0, 3));
        let row_major: Vec<f64> = c.transpose().iter().copied().collect();
        let rhs: Vec<f64> = (0..7).map(|_| pseudo_random(&mut seed)).collect();
        let mut plain = NullSpace::new(12, 7);
        plain.reduce(&row_major, &rhs, 7);
        for how in [Summation::Sequential, Summation::Lanes] {
            let mut seg = NullSpace::new(12, 7);
            seg.set_segments(&[0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]);
            seg.set_summation(how);
            seg.reduce(&row_major, &rhs, 7);
            assert_eq!(seg.dim, 5);
            // The positions' group stands apart: its reflectors never reach the
            // velocity equations, whose solution reads the positions' instead.
            assert!(seg.made[0].apart && !seg.made[1].apart);
            for i in 0..4 {
                assert!(seg.row(i).1.is_empty(), "row {i} of N");
            }
            for i in 0..12 {
                assert!((seg.particular[i] - plain.particular[i]).abs() < 1e-12);
            }
            let n = DMatrix::from_row_slice(12, seg.dim, &seg.basis());
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
            assert!((n.transpose() * &n - DMatrix::identity(seg.dim, seg.dim)).amax() < 1e-12);
            let b2 = &c * DMatrix::from_fn(12, 1, |_, _| pseudo_random(&mut seed));
            let (mut x1, mut x2) = (vec![0.0; 12], vec![0.0; 12]);
            plain.solve(b2.as_slice(), &mut x1);
            seg.solve(b2.as_slice(), &mut x2);
            assert!(x1.iter().zip(&x2).all(|(a, b)| (a - b).abs() < 1e-12));
            let mu_true = DMatrix::from_fn(7, 1, |_, _| pseudo_random(&mut seed));
            let r = c.transpose() * &mu_true;
            let mut mu = vec![0.0; 7];
            seg.solve_transpose(r.as_slice(), &mut mu);
            let back = c.transpose() * DMatrix::from_column_slice(7, 1, &mu);
            assert!((back - &r).amax() < 1e-10, "Cᵀμ = r");
        }
    }

    #[test]
    fn basis_is_q_applied_to_each_unit_vector_to_the_bit() {
        // The basis is formed for all its columns at once (`apply_q_columns`): each
        // column must be what `apply_q` makes of its unit vector alone, bit for bit,
        // in both summations, with segments (a group apart and one not) and a rank
        // loss, at a size where the QR tracks its columns' supports.
        let mut seed = 11;
        let (p, s) = (70, 210);
        let mut c = DMatrix::zeros(2 * p - 1, s);
        for r in 0..p {
            // A chain: equation r touches positions r … r + 5 (and its velocity row
            // the same velocities and positions).
            for j in (r..r + 6).map(|j| j % p) {
                c[(r, j)] = pseudo_random(&mut seed);
                if r + 1 < p {
                    c[(p + r, p + j)] = pseudo_random(&mut seed);
                    c[(p + r, j)] = pseudo_random(&mut seed);
                }
            }
        }
        // A redundant velocity equation: twice the first.
        let first = c.row(p).clone_owned();
        c.row_mut(2 * p - 2).copy_from(&(first * 2.0));
        let rows = c.nrows();
        let row_major: Vec<f64> = c.transpose().iter().copied().collect();
        let rhs: Vec<f64> = (0..rows).map(|_| pseudo_random(&mut seed)).collect();
        let segments: Vec<usize> = (0..s).map(|i| i / p).collect();
        for how in [Summation::Sequential, Summation::Lanes] {
            let mut ns = NullSpace::new(s, rows);
            ns.set_segments(&segments);
            ns.set_summation(how);
            ns.reduce(&row_major, &rhs, rows);
            let sf = ns.free.len();
            let rank = ns.rank - (s - sf - ns.untouched.len());
            let q = sf - rank;
            assert!(q > 0 && rank > 0 && ns.rank < rows, "a rank loss to see");
            for j in rank..sf {
                ns.w[..sf].fill(0.0);
                ns.w[j] = 1.0;
                ns.apply_q_to_w(sf);
                for a in 0..sf {
                    assert_eq!(
                        ns.dense[a * q + (j - rank)].to_bits(),
                        ns.w[a].to_bits(),
                        "{how:?}: row {a} of column {}",
                        j - rank
                    );
                }
            }
            let n = DMatrix::from_row_slice(s, ns.dim, &ns.basis());
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
        }
    }

    #[test]
    fn multipliers_solve_the_least_squares_problem() {
        // Dense rank-deficient equations, and unit rows (one of them a duplicate)
        // next to them: C(Cᵀλ + g) = 0 is the least-squares condition.
        let mut seed = 5;
        for &(rows, s, rank, units) in &[(3, 6, 3, 0), (6, 12, 4, 0), (7, 9, 3, 3), (5, 5, 4, 2)] {
            let mut c = DMatrix::zeros(rows, s);
            let dense = low_rank(rows - units, s, rank, &mut seed);
            c.view_mut((units, 0), (rows - units, s)).copy_from(&dense);
            for u in 0..units {
                c[(u, 1 + (u % 2) * 2)] = 1.5 + u as f64;
            }
            let g = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, &vec![0.0; rows], rows);
            let mut lambda = vec![0.0; rows];
            ns.multipliers(g.as_slice(), &mut lambda);
            let l = DMatrix::from_column_slice(rows, 1, &lambda);
            let residual = c.transpose() * l + &g;
            assert!(
                (&c * &residual).amax() < 1e-12,
                "C(Cᵀλ + g) = {:e} for a {rows}×{s} system of rank {rank}",
                (&c * &residual).amax()
            );
        }
    }

    #[test]
    fn no_equations_leave_every_direction_free() {
        let mut ns = NullSpace::new(3, 2);
        ns.reduce(&[], &[], 0);
        assert_eq!(ns.dim, 3);
        assert_eq!(
            ns.basis(),
            vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        );
    }
}

mod sparse {
    use super::super::householder::*;
    use super::super::*;

    fn pseudo_random(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// Cᵀ (column-major s × m) of a chain, two segments of `s_half` unknowns with
    /// `per` equations each: equation j touches unknowns `step`·j … `step`·j + `width`
    /// of its segment, the later segment's equations also the earlier segment's same
    /// unknowns (like [Φ_q 0; Φ̇_q Φ_q]); the last equation repeats equation `copied`
    /// (dependent).
    fn chain_of(
        (s_half, per): (usize, usize),
        (step, width): (usize, usize),
        copied: usize,
        seed: &mut u64,
    ) -> (Vec<f64>, usize, Vec<usize>) {
        let s = 2 * s_half;
        let m = 2 * per + 1;
        let mut a = vec![0.0; s * m];
        let mut group = vec![0; m];
        for seg in 0..2 {
            for j in 0..per {
                let col = seg * per + j;
                group[col] = seg;
                for i in step * j..step * j + width {
                    a[col * s + seg * s_half + i] = pseudo_random(seed);
                    if seg == 1 {
                        a[col * s + i] = pseudo_random(seed);
                    }
                }
            }
        }
        let copy: Vec<f64> = a[copied * s..(copied + 1) * s].to_vec();
        a[(m - 1) * s..m * s].copy_from_slice(&copy);
        group[m - 1] = 0;
        (a, m, group)
    }

    /// A chain of one equation per two unknowns, 4 unknowns each.
    fn chain(s_half: usize, seed: &mut u64) -> (Vec<f64>, usize, Vec<usize>) {
        chain_of((s_half, (s_half - 4) / 2), (2, 4), 2, seed)
    }

    /// A chain with nearly as many equations as unknowns per segment (a planar
    /// chain's two per point), 3 unknowns each, two unknowns per segment left free.
    fn tight_chain(s_half: usize, seed: &mut u64) -> (Vec<f64>, usize, Vec<usize>) {
        chain_of((s_half, s_half - 2), (1, 3), 5, seed)
    }

    /// The grouped QR of the column-major s × m `a0` (groups `group0`), with the
    /// supports tracked or not and the pivots along them or not: the rank, the
    /// factors, R's diagonal, β, the permutation and the groups after it.
    #[allow(clippy::type_complexity)]
    fn grouped_qr(
        a0: &[f64],
        group0: &[usize],
        (s, m): (usize, usize),
        seg_end: &[usize],
        track: bool,
        order: bool,
    ) -> (usize, Vec<f64>, Vec<f64>, Vec<f64>, Vec<usize>, Vec<usize>) {
        let mut a = a0.to_vec();
        let mut group = group0.to_vec();
        let (mut rend, mut made) = (vec![0; s.min(m)], Vec::new());
        let (mut rdiag, mut beta) = (vec![0.0; s.min(m)], vec![0.0; s.min(m)]);
        let (mut perm, mut norms) = (vec![0; m], vec![0.0; 2 * m]);
        let mut support = vec![0u64; if track { (m + 1) * s.div_ceil(64) } else { 0 }];
        let (mut starts, mut ends) = (vec![0; m], vec![0; m]);
        let rank = householder_grouped(
            &mut a,
            s,
            m,
            Grouping {
                group: &mut group,
                seg_end,
                rend: &mut rend,
                made: &mut made,
            },
            Summation::Sequential,
            &mut rdiag,
            &mut beta,
            &mut perm,
            &mut norms,
            Sparsity {
                support: &mut support,
                starts: &mut starts,
                ends: &mut ends,
                order,
                nonzeros: None,
            },
        );
        (rank, a, rdiag, beta, perm, group)
    }

    #[test]
    fn tracking_the_supports_changes_no_bit() {
        let mut seed = 11;
        for s_half in [TRACK_SUPPORT_FROM / 2 + 4, 70, 131] {
            let (a0, m, group0) = chain(s_half, &mut seed);
            let s = 2 * s_half;
            let seg_end = [s_half, s];
            let run = |track: bool| {
                let (rank, a, rdiag, beta, perm, group) =
                    grouped_qr(&a0, &group0, (s, m), &seg_end, track, false);
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                (rank, bits(&a), bits(&rdiag), bits(&beta), perm, group)
            };
            let (tracked, plain) = (run(true), run(false));
            assert_eq!(tracked.0, m - 1, "the repeated equation is dependent");
            assert!(tracked == plain, "s = {s}: the tracked QR differs");
        }
    }

    /// The chain's equations listed out of order (every third, then the rest), as a
    /// scene lists cranks before couplers.
    fn scrambled(a: &[f64], s: usize, m: usize, group: &[usize]) -> (Vec<f64>, Vec<usize>) {
        let order: Vec<usize> = (0..m)
            .step_by(3)
            .chain((0..m).filter(|j| j % 3 != 0))
            .collect();
        let mut out = vec![0.0; s * m];
        let mut g = vec![0; m];
        for (new, &old) in order.iter().enumerate() {
            out[new * s..(new + 1) * s].copy_from_slice(&a[old * s..(old + 1) * s]);
            g[new] = group[old];
        }
        (out, g)
    }

    /// Pivots that follow the supports keep a chain's reflectors within its band: far
    /// fewer nonzeros below the diagonal than the largest-norm order leaves, and the
    /// same rank.
    #[test]
    fn pivots_along_the_supports_keep_the_factors_banded() {
        let mut seed = 5;
        for s_half in [70, 131] {
            let (a0, m, group0) = tight_chain(s_half, &mut seed);
            let s = 2 * s_half;
            let (a0, group0) = scrambled(&a0, s, m, &group0);
            let seg_end = [s_half, s];
            let run = |order: bool| {
                let (rank, a, ..) = grouped_qr(&a0, &group0, (s, m), &seg_end, true, order);
                let below = (0..rank)
                    .map(|k| {
                        a[k * s + k + 1..(k + 1) * s]
                            .iter()
                            .filter(|v| **v != 0.0)
                            .count()
                    })
                    .sum::<usize>();
                (rank, below)
            };
            let ((rank, banded), (rank_plain, filled)) = (run(true), run(false));
            assert_eq!(rank, m - 1, "the repeated equation is dependent");
            assert_eq!(rank, rank_plain);
            assert!(
                3 * banded < filled,
                "s = {s}: {banded} nonzeros in the reflectors, {filled} in largest-norm order"
            );
        }
    }

    /// The reduction of a large scrambled chain through the support-ordered QR: an
    /// orthonormal basis of C's null space and the least-norm solution of C δ = b.
    #[test]
    fn a_large_scrambled_chain_reduces_exactly() {
        let mut seed = 17;
        let s_half = 131;
        let (a, m, group) = tight_chain(s_half, &mut seed);
        let s = 2 * s_half;
        let (a, _) = scrambled(&a, s, m, &group);
        // C row-major m × s is Cᵀ column-major.
        let c = a.clone();
        let mut b: Vec<f64> = (0..m).map(|_| pseudo_random(&mut seed)).collect();
        // The repeated equation must agree with the one it repeats.
        let row = |j: usize| &c[j * s..(j + 1) * s];
        let (original, copy) = (0..m)
            .flat_map(|i| (i + 1..m).map(move |j| (i, j)))
            .find(|&(i, j)| row(i) == row(j))
            .expect("the repeated equation");
        b[copy] = b[original];
        let mut ns = NullSpace::new(s, m);
        let segment: Vec<usize> = (0..s).map(|i| usize::from(i >= s_half)).collect();
        ns.set_segments(&segment);
        ns.reduce(&c, &b, m);
        assert_eq!(ns.dim, s - (m - 1));
        let n = ns.basis();
        let d = ns.dim;
        for j in 0..m {
            let row = &c[j * s..(j + 1) * s];
            let cp: f64 = row.iter().zip(&ns.particular).map(|(x, y)| x * y).sum();
            assert!(
                (cp - b[j]).abs() < 1e-12,
                "equation {j}: C p − b = {}",
                cp - b[j]
            );
            for col in 0..d {
                let cn: f64 = (0..s).map(|i| row[i] * n[i * d + col]).sum();
                assert!(cn.abs() < 1e-12, "C N[{j}, {col}] = {cn}");
            }
        }
        for x in 0..d {
            for y in 0..d {
                let g: f64 = (0..s).map(|i| n[i * d + x] * n[i * d + y]).sum();
                let want = if x == y { 1.0 } else { 0.0 };
                assert!((g - want).abs() < 1e-12, "NᵀN[{x}, {y}] = {g}");
            }
            // Least norm: p ⟂ the null space.
            let pn: f64 = (0..s).map(|i| ns.particular[i] * n[i * d + x]).sum();
            assert!(pn.abs() < 1e-12, "pᵀN[{x}] = {pn}");
        }
    }
}
