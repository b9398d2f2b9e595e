//! The hand-written dense kernels of `mbfg::linalg` against faer's in-place ones, at
//! the sizes a step has (4–70 unknowns; 120 ≈ 4n for inverse dynamics with n = 30):
//! `cholesky` (factor + one solve), `lu` (factor + n right-hand sides, as the
//! dynamics kernel's Jacobians solve them) and `nullspace` (the reduction of a dense
//! m × s constraint block: pivoted QR, null-space basis and least-norm solution) and
//! `gram` (the lower triangle of YᵀY, the marginal prior's product).
//!
//! Both sides of `cholesky` and `lu` are the library's own functions
//! (`dense::*_by_hand` and `dense::*_faer`; `dense::cholesky` and `dense::lu` pick
//! one by size from these numbers): faer runs on the same row-major buffers (viewed
//! with strides, nothing transposed) with its `MemStack` scratch, plus what the
//! hand-written kernels' contracts add (the zeroed upper triangle of L, the
//! singular-pivot test of LU). The faer side of `nullspace` is written here: the
//! reduction of one segment with faer's column-pivoted QR, blocked reflectors and
//! the same per-equation normalization and rank cut. Run with
//! `cargo bench --bench linalg`; one group with e.g. `cargo bench --bench linalg -- lu/`.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::householder;
use faer::linalg::qr::{col_pivoting as cpqr, no_pivoting};
use faer::linalg::triangular_solve;
use faer::prelude::*;
use faer::{Conj, Par};
use mbfg::linalg::dense;
use mbfg::linalg::nullspace::NullSpace;
use std::hint::black_box;
use std::time::Duration;

const SIZES: [usize; 9] = [4, 8, 16, 32, 48, 70, 85, 96, 120];

/// Deterministic entries in [−0.5, 0.5) from a linear congruential generator.
fn entries(len: usize, seed: u64) -> Vec<f64> {
    let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    (0..len)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        })
        .collect()
}

/// AᵀA + nI, row-major n × n.
fn spd(n: usize) -> Vec<f64> {
    let a = entries(n * n, n as u64);
    let mut m = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..n {
            m[i * n + j] = (0..n).map(|k| a[k * n + i] * a[k * n + j]).sum::<f64>();
        }
        m[i * n + i] += n as f64;
    }
    m
}

/// A random n × n matrix plus I: needs pivoting, well conditioned.
fn general(n: usize) -> Vec<f64> {
    let mut a = entries(n * n, 1000 + n as u64);
    for i in 0..n {
        a[i * n + i] += 1.0;
    }
    a
}

fn configure<'a>(
    c: &'a mut Criterion,
    name: &str,
) -> criterion::BenchmarkGroup<'a, criterion::measurement::WallTime> {
    let mut group = c.benchmark_group(name);
    group
        .sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2));
    group
}

/// Factor + one solve (the substitutions are the same hand-written ones on both
/// sides; only the factorization differs).
fn cholesky(c: &mut Criterion) {
    let mut group = configure(c, "cholesky");
    for n in SIZES {
        let a = spd(n);
        let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.3).sin()).collect();
        let mut work = a.clone();
        let mut x = b.clone();
        group.bench_with_input(BenchmarkId::new("hand", n), &n, |bench, &n| {
            bench.iter(|| {
                work.copy_from_slice(&a);
                x.copy_from_slice(&b);
                dense::cholesky_by_hand(&mut work, n, n, dense::Summation::Sequential).unwrap();
                dense::cholesky_solve(&work, n, &mut x);
                black_box(&x);
            })
        });
        group.bench_with_input(BenchmarkId::new("faer", n), &n, |bench, &n| {
            bench.iter(|| {
                work.copy_from_slice(&a);
                x.copy_from_slice(&b);
                dense::cholesky_faer(&mut work, n, n).unwrap();
                dense::cholesky_solve(&work, n, &mut x);
                black_box(&x);
            })
        });
    }
    group.finish();
}

/// Factor + as many right-hand sides as unknowns (the dynamics Jacobians solve 2n
/// columns for n + m unknowns).
fn lu(c: &mut Criterion) {
    let mut group = configure(c, "lu");
    for n in SIZES {
        let k = n;
        let a = general(n);
        let b = entries(n * k, 77 + n as u64);
        let mut work = a.clone();
        let mut x = b.clone();
        let mut perm = vec![0usize; n];
        let mut tmp = vec![0.0; n * k];
        group.bench_with_input(BenchmarkId::new("hand", n), &n, |bench, &n| {
            bench.iter(|| {
                work.copy_from_slice(&a);
                x.copy_from_slice(&b);
                dense::lu_by_hand(&mut work, n, &mut perm).unwrap();
                dense::lu_solve_many_by_hand(&work, n, &perm, &mut x, k, &mut tmp);
                black_box(&x);
            })
        });
        group.bench_with_input(BenchmarkId::new("faer", n), &n, |bench, &n| {
            bench.iter(|| {
                work.copy_from_slice(&a);
                x.copy_from_slice(&b);
                dense::lu_faer(&mut work, n, &mut perm).unwrap();
                dense::lu_solve_faer(&work, n, &perm, &mut x, k, &mut tmp);
                black_box(&x);
            })
        });
    }
    group.finish();
}

/// Buffers of the faer reduction of m equations on s unknowns.
struct FaerReduction {
    s: usize,
    m: usize,
    block: usize,
    a: Vec<f64>,
    h: Vec<f64>,
    scale: Vec<f64>,
    perm: Vec<usize>,
    perm_inv: Vec<usize>,
    basis: Vec<f64>,
    particular: Vec<f64>,
    mem: MemBuffer,
}

impl FaerReduction {
    fn new(s: usize, m: usize) -> Self {
        let size = s.min(m);
        let block = no_pivoting::factor::recommended_block_size::<f64>(s, m);
        let req = StackReq::any_of(&[
            cpqr::factor::qr_in_place_scratch::<usize, f64>(s, m, block, Par::Seq, default()),
            householder::apply_block_householder_sequence_on_the_left_in_place_scratch::<f64>(
                s, block, s,
            ),
        ]);
        FaerReduction {
            s,
            m,
            block,
            a: vec![0.0; s * m],
            h: vec![0.0; block * size],
            scale: vec![0.0; m],
            perm: vec![0; m],
            perm_inv: vec![0; m],
            basis: vec![0.0; s * s],
            particular: vec![0.0; s],
            mem: MemBuffer::new(req),
        }
    }

    /// What `NullSpace::reduce` computes for dense C (m × s row-major) with one
    /// segment: Cᵀ with unit columns = Q R Pᵀ, the rank from R's diagonal, the basis
    /// Q[:, rank..] (column-major s × (s − rank)) and the least-norm solution Q₁ R₁⁻ᵀ
    /// (P ᵀ b)₁..rank. Returns the rank.
    fn reduce(&mut self, c: &[f64], b: &[f64]) -> usize {
        let (s, m) = (self.s, self.m);
        let size = s.min(m);
        // C row-major is Cᵀ column-major.
        self.a.copy_from_slice(&c[..s * m]);
        for (col, sc) in self.a.chunks_exact_mut(s).zip(&mut self.scale) {
            let norm = col.iter().map(|v| v * v).sum::<f64>().sqrt();
            *sc = if norm > 0.0 { 1.0 / norm } else { 1.0 };
            col.iter_mut().for_each(|v| *v *= *sc);
        }
        let stack = MemStack::new(&mut self.mem);
        let mut qr = MatMut::from_column_major_slice_mut(&mut self.a, s, m);
        let h = MatMut::from_column_major_slice_mut(&mut self.h, self.block, size);
        cpqr::factor::qr_in_place(
            qr.rb_mut(),
            h,
            &mut self.perm,
            &mut self.perm_inv,
            Par::Seq,
            stack,
            default(),
        );
        let qr = qr.rb();
        let largest = qr[(0, 0)].abs();
        let rank = (0..size)
            .take_while(|&k| qr[(k, k)].abs() > NullSpace::RANK_TOLERANCE * largest)
            .count();
        let h = MatRef::from_column_major_slice(&self.h, self.block, size);
        let basis_of = qr.get(.., ..size);
        let q = s - rank;
        let basis = &mut self.basis[..s * q];
        basis.fill(0.0);
        for j in 0..q {
            basis[j * s + rank + j] = 1.0;
        }
        householder::apply_block_householder_sequence_on_the_left_in_place_with_conj(
            basis_of,
            h,
            Conj::No,
            MatMut::from_column_major_slice_mut(basis, s, q),
            Par::Seq,
            stack,
        );
        let x = &mut self.particular;
        x.fill(0.0);
        for (xi, &j) in x[..rank].iter_mut().zip(&self.perm) {
            *xi = b[j] * self.scale[j];
        }
        triangular_solve::solve_lower_triangular_in_place(
            qr.get(..rank, ..rank).transpose(),
            MatMut::from_column_major_slice_mut(&mut x[..rank], rank, 1),
            Par::Seq,
        );
        householder::apply_block_householder_sequence_on_the_left_in_place_with_conj(
            basis_of,
            h,
            Conj::No,
            MatMut::from_column_major_slice_mut(x, s, 1),
            Par::Seq,
            stack,
        );
        rank
    }
}

fn nullspace(c: &mut Criterion) {
    let mut group = configure(c, "nullspace");
    for s in SIZES {
        for m in [s / 2, s - s / 4] {
            let cm = entries(m * s, 500 + (s * 1000 + m) as u64);
            let b = entries(m, 9 + s as u64);
            let label = format!("{s}x{m}");
            let mut ns = NullSpace::new(s, m);
            group.bench_function(BenchmarkId::new("hand", &label), |bench| {
                bench.iter(|| {
                    ns.reduce(&cm, &b, m);
                    black_box(&ns.particular);
                })
            });
            let mut fr = FaerReduction::new(s, m);
            group.bench_function(BenchmarkId::new("faer", &label), |bench| {
                bench.iter(|| black_box(fr.reduce(&cm, &b)))
            });
            // Both find the same space and the same least-norm solution.
            ns.reduce(&cm, &b, m);
            let rank = fr.reduce(&cm, &b);
            assert_eq!(rank, ns.rank, "rank at {label}");
            for (x, y) in ns.particular.iter().zip(&fr.particular) {
                assert!(
                    (x - y).abs() < 1e-9 * (1.0 + x.abs()),
                    "particular at {label}"
                );
            }
        }
    }
    group.finish();
}

/// The Schur complement's YᵀY (lower triangle) of a DC step leaving the window: Y is
/// (n + 2) × 3n for n coordinates (the four-bar, and the N four-bar with N = 10, 20,
/// 40), by the loops and by faer (`dense::gram_lower` picks one by size).
fn gram(c: &mut Criterion) {
    let mut group = configure(c, "gram");
    for n in [5, 23, 43, 83] {
        let (k, s) = (n + 2, 3 * n);
        let y = entries(k * s, s as u64);
        let mut out = vec![0.0; s * s];
        group.bench_with_input(BenchmarkId::new("hand", s), &s, |bench, &s| {
            bench.iter(|| {
                dense::gram_lower_by_hand(&y, k, s, &mut out);
                black_box(&out);
            })
        });
        group.bench_with_input(BenchmarkId::new("faer", s), &s, |bench, &s| {
            bench.iter(|| {
                dense::gram_lower_faer(
                    dense::rows_mut(&mut out, s, s, s),
                    dense::rows(&y, k, s, s),
                );
                black_box(&out);
            })
        });
    }
    group.finish();
}

criterion_group!(benches, cholesky, lu, nullspace, gram);
criterion_main!(benches);
