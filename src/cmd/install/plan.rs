//! PURE: what `klipcal install` changes in the text files of a printer_data folder and how
//! `klipcal uninstall` takes it back. File contents in, new contents (or a refusal naming the
//! conflict) out; the shell in `install/mod.rs` reads, backs up, writes and records.

use crate::klipper::Config;

/// The include line klipcal adds to printer.cfg.
pub(crate) const INCLUDE_LINE: &str = "[include klipcal.cfg]";
/// The section Klipper needs for klipcal's console answers and prompts.
pub(crate) const RESPOND_LINE: &str = "[respond]";
/// The service name Moonraker may restart (moonraker.asvc) and the update_manager entry.
pub(crate) const SERVICE: &str = "klipcal";

/// Why the install refuses.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub(crate) struct Conflict(pub String);

/// The macro names config/klipcal.cfg defines (`[gcode_macro NAME]`, lower-cased).
#[must_use]
pub(crate) fn macro_sections(macros_cfg: &str) -> Vec<String> {
    macros_cfg
        .lines()
        .filter_map(|l| {
            let l = l.trim();
            let name = l.strip_prefix('[')?.strip_suffix(']')?;
            name.to_ascii_lowercase()
                .starts_with("gcode_macro ")
                .then(|| name.to_ascii_lowercase())
        })
        .collect()
}

/// Whether the loaded config already reads a `klipcal.cfg` at the config root.
fn reads_klipcal_cfg(loaded: &Config) -> bool {
    loaded
        .files()
        .iter()
        .any(|f| f.path.file_name().is_some_and(|n| n == "klipcal.cfg"))
}

/// printer.cfg with `[include klipcal.cfg]` (and `[respond]` when `add_respond`), or `None`
/// when nothing is to change. `loaded` is the printer's config as Klipper reads it now.
///
/// # Errors
/// A macro of klipcal's already defined by another file (named with its place).
pub(crate) fn printer_cfg(
    text: &str,
    loaded: &Config,
    macros_cfg: &str,
    add_respond: bool,
) -> Result<Option<String>, Conflict> {
    let reads = reads_klipcal_cfg(loaded);
    let ours = macro_sections(macros_cfg);
    for sec in loaded.sections() {
        let name = sec.name.to_ascii_lowercase();
        if !ours.contains(&name) {
            continue;
        }
        let from = sec
            .options
            .first()
            .map(|o| o.origin.path.clone())
            .unwrap_or_default();
        if from.file_name().is_some_and(|n| n == "klipcal.cfg") {
            continue;
        }
        return Err(Conflict(format!(
            "[{}] is already defined in {}: klipcal.cfg defines it too; rename or remove \
             yours, then install again",
            sec.name,
            from.display()
        )));
    }
    let need_include = !reads;
    let need_respond = add_respond && !loaded.has_section("respond");
    if !need_include && !need_respond {
        return Ok(None);
    }
    let mut add = String::new();
    if need_include {
        add.push_str(INCLUDE_LINE);
        add.push('\n');
    }
    if need_respond {
        add.push_str(RESPOND_LINE);
        add.push('\n');
    }
    Ok(Some(insert_at_top(text, &add)))
}

/// Inserts `block` after the file's opening comment lines (before its first section), with a
/// blank line after it.
fn insert_at_top(text: &str, block: &str) -> String {
    let mut at = 0;
    for line in text.split_inclusive('\n') {
        let t = line.trim();
        if t.starts_with('#') || t.starts_with(';') {
            at += line.len();
        } else {
            break;
        }
    }
    let (head, tail) = text.split_at(at);
    let sep = if head.is_empty() || head.ends_with('\n') {
        ""
    } else {
        "\n"
    };
    format!("{head}{sep}{block}\n{tail}")
}

/// Whether the printer's config has `[respond]`.
#[must_use]
pub(crate) fn has_respond(loaded: &Config) -> bool {
    loaded.has_section("respond")
}

/// moonraker.asvc with `service` listed, or `None` when it is. A missing file is created with
/// Moonraker's default services (what Moonraker itself would write) and klipcal.
#[must_use]
pub(crate) fn asvc(
    current: Option<&str>,
    moonraker_defaults: &str,
    service: &str,
) -> Option<String> {
    let text = current.unwrap_or(moonraker_defaults);
    let listed = text.lines().any(|l| {
        let l = l.trim();
        l == service || l.strip_suffix(".service") == Some(service)
    });
    if listed && current.is_some() {
        return None;
    }
    let mut out = text.to_string();
    if !listed {
        if !out.is_empty() && !out.ends_with('\n') {
            out.push('\n');
        }
        out.push_str(service);
        out.push('\n');
    }
    Some(out)
}

/// Where a printer's Moonraker listens, from its moonraker.conf `[server]` section: `host`
/// (default `0.0.0.0`) and `port` (default 7125).
///
/// # Errors
/// A `port` that is not a port number.
pub(crate) fn moonraker_address(conf: &str) -> Result<(String, u16), Conflict> {
    let mut in_server = false;
    let (mut host, mut port) = ("0.0.0.0".to_string(), 7125u16);
    for line in conf.lines() {
        let t = line.trim();
        if t.starts_with('[') && t.ends_with(']') {
            in_server = t[1..t.len() - 1].trim().eq_ignore_ascii_case("server");
            continue;
        }
        if !in_server || t.starts_with('#') || t.starts_with(';') || line.starts_with([' ', '\t']) {
            continue;
        }
        let Some((k, v)) = t.split_once([':', '=']) else {
            continue;
        };
        let v = v.split(['#', ';']).next().unwrap_or("").trim();
        match k.trim().to_ascii_lowercase().as_str() {
            "host" => host = v.to_string(),
            "port" => {
                port = v.parse().map_err(|_| {
                    Conflict(format!(
                        "moonraker.conf [server] port: {v:?} is not a port number"
                    ))
                })?;
            }
            _ => {}
        }
    }
    Ok((host, port))
}

/// The websocket URL klipcal on this host reaches that Moonraker at (a wildcard host is
/// reached on loopback).
#[must_use]
pub(crate) fn moonraker_url(host: &str, port: u16) -> String {
    let h = match host.trim() {
        "" | "0.0.0.0" | "all" | "::" | "[::]" => "127.0.0.1".to_string(),
        h if h.contains(':') && !h.starts_with('[') => format!("[{h}]"),
        h => h.to_string(),
    };
    format!("ws://{h}:{port}/websocket")
}

/// The printer's name on a host with several, from its printer_data folder's name
/// (`printer_2_data` → `printer_2`); `None` for the conventional single `printer_data`.
#[must_use]
pub(crate) fn instance(printer_data_name: &str) -> Option<String> {
    if printer_data_name == "printer_data" {
        return None;
    }
    let stem = printer_data_name
        .strip_suffix("_data")
        .filter(|s| !s.is_empty())
        .unwrap_or(printer_data_name);
    let clean: String = stem
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    Some(clean)
}

/// The systemd service (and moonraker.asvc name) of a printer's klipcal: `klipcal` for the
/// single printer, `klipcal-printer_2` for another (as KIAUH names `moonraker-printer_2`).
#[must_use]
pub(crate) fn service_name(instance: Option<&str>) -> String {
    instance.map_or_else(|| SERVICE.to_string(), |i| format!("{SERVICE}-{i}"))
}

/// klipcal's page port for a printer: 7150 beside Moonraker's 7125, one up for each port
/// Moonraker is up (7126 → 7151), then the next port no other printer's klipcal and no
/// running program uses (`taken`).
#[must_use]
pub(crate) fn http_port(moonraker_port: u16, taken: &[u16]) -> u16 {
    let mut p = if (7125..7150).contains(&moonraker_port) {
        7150 + (moonraker_port - 7125)
    } else {
        7150
    };
    while taken.contains(&p) && p < u16::MAX {
        p += 1;
    }
    p
}

/// The settings file as install writes it for one printer: the documented template with its
/// Moonraker URL, its own data folder and its own page port.
#[must_use]
pub(crate) fn settings(template: &str, url: &str, data_dir: &str, http_port: u16) -> String {
    let quote = |v: &str| format!("\"{}\"", v.replace('\\', "\\\\").replace('"', "\\\""));
    let mut section = String::new();
    let mut out = String::new();
    for line in template.split_inclusive('\n') {
        let t = line.trim();
        if t.starts_with('[') && t.ends_with(']') {
            section = t.to_string();
        }
        let key = t.split('=').next().unwrap_or("").trim();
        let new = match (section.as_str(), key) {
            ("[moonraker]", "url") if !t.starts_with('#') => {
                Some(format!("url = {}\n", quote(url)))
            }
            ("[daemon]", "data_dir") if !t.starts_with('#') => {
                Some(format!("data_dir = {}\n", quote(data_dir)))
            }
            ("[http]", "bind") if !t.starts_with('#') => {
                Some(format!("bind = \"0.0.0.0:{http_port}\"\n"))
            }
            _ => None,
        };
        out.push_str(new.as_deref().unwrap_or(line));
    }
    out
}

/// The `[update_manager <service>]` section: the `executable` type (one binary from the
/// release's assets, named in release_info.json; the folder is not wiped on update). Moonraker
/// restarts the service its section is named after, so a second printer's section is
/// `[update_manager klipcal-printer_2]`.
#[must_use]
pub(crate) fn update_manager_section(bin_dir: &str, repo: &str, service: &str) -> String {
    format!(
        "[update_manager {service}]\n\
         # added by klipcal install; klipcal uninstall removes it\n\
         type: executable\n\
         channel: stable\n\
         repo: {repo}\n\
         path: {bin_dir}\n\
         managed_services: {service}\n"
    )
}

/// The byte range of `[header]`'s section in `text`: from its header line to the next
/// section header (or the end), trailing blank lines excluded.
fn section_span(text: &str, header: &str) -> Option<(usize, usize)> {
    let mut pos = 0;
    let mut start = None;
    let mut end_content = 0;
    for line in text.split_inclusive('\n') {
        let t = line.trim();
        let is_header = t.starts_with('[') && t.ends_with(']');
        match start {
            None if is_header && t.eq_ignore_ascii_case(header) => {
                start = Some(pos);
                end_content = pos + line.len();
            }
            Some(s) if is_header => return Some((s, end_content)),
            Some(_) if !t.is_empty() => end_content = pos + line.len(),
            _ => {}
        }
        pos += line.len();
    }
    start.map(|s| (s, end_content))
}

/// moonraker.conf with klipcal's update_manager section, or `None` when it is there as is.
/// `ours` says the present section is klipcal's own from an earlier install (then it is
/// replaced; otherwise a different one is a conflict).
///
/// # Errors
/// A different `[update_manager klipcal]` that klipcal did not write.
pub(crate) fn moonraker_conf(
    text: &str,
    section: &str,
    ours: bool,
) -> Result<Option<String>, Conflict> {
    let header = section.lines().next().unwrap_or("");
    match section_span(text, header) {
        Some((s, e)) => {
            if text[s..e] == *section {
                return Ok(None);
            }
            if !ours {
                return Err(Conflict(format!(
                    "moonraker.conf already has {header} that klipcal did not write; remove it \
                     (or rename it) and install again"
                )));
            }
            Ok(Some(format!("{}{section}{}", &text[..s], &text[e..])))
        }
        None => {
            let mut out = text.to_string();
            if !out.is_empty() && !out.ends_with('\n') {
                out.push('\n');
            }
            if !out.is_empty() {
                out.push('\n');
            }
            out.push_str(section);
            Ok(Some(out))
        }
    }
}

/// Takes klipcal's additions out of a file the user changed since the install: the lines it
/// added (`added`) and the update_manager section, leaving everything else.
#[must_use]
pub(crate) fn remove_additions(
    text: &str,
    added_lines: &[String],
    section_header: Option<&str>,
) -> String {
    let mut out = text.to_string();
    if let Some(h) = section_header {
        if let Some((s, e)) = section_span(&out, h) {
            // with the blank line install put before the section
            let s = if out[..s].ends_with("\n\n") { s - 1 } else { s };
            out = format!("{}{}", &out[..s], &out[e..]);
        }
    }
    for line in added_lines {
        let mut kept = String::with_capacity(out.len());
        let mut removed = false;
        for l in out.split_inclusive('\n') {
            if !removed && l.trim() == line.trim() {
                removed = true;
                continue;
            }
            kept.push_str(l);
        }
        out = kept;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::klipper::MemFiles;
    use std::path::Path;

    const MACROS: &str = "[gcode_macro KLIPCAL_STATUS]\ngcode:\n  RESPOND MSG=hi\n";

    fn loaded(files: &MemFiles) -> Config {
        Config::load(files, Path::new("/pd/config/printer.cfg")).unwrap()
    }

    #[test]
    fn the_include_goes_after_the_opening_comments_once() {
        let text = "# my printer\n# notes\n[printer]\nkinematics: corexy\n";
        let files = MemFiles::new().with("/pd/config/printer.cfg", text);
        let out = printer_cfg(text, &loaded(&files), MACROS, true)
            .unwrap()
            .unwrap();
        assert_eq!(
            out,
            "# my printer\n# notes\n[include klipcal.cfg]\n[respond]\n\n[printer]\nkinematics: corexy\n"
        );
        // Installed: nothing more to change.
        let files = MemFiles::new()
            .with("/pd/config/printer.cfg", out.clone())
            .with("/pd/config/klipcal.cfg", MACROS);
        assert_eq!(
            printer_cfg(&out, &loaded(&files), MACROS, true).unwrap(),
            None
        );
    }

    #[test]
    fn an_include_that_already_reads_klipcal_cfg_is_enough() {
        let text = "[include klip*.cfg]\n[respond]\n[printer]\nkinematics: corexy\n";
        let files = MemFiles::new()
            .with("/pd/config/printer.cfg", text)
            .with("/pd/config/klipcal.cfg", MACROS);
        assert_eq!(
            printer_cfg(text, &loaded(&files), MACROS, true).unwrap(),
            None
        );
    }

    #[test]
    fn a_macro_of_ours_defined_elsewhere_is_a_conflict_named_with_its_file() {
        let text = "[include macros.cfg]\n[printer]\nkinematics: corexy\n";
        let files = MemFiles::new().with("/pd/config/printer.cfg", text).with(
            "/pd/config/macros.cfg",
            "[gcode_macro klipcal_status]\ngcode:\n  M117 x\n",
        );
        let e = printer_cfg(text, &loaded(&files), MACROS, false).unwrap_err();
        assert!(
            e.0.contains("klipcal_status") && e.0.contains("macros.cfg"),
            "{e}"
        );
    }

    #[test]
    fn respond_is_added_only_when_asked_for_and_missing() {
        let text = "[printer]\nkinematics: corexy\n";
        let files = MemFiles::new().with("/pd/config/printer.cfg", text);
        let out = printer_cfg(text, &loaded(&files), MACROS, false)
            .unwrap()
            .unwrap();
        assert!(
            out.starts_with("[include klipcal.cfg]\n\n[printer]"),
            "{out}"
        );
        assert!(!out.contains("[respond]"));
    }

    #[test]
    fn asvc_lists_klipcal_once_and_a_missing_file_keeps_moonrakers_defaults() {
        assert_eq!(asvc(Some("klipper_mcu\nklipcal\n"), "", "klipcal"), None);
        assert_eq!(
            asvc(Some("klipper_mcu"), "", "klipcal").unwrap(),
            "klipper_mcu\nklipcal\n"
        );
        assert_eq!(
            asvc(None, "crowsnest\n", "klipcal").unwrap(),
            "crowsnest\nklipcal\n"
        );
        // A second printer's Moonraker may restart only its own klipcal.
        assert_eq!(
            asvc(Some("klipper_mcu\nklipcal\n"), "", "klipcal-printer_2").unwrap(),
            "klipper_mcu\nklipcal\nklipcal-printer_2\n"
        );
    }

    #[test]
    fn the_update_manager_section_is_added_replaced_when_ours_and_refused_when_not() {
        let sec = update_manager_section("~/klipcal", "klipcal/klipcal", SERVICE);
        let conf = "[server]\nhost: 0.0.0.0\n";
        let out = moonraker_conf(conf, &sec, false).unwrap().unwrap();
        assert_eq!(out, format!("{conf}\n{sec}"));
        assert_eq!(moonraker_conf(&out, &sec, false).unwrap(), None);
        let theirs = format!("{conf}\n[update_manager klipcal]\ntype: git_repo\npath: ~/klipcal\n\n[webcam x]\nservice: iframe\n");
        let e = moonraker_conf(&theirs, &sec, false).unwrap_err();
        assert!(e.0.contains("did not write"), "{e}");
        let replaced = moonraker_conf(&theirs, &sec, true).unwrap().unwrap();
        assert!(replaced.contains("type: executable") && !replaced.contains("git_repo"));
        assert!(
            replaced.ends_with("\n[webcam x]\nservice: iframe\n"),
            "{replaced}"
        );
    }

    #[test]
    fn additions_come_out_of_a_file_the_user_changed_since() {
        let sec = update_manager_section("~/klipcal", "klipcal/klipcal", SERVICE);
        let installed = format!("[server]\nhost: 0.0.0.0\n\n{sec}");
        let changed = format!("{installed}\n[webcam cam]\nservice: mjpegstreamer\n");
        let back = remove_additions(&changed, &[], Some("[update_manager klipcal]"));
        assert_eq!(
            back,
            "[server]\nhost: 0.0.0.0\n\n[webcam cam]\nservice: mjpegstreamer\n"
        );
        let cfg = "[include klipcal.cfg]\n\n[printer]\nkinematics: corexy\n[fan]\npin: PA1\n";
        let back = remove_additions(cfg, &[INCLUDE_LINE.to_string()], None);
        assert_eq!(back, "\n[printer]\nkinematics: corexy\n[fan]\npin: PA1\n");
    }

    #[test]
    fn each_printer_gets_its_moonraker_its_service_and_its_own_page_port() {
        let conf =
            "[server]\nhost: 0.0.0.0\nport: 7126\nklippy_uds_address: x\n\n[webcam]\nport = 1\n";
        let (h, p) = moonraker_address(conf).unwrap();
        assert_eq!((h.as_str(), p), ("0.0.0.0", 7126));
        assert_eq!(moonraker_url(&h, p), "ws://127.0.0.1:7126/websocket");
        assert_eq!(
            moonraker_address("[server]\nhost = 192.168.1.5 # lan\n").unwrap(),
            ("192.168.1.5".to_string(), 7125)
        );
        assert_eq!(moonraker_address("").unwrap().1, 7125);
        assert!(moonraker_address("[server]\nport: 71x\n").is_err());
        assert_eq!(moonraker_url("::1", 7125), "ws://[::1]:7125/websocket");
        assert_eq!(instance("printer_data"), None);
        assert_eq!(instance("printer_2_data").as_deref(), Some("printer_2"));
        assert_eq!(service_name(None), "klipcal");
        assert_eq!(service_name(Some("printer_2")), "klipcal-printer_2");
        assert_eq!(http_port(7125, &[]), 7150);
        assert_eq!(http_port(7126, &[7150]), 7151);
        assert_eq!(http_port(43211, &[7150, 7151]), 7152);
        let t = "[moonraker]\n# url = \"x\"\nurl = \"ws://127.0.0.1:7125/websocket\"\n[daemon]\n\
                 data_dir = \"~/printer_data/klipcal\"\n[http]\nenabled = true\nbind = \"0.0.0.0:7150\"\n";
        let out = settings(
            t,
            "ws://127.0.0.1:7126/websocket",
            "/home/pi/printer_2_data/klipcal",
            7151,
        );
        assert!(
            out.contains("# url = \"x\"\nurl = \"ws://127.0.0.1:7126/websocket\"\n"),
            "{out}"
        );
        assert!(
            out.contains("data_dir = \"/home/pi/printer_2_data/klipcal\"\n"),
            "{out}"
        );
        assert!(out.contains("bind = \"0.0.0.0:7151\"\n"), "{out}");
        let cfg = crate::config::Config::parse(&settings(
            include_str!("../../../config/klipcal.toml"),
            "ws://127.0.0.1:7126/websocket",
            "/x/printer_2_data/klipcal",
            7151,
        ))
        .unwrap();
        assert_eq!(cfg.moonraker.url, "ws://127.0.0.1:7126/websocket");
        assert_eq!(cfg.daemon.data_dir, "/x/printer_2_data/klipcal");
        assert_eq!(cfg.http.bind, "0.0.0.0:7151");
    }
}
