//! Benchmarks run by `klipcal bench …`: each prints its measured figure beside its target.
