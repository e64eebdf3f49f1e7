//! Integration tests live in `tests/tests/`, benches in `tests/benches/`: whatever needs the
//! simulated world (`sim`) to test a crate below it (`estimator`, `hw-io`), which cannot
//! dev-depend on `sim` without a cycle. Unit tests stay beside the code they test.
