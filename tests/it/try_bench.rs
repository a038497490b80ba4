//! "Try it on a simulated printer" in docs/development.md (issue 25 E): `scripts/try-bench.sh`
//! starts a simulated printer of each variant with the daemon, and a macro run by Klipper
//! reaches klipcal.

use std::process::Command;

use crate::bench::repo;

fn smoke(args: &[&str]) {
    let out = Command::new("bash")
        .arg(repo().join("scripts/try-bench.sh"))
        .args(args)
        .arg("--smoke")
        .env("KLIPCAL_BIN", env!("CARGO_BIN_EXE_klipcal"))
        .current_dir(repo())
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "try-bench.sh {args:?}: {text}");
    assert!(
        text.contains("klipcal answered KLIPCAL_STATUS through Klipper"),
        "{text}"
    );
}

#[test]
fn every_variant_of_the_readmes_simulated_printer_starts_and_reaches_klipcal() {
    smoke(&["ab"]);
    smoke(&["mesh"]);
    smoke(&["backlash", "--cartesian"]);
    // A typo is refused with what is expected, before anything starts.
    let out = Command::new("bash")
        .arg(repo().join("scripts/try-bench.sh"))
        .arg("meshh")
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("expected ab, mesh, backlash"));
}
