//! Benchmarks run by `klipcal bench …`: each prints its measured figure beside its target.

/// `klipcal bench metrology`: runs the closed-loop simulation of `calib::bench_metrology`,
/// prints every figure beside its target and the wall time; fails when a target is missed.
///
/// # Errors
/// None today; the signature matches the other commands.
pub fn metrology(args: &crate::cli::MetrologyArgs) -> anyhow::Result<std::process::ExitCode> {
    use crate::calib::bench_metrology::{all_targets_met, format_report, run, BenchConfig};
    let cfg = BenchConfig {
        machines: args.machines.max(1),
        seed: args.seed,
        max_prints: args.max_prints.max(1),
        ..BenchConfig::default()
    };
    let started = std::time::Instant::now();
    let reports = run(&cfg);
    print!("{}", format_report(&reports));
    println!(
        "wall time: {:.1} s for {} machines × 4 scenarios",
        started.elapsed().as_secs_f64(),
        cfg.machines
    );
    Ok(if all_targets_met(&reports) {
        std::process::ExitCode::SUCCESS
    } else {
        std::process::ExitCode::FAILURE
    })
}
