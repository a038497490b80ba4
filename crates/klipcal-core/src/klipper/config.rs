//! Reads Klipper config files exactly as klippy/configfile.py (0.12) does on top of Python's
//! `configparser`, keeping where every effective option is defined. PURE: file text and glob
//! results come from a [`Files`] implementation; never std::fs.
//!
//! The rules reproduced (Klipper `configfile.py` + Python 3.11 `RawConfigParser(strict=False,
//! inline_comment_prefixes=(';', '#'))`):
//! - Python's universal newlines: `\r\n` and a lone `\r` become `\n`. A UTF-8 byte order mark
//!   is not removed (Python's `utf-8` codec keeps it), so Klipper refuses such a file ("File
//!   contains no section headers"); so does this reader, saying why. On every line Klipper first cuts everything from the first `#`, wherever
//!   it is (also inside G-code macros). A line that was only a `#` comment thus becomes blank,
//!   and a blank line inside a multi-line value adds an empty line to that value.
//! - `;` starts a comment at the start of a line or after whitespace only (`M117 a;b` keeps `;b`).
//! - `[header]`: the header is everything between the first `[` and the last `]` (not trimmed,
//!   case-sensitive). Sections seen again are reopened; an option set again replaces the value
//!   (its position in the section stays the first one). Option names are lowercased; the name
//!   ends at the first `:` or `=`.
//! - A line indented deeper than the line that started the option continues its value; the
//!   value's lines are joined with `\n` (each stripped) and trailing whitespace removed.
//! - `[include spec]` (exactly `include ` then the spec) is resolved relative to the including
//!   file's folder as a glob; matches are sorted and read in order, each as if pasted there. A
//!   spec that matches nothing is an error only when it has no wildcard. The parser state is
//!   reset at every include, so options after an include need a new section header. A file that
//!   (indirectly) includes itself is an error.
//! - SAVE_CONFIG: the main file is cut at the first
//!   `\n#*# <---------------------- SAVE_CONFIG ---------------------->\n#*# DO NOT EDIT THIS
//!   BLOCK OR BELOW. The contents are auto-generated.\n#*#\n`. The rest, stripped, must be made
//!   only of lines starting `#*# ` (or exactly `#*#`), and no regular line may start with `#*# `,
//!   else Klipper logs "autosave state corrupted" and reads the whole file as regular config (the
//!   `#*#` lines are then comments). The block's options that the regular config (main file +
//!   includes) also defines are commented out (`_strip_duplicates`): **the regular definition
//!   wins**. The rest of the block is appended after everything else, so it overrides nothing
//!   but fills in what the regular config lacks.
//!
//! Not supported: a `[DEFAULT]` section (configparser would copy its options into every section,
//! which no Klipper config can use; it is reported as an error).

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use super::files::{has_magic, normalize_path, Files};
use super::kalico::{self, Dialect};
use super::Error;

/// The first line of Klipper's auto-generated block (`configfile.AUTOSAVE_HEADER`).
pub const SAVE_CONFIG_MARKER: &str =
    "#*# <---------------------- SAVE_CONFIG ---------------------->";
const SAVE_CONFIG_SECOND: &str =
    "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.";
const SAVE_CONFIG_THIRD: &str = "#*#";

/// One file read while loading, with its exact text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SourceFile {
    /// The path as it was read (normalised lexically).
    pub path: PathBuf,
    /// The file's text, byte for byte.
    pub text: String,
}

/// Where an effective option is defined.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Origin {
    /// Index into [`Config::files`].
    pub file: usize,
    /// Path of that file.
    pub path: PathBuf,
    /// 1-based line of `key: value`.
    pub first_line: usize,
    /// 1-based last line holding part of the value (equal to `first_line` for one-line values).
    pub last_line: usize,
    /// True when the definition is in the main file's SAVE_CONFIG block (`#*# key = value`).
    pub in_save_config: bool,
    /// Byte range, in the file's text, of the value text on `first_line` (comments and
    /// surrounding spaces excluded; empty when the value starts on the next line).
    pub value_span: Range<usize>,
}

/// One effective option.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigOption {
    /// Lowercased option name.
    pub key: String,
    /// The raw value as Klipper sees it (multi-line values joined with `\n`); with Kalico's
    /// references replaced ([`Dialect::Kalico`]).
    pub value: String,
    /// The value as written when it differs from `value` because Kalico replaced references
    /// in it (`${constants.rd_x}`): an edit must not overwrite such a value blindly.
    pub written: Option<String>,
    /// Where the effective definition is.
    pub origin: Origin,
}

/// One section: its name as written and its options in first-definition order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Section {
    /// Section name, case preserved (`gcode_macro PRINT_START`).
    pub name: String,
    /// Options in the order they were first defined.
    pub options: Vec<ConfigOption>,
}

impl Section {
    /// The option `key` (matched lowercased).
    pub fn option(&self, key: &str) -> Option<&ConfigOption> {
        let key = key.to_lowercase();
        self.options.iter().find(|o| o.key == key)
    }
}

/// What happened to the main file's SAVE_CONFIG block.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SaveConfigStatus {
    /// No SAVE_CONFIG header in the main file.
    Absent,
    /// The block was read; its options were merged as Klipper does.
    Read,
    /// Klipper would ignore the block (logging a warning) and read the file as regular config.
    Corrupted {
        /// Why, in Klipper's words.
        reason: String,
    },
}

/// A SAVE_CONFIG option that Klipper ignores because the regular config defines it too.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShadowedOption {
    /// Section as written in the block.
    pub section: String,
    /// Lowercased option name.
    pub key: String,
    /// 1-based line in the main file.
    pub line: usize,
}

/// A loaded Klipper configuration: effective sections and options, with their sources.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Config {
    dialect: Dialect,
    files: Vec<SourceFile>,
    sections: Vec<Section>,
    save_config: SaveConfigStatus,
    shadowed: Vec<ShadowedOption>,
}

impl Config {
    /// Loads `main_path` the way Klipper loads its main config (`read_main_config`):
    /// includes followed, SAVE_CONFIG block merged.
    ///
    /// # Errors
    /// [`Error::Read`] when a file cannot be read, [`Error::IncludeNotFound`],
    /// [`Error::IncludeCycle`], [`Error::Syntax`] for lines configparser rejects.
    pub fn load(files: &dyn Files, main_path: &Path) -> Result<Config, Error> {
        Self::load_as(files, main_path, Dialect::Klipper)
    }

    /// [`Config::load`] by `dialect`'s rules ([`Dialect::Kalico`]: references replaced,
    /// `!!include` in values, recursive `**` includes; see [`super::kalico`]).
    ///
    /// # Errors
    /// As [`Config::load`]; [`Error::BadValue`] for a reference Kalico cannot follow.
    pub fn load_as(files: &dyn Files, main_path: &Path, dialect: Dialect) -> Result<Config, Error> {
        let mut loader = Loader {
            files,
            dialect,
            sources: Vec::new(),
            by_path: BTreeMap::new(),
        };
        let main = loader.file(main_path)?;
        let lines = split_lines(main, &loader.sources[main].text);
        let (regular, autosave, status) = split_save_config(lines);

        // Pass 1: the regular config alone, to find SAVE_CONFIG options it shadows.
        let mut regular_cfg = Parser::default();
        let mut visited = Vec::new();
        loader.parse_lines(&mut regular_cfg, main_path, regular.clone(), &mut visited)?;

        let (autosave, shadowed) = strip_duplicates(autosave, &regular_cfg);
        // Klipper also parses the block alone (`self.autosave`); it must parse by itself.
        loader.parse_lines(
            &mut Parser::default(),
            main_path,
            autosave.clone(),
            &mut visited,
        )?;

        // Pass 2: regular + (block without duplicates), as one text, like Klipper.
        let mut all = Parser::default();
        let mut combined = regular;
        combined.extend(autosave);
        loader.parse_lines(&mut all, main_path, combined, &mut visited)?;

        let sources = loader.sources;
        let sections = all
            .sections
            .into_iter()
            .map(|s| Section {
                name: s.name,
                options: s
                    .options
                    .into_iter()
                    .map(|o| ConfigOption {
                        key: o.key,
                        value: join_value(&o.lines),
                        written: None,
                        origin: Origin {
                            file: o.file,
                            path: sources[o.file].path.clone(),
                            first_line: o.first_line,
                            last_line: o.last_line,
                            in_save_config: o.in_save_config,
                            value_span: o.value_span,
                        },
                    })
                    .collect(),
            })
            .collect::<Vec<Section>>();
        let mut sections = sections;
        if dialect == Dialect::Kalico {
            for (si, oi, value) in kalico::resolve_references(&sections)? {
                let o = &mut sections[si].options[oi];
                o.written = Some(std::mem::replace(&mut o.value, value));
            }
        }
        Ok(Config {
            dialect,
            files: sources,
            sections,
            save_config: status,
            shadowed,
        })
    }

    /// Whose rules the config was read by.
    pub(crate) fn dialect(&self) -> Dialect {
        self.dialect
    }

    /// Every file read, the main file first.
    pub fn files(&self) -> &[SourceFile] {
        &self.files
    }

    /// Sections in first-appearance order.
    pub fn sections(&self) -> &[Section] {
        &self.sections
    }

    /// The section named exactly `name` (section names are case-sensitive, as in Klipper).
    pub fn section(&self, name: &str) -> Option<&Section> {
        self.sections.iter().find(|s| s.name == name)
    }

    /// True when the section named exactly `name` exists.
    pub fn has_section(&self, name: &str) -> bool {
        self.section(name).is_some()
    }

    /// The effective option `key` (case-insensitive) of section `section`.
    pub fn option(&self, section: &str, key: &str) -> Option<&ConfigOption> {
        self.section(section)?.option(key)
    }

    /// The effective raw value of `[section] key`.
    pub fn get(&self, section: &str, key: &str) -> Option<&str> {
        self.option(section, key).map(|o| o.value.as_str())
    }

    /// What happened to the SAVE_CONFIG block.
    #[cfg(test)]
    pub fn save_config_status(&self) -> &SaveConfigStatus {
        &self.save_config
    }

    /// SAVE_CONFIG options Klipper ignores because the regular config defines them.
    #[cfg(test)]
    pub fn shadowed_save_config(&self) -> &[ShadowedOption] {
        &self.shadowed
    }
}

/// One line as fed to the parser.
#[derive(Debug, Clone)]
struct Line {
    file: usize,
    /// 1-based line number in that file.
    lineno: usize,
    /// The logical text (the `#*# ` prefix and a `\r` before `\n` removed).
    text: String,
    /// Byte offset in the file text where `text` starts.
    offset: usize,
    in_save_config: bool,
}

fn split_lines(file: usize, text: &str) -> Vec<Line> {
    // Klipper opens the file in Python's text mode: universal newlines turn "\r\n" and a lone
    // "\r" into "\n". Offsets keep pointing into the original bytes.
    let bytes = text.as_bytes();
    let mut out = Vec::new();
    let mut start = 0;
    let mut i = 0;
    let push = |out: &mut Vec<Line>, start: usize, end: usize| {
        out.push(Line {
            file,
            lineno: out.len() + 1,
            text: text[start..end].to_string(),
            offset: start,
            in_save_config: false,
        });
    };
    while i < bytes.len() {
        match bytes[i] {
            b'\n' => {
                push(&mut out, start, i);
                i += 1;
                start = i;
            }
            b'\r' => {
                push(&mut out, start, i);
                i += if bytes.get(i + 1) == Some(&b'\n') {
                    2
                } else {
                    1
                };
                start = i;
            }
            _ => i += 1,
        }
    }
    push(&mut out, start, bytes.len());
    out
}

/// Splits the main file's lines into regular lines and SAVE_CONFIG lines (prefix removed), as
/// `PrinterConfig._find_autosave_data`.
fn split_save_config(lines: Vec<Line>) -> (Vec<Line>, Vec<Line>, SaveConfigStatus) {
    let header = (1..lines.len().saturating_sub(3)).find(|&i| {
        lines[i].text == SAVE_CONFIG_MARKER
            && lines[i + 1].text == SAVE_CONFIG_SECOND
            && lines[i + 2].text == SAVE_CONFIG_THIRD
    });
    let corrupted_by_regular =
        |upto: usize| lines[1..upto].iter().any(|l| l.text.starts_with("#*# "));
    let Some(pos) = header else {
        if corrupted_by_regular(lines.len()) {
            return (
                lines,
                Vec::new(),
                SaveConfigStatus::Corrupted {
                    reason: "Can't read autosave from config file - autosave state corrupted"
                        .into(),
                },
            );
        }
        return (lines, Vec::new(), SaveConfigStatus::Absent);
    };
    if corrupted_by_regular(pos) {
        return (
            lines,
            Vec::new(),
            SaveConfigStatus::Corrupted {
                reason: "Can't read autosave from config file - autosave state corrupted".into(),
            },
        );
    }
    // The block after the header, stripped of surrounding whitespace (Python `.strip()`).
    let mut block: Vec<Line> = lines[pos + 3..].to_vec();
    while block.first().is_some_and(|l| py_strip(&l.text).is_empty()) {
        block.remove(0);
    }
    while block.last().is_some_and(|l| py_strip(&l.text).is_empty()) {
        block.pop();
    }
    if let Some(first) = block.first_mut() {
        let trimmed = py_lstrip(&first.text);
        first.offset += first.text.len() - trimmed.len();
        first.text = trimmed.to_string();
    }
    if let Some(last) = block.last_mut() {
        last.text = py_rstrip(&last.text).to_string();
    }
    let mut autosave = Vec::with_capacity(block.len());
    for mut line in block {
        let ok = line.text.starts_with("#*#")
            && (line.text.chars().count() < 4 || line.text.starts_with("#*# "));
        if !ok {
            return (
                lines,
                Vec::new(),
                SaveConfigStatus::Corrupted {
                    reason: "Can't read autosave from config file - modifications after header"
                        .into(),
                },
            );
        }
        let cut = line.text.len().min(4);
        line.text = line.text[cut..].to_string();
        line.offset += cut;
        line.in_save_config = true;
        autosave.push(line);
    }
    let mut regular = lines;
    regular.truncate(pos);
    (regular, autosave, SaveConfigStatus::Read)
}

/// `PrinterConfig._strip_duplicates`: comments out block options the regular config defines.
fn strip_duplicates(mut autosave: Vec<Line>, regular: &Parser) -> (Vec<Line>, Vec<ShadowedOption>) {
    let mut shadowed = Vec::new();
    let mut section: Option<String> = None;
    let mut is_dup = false;
    for line in &mut autosave {
        let cut = line.text.find(['#', ';']).unwrap_or(line.text.len());
        let pruned = py_rstrip(&line.text[..cut]);
        let Some(first) = pruned.chars().next() else {
            continue;
        };
        if py_isspace(first) {
            if is_dup {
                line.text.insert(0, '#');
            }
            continue;
        }
        is_dup = false;
        if first == '[' {
            // Python `pruned_line[1:-1].strip()`
            let chars: Vec<char> = pruned.chars().collect();
            let inner: String = chars[1..chars.len().saturating_sub(1).max(1)]
                .iter()
                .collect();
            section = Some(py_strip(&inner).to_string());
            continue;
        }
        let field_end = pruned
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(pruned.len());
        let field = pruned[..field_end].to_lowercase();
        if let Some(sec) = &section {
            if regular.has_option(sec, &field) {
                is_dup = true;
                shadowed.push(ShadowedOption {
                    section: sec.clone(),
                    key: field,
                    line: line.lineno,
                });
                line.text.insert(0, '#');
            }
        }
    }
    (autosave, shadowed)
}

struct Loader<'a> {
    files: &'a dyn Files,
    dialect: Dialect,
    sources: Vec<SourceFile>,
    by_path: BTreeMap<PathBuf, usize>,
}

impl Loader<'_> {
    /// Reads (once) and registers a file; returns its index.
    fn file(&mut self, path: &Path) -> Result<usize, Error> {
        let key = normalize_path(path);
        if let Some(&i) = self.by_path.get(&key) {
            return Ok(i);
        }
        let text = self.files.read(path).map_err(|e| Error::Read {
            path: path.to_path_buf(),
            cause: e,
        })?;
        if text.starts_with('\u{feff}') {
            return Err(Error::Syntax {
                path: path.to_path_buf(),
                line: 1,
                message: "the file starts with a UTF-8 byte order mark (BOM, bytes EF BB BF); \
                          Klipper reads it as text and refuses the file (\"File contains no \
                          section headers\"); save it as UTF-8 without BOM"
                    .into(),
            });
        }
        let i = self.sources.len();
        self.sources.push(SourceFile {
            path: key.clone(),
            text,
        });
        self.by_path.insert(key, i);
        Ok(i)
    }

    /// `PrinterConfig._parse_config` for one file's lines; `path` as it was named (includes are
    /// resolved against its folder), compared normalised to detect recursion.
    fn parse_lines(
        &mut self,
        parser: &mut Parser,
        path: &Path,
        lines: Vec<Line>,
        visited: &mut Vec<PathBuf>,
    ) -> Result<(), Error> {
        let key = normalize_path(path);
        if visited.contains(&key) {
            let mut chain: Vec<String> = visited.iter().map(|p| p.display().to_string()).collect();
            chain.push(key.display().to_string());
            return Err(Error::IncludeCycle {
                path: key,
                chain: chain.join(" -> "),
            });
        }
        visited.push(key);
        parser.reset_chunk();
        for mut line in lines {
            if let Some(pos) = line.text.find('#') {
                line.text.truncate(pos);
            }
            if let Some(header) = section_header(&line.text) {
                if let Some(spec) = header.strip_prefix("include ") {
                    let spec = py_strip(spec).to_string();
                    parser.reset_chunk();
                    self.include(parser, path, &spec, line.lineno, visited)?;
                    parser.reset_chunk();
                    continue;
                }
            }
            if self.dialect == Dialect::Kalico {
                self.value_include(&mut line, path)?;
            }
            parser.feed(&line, &self.sources[line.file].path)?;
        }
        parser.reset_chunk();
        visited.pop();
        Ok(())
    }

    /// Kalico's `!!include FILE` in a value: the name made absolute; the file must exist.
    fn value_include(&mut self, line: &mut Line, path: &Path) -> Result<(), Error> {
        let dir = path.parent().unwrap_or(Path::new(""));
        let Some((text, file)) = kalico::fix_value_include(&line.text, dir) else {
            return Ok(());
        };
        self.files.read(&file).map_err(|e| Error::Syntax {
            path: path.to_path_buf(),
            line: line.lineno,
            message: format!(
                "!!include {}: Kalico includes an existing file here ({e})",
                file.display()
            ),
        })?;
        line.text = text;
        Ok(())
    }

    fn include(
        &mut self,
        parser: &mut Parser,
        from: &Path,
        spec: &str,
        lineno: usize,
        visited: &mut Vec<PathBuf>,
    ) -> Result<(), Error> {
        let dir = from.parent().unwrap_or(Path::new(""));
        let pattern = dir.join(spec);
        // The pattern goes out as written (Python does not normalise it either: on a real file
        // system `missing/../x.cfg` does not exist); identity uses the normalised path.
        let found = if self.dialect == Dialect::Kalico && kalico::is_recursive(&pattern) {
            self.files.glob_recursive(&pattern)
        } else {
            self.files.glob(&pattern)
        };
        let mut found = found.map_err(|e| Error::Read {
            path: pattern.clone(),
            cause: e,
        })?;
        if found.is_empty() && !has_magic(&pattern.to_string_lossy()) {
            return Err(Error::IncludeNotFound {
                path: from.to_path_buf(),
                line: lineno,
                pattern,
            });
        }
        found.sort_by(|a, b| a.as_os_str().cmp(b.as_os_str()));
        for inc in found {
            let idx = self.file(&inc)?;
            let lines = split_lines(idx, &self.sources[idx].text);
            self.parse_lines(parser, &inc, lines, visited)?;
        }
        Ok(())
    }
}

/// An option while parsing: its value lines (joined at the end) and origin.
#[derive(Debug, Clone)]
struct RawOption {
    key: String,
    lines: Vec<String>,
    file: usize,
    first_line: usize,
    last_line: usize,
    in_save_config: bool,
    value_span: Range<usize>,
}

#[derive(Debug, Clone)]
struct RawSection {
    name: String,
    options: Vec<RawOption>,
}

/// Python `RawConfigParser` state: the sections, plus the per-`read_file` cursor state.
#[derive(Debug, Default)]
struct Parser {
    sections: Vec<RawSection>,
    /// Current section index (None before the first header of a chunk).
    cursect: Option<usize>,
    /// Current option index within the current section.
    optname: Option<usize>,
    indent_level: usize,
}

impl Parser {
    fn reset_chunk(&mut self) {
        self.cursect = None;
        self.optname = None;
        self.indent_level = 0;
    }

    fn has_option(&self, section: &str, key: &str) -> bool {
        self.sections
            .iter()
            .any(|s| s.name == section && s.options.iter().any(|o| o.key == key))
    }

    /// One line of `RawConfigParser._read`.
    fn feed(&mut self, line: &Line, path: &Path) -> Result<(), Error> {
        let text = line.text.as_str();
        let comment_start = comment_start(text);
        let before = &text[..comment_start.unwrap_or(text.len())];
        let value = py_strip(before);
        if value.is_empty() {
            // empty_lines_in_values: a blank line (not a comment) adds an empty value line
            if comment_start.is_none() {
                if let (Some(s), Some(o)) = (self.cursect, self.optname) {
                    self.sections[s].options[o].lines.push(String::new());
                }
            }
            return Ok(());
        }
        let cur_indent = text.chars().take_while(|&c| py_isspace(c)).count();
        if let (Some(s), Some(o), true) =
            (self.cursect, self.optname, cur_indent > self.indent_level)
        {
            let opt = &mut self.sections[s].options[o];
            opt.lines.push(value.to_string());
            opt.last_line = line.lineno;
            return Ok(());
        }
        self.indent_level = cur_indent;
        if let Some(name) = section_header(value) {
            if name == "DEFAULT" {
                return Err(Error::Syntax {
                    path: path.to_path_buf(),
                    line: line.lineno,
                    message: "a [DEFAULT] section is not supported (configparser would copy its \
                              options into every section); move its options into real sections"
                        .into(),
                });
            }
            let idx = match self.sections.iter().position(|s| s.name == name) {
                Some(i) => i,
                None => {
                    self.sections.push(RawSection {
                        name: name.to_string(),
                        options: Vec::new(),
                    });
                    self.sections.len() - 1
                }
            };
            self.cursect = Some(idx);
            self.optname = None;
            return Ok(());
        }
        let Some(s) = self.cursect else {
            return Err(Error::Syntax {
                path: path.to_path_buf(),
                line: line.lineno,
                message: format!(
                    "'{}' is outside any section; expected a [section] header first \
                     (after an [include] a new header is needed)",
                    value
                ),
            });
        };
        let Some(delim) = value.find([':', '=']) else {
            return Err(Error::Syntax {
                path: path.to_path_buf(),
                line: line.lineno,
                message: format!("'{value}' is not 'key: value', 'key = value' or a [section]"),
            });
        };
        let key = py_rstrip(&value[..delim]);
        if key.is_empty() {
            return Err(Error::Syntax {
                path: path.to_path_buf(),
                line: line.lineno,
                message: format!(
                    "'{value}' has no option name before the '{}'",
                    &value[delim..delim + 1]
                ),
            });
        }
        let key = key.to_lowercase();
        let after = &value[delim + 1..];
        let optval = py_lstrip(after);
        // byte position of the value in the file
        let value_start_in_line =
            (before.len() - py_lstrip(before).len()) + delim + 1 + (after.len() - optval.len());
        let start = line.offset + value_start_in_line;
        let span = start..start + optval.len();
        let raw = RawOption {
            key: key.clone(),
            lines: vec![optval.to_string()],
            file: line.file,
            first_line: line.lineno,
            last_line: line.lineno,
            in_save_config: line.in_save_config,
            value_span: span,
        };
        let sec = &mut self.sections[s];
        let o = match sec.options.iter().position(|o| o.key == key) {
            Some(i) => {
                sec.options[i] = raw;
                i
            }
            None => {
                sec.options.push(raw);
                sec.options.len() - 1
            }
        };
        self.optname = Some(o);
        Ok(())
    }
}

/// Where an inline comment starts: `;` (or `#`) at the start or after whitespace, or 0 for a
/// whole-line comment; None when the line has no comment.
fn comment_start(text: &str) -> Option<usize> {
    let trimmed = py_strip(text);
    if trimmed.starts_with('#') || trimmed.starts_with(';') {
        return Some(0);
    }
    let mut prev: Option<char> = None;
    for (i, c) in text.char_indices() {
        let after_space = match prev {
            None => true,
            Some(p) => py_isspace(p),
        };
        if (c == ';' || c == '#') && after_space {
            return Some(i);
        }
        prev = Some(c);
    }
    None
}

/// configparser's `SECTCRE.match`: `[` then the header up to the last `]` (at least one char).
fn section_header(text: &str) -> Option<&str> {
    let rest = text.strip_prefix('[')?;
    let end = rest.rfind(']')?;
    (end >= 1).then(|| &rest[..end])
}

fn join_value(lines: &[String]) -> String {
    py_rstrip(&lines.join("\n")).to_string()
}

/// Python's `str.isspace` for one character.
pub fn py_isspace(c: char) -> bool {
    c.is_whitespace() || ('\u{1c}'..='\u{1f}').contains(&c)
}

pub fn py_strip(s: &str) -> &str {
    s.trim_matches(py_isspace)
}

fn py_lstrip(s: &str) -> &str {
    s.trim_start_matches(py_isspace)
}

fn py_rstrip(s: &str) -> &str {
    s.trim_end_matches(py_isspace)
}

#[cfg(test)]
pub mod tests {
    use super::super::files::MemFiles;
    use super::*;

    /// The realistic CoreXY fixture used across the klipper tests.
    pub const PRINTER_CFG: &str = "\
# Voron-style CoreXY
[include steppers.cfg]
[include macros/*.cfg]

[printer]
kinematics: corexy
max_velocity: 300   # mm/s
max_accel: 3000 ; mm/s^2

[extruder]
nozzle_diameter = 0.400
filament_diameter = 1.750
rotation_distance: 22.6789511

[heater_bed]
heater_pin: PA1

[virtual_sdcard]
path: ~/printer_data/gcodes

[exclude_object]

[respond]

[bed_mesh]
mesh_min: 10, 10
mesh_max: 240, 240

[skew_correction]

[gcode_macro PRINT_START]
description: Start the print; heats, homes
gcode:
    {% set bed = params.BED|default(60)|float %}  # jinja set
    M190 S{bed}
    ; a full-line semicolon comment
    G28
    M117 a;b
    RESPOND MSG=\"hot {bed}\" ; trailing comment

[stepper_x]
microsteps: 32

#*# <---------------------- SAVE_CONFIG ---------------------->
#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.
#*#
#*# [bed_mesh default]
#*# version = 1
#*# points =
#*# \t  0.012500, 0.025000
#*# \t  -0.010000, 0.005000
#*# x_count = 2
#*# y_count = 2
#*#
#*# [skew_correction calilantern]
#*# xy_skew = 0.0012
#*# xz_skew = 0.0
#*# yz_skew = 0.0
#*#
#*# [stepper_x]
#*# microsteps = 64
#*# position_endstop = 249.5
";

    pub const STEPPERS_CFG: &str = "\
[stepper_x]
step_pin: PF13
rotation_distance: 40
microsteps: 16
full_steps_per_rotation: 200
position_max: 250
position_min: -2

[stepper_y]
step_pin: PF11
rotation_distance = 40 ; GT2 20T
microsteps: 16
gear_ratio: 80:20, 2:1
position_max: 255
";

    pub const MACROS_CFG: &str = "\
[gcode_macro PARK]
gcode:
  G1 X10 Y10
";

    pub fn fixture_files() -> MemFiles {
        MemFiles::new()
            .with("/home/pi/printer_data/config/printer.cfg", PRINTER_CFG)
            .with("/home/pi/printer_data/config/steppers.cfg", STEPPERS_CFG)
            .with("/home/pi/printer_data/config/macros/park.cfg", MACROS_CFG)
    }

    pub fn fixture() -> Config {
        Config::load(
            &fixture_files(),
            Path::new("/home/pi/printer_data/config/printer.cfg"),
        )
        .expect("fixture loads")
    }

    #[test]
    fn included_file_values_are_visible_with_their_origin() {
        let cfg = fixture();
        let o = cfg.option("stepper_y", "rotation_distance").unwrap();
        assert_eq!(o.value, "40");
        assert_eq!(
            o.origin.path,
            PathBuf::from("/home/pi/printer_data/config/steppers.cfg")
        );
        assert_eq!(o.origin.first_line, 11);
        let text = &cfg.files()[o.origin.file].text;
        assert_eq!(&text[o.origin.value_span.clone()], "40");
    }

    #[test]
    fn later_definitions_override_earlier_ones_across_files() {
        // steppers.cfg (included first) says 16, printer.cfg later says 32
        let cfg = fixture();
        let o = cfg.option("stepper_x", "microsteps").unwrap();
        assert_eq!(o.value, "32");
        assert_eq!(o.origin.file, 0);
        assert!(!o.origin.in_save_config);
    }

    #[test]
    fn save_config_value_is_ignored_when_the_regular_config_defines_the_option() {
        let cfg = fixture();
        assert_eq!(cfg.get("stepper_x", "microsteps"), Some("32"));
        assert!(cfg
            .shadowed_save_config()
            .iter()
            .any(|s| s.section == "stepper_x" && s.key == "microsteps"));
        // but an option only the block defines is taken from it
        let pe = cfg.option("stepper_x", "position_endstop").unwrap();
        assert_eq!(pe.value, "249.5");
        assert!(pe.origin.in_save_config);
        assert_eq!(cfg.save_config_status(), &SaveConfigStatus::Read);
    }

    #[test]
    fn save_config_profiles_are_read_with_multi_line_values() {
        let cfg = fixture();
        assert_eq!(
            cfg.get("bed_mesh default", "points"),
            Some("\n0.012500, 0.025000\n-0.010000, 0.005000")
        );
        let skew = cfg
            .option("skew_correction calilantern", "xy_skew")
            .unwrap();
        assert_eq!(skew.value, "0.0012");
        assert_eq!(
            &cfg.files()[0].text[skew.origin.value_span.clone()],
            "0.0012"
        );
    }

    #[test]
    fn comments_are_stripped_like_klipper_does() {
        let cfg = fixture();
        assert_eq!(cfg.get("printer", "max_velocity"), Some("300"));
        assert_eq!(cfg.get("printer", "max_accel"), Some("3000"));
        assert_eq!(cfg.get("stepper_y", "rotation_distance"), Some("40"));
        // ';' without whitespace before it is not a comment
        assert_eq!(
            cfg.get("gcode_macro PRINT_START", "description"),
            Some("Start the print; heats, homes")
        );
    }

    #[test]
    fn macro_gcode_blocks_keep_jinja_and_drop_comments() {
        let cfg = fixture();
        assert_eq!(
            cfg.get("gcode_macro PRINT_START", "gcode"),
            Some(
                "\n{% set bed = params.BED|default(60)|float %}\nM190 S{bed}\nG28\nM117 a;b\n\
                 RESPOND MSG=\"hot {bed}\""
            )
        );
        let o = cfg.option("gcode_macro PRINT_START", "gcode").unwrap();
        assert_eq!(o.origin.last_line, o.origin.first_line + 6);
    }

    #[test]
    fn a_hash_comment_line_inside_a_value_adds_an_empty_line_as_configparser_does() {
        let files = MemFiles::new().with(
            "/p.cfg",
            "[m]\ngcode:\n  A\n  # note\n  B\n  ; other\n  C\n",
        );
        let cfg = Config::load(&files, Path::new("/p.cfg")).unwrap();
        assert_eq!(cfg.get("m", "gcode"), Some("\nA\n\nB\nC"));
    }

    #[test]
    fn keys_are_lowercased_and_sections_are_case_sensitive() {
        let files = MemFiles::new().with("/p.cfg", "[Foo]\nRotation_Distance = 40\n[foo]\nx: 1\n");
        let cfg = Config::load(&files, Path::new("/p.cfg")).unwrap();
        assert_eq!(cfg.get("Foo", "rotation_distance"), Some("40"));
        assert_eq!(cfg.get("Foo", "ROTATION_DISTANCE"), Some("40"));
        assert_eq!(cfg.get("foo", "x"), Some("1"));
        assert_eq!(cfg.get("foo", "rotation_distance"), None);
    }

    #[test]
    fn glob_includes_are_read_in_sorted_order() {
        let files = MemFiles::new()
            .with("/c/printer.cfg", "[include parts/*.cfg]\n")
            .with("/c/parts/b.cfg", "[s]\nv: b\n")
            .with("/c/parts/a.cfg", "[s]\nv: a\nonly_a: 1\n");
        let cfg = Config::load(&files, Path::new("/c/printer.cfg")).unwrap();
        assert_eq!(cfg.get("s", "v"), Some("b"));
        assert_eq!(cfg.get("s", "only_a"), Some("1"));
    }

    #[test]
    fn nested_includes_resolve_against_the_including_files_folder() {
        let files = MemFiles::new()
            .with("/c/printer.cfg", "[include macros/main.cfg]\n")
            .with("/c/macros/main.cfg", "[include helpers.cfg]\n")
            .with("/c/macros/helpers.cfg", "[m]\nfrom: macros\n")
            .with("/c/helpers.cfg", "[m]\nfrom: top\n");
        let cfg = Config::load(&files, Path::new("/c/printer.cfg")).unwrap();
        assert_eq!(cfg.get("m", "from"), Some("macros"));
        assert_eq!(cfg.files().len(), 3);
    }

    #[test]
    fn a_wildcard_include_matching_nothing_is_fine_but_a_missing_file_is_an_error() {
        let ok = MemFiles::new().with("/c/printer.cfg", "[include none/*.cfg]\n[a]\nx: 1\n");
        assert!(Config::load(&ok, Path::new("/c/printer.cfg")).is_ok());
        let bad = MemFiles::new().with("/c/printer.cfg", "[a]\n[include missing.cfg]\n");
        let err = Config::load(&bad, Path::new("/c/printer.cfg")).unwrap_err();
        assert!(
            matches!(err, Error::IncludeNotFound { line: 2, .. }),
            "{err}"
        );
        assert!(err.to_string().contains("/c/missing.cfg"), "{err}");
    }

    #[test]
    fn include_cycles_are_an_error_naming_the_file() {
        let files = MemFiles::new()
            .with("/c/printer.cfg", "[include a.cfg]\n")
            .with("/c/a.cfg", "[include ./sub/../printer.cfg]\n");
        let err = Config::load(&files, Path::new("/c/printer.cfg")).unwrap_err();
        assert!(matches!(err, Error::IncludeCycle { .. }));
        assert!(err.to_string().contains("/c/printer.cfg"), "{err}");
    }

    #[test]
    fn options_after_an_include_need_a_new_section_header() {
        let files = MemFiles::new()
            .with(
                "/c/printer.cfg",
                "[printer]\n[include a.cfg]\nkinematics: corexy\n",
            )
            .with("/c/a.cfg", "[a]\n");
        let err = Config::load(&files, Path::new("/c/printer.cfg")).unwrap_err();
        assert!(matches!(err, Error::Syntax { line: 3, .. }), "{err}");
    }

    #[test]
    fn crlf_files_parse_and_spans_point_at_the_value() {
        let text = "[stepper_x]\r\nrotation_distance: 40 \r\n";
        let files = MemFiles::new().with("/p.cfg", text);
        let cfg = Config::load(&files, Path::new("/p.cfg")).unwrap();
        let o = cfg.option("stepper_x", "rotation_distance").unwrap();
        assert_eq!(o.value, "40");
        assert_eq!(&text[o.origin.value_span.clone()], "40");
    }

    #[test]
    fn lone_cr_line_endings_are_lines_as_in_pythons_universal_newlines() {
        // Klipper opens config files in text mode: "\r" alone ends a line (old Mac editors).
        let text = "[printer]\rkinematics: corexy\r[stepper_x]\rrotation_distance: 40\r\
                    microsteps: 16\r\n[stepper_y]\nrotation_distance: 39.5\r";
        let files = MemFiles::new().with("/p.cfg", text);
        let cfg = Config::load(&files, Path::new("/p.cfg")).unwrap();
        assert_eq!(cfg.get("printer", "kinematics"), Some("corexy"));
        assert_eq!(cfg.get("stepper_x", "microsteps"), Some("16"));
        let o = cfg.option("stepper_x", "rotation_distance").unwrap();
        assert_eq!(o.value, "40");
        assert_eq!(o.origin.first_line, 4);
        assert_eq!(&text[o.origin.value_span.clone()], "40");
        let y = cfg.option("stepper_y", "rotation_distance").unwrap();
        assert_eq!((y.value.as_str(), y.origin.first_line), ("39.5", 7));
        // and an edit keeps the lone CRs
        let edit =
            super::super::edit::set_value(&cfg, "stepper_x", "rotation_distance", "40.2").unwrap();
        assert_eq!(edit.new_text, text.replacen(": 40\r", ": 40.2\r", 1));
    }

    #[test]
    fn a_file_starting_with_a_byte_order_mark_is_refused_as_klipper_refuses_it() {
        // Python's utf-8 codec keeps U+FEFF, so configparser sees "\u{feff}[printer]" and
        // stops with "File contains no section headers" (checked with the bench's Python).
        for text in [
            "\u{feff}[printer]\nkinematics: corexy\n",
            "\u{feff}# c\n[a]\nx: 1\n",
        ] {
            let files = MemFiles::new()
                .with("/c/printer.cfg", "[include inc.cfg]\n")
                .with("/c/inc.cfg", text);
            let err = Config::load(&files, Path::new("/c/printer.cfg")).unwrap_err();
            let msg = err.to_string();
            assert!(matches!(err, Error::Syntax { line: 1, .. }), "{msg}");
            assert!(
                msg.starts_with("/c/inc.cfg line 1: the file starts with a UTF-8 byte order mark"),
                "{msg}"
            );
            assert!(msg.contains("save it as UTF-8 without BOM"), "{msg}");
        }
    }

    #[test]
    fn a_read_error_names_its_cause_once() {
        let err = Config::load(&MemFiles::new(), Path::new("/c/printer.cfg")).unwrap_err();
        let shown = format!("{:#}", anyhow::Error::new(err));
        assert_eq!(shown.matches("no such file").count(), 1, "{shown}");
        assert!(
            shown.starts_with("cannot read Klipper config file /c/printer.cfg"),
            "{shown}"
        );
    }

    #[test]
    fn includes_read_every_matched_file_whatever_its_extension_and_fail_on_a_folder() {
        // Klipper's glob.glob("configs/*") also returns steppers.cfg.bak and reads it.
        let files = MemFiles::new()
            .with("/c/printer.cfg", "[include configs/*]\n")
            .with(
                "/c/configs/steppers.cfg",
                "[stepper_x]\nrotation_distance: 40\n",
            )
            .with(
                "/c/configs/steppers.cfg.bak",
                "[stepper_x]\nrotation_distance: 39\n",
            );
        let cfg = Config::load(&files, Path::new("/c/printer.cfg")).unwrap();
        assert_eq!(cfg.get("stepper_x", "rotation_distance"), Some("39"));
        assert_eq!(cfg.files().len(), 3);
        // a folder matched by the pattern stops the load, as open() on it stops Klipper
        let files = files.with("/c/configs/old/x.cfg", "[a]\n");
        let err = Config::load(&files, Path::new("/c/printer.cfg")).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, Error::Read { .. }), "{msg}");
        assert!(msg.contains("/c/configs/old"), "{msg}");
        assert!(msg.contains("it is a folder"), "{msg}");
    }

    #[test]
    fn a_blank_line_inside_the_save_config_block_makes_klipper_ignore_the_block() {
        let text = "[a]\nx: 1\n\n#*# <---------------------- SAVE_CONFIG ---------------------->\n\
                    #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n#*#\n\
                    #*# [b]\n\n#*# y = 2\n";
        let files = MemFiles::new().with("/p.cfg", text);
        let cfg = Config::load(&files, Path::new("/p.cfg")).unwrap();
        assert!(matches!(
            cfg.save_config_status(),
            SaveConfigStatus::Corrupted { .. }
        ));
        assert!(!cfg.has_section("b"));
    }

    #[test]
    fn a_line_without_delimiter_is_a_syntax_error_with_its_line() {
        let files = MemFiles::new().with("/p.cfg", "[a]\nx: 1\nnonsense\n");
        let err = Config::load(&files, Path::new("/p.cfg")).unwrap_err();
        assert!(matches!(err, Error::Syntax { line: 3, .. }), "{err}");
    }
}
