//! The problems mbfg solves on a factor graph: forward dynamics (the motion from
//! the forces, [`forward`]) and inverse dynamics (the forces from a prescribed
//! motion, [`inverse`]).

pub mod estimate;
pub mod forward;
pub mod inverse;
mod prediction;
