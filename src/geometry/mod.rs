//! Integer line directions with exact solid angles, discrete lines and lexicographic orders.
