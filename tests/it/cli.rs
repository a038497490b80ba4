//! The offline commands as a shell uses them: output piped into a reader that stops early.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

use crate::bench::klipcal_ok;

/// `klipcal bench soak | head -1`: the reader goes after one line; klipcal ends without a
/// panic message (it panicked with "failed printing to stdout: Broken pipe" before).
#[test]
fn an_offline_command_piped_into_a_reader_that_stops_early_ends_quietly() {
    let mut child = Command::new(crate::bench::klipcal_with_bench())
        .args(["bench", "soak", "--beds", "40"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    assert!(first.starts_with("bench soak"), "{first}");
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !stderr.contains("panicked") && !stderr.contains("Broken pipe"),
        "{stderr}"
    );
}

/// `klipcal soak-detect --klippy-log`: a real bed's heat-up (tests/fixtures/soak/real) written
/// back as Klipper logs it, config dump first, a timestamp before some lines. One hold at 80 °C
/// comes back with its length, the config's control and max_power (default 1.0), and the
/// declaration the detector makes on it.
#[test]
fn soak_detect_judges_each_hold_of_a_klippy_log() {
    let csv = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/soak/real/ryszardwpl-vzbot-old-1.csv"
    ))
    .unwrap();
    let mut log = String::from(
        "Starting Klippy...\n===== Config file =====\n[heater_bed]\ncontrol = pid\n\
         =======================\n",
    );
    for k in 0..30 {
        log += &format!(
            "Stats {}.0: gcodein=0 heater_bed: target=0 temp=22.0 pwm=0.000\n",
            1000 + k
        );
    }
    let mut last = 0.0;
    for (i, line) in csv
        .lines()
        .filter(|l| l.starts_with(|c: char| c.is_ascii_digit()))
        .enumerate()
    {
        let v: Vec<&str> = line.split(',').collect();
        let t: f64 = v[0].parse().unwrap();
        last = t;
        let stamp = if i % 2 == 0 { "12:25:06.344: " } else { "" };
        log += &format!(
            "{stamp}Stats {:.1}: gcodein=0 mcu: mcu_awake=0.003 heater_bed: target={} temp={} pwm={} sysload=0.1\n",
            1030.0 + t,
            v[3],
            v[2],
            v[1]
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("klippy.log");
    std::fs::write(&path, log).unwrap();
    // Judged twice: with the defaults (nothing known of the bed: the weakest coupling, decays up
    // to 60 min), then as an open frame (`soak.frame = "open"` in the settings file).
    let open = dir.path().join("klipcal.toml");
    std::fs::write(&open, "[soak]\nframe = \"open\"\n").unwrap();
    let judge = |config: Option<&std::path::Path>| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_klipcal"));
        cmd.args(["soak-detect", "--json", "--klippy-log"])
            .arg(&path);
        // No user settings file may leak in: the defaults are an explicit empty file.
        let empty = dir.path().join("empty.toml");
        std::fs::write(&empty, "").unwrap();
        cmd.arg("--config").arg(config.unwrap_or(&empty));
        let out = klipcal_ok(&mut cmd);
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let holds = v["holds"].as_array().unwrap().clone();
        assert_eq!(holds.len(), 1, "{v}");
        let h = holds[0].clone();
        assert_eq!(h["target_c"], 80.0);
        assert_eq!(h["control"], "pid");
        assert_eq!(h["max_power"], 1.0);
        assert!((h["held_s"].as_f64().unwrap() - last).abs() < 0.1, "{h}");
        h
    };
    // Defaults: this bed's heat-up cannot rule out glass on clips, so within its 74 min hold
    // the surface can still warm by about the budget; the reason says so in kelvin.
    let h = judge(None);
    let reason = h["reason"].as_str().unwrap();
    match h["stable_after_s"].as_f64() {
        Some(stable) => assert!(stable > 60.0 + 480.0 && stable < last, "{h}"),
        None => assert!(
            reason.contains("the print surface can still warm by at most")
                && reason.contains("budget 1.0 K"),
            "{h}"
        ),
    }
    // An open frame: declared, never before the bed reached its band (about a minute) and
    // settled (settle + minimum soak).
    let h = judge(Some(&open));
    let stable = h["stable_after_s"]
        .as_f64()
        .expect("declared within the 74 min hold on an open frame");
    assert!(stable > 60.0 + 480.0 && stable < last, "{h}");
    assert!(
        h["reason"]
            .as_str()
            .unwrap()
            .contains("power stopped falling"),
        "{h}"
    );
}
