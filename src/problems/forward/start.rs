//! Where a forward run, or a segment of one, starts ([`Start`]): the state its
//! graph's initial priors hold and the independent coordinates it integrates in IC.

use crate::model::{Model, State};

/// The start of a forward run or of one of its segments: a later segment starts
/// from the state the one before ended with, in the coordinates it re-selected; a
/// failed step's substeps start from the step before. The model itself holds only
/// the scene's own start ([`Start::of`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Start {
    /// Positions and velocities at the start.
    pub state: State,
    /// The independent coordinates z of a graph in IC (indices into q, in z's
    /// order); unused in DC.
    pub independent: Vec<usize>,
}

impl Start {
    /// The scene's start: its assembled initial state and its declared independent
    /// coordinates.
    pub fn of(model: &Model) -> Start {
        Start {
            state: model.initial.clone(),
            independent: model.independent.clone(),
        }
    }
}
