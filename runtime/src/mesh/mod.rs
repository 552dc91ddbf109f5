//! Tetrahedral meshes: model, readers/writers, mesher, validation (issue 3).
