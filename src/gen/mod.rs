//! Scene generators: the Cornell box and procedural scenes of any size, for examples and tests.
