//! softc compiler: front end (pest grammar → AST with spans), semantic analysis (names, types,
//! units, bounds), and later the kernel IR, passes and backends.
