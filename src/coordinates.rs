//! The two coordinate choices of the paper, shared by the forward and the inverse
//! problem: dependent (natural) coordinates (DC) and independent coordinates (IC).

/// The coordinates a graph integrates (forward) or solves for (inverse).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coordinates {
    /// Dependent (natural) coordinates q.
    Dependent,
    /// Independent coordinates z ⊂ q, with q recovered by the position problem.
    Independent,
}
