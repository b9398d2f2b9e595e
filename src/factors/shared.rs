//! What the factor families share: the `keys` accessor, the identity block of a
//! Jacobian and y = A x.

/// The `keys` method every factor here answers from its own field.
macro_rules! key_accessor {
    () => {
        fn keys(&self) -> &[Key] {
            &self.keys
        }
    };
}
pub(crate) use key_accessor;

/// Writes `scale`·I into a row-major d × d block.
pub(crate) fn identity(block: &mut [f64], d: usize, scale: f64) {
    block.fill(0.0);
    for i in 0..d {
        block[i * d + i] = scale;
    }
}

/// y = A x for a row-major rows × cols A.
pub(super) fn mat_vec(a: &[f64], rows: usize, cols: usize, x: &[f64], y: &mut [f64]) {
    for i in 0..rows {
        y[i] = (0..cols).map(|j| a[i * cols + j] * x[j]).sum();
    }
}

/// How many of the c columns of the row-major direction blocks `dirs` are nonzero
/// somewhere.
pub(super) fn nonzero_columns(dirs: &[&[f64]], c: usize) -> usize {
    (0..c)
        .filter(|&j| {
            dirs.iter()
                .any(|v| v.chunks_exact(c).any(|row| row[j] != 0.0))
        })
        .count()
}
