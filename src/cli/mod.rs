//! Pieces of the `mbfg` command line that are not argument parsing: where outputs
//! go, and what Ctrl-C and panics turn into.

pub mod interrupt;
pub mod output;
pub mod panic;
