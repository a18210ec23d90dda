//! (to be written)
pub struct SolveOptions;
pub fn solve() {}
