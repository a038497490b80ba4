//! The offline commands, each the thin shell of one CLI command: read files, call the pure
//! modules, print. No calibration logic and no Moonraker session here. The benchmarks and their
//! simulators are in their own crate (`crates/klipcal-bench`), not in the printer's binary.

pub mod backlash;
pub mod install;
pub mod mesh;
pub mod pylons;
pub mod soak;
pub mod solve;

/// `klipcal macros --readme --write FILE`: puts the operations table into FILE between its
/// markers, the rest of the file as it was; a file left unchanged is not written.
///
/// # Errors
/// A file that cannot be read or written, or one without the markers (the message says which).
pub(crate) fn write_operations_table(path: &std::path::Path, table: &str) -> anyhow::Result<()> {
    use anyhow::Context;
    let page =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let new = crate::jobs::table::with_table(&page, table)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    if new == page {
        println!(
            "{}: the operations table is already current",
            path.display()
        );
        return Ok(());
    }
    std::fs::write(path, new).with_context(|| format!("writing {}", path.display()))?;
    println!("{}: operations table written", path.display());
    Ok(())
}
