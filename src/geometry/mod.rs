//! Integer line directions with exact solid angles, discrete lines and lexicographic orders.
//!
//! `directions` builds the direction set (integer vectors on a cube surface, weighted by the exact
//! solid angle of their cell); `lines` maps a voxel to its discrete line `(i, j)` for a direction;
//! `order` gives the lexicographic traversal in which every line comes out sorted along its
//! direction.

pub mod directions;
pub mod lines;
pub mod order;
