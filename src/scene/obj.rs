//! OBJ + MTL reader.
