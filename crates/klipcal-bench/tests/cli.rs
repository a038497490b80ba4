//! The benchmarks' binary as `klipcal bench …` reaches it: every benchmark is listed, and an
//! unknown one is refused with the list. (An integration test also makes `cargo test
//! --workspace` build `target/<profile>/klipcal-bench`, the binary the daemon's tests exec.)

use std::process::Command;

const BENCHMARKS: [&str; 6] = [
    "footprint",
    "metrology",
    "soak",
    "mesh",
    "backlash",
    "camera",
];

#[test]
fn help_lists_every_benchmark() {
    let out = Command::new(env!("CARGO_BIN_EXE_klipcal-bench"))
        .arg("--help")
        .output()
        .unwrap();
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for name in BENCHMARKS {
        assert!(
            help.lines().any(|l| l.trim_start().starts_with(name)),
            "{name} missing from --help:\n{help}"
        );
    }
}

#[test]
fn an_unknown_benchmark_is_refused_with_what_exists() {
    let out = Command::new(env!("CARGO_BIN_EXE_klipcal-bench"))
        .arg("thermal")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unrecognized subcommand 'thermal'"), "{err}");
}
