//! tests/run-all.sh, the one test command README.md names (and .ci/run runs), runs every kind
//! of test: checked by running the script with a recording stand-in for `cargo` first on PATH,
//! and one for the cross test (tests/cross/run.sh, which uses Debian's cargo, not the one on
//! PATH).

use std::os::unix::fs::PermissionsExt;
use std::process::Command;

use crate::bench::repo;

#[test]
fn run_all_also_runs_the_documentation_examples() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("cargo.log");
    let fake = dir.path().join("cargo");
    let host_log = dir.path().join("host.log");
    std::fs::write(
        &fake,
        format!(
            "#!/bin/sh\necho \"$*\" >> '{}'\n\
             [ -n \"$KLIPCAL_KLIPPY\" ] && echo \"$KLIPCAL_KLIPPY: $*\" >> '{}'\nexit 0\n",
            log.display(),
            host_log.display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
    let cross_log = dir.path().join("cross.log");
    let cross = dir.path().join("cross-run.sh");
    std::fs::write(
        &cross,
        format!("#!/bin/sh\necho cross >> '{}'\n", cross_log.display()),
    )
    .unwrap();
    std::fs::set_permissions(&cross, std::fs::Permissions::from_mode(0o755)).unwrap();
    let path = format!(
        "{}:{}",
        dir.path().display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let out = Command::new("bash")
        .arg(repo().join("tests/run-all.sh"))
        .env("PATH", path)
        .env("KLIPCAL_CROSS_TEST", &cross)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let calls = std::fs::read_to_string(&log).unwrap();
    let calls: Vec<&str> = calls.lines().collect();
    assert!(
        calls
            .iter()
            .any(|c| c.starts_with("test --workspace --all-targets")),
        "{calls:?}"
    );
    assert!(
        calls
            .iter()
            .any(|c| c.starts_with("clippy -p klipcal --lib --bins")),
        "run-all.sh must lint the printer's build (the daemon alone) too: {calls:?}"
    );
    assert!(
        calls
            .iter()
            .any(|c| c.split_whitespace().eq(["test", "--workspace", "--doc"])),
        "run-all.sh must run `cargo test --doc` (--all-targets skips doctests): {calls:?}"
    );
    // The Klipper-facing integration tests run a second time on Kalico.
    let kalico = std::fs::read_to_string(&host_log).unwrap_or_default();
    let kalico: Vec<&str> = kalico.lines().collect();
    assert_eq!(kalico.len(), 1, "{kalico:?}");
    for name in [
        "kalico: test -p klipcal --test it",
        "hosts::",
        "session::",
        "skew::",
        "mesh_job::",
    ] {
        assert!(kalico[0].contains(name), "{name}: {kalico:?}");
    }
    for name in ["backlash_job::", "faults::", "install::"] {
        assert!(kalico[0].contains(name), "{name}: {kalico:?}");
    }
    assert_eq!(
        std::fs::read_to_string(&cross_log).unwrap_or_default(),
        "cross\n",
        "run-all.sh must run the cross test (tests/cross/run.sh) once"
    );
    let script = std::fs::read_to_string(repo().join("tests/run-all.sh")).unwrap();
    assert!(script.contains("tests/cross/run.sh"), "{script}");
    // README names the script as the test command.
    let readme = std::fs::read_to_string(repo().join("README.md")).unwrap();
    assert!(readme.contains("./tests/run-all.sh"));
}
