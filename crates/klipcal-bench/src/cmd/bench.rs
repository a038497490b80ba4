//! Benchmarks run by `klipcal bench …`: each prints its measured figure beside its target and
//! the anchor it is compared with, all measured in the same run.

use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Context;

use crate::cli::FootprintArgs;

/// Resident memory (kB) and total CPU time (clock ticks) of a process, from /proc.
fn sample(pid: u32) -> anyhow::Result<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .with_context(|| format!("process {pid} is not running"))?;
    let rss_kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .with_context(|| format!("no VmRSS for process {pid}"))?;
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .with_context(|| format!("process {pid} is not running"))?;
    // Fields after the command name (which may hold spaces) start after the last ')'.
    let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or_default();
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(0)
    };
    // utime and stime are fields 14 and 15 of stat, i.e. 11 and 12 after the state field.
    Ok((rss_kb, ticks(11) + ticks(12)))
}

/// A process's anonymous resident memory (heap, stacks: what the kernel cannot drop and reload
/// from a file), KiB.
fn anon_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("RssAnon:"))
                .and_then(|v| v.split_whitespace().next())
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0)
}

/// `klipcal bench footprint`: samples the daemon's RSS and CPU for the given time beside
/// Moonraker's and klippy's RSS. Targets: klipcal at most 1/10 of Moonraker's RSS and below 0.5 %
/// of one core on average.
///
/// # Errors
/// A process that is not running.
pub(crate) async fn footprint(a: &FootprintArgs) -> anyhow::Result<ExitCode> {
    const TICKS_PER_S: f64 = 100.0; // Linux USER_HZ
    let start = Instant::now();
    let (_, cpu0) = sample(a.klipcal_pid)?;
    let mut peak = [0u64; 3];
    let mut sum = [0u64; 3];
    let mut n = 0u64;
    let end = start + Duration::from_secs_f64(a.seconds);
    // An open page: what its script fetches, on its schedule.
    let page = a
        .page_url
        .clone()
        .map(|url| tokio::spawn(poll_like_the_page(url)));
    while Instant::now() < end {
        for (i, pid) in [a.klipcal_pid, a.moonraker_pid, a.klippy_pid]
            .iter()
            .enumerate()
        {
            let (rss, _) = sample(*pid)?;
            peak[i] = peak[i].max(rss);
            sum[i] += rss;
        }
        n += 1;
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    if let Some(p) = page {
        p.abort();
    }
    let (_, cpu1) = sample(a.klipcal_pid)?;
    let wall = start.elapsed().as_secs_f64();
    let cpu_pct = (cpu1 - cpu0) as f64 / TICKS_PER_S / wall * 100.0;
    let mean = |i: usize| sum[i] as f64 / n.max(1) as f64 / 1024.0;
    let ratio = mean(0) / mean(1);
    println!("footprint over {wall:.1} s ({n} samples)");
    println!(
        "  klipcal   RSS mean {:7.1} MiB, peak {:7.1} MiB",
        mean(0),
        peak[0] as f64 / 1024.0
    );
    println!(
        "  moonraker RSS mean {:7.1} MiB, peak {:7.1} MiB   (anchor)",
        mean(1),
        peak[1] as f64 / 1024.0
    );
    println!(
        "  klippy    RSS mean {:7.1} MiB, peak {:7.1} MiB   (anchor)",
        mean(2),
        peak[2] as f64 / 1024.0
    );
    let (anon_k, anon_m) = (anon_kib(a.klipcal_pid), anon_kib(a.moonraker_pid));
    println!(
        "  anonymous memory: klipcal {:.1} MiB, moonraker {:.1} MiB (anchor), ratio {:.3}   \
         (the rest of RSS is read-only code mapped from the binary and shared libraries)",
        anon_k as f64 / 1024.0,
        anon_m as f64 / 1024.0,
        anon_k as f64 / anon_m.max(1) as f64
    );
    let rss_ok = ratio <= 0.1;
    let cpu_ok = cpu_pct < 0.5;
    println!(
        "  page       {}",
        if a.page_url.is_some() {
            "open (status every 3 s, soak plot every 15 s)"
        } else {
            "not open"
        }
    );
    println!(
        "  klipcal/moonraker RSS {:.3}   target <= 0.100   {}",
        ratio,
        if rss_ok { "PASS" } else { "FAIL" }
    );
    println!(
        "  klipcal CPU {:.3} % of a core   target < 0.5 %   {}",
        cpu_pct,
        if cpu_ok { "PASS" } else { "FAIL" }
    );
    let small_ok = small_and_quick(a)?;
    Ok(if rss_ok && cpu_ok && small_ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// What klipcal's page fetches while open: the status every 3 s, the soak plot every 15 s,
/// the page itself every minute (failures counted and said).
async fn poll_like_the_page(url: String) {
    let client = reqwest::Client::new();
    let mut tick = 0u64;
    let mut failures = 0u64;
    loop {
        let base = url.trim_end_matches('/');
        let mut paths = vec!["/api/status"];
        if tick % 5 == 0 {
            paths.push("/api/plots/soak.svg");
        }
        if tick % 20 == 0 {
            paths.push("/");
        }
        for p in paths {
            let ok = client
                .get(format!("{base}{p}"))
                .send()
                .await
                .is_ok_and(|r| r.status().is_success());
            failures += u64::from(!ok);
        }
        tick += 1;
        if tick % 20 == 1 && failures > 0 {
            eprintln!("footprint: {failures} page request(s) failed so far");
        }
        tokio::time::sleep(Duration::from_secs(3)).await;
    }
}

/// The binary's size (at most 20 MiB) and the start-up time to "connected to Moonraker" (at
/// most 2 s), when given; whether both are met.
fn small_and_quick(a: &FootprintArgs) -> anyhow::Result<bool> {
    let mut small_ok = true;
    if let Some(bin) = &a.binary {
        let size = std::fs::metadata(bin)
            .with_context(|| format!("reading {}", bin.display()))?
            .len() as f64
            / 1024.0
            / 1024.0;
        small_ok &= size <= 20.0;
        println!(
            "  binary {size:.1} MiB ({})   target <= 20 MiB   {}",
            bin.display(),
            if size <= 20.0 { "PASS" } else { "FAIL" }
        );
    }
    if let Some(ms) = a.startup_ms {
        small_ok &= ms <= 2000.0;
        println!(
            "  start to \"connected to Moonraker\" {ms:.0} ms   target <= 2000 ms   {}",
            if ms <= 2000.0 { "PASS" } else { "FAIL" }
        );
    }
    Ok(small_ok)
}

/// `klipcal bench metrology`: runs the closed-loop simulation of `calib::bench_metrology`,
/// prints every figure beside its target and the wall time; fails when a target is missed.
///
/// # Errors
/// None today; the signature matches the other commands.
pub(crate) fn metrology(
    args: &crate::cli::MetrologyArgs,
) -> anyhow::Result<std::process::ExitCode> {
    use crate::bench_metrology::{all_targets_met, format_report, run, BenchConfig};
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
