//! The grouped Householder QR under the null-space reduction: reflectors that stay
//! within their segment's rows, columns pivoted within their group.

use super::*;

/// Marks a column of the QR found dependent.
pub(super) const DROPPED: usize = usize::MAX;

/// How the columns of a grouped QR are grouped: per column its group (a segment),
/// per segment the end of its rows; filled in, per reflector the end of its rows,
/// and per group the reflectors it made and whether it stands apart (see
/// [`householder_grouped`]).
pub(super) struct Grouping<'a> {
    pub(super) group: &'a mut [usize],
    pub(super) seg_end: &'a [usize],
    pub(super) rend: &'a mut [usize],
    pub(super) made: &'a mut Vec<GroupReflectors>,
}

/// The reflectors ks..ke of one group; `apart` when they span exactly its segment's
/// rows (nothing left of earlier segments, the segment fully determined): they were
/// not applied to the later groups' columns, whose rows there keep C's coefficients.
#[derive(Debug, Clone, Copy)]
pub(super) struct GroupReflectors {
    pub(super) ks: usize,
    pub(super) ke: usize,
    pub(super) apart: bool,
}

// Kept hand-written although faer's column-pivoted QR is faster on one dense segment
// from s ≈ 16 on (`benches/linalg.rs`, group `nullspace`: faer/hand 1.3–1.8 at s ≤ 8,
// 0.9 at 16–32, 0.3 at 70–120): faer pivots over all columns and blocks its
// reflectors, so it cannot pivot segment by segment, stop a reflector at its
// segment's rows or leave a group apart, which the solver's reductions rely on.
/// Householder QR with column pivoting of the column-major `s` × `m` matrix `a`,
/// group by group: the pivot is the column of largest remaining norm in the current
/// group, whose columns are 0 past their segment's rows, so its reflectors and their
/// updates stop there. A group ends at its first pivot below
/// [`NullSpace::RANK_TOLERANCE`] relative to the largest column (its other columns
/// are dependent). A group's reflectors reach the later groups' columns only when
/// they must: when the group leaves rows of its segment (or found rows of earlier
/// ones) for the later groups; when it determines exactly its segment's rows, the
/// later columns keep C's coefficients there, and [`NullSpace::solve`] substitutes
/// the segment's solution into them instead. Returns the rank. With one group this
/// is the plain pivoted QR, operation for operation. Reflectors stay below the
/// diagonal, R above it with its diagonal in `rdiag`; `perm[k]` is the original
/// column now at k. Column norms are downdated, and recomputed when cancellation has
/// eaten most of them.
///
/// A large mechanism's equations touch a few unknowns each, and many reflectors
/// never meet many columns: `support` (at least (m + 1) × ⌈s/64⌉ words) tracks per
/// column a superset of its nonzero rows, and a reflector whose rows miss a
/// column's is not applied to it. Its product would be a sum of exact zeros, so the
/// result is the same to the bit. An empty `support` tracks nothing (below
/// [`TRACK_SUPPORT_FROM`] rows the tracking costs more than it saves).
#[allow(clippy::too_many_arguments)]
pub(super) fn householder_grouped(
    a: &mut [f64],
    s: usize,
    m: usize,
    grouping: Grouping,
    how: Summation,
    rdiag: &mut [f64],
    beta: &mut [f64],
    perm: &mut [usize],
    norms: &mut [f64],
    sparsity: Sparsity,
) -> usize {
    let Sparsity {
        support,
        starts,
        ends,
        order,
        nonzeros,
    } = sparsity;
    let Grouping {
        group,
        seg_end,
        rend,
        made,
    } = grouping;
    made.clear();
    if m == 0 || s == 0 {
        return 0;
    }
    let (partial, reference) = norms.split_at_mut(m);
    let words = if support.is_empty() {
        0
    } else {
        s.div_ceil(64)
    };
    let (support, mask) = support[..(m + 1) * words].split_at_mut(m * words);
    let mut largest = 0.0f64;
    for j in 0..m {
        perm[j] = j;
        let col = &a[j * s..(j + 1) * s];
        // A sequential sum over the nonzeros alone is the sum over all, to the bit.
        let mut n2 = None;
        if words > 0 {
            let sj = &mut support[j * words..(j + 1) * words];
            sj.fill(0);
            (starts[j], ends[j]) = (s, 0);
            let mut sum = 0.0;
            let mut add = |i: usize, v: f64| {
                sj[i / 64] |= 1 << (i % 64);
                starts[j] = starts[j].min(i);
                ends[j] = i + 1;
                sum += v * v;
            };
            match nonzeros {
                Some((rows, bounds)) => {
                    for &i in &rows[bounds[j]..bounds[j + 1]] {
                        add(i, col[i]);
                    }
                }
                None => {
                    for (i, v) in col.iter().enumerate() {
                        if *v != 0.0 {
                            add(i, *v);
                        }
                    }
                }
            }
            n2 = (how == Summation::Sequential).then_some(sum);
        }
        let n2 = n2.unwrap_or_else(|| dot(col, col, how));
        partial[j] = n2;
        reference[j] = n2;
        largest = largest.max(n2);
    }
    let tol2 = (NullSpace::RANK_TOLERANCE * largest.sqrt()).powi(2);
    let groups = seg_end.len();
    let mut k = 0;
    for g in 0..groups {
        let end = seg_end[g];
        let start = if g > 0 { seg_end[g - 1] } else { 0 };
        let ks = k;
        // The group's columns lie before `ge` and stay there: a pivot's swap moves
        // the column at k, a dropped one or one of the group, to the pivot's place.
        // The searches and updates of the group's own columns stop there.
        let ge = (k..m).rev().find(|&j| group[j] == g).map_or(k, |j| j + 1);
        if groups > 1 {
            // Norms over the live rows (earlier groups' reflectors may not have
            // reached these columns).
            for j in k..ge {
                if group[j] == g {
                    // Within the column's rows where they are tracked (the same sum).
                    let (lo, hi) = if words > 0 && how == Summation::Sequential {
                        (k.max(starts[j]), end.min(ends[j]).max(k.max(starts[j])))
                    } else {
                        (k, end)
                    };
                    let live = &a[j * s + lo..j * s + hi];
                    partial[j] = dot(live, live, how);
                    reference[j] = partial[j];
                }
            }
        }
        while k < s.min(m) {
            let mut best = None;
            for j in k..ge {
                if group[j] == g && best.is_none_or(|b| partial[j] > partial[b]) {
                    best = Some(j);
                }
            }
            let largest_left = best;
            let exhausted = match best {
                None => true,
                Some(b) if partial[b] <= tol2 => {
                    // Confirm with exact norms before declaring the rest dependent.
                    let live = &a[b * s + k..b * s + end];
                    let exact = dot(live, live, how);
                    if exact <= tol2 {
                        true
                    } else {
                        partial[b] = exact;
                        false
                    }
                }
                Some(_) => false,
            };
            if exhausted {
                for gj in group[k..ge].iter_mut().filter(|gj| **gj == g) {
                    *gj = DROPPED;
                }
                break;
            }
            let mut best = best.expect("a column of the group");
            if words > 0 && order {
                best = sparse_pivot(partial, group, g, (k, ge), largest_left, |j| {
                    (ends[j], first_row(&support[j * words..(j + 1) * words], k))
                });
            }
            if best != k {
                // Rows outside both columns' tracked ranges are 0 in both.
                let (lo, hi) = if words > 0 {
                    (starts[k].min(starts[best]), ends[k].max(ends[best]))
                } else {
                    (0, s)
                };
                for i in lo..hi {
                    a.swap(k * s + i, best * s + i);
                }
                for w in 0..words {
                    support.swap(k * words + w, best * words + w);
                }
                if words > 0 {
                    starts.swap(k, best);
                    ends.swap(k, best);
                }
                perm.swap(k, best);
                partial.swap(k, best);
                reference.swap(k, best);
                group.swap(k, best);
            }
            let col = &mut a[k * s + k..k * s + end];
            let norm = dot(col, col, how).sqrt();
            let alpha = if col[0] > 0.0 { -norm } else { norm };
            col[0] -= alpha;
            let vnorm2 = dot(col, col, how);
            let b = if vnorm2 > 0.0 { 2.0 / vnorm2 } else { 0.0 };
            rdiag[k] = alpha;
            beta[k] = b;
            let v_end = reflector_rows(support, k, end, words, mask);
            // Applied later over its own rows only (the rest of the segment's are
            // exact zeros, which sequential sums lose to the bit).
            rend[k] = if how == Summation::Sequential {
                v_end
            } else {
                end
            };
            let (left, right) = a.split_at_mut((k + 1) * s);
            let v = &left[k * s + k..k * s + end];
            for (jj, y) in right.chunks_exact_mut(s).take(ge - k - 1).enumerate() {
                let j = k + 1 + jj;
                // This group's columns now; the later ones below, if at all. A column
                // whose rows miss the reflector's is 0 on row k too: nothing changes
                // (and its entries stay out of the cache).
                if group[j] != g || (words > 0 && (starts[j] >= v_end || ends[j] <= k)) {
                    continue;
                }
                let live = &mut y[k..end];
                if let Some((lo, hi)) = overlap(
                    &mut support[j * words..(j + 1) * words],
                    mask,
                    (k, end),
                    how,
                ) {
                    if words > 0 {
                        starts[j] = starts[j].min(k);
                        ends[j] = ends[j].max(v_end);
                    }
                    let f = b * dot(&v[lo - k..hi - k], &live[lo - k..hi - k], how);
                    let reach = v_end - k;
                    for (yi, vi) in live[..reach].iter_mut().zip(&v[..reach]) {
                        *yi -= f * vi;
                    }
                }
                // Downdate the partial norm of rows k+1.. of this column.
                partial[j] -= live[0] * live[0];
                if partial[j] < 1e-4 * reference[j] {
                    partial[j] = dot(&y[k + 1..], &y[k + 1..], how);
                    reference[j] = partial[j];
                }
            }
            k += 1;
        }
        let apart = ks == start && k == end;
        if !apart && g + 1 < groups {
            // The later groups' columns see this group's reflectors, in order.
            for r in ks..k {
                let v_end = reflector_rows(support, r, end, words, mask);
                let (left, right) = a.split_at_mut((r + 1) * s);
                let v = &left[r * s + r..r * s + end];
                for (jj, y) in right.chunks_exact_mut(s).take(m - r - 1).enumerate() {
                    let j = r + 1 + jj;
                    if group[j] == DROPPED
                        || group[j] <= g
                        || (words > 0 && (starts[j] >= v_end || ends[j] <= r))
                    {
                        continue;
                    }
                    let Some((lo, hi)) = overlap(
                        &mut support[j * words..(j + 1) * words],
                        mask,
                        (r, end),
                        how,
                    ) else {
                        continue;
                    };
                    if words > 0 {
                        starts[j] = starts[j].min(r);
                        ends[j] = ends[j].max(v_end);
                    }
                    let live = &mut y[r..end];
                    let f = beta[r] * dot(&v[lo - r..hi - r], &live[lo - r..hi - r], how);
                    let reach = v_end - r;
                    for (yi, vi) in live[..reach].iter_mut().zip(&v[..reach]) {
                        *yi -= f * vi;
                    }
                }
            }
        }
        made.push(GroupReflectors { ks, ke: k, apart });
        if k == s.min(m) {
            break;
        }
    }
    k
}

/// The column supports a large mechanism's QR tracks (see [`householder_grouped`]):
/// per column a superset of its nonzero rows (bits), with room for one reflector's
/// rows after them, and the range of those rows (first, one past the last); and
/// whether the pivots follow the supports ([`SPARSE_PIVOT`]). An empty `support`
/// tracks nothing.
pub(super) struct Sparsity<'a> {
    pub(super) support: &'a mut [u64],
    pub(super) starts: &'a mut [usize],
    pub(super) ends: &'a mut [usize],
    pub(super) order: bool,
    /// Each column's nonzero rows, ascending, where the caller knows them
    /// (column j's are rows[bounds[j]..bounds[j + 1]]): the support is made from
    /// them instead of a scan of the column.
    pub(super) nonzeros: Option<(&'a [usize], &'a [usize])>,
}

/// A pivot this close to the largest column left (its remaining norm at least this
/// fraction of the largest) is as good a pivot for a large mechanism's QR: the
/// rank test and the damped corrections still see the largest, and the pivots taken
/// stay well away from 0. Among those, [`householder_grouped`] takes the column
/// whose rows end first, so that each reflector stays within the band of unknowns
/// its equation touches: a chain's equations are then factored along the chain,
/// each reflector a few rows long, where the largest-norm order jumps along it and
/// fills the factors.
pub(super) const SPARSE_PIVOT: f64 = 0.1;

/// The pivot among the group's columns `range` (of group `g`) whose remaining norm
/// (squared, `partial`) is at least [`SPARSE_PIVOT`] of the largest one's
/// (`largest`): the one whose rows (`extent`: last, first) end first, then start
/// first; on a tie, the larger.
fn sparse_pivot(
    partial: &[f64],
    group: &[usize],
    g: usize,
    (k, m): (usize, usize),
    largest: Option<usize>,
    first: impl Fn(usize) -> (usize, usize),
) -> usize {
    let largest = largest.expect("a column of the group");
    let floor = SPARSE_PIVOT * SPARSE_PIVOT * partial[largest];
    let mut pick = (first(largest), largest);
    for j in k..m {
        if j == largest || group[j] != g || partial[j] < floor {
            continue;
        }
        let row = first(j);
        if row < pick.0 || (row == pick.0 && partial[j] > partial[pick.1]) {
            pick = (row, j);
        }
    }
    pick.1
}

/// The first row from `k` on in a column's support bits (`usize::MAX` if none).
fn first_row(bits: &[u64], k: usize) -> usize {
    let mut w = k / 64;
    let mut word = bits.get(w).map_or(0, |b| b & (!0u64 << (k % 64)));
    while word == 0 {
        w += 1;
        match bits.get(w) {
            Some(b) => word = *b,
            None => return usize::MAX,
        }
    }
    w * 64 + word.trailing_zeros() as usize
}

/// The number of rows from which [`householder_grouped`] tracks the columns'
/// supports: it slows a small mechanism's QR and speeds up a long chain's.
pub(super) const TRACK_SUPPORT_FROM: usize = 48;

/// The rows reflector k (made from column k, on rows k..end) can be nonzero on:
/// column k's support within them, and row k, into `mask`; returns the end of the
/// last of them (`end` untracked).
fn reflector_rows(support: &[u64], k: usize, end: usize, words: usize, mask: &mut [u64]) -> usize {
    if words == 0 {
        return end;
    }
    mask.copy_from_slice(&support[k * words..(k + 1) * words]);
    for (w, bits) in mask.iter_mut().enumerate() {
        let (lo, hi) = (w * 64, w * 64 + 64);
        if hi <= k || lo >= end {
            *bits = 0;
            continue;
        }
        if lo < k {
            *bits &= !0u64 << (k - lo);
        }
        if hi > end {
            *bits &= !0u64 >> (hi - end);
        }
    }
    mask[k / 64] |= 1 << (k % 64);
    last_row(mask).map_or(end, |r| r + 1)
}

/// The last row set in `bits`.
fn last_row(bits: &[u64]) -> Option<usize> {
    let w = bits.iter().rposition(|b| *b != 0)?;
    Some(w * 64 + 63 - bits[w].leading_zeros() as usize)
}

/// The rows [lo, hi) outside which a column with support `column` and a reflector
/// with rows `mask` have no nonzero in common, or None where they have none (the
/// whole reflector's rows `rows` untracked, or with sums taken in lanes, whose
/// grouping depends on where a sum starts). Where they meet, the reflector may fill
/// the column on its rows: its support grows by them.
fn overlap(
    column: &mut [u64],
    mask: &[u64],
    rows: (usize, usize),
    how: Summation,
) -> Option<(usize, usize)> {
    if mask.is_empty() {
        return Some(rows);
    }
    // The mask is 0 outside the words of the reflector's rows.
    let (w0, w1) = (rows.0 / 64, rows.1.div_ceil(64).min(mask.len()));
    let (column, mask) = (&mut column[w0..w1], &mask[w0..w1]);
    let first = column.iter().zip(mask).position(|(c, m)| c & m != 0)?;
    let lo = (w0 + first) * 64 + (column[first] & mask[first]).trailing_zeros() as usize;
    let last = column.iter().zip(mask).rposition(|(c, m)| c & m != 0)?;
    let hi = (w0 + last) * 64 + 64 - (column[last] & mask[last]).leading_zeros() as usize;
    for (c, m) in column.iter_mut().zip(mask) {
        *c |= m;
    }
    match how {
        Summation::Sequential => Some((lo, hi)),
        Summation::Lanes => Some(rows),
    }
}

/// x ← H₀ H₁ … H_{r−1} x with the reflectors stored below the diagonal of `a`
/// (reflector k nonzero on rows k..rend[k]), leaving out the groups apart (their
/// rows are 0 in the null-space vectors, and `solve` applies them itself).
#[allow(clippy::too_many_arguments)]
pub(super) fn apply_q(
    a: &[f64],
    beta: &[f64],
    rend: &[usize],
    made: &[GroupReflectors],
    s: usize,
    x: &mut [f64],
    how: Summation,
) {
    for g in made.iter().rev().filter(|g| !g.apart) {
        for k in (g.ks..g.ke).rev() {
            let end = rend[k];
            let v = &a[k * s + k..k * s + end];
            let y = &mut x[k..end];
            let f = beta[k] * dot(v, y, how);
            for (yi, vi) in y.iter_mut().zip(v) {
                *yi -= f * vi;
            }
        }
    }
}

/// X ← H₀ H₁ … H_{r−1} X for the `q` columns X[:, c] = e_{r+c} at once (`x`
/// row-major, `sf` × `q`, overwritten): the null-space basis of the last QR, with
/// the sums of each column taken exactly as [`apply_q`] takes them for one vector.
/// A column is still its unit vector until a reflector reaches its row, and so is
/// left out until then; the rows of the others are swept once per reflector, all
/// columns together, instead of once per column.
#[allow(clippy::too_many_arguments)]
pub(super) fn apply_q_columns(
    a: &[f64],
    beta: &[f64],
    rend: &[usize],
    made: &[GroupReflectors],
    sf: usize,
    r: usize,
    q: usize,
    x: &mut [f64],
    sums: &mut Vec<f64>,
    how: Summation,
) {
    let x = &mut x[..sf * q];
    x.fill(0.0);
    for c in 0..q {
        x[(r + c) * q + c] = 1.0;
    }
    if sums.len() < 5 * q {
        sums.resize(5 * q, 0.0);
    }
    // Columns 0..active have met a reflector; the rest are still e_{r+c}.
    let mut active = 0;
    for g in made.iter().rev().filter(|g| !g.apart) {
        for k in (g.ks..g.ke).rev() {
            let end = rend[k];
            active = active.max(end.saturating_sub(r)).min(q);
            if active == 0 {
                continue;
            }
            let v = &a[k * sf + k..k * sf + end];
            let (lanes, tail) = sums.split_at_mut(4 * q);
            let (lanes, tail) = (&mut lanes[..4 * active], &mut tail[..active]);
            // f[c] = β vᵀ X[k..end, c], summed as `dot` sums one column.
            let full = match how {
                Summation::Sequential => 0,
                Summation::Lanes => v.len() / 4 * 4,
            };
            lanes.fill(0.0);
            tail.fill(-0.0);
            for (t, vt) in v.iter().enumerate() {
                let row = &x[(k + t) * q..(k + t) * q + active];
                let acc = if t < full {
                    &mut lanes[(t % 4) * active..(t % 4 + 1) * active]
                } else {
                    &mut *tail
                };
                for (s, xv) in acc.iter_mut().zip(row) {
                    *s += vt * xv;
                }
            }
            for c in 0..active {
                let d = match how {
                    Summation::Sequential => tail[c],
                    Summation::Lanes => {
                        let l = |i: usize| lanes[i * active + c];
                        (l(0) + l(1)) + (l(2) + l(3)) + tail[c]
                    }
                };
                tail[c] = beta[k] * d;
            }
            for (t, vt) in v.iter().enumerate() {
                let row = &mut x[(k + t) * q..(k + t) * q + active];
                for (xv, f) in row.iter_mut().zip(tail.iter()) {
                    *xv -= f * vt;
                }
            }
        }
    }
}
