//! Loading: TOML text + environment overrides layered by the `config` crate, then
//! the structural check against the JSON Schema ([`structure`](super::structure)),
//! then the stages' semantic validation ([`validate`](super::validate)).
//!
//! # Every problem at once
//!
//! The structural check looks at every key of the layered tree and reports every
//! unknown key, wrong type, missing key and unknown enum value with its path. Then:
//!
//! - unknown keys are taken out of the tree: nothing else depends on them;
//! - an entry (`devices.X`, `channels.X`, `nc_modules.X`, `axes.X`,
//!   `sim.channels.X`, `sim.nc_modules.X`, or a whole single section such as
//!   `[gateway]`) with any other structural problem is taken out as a whole, and its
//!   name counts as defined, so references to it cause no follow-up problem. Its own
//!   references (a channel's `device`, an axis' `nc_module` and term channels) are
//!   still checked on the raw values;
//! - what remains is deserialized and validated by the stages; findings below a
//!   removed entry cannot occur.
//!
//! An environment value that the `config` crate parsed as a number or bool where the
//! schema wants text is turned back into the text that was set.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;

use config::{Environment, File, FileFormat, Source};
use serde::Deserialize;

use super::keys::{entry_prefix, is_under, key_segment, render, render_expr, Seg};
use super::problem::{ConfigError, ConfigProblem};
use super::root::{list, validate_assuming, Assumed, Config};
use super::structure::{self, closest, Finding, Kind};
use super::{ENV_PREFIX, ENV_SEPARATOR};

#[cfg(test)]
use super::structure::edit_distance;

/// Loads `path` with overrides from the process environment (`COMPGATE__...`) and
/// validates it for `run`: what the gateway connects to must be reachable (no port
/// 0). Returns the configuration only when nothing is wrong; otherwise every problem
/// at once.
pub fn load(path: &Path) -> Result<Config, ConfigError> {
    load_with_env(path, process_env())
}

/// As [`load`], also returning the environment overrides that went into the
/// configuration, sorted by key: `validate` and `run` name them, as nothing in the file
/// shows that a value came from elsewhere.
pub fn load_listing_overrides(path: &Path) -> Result<(Config, Vec<EnvOverride>), ConfigError> {
    let file = path.display().to_string();
    load_text(&read(path)?, &file, process_env(), false)
}

/// As [`load`], with the environment given explicitly (tests, or a caller that has
/// already filtered it). Only entries named `COMPGATE__...` are used.
pub fn load_with_env(
    path: &Path,
    env: impl IntoIterator<Item = (String, String)>,
) -> Result<Config, ConfigError> {
    let file = path.display().to_string();
    load_text(&read(path)?, &file, env, false).map(|(cfg, _)| cfg)
}

/// As [`load`] for the simulated plant (`compgate sim`): in a file with `[sim]`, port
/// 0 in an address passes, as the plant binds a free port for it.
pub fn load_for_sim(path: &Path) -> Result<Config, ConfigError> {
    let file = path.display().to_string();
    load_text(&read(path)?, &file, process_env(), true).map(|(cfg, _)| cfg)
}

/// Loads and validates configuration text, e.g. the demo's embedded file or a test's.
/// `origin` names it in problems. In a text with `[sim]` port 0 passes, as for
/// [`load_for_sim`]: the simulated plant binds a free port for it and writes the port
/// into the address before the gateway connects. The process environment is **not**
/// consulted (so tests are not at the mercy of the environment they run in); use
/// [`load_str_with_env`] for that.
pub fn load_str(text: &str, origin: &str) -> Result<Config, ConfigError> {
    load_str_with_env(text, origin, std::iter::empty())
}

/// As [`load_str`], with environment overrides from `env` (pass `std::env::vars()` to
/// let an embedded configuration be overridden like a file).
pub fn load_str_with_env(
    text: &str,
    origin: &str,
    env: impl IntoIterator<Item = (String, String)>,
) -> Result<Config, ConfigError> {
    load_text(text, origin, env, true).map(|(cfg, _)| cfg)
}

/// The largest configuration file read, bytes. A cell's is a few kB and a line's with
/// 10000 channels about 5 MB; anything far larger is not a configuration
/// (`--config /dev/zero` would read until memory ran out).
pub const MAX_FILE_BYTES: u64 = 64 << 20;

/// The text of the file at `path`, refused beyond [`MAX_FILE_BYTES`] and with a
/// hint when it is not UTF-8.
fn read(path: &Path) -> Result<String, ConfigError> {
    use std::io::Read;
    let failed = |message: String| ConfigError::Read {
        file: path.display().to_string(),
        message,
    };
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_FILE_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| failed(e.to_string()))?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(failed(format!(
            "larger than {} MB; not a configuration (10000 channels take about 5 MB)",
            MAX_FILE_BYTES >> 20
        )));
    }
    if compgate_core::measure::is_utf16(&bytes) {
        return Err(failed(
            "the file is UTF-16 text (Windows Notepad's \"Unicode\"); save it as UTF-8".into(),
        ));
    }
    String::from_utf8(bytes).map_err(|e| {
        let at = &e.as_bytes()[..e.utf8_error().valid_up_to()];
        let line = at.iter().filter(|b| **b == b'\n').count() + 1;
        failed(format!(
            "line {line} is not UTF-8 text (a legacy code page?); save the file as UTF-8"
        ))
    })
}

fn process_env() -> impl Iterator<Item = (String, String)> {
    std::env::vars_os().map(|(k, v)| {
        (
            k.to_string_lossy().into_owned(),
            v.to_string_lossy().into_owned(),
        )
    })
}

/// Loads and validates `text`; `for_sim` as [`validate_assuming`]. With the
/// configuration, the environment overrides in it.
fn load_text(
    text: &str,
    origin: &str,
    env: impl IntoIterator<Item = (String, String)>,
    for_sim: bool,
) -> Result<(Config, Vec<EnvOverride>), ConfigError> {
    let invalid = |p: ConfigProblem| ConfigError::Invalid(vec![p]);
    let file_tree: toml::Table = text
        .parse()
        .map_err(|e| invalid(syntax_problem(origin, text, &e)))?;

    let mut problems = Vec::new();
    let overrides = env_overrides(env, &file_tree, origin, &mut problems);

    let layered = config::Config::builder()
        .add_source(File::from_str(text, FileFormat::Toml))
        .add_source(CaseRestoredEnv(
            overrides
                .iter()
                .map(|o| (render_expr(&o.path), o.value.clone()))
                .collect(),
        ))
        .build()
        .and_then(|c| c.try_deserialize::<toml::Value>());
    let mut tree = match layered {
        Ok(tree) => tree,
        Err(e) => {
            problems.push(ConfigProblem::new(origin, "(file)", e.to_string()));
            return Err(ConfigError::Invalid(problems));
        }
    };

    let schema = super::schema::json_schema();
    let mut findings = structure::check(&schema, &tree);
    // A number or bool from the environment where text is expected: the variable
    // meant the text.
    let mut coerced = false;
    for f in findings.iter().filter(|f| f.kind == Kind::NotText) {
        if let Some(o) = overrides.iter().find(|o| o.path == f.path) {
            coerced |= set(&mut tree, &f.path, toml::Value::String(o.raw.clone()));
        }
    }
    if coerced {
        findings = structure::check(&schema, &tree);
    }

    let raw = tree.clone();
    let (cfg, broken, assumed) = clean(tree, &findings);
    problems.extend(
        findings
            .iter()
            .map(|f| ConfigProblem::new(origin, render(&f.path), f.message.clone())),
    );
    match cfg {
        Ok(cfg) => {
            let tainted: Vec<String> = broken.iter().map(|b| render(b)).collect();
            let recorder_broken = tainted.iter().any(|t| t == "recorder");
            problems.extend(
                validate_assuming(&cfg, origin, &assumed, for_sim)
                    .into_iter()
                    .filter(|p| !tainted.iter().any(|t| is_under(&p.key, t)))
                    .filter(|p| !(recorder_broken && p.key == "mqtt")),
            );
            problems.extend(broken_references(&raw, &broken, origin));
            for p in &mut problems {
                annotate_env(p, &overrides);
            }
            if problems.is_empty() {
                Ok((cfg, overrides))
            } else {
                Err(ConfigError::Invalid(problems))
            }
        }
        Err(e) => {
            if problems.is_empty() {
                problems.push(ConfigProblem::new(origin, "(file)", humanize(e.message())));
            }
            for p in &mut problems {
                annotate_env(p, &overrides);
            }
            Err(ConfigError::Invalid(problems))
        }
    }
}

/// The sections every file must have; a missing or broken one becomes empty. NC
/// targets (`[targets]`, `[nc_modules]`) and axes are optional: a monitoring-only
/// config has neither.
const REQUIRED_SECTIONS: [&str; 2] = ["devices", "channels"];

/// Takes the unknown keys and the broken entries out of `tree` and deserializes the
/// rest. Returns the configuration (or serde's error), the broken entries and the
/// names that count as defined.
fn clean(
    mut tree: toml::Value,
    findings: &[Finding],
) -> (Result<Config, toml::de::Error>, BTreeSet<Vec<Seg>>, Assumed) {
    let mut broken: BTreeSet<Vec<Seg>> = BTreeSet::new();
    let mut unknown: Vec<&[Seg]> = Vec::new();
    for f in findings {
        match f.kind {
            Kind::Unknown => unknown.push(&f.path),
            Kind::NotText | Kind::Broken => {
                broken.insert(entry_prefix(&f.path).to_vec());
            }
        }
    }
    for path in unknown {
        remove(&mut tree, path);
    }
    let mut assumed = Assumed::default();
    for b in &broken {
        if let [Seg::Key(section), Seg::Key(name)] = b.as_slice() {
            if section == "channels" {
                let device = tree
                    .get("channels")
                    .and_then(|c| c.get(name))
                    .and_then(|c| c.get("device"))
                    .and_then(toml::Value::as_str);
                match device {
                    Some(d) => assumed.devices_read.insert(d.to_string()),
                    None => assumed.devices_read.any = true,
                }
            }
        }
        remove(&mut tree, b);
        let (section, name) = match b.as_slice() {
            [Seg::Key(section)] => (section.as_str(), None),
            [Seg::Key(section), Seg::Key(name)] => (section.as_str(), Some(name)),
            _ => continue,
        };
        let names = match section {
            "devices" => &mut assumed.devices,
            "channels" => &mut assumed.channels,
            // Targets and NC modules are one namespace for the axes.
            "nc_modules" | "targets" => &mut assumed.nc_modules,
            _ => continue,
        };
        match name {
            Some(n) => names.insert(n.clone()),
            None => names.any = true,
        }
    }
    if let toml::Value::Table(t) = &mut tree {
        for section in REQUIRED_SECTIONS {
            if !t.contains_key(section) {
                t.insert(section.to_string(), toml::Value::Table(toml::Table::new()));
                match section {
                    "devices" => assumed.devices.any = true,
                    "channels" => assumed.channels.any = true,
                    _ => {}
                }
            }
        }
    }
    let cfg = Config::deserialize(tree);
    (cfg, broken, assumed)
}

/// The references of entries left out for structural problems, checked on the raw
/// values: a channel's `device`, an axis' `nc_module` and its terms' channels.
fn broken_references(
    raw: &toml::Value,
    broken: &BTreeSet<Vec<Seg>>,
    origin: &str,
) -> Vec<ConfigProblem> {
    let section = |name: &str| raw.get(name).and_then(toml::Value::as_table);
    let names = |name: &str| -> Option<Vec<String>> {
        // An axis names a target in `[targets]` or in the older `[nc_modules]`.
        if name == "nc_modules" {
            let both: Vec<String> = ["targets", "nc_modules"]
                .iter()
                .filter_map(|s| section(s))
                .flat_map(|t| t.keys().cloned())
                .collect();
            return Some(both);
        }
        section(name).map(|t| t.keys().cloned().collect())
    };
    let mut out = Vec::new();
    let mut check = |key: String, value: Option<&toml::Value>, sec: &str, what: &str| {
        let (Some(v), Some(defined)) = (value.and_then(toml::Value::as_str), names(sec)) else {
            return;
        };
        if !defined.iter().any(|d| d == v) {
            out.push(ConfigProblem::new(
                origin,
                key,
                format!(
                    "unknown {what} `{v}`; expected one of the names in [{sec}]: {}",
                    list(defined.iter())
                ),
            ));
        }
    };
    for b in broken {
        let [Seg::Key(sec), Seg::Key(name)] = b.as_slice() else {
            continue;
        };
        let Some(e) = section(sec).and_then(|t| t.get(name)) else {
            continue;
        };
        let key = |f: &str| format!("{sec}.{}.{f}", key_segment(name));
        match sec.as_str() {
            "channels" => check(key("device"), e.get("device"), "devices", "device"),
            "axes" => {
                check(
                    key("nc_module"),
                    e.get("nc_module"),
                    "nc_modules",
                    "NC module",
                );
                for model in ["k0", "tan_beta"] {
                    let terms = e
                        .get(model)
                        .and_then(|m| m.get("terms"))
                        .and_then(toml::Value::as_array);
                    for (i, t) in terms.into_iter().flatten().enumerate() {
                        check(
                            key(&format!("{model}.terms[{i}].channel")),
                            t.get("channel"),
                            "channels",
                            "channel",
                        );
                    }
                }
            }
            _ => {}
        }
    }
    out
}

fn node_mut<'a>(tree: &'a mut toml::Value, path: &[Seg]) -> Option<&'a mut toml::Value> {
    let mut node = tree;
    for seg in path {
        node = match (node, seg) {
            (toml::Value::Table(t), Seg::Key(k)) => t.get_mut(k)?,
            (toml::Value::Array(a), Seg::Index(i)) => a.get_mut(*i)?,
            _ => return None,
        };
    }
    Some(node)
}

/// Sets the value at `path`; false when the place does not exist.
fn set(tree: &mut toml::Value, path: &[Seg], value: toml::Value) -> bool {
    match node_mut(tree, path) {
        Some(node) => {
            *node = value;
            true
        }
        None => false,
    }
}

/// Removes the table key at `path` (array elements stay: entries are tables).
fn remove(tree: &mut toml::Value, path: &[Seg]) {
    let Some((Seg::Key(last), parent)) = path.split_last() else {
        return;
    };
    if let Some(toml::Value::Table(t)) = node_mut(tree, parent) {
        t.remove(last);
    }
}

fn syntax_problem(origin: &str, text: &str, e: &toml::de::Error) -> ConfigProblem {
    let key = match e.span() {
        Some(span) => {
            let before = &text[..span.start.min(text.len())];
            let line = before.matches('\n').count() + 1;
            let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
            format!("line {line}, column {column}")
        }
        None => "(syntax)".to_string(),
    };
    let message = e.message().trim();
    // A model pasted beside the [axes.X] already there (`cat config.toml model.toml`)
    // got "duplicate key" alone.
    let hint = if message.starts_with("duplicate key") {
        " (a table or key given twice: a model from calibrate or diagnose goes in place \
         of the axis' table, not beside it)"
    } else {
        ""
    };
    ConfigProblem::new(origin, key, format!("TOML syntax error: {message}{hint}"))
}

// ------------------------------------------------------------------ environment --

/// One `COMPGATE__...` variable, its key mapped back onto the file's spelling.
///
/// Shown as `VAR -> key`, without the value: a password may be in one.
pub struct EnvOverride {
    /// The variable's name as set.
    var: String,
    /// The value as set, before the `config` crate parsed it.
    raw: String,
    /// The key it sets, in the file's spelling.
    path: Vec<Seg>,
    /// The value as the `config` crate parsed it (bool, integer, float or string).
    value: config::Value,
    /// The table above `path` the file does not have, which the override creates
    /// (e.g. `devices.ain2` for `COMPGATE__DEVICES__AIN2__TIMEOUT_S`).
    creates: Option<Vec<Seg>>,
}

impl EnvOverride {
    /// The variable's name as set.
    pub fn var(&self) -> &str {
        &self.var
    }

    /// The key it sets, as problems name keys (e.g. `axes.X.k0.terms[1].ref_degc`).
    pub fn key(&self) -> String {
        render(&self.path)
    }
}

impl std::fmt::Display for EnvOverride {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} -> {}", self.var, self.key())
    }
}

// By hand, as a derived Debug would print the value to wherever the record is logged.
impl std::fmt::Debug for EnvOverride {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EnvOverride")
            .field("var", &self.var)
            .field("path", &self.path)
            .field("creates", &self.creates)
            .finish_non_exhaustive()
    }
}

/// The `config` crate's [`Environment`] source does the parsing (prefix, `__`
/// separator, value types); its lowercased keys are then matched against the file's
/// keys ignoring case, so `COMPGATE__CHANNELS__T_BED__ADDRESS` sets `channels.T_bed`
/// rather than creating a channel `t_bed`. A level that is a number and meets an array
/// in the file becomes an index.
///
/// An empty variable and a `COMPGATE_...__...` one (one `_` after the prefix) are
/// problems, not ignored: both are what a template with a missing value or a typo
/// produces, and ignoring them runs the file's value, e.g. another machine's NC
/// address.
fn env_overrides(
    env: impl IntoIterator<Item = (String, String)>,
    file: &toml::Table,
    origin: &str,
    problems: &mut Vec<ConfigProblem>,
) -> Vec<EnvOverride> {
    let pattern = format!("{ENV_PREFIX}{ENV_SEPARATOR}").to_lowercase();
    let root = toml::Value::Table(file.clone());
    // Variables the file names itself (`user_env`, `password_env`) are no overrides,
    // whatever their spelling.
    let mut named = Vec::new();
    env_names(&root, &mut named);
    let mut env: Vec<(String, String)> = env.into_iter().collect();
    env.sort();
    let mut selected: HashMap<String, String> = HashMap::new();
    for (name, raw) in env {
        let Some(rest) = name.to_lowercase().strip_prefix(&pattern).map(dotted) else {
            if let Some(meant) = mistyped_prefix(&name).filter(|_| !named.contains(&&*name)) {
                let key = file_key(&root, &dotted(&meant[pattern.len()..]));
                problems.push(ConfigProblem::new(
                    origin,
                    key,
                    format!(
                        "the environment variable {name} looks like an override but has one \
                         `_` after {ENV_PREFIX}: write {meant}"
                    ),
                ));
            }
            continue;
        };
        if raw.is_empty() {
            let keep = match restore_case(&root, &rest) {
                Ok(path) if node(&root, &path).is_some() => {
                    "unset it to keep the file's value, or give one"
                }
                _ => "unset it or give a value",
            };
            problems.push(ConfigProblem::new(
                origin,
                file_key(&root, &rest),
                format!("the environment variable {name} is empty: {keep}"),
            ));
            continue;
        }
        selected.insert(name, raw);
    }
    if selected.is_empty() {
        return Vec::new();
    }
    // The same key computation as the Environment source, to find the raw value and
    // the variable's name again.
    let mut by_key: BTreeMap<String, Vec<(&String, &String)>> = BTreeMap::new();
    for (name, raw) in &selected {
        let key = dotted(&name.to_lowercase()[pattern.len()..]);
        by_key.entry(key).or_default().push((name, raw));
    }
    let parsed = Environment::with_prefix(ENV_PREFIX)
        .separator(ENV_SEPARATOR)
        .try_parsing(true)
        .source(Some(selected.clone().into_iter().collect()))
        .collect();
    let parsed = match parsed {
        Ok(p) => p,
        Err(e) => {
            problems.push(ConfigProblem::new(origin, "(environment)", e.to_string()));
            return Vec::new();
        }
    };
    let mut out = Vec::new();
    for (key, value) in parsed {
        let Some(vars) = by_key.get(&key) else {
            continue;
        };
        let mut names: Vec<&String> = vars.iter().map(|(n, _)| *n).collect();
        names.sort();
        let var = names
            .iter()
            .map(|n| n.as_str())
            .collect::<Vec<_>>()
            .join(", ");
        if vars.len() > 1 {
            problems.push(ConfigProblem::new(
                origin,
                key.clone(),
                format!("set by several environment variables differing in case: {var}"),
            ));
            continue;
        }
        let raw = vars[0].1.clone();
        match restore_case(&root, &key) {
            Ok(path) => out.push(EnvOverride {
                var,
                raw,
                creates: created_table(&root, &path),
                path,
                value,
            }),
            Err(why) => problems.push(ConfigProblem::new(
                origin,
                key.clone(),
                format!("environment variable {var}: {why}"),
            )),
        }
    }
    out.sort_by(|a, b| a.path.cmp(&b.path));
    out
}

/// The values of every `..._env` key in `node`: names of variables the config reads.
fn env_names<'a>(node: &'a toml::Value, out: &mut Vec<&'a str>) {
    match node {
        toml::Value::Table(t) => {
            for (k, v) in t {
                match v.as_str() {
                    Some(name) if k.ends_with("_env") => out.push(name),
                    _ => env_names(v, out),
                }
            }
        }
        toml::Value::Array(a) => a.iter().for_each(|v| env_names(v, out)),
        _ => {}
    }
}

/// The dotted, lowercased key of an override's name after the prefix, as the
/// Environment source computes it.
fn dotted(rest: &str) -> String {
    rest.to_lowercase().replace(ENV_SEPARATOR, ".")
}

/// `key` (dotted, lowercased) as problems name it: in the file's spelling where the
/// file has it, else as given.
fn file_key(root: &toml::Value, key: &str) -> String {
    restore_case(root, key).map_or_else(|_| key.to_string(), |path| render(&path))
}

/// The override `name` was meant to be when it starts with `COMPGATE_` (any case)
/// followed by a level and `__`, e.g. `COMPGATE_NC_MODULES__NC_X__ADDRESS`; `None`
/// for a name without `__` after the prefix, such as the `COMPGATE_OPCUA_USER` a
/// `user_env` names.
fn mistyped_prefix(name: &str) -> Option<String> {
    let prefix = name.get(..ENV_PREFIX.len())?;
    let rest = name.get(ENV_PREFIX.len()..)?.strip_prefix('_')?;
    let mistyped = prefix.eq_ignore_ascii_case(ENV_PREFIX)
        && !rest.starts_with('_')
        && rest.contains(ENV_SEPARATOR);
    mistyped.then(|| format!("{ENV_PREFIX}{ENV_SEPARATOR}{rest}"))
}

/// The value at `path`, if `root` has it.
fn node<'a>(root: &'a toml::Value, path: &[Seg]) -> Option<&'a toml::Value> {
    let mut node = root;
    for seg in path {
        node = match (node, seg) {
            (toml::Value::Table(t), Seg::Key(k)) => t.get(k)?,
            (toml::Value::Array(a), Seg::Index(i)) => a.get(*i)?,
            _ => return None,
        };
    }
    Some(node)
}

/// Maps a lowercased dotted key onto the spelling of the keys in `root`.
fn restore_case(root: &toml::Value, key: &str) -> Result<Vec<Seg>, EnvKeyError> {
    let mut path = Vec::new();
    let mut node = Some(root);
    for seg in key.split('.') {
        node = match node {
            Some(toml::Value::Table(t)) => {
                if let Some(v) = t.get(seg) {
                    path.push(Seg::Key(seg.to_string()));
                    Some(v)
                } else {
                    let matches: Vec<(&String, &toml::Value)> =
                        t.iter().filter(|(k, _)| k.to_lowercase() == seg).collect();
                    match matches.as_slice() {
                        [] => {
                            path.push(Seg::Key(seg.to_string()));
                            None
                        }
                        [(k, v)] => {
                            path.push(Seg::Key((*k).clone()));
                            Some(*v)
                        }
                        many => {
                            let names: Vec<String> =
                                many.iter().map(|(k, _)| format!("`{k}`")).collect();
                            return Err(EnvKeyError::Ambiguous {
                                seg: seg.to_string(),
                                names: names.join(" and "),
                            });
                        }
                    }
                }
            }
            Some(toml::Value::Array(a)) => match seg.parse::<usize>() {
                Ok(i) if i < a.len() => {
                    path.push(Seg::Index(i));
                    a.get(i)
                }
                Ok(i) => {
                    return Err(EnvKeyError::BeyondEnd {
                        index: i,
                        len: a.len(),
                        array: render(&path),
                    })
                }
                Err(_) => {
                    return Err(EnvKeyError::NotAnIndex {
                        array: render(&path),
                        seg: seg.to_string(),
                    })
                }
            },
            _ => {
                path.push(Seg::Key(seg.to_string()));
                None
            }
        };
    }
    Ok(path)
}

/// The first table on `path` that `root` lacks, when it lies above the key itself.
fn created_table(root: &toml::Value, path: &[Seg]) -> Option<Vec<Seg>> {
    let mut node = root;
    for (i, seg) in path.iter().enumerate() {
        let next = match (node, seg) {
            (toml::Value::Table(t), Seg::Key(k)) => t.get(k),
            (toml::Value::Array(a), Seg::Index(i)) => a.get(*i),
            _ => None,
        };
        match next {
            Some(n) => node = n,
            None => return (i + 1 < path.len()).then(|| path[..=i].to_vec()),
        }
    }
    None
}

/// The overrides as a `config` source, keys in the file's spelling.
#[derive(Debug, Clone)]
struct CaseRestoredEnv(config::Map<String, config::Value>);

impl Source for CaseRestoredEnv {
    fn clone_into_box(&self) -> Box<dyn Source + Send + Sync> {
        Box::new(self.clone())
    }

    fn collect(&self) -> Result<config::Map<String, config::Value>, config::ConfigError> {
        Ok(self.0.clone())
    }
}

/// ` (environment: VAR)` when a `COMPGATE__...` variable of the process environment
/// set `key` (as problems name it, e.g. `recorder.path`; no array element), else `""`:
/// a check made after loading (the recorder's path on the file system) says where the
/// value came from, as the problems of loading do.
pub fn env_note(key: &str) -> String {
    let env = std::env::vars_os()
        .filter_map(|(k, v)| Some((k.into_string().ok()?, v.into_string().ok()?)));
    env_suffix(&env_vars_setting(env, key))
}

/// The variables of `env` that set `key`, sorted. An empty one sets nothing.
fn env_vars_setting(env: impl IntoIterator<Item = (String, String)>, key: &str) -> Vec<String> {
    let pattern = format!("{ENV_PREFIX}{ENV_SEPARATOR}").to_lowercase();
    let key = key.to_lowercase();
    let mut vars: Vec<String> = env
        .into_iter()
        .filter(|(name, value)| {
            !value.is_empty()
                && name
                    .to_lowercase()
                    .strip_prefix(&pattern)
                    .is_some_and(|rest| rest.replace(ENV_SEPARATOR, ".") == key)
        })
        .map(|(name, _)| name)
        .collect();
    vars.sort();
    vars
}

fn env_suffix(vars: &[String]) -> String {
    if vars.is_empty() {
        String::new()
    } else {
        format!(" (environment: {})", vars.join(", "))
    }
}

/// Says which environment variables touched the key of a problem, and which created
/// the entry it lies in: a key missing from an entry the file does not have is not the
/// file's fault.
fn annotate_env(p: &mut ConfigProblem, overrides: &[EnvOverride]) {
    let vars: Vec<String> = overrides
        .iter()
        .filter_map(|o| {
            if let Some(table) = o.creates.as_deref().map(render) {
                if is_under(&p.key, &table) {
                    return Some(format!("{} creates `{table}` which the file lacks", o.var));
                }
            }
            let k = render(&o.path);
            (is_under(&p.key, &k) || is_under(&k, &p.key)).then(|| o.var.clone())
        })
        .collect();
    p.message.push_str(&env_suffix(&vars));
}

/// Why an environment variable's name does not fit the file.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
enum EnvKeyError {
    /// Several keys of the file match the level ignoring case.
    #[error("`{seg}` matches {names} ignoring case; rename them")]
    Ambiguous { seg: String, names: String },
    /// An array index past the end.
    #[error("index {index} is beyond the {len} elements of {array}")]
    BeyondEnd {
        index: usize,
        len: usize,
        array: String,
    },
    /// A level that is not a number meets an array.
    #[error("{array} is an array; expected a 0-based index instead of `{seg}`")]
    NotAnIndex { array: String, seg: String },
}

/// Every `quoted` word in `s`.
fn backticked(s: &str) -> Vec<&str> {
    s.split('`').skip(1).step_by(2).collect()
}

/// serde's messages in the operator's words; the key path is shown separately.
fn humanize(message: &str) -> String {
    if let Some(rest) = message.strip_prefix("unknown field `") {
        let Some((name, tail)) = rest.split_once('`') else {
            return message.to_string();
        };
        let expected = backticked(tail);
        if let Some(best) = closest(name, &expected) {
            return format!("unknown key; did you mean `{best}`?");
        }
        if let Some(note) = tail.strip_prefix(' ') {
            return format!("unknown key {note}");
        }
        return match expected.as_slice() {
            [] => "unknown key; this table takes no keys".to_string(),
            keys => format!(
                "unknown key; expected one of {}",
                keys.iter()
                    .map(|k| format!("`{k}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
    }
    if message.starts_with("missing field `") {
        return "required key is missing".to_string();
    }
    if let Some(rest) = message.strip_prefix("unknown variant ") {
        return format!("unknown value {rest}");
    }
    let mut m = message.to_string();
    for (from, to) in [
        ("expected f64", "expected a number"),
        ("expected u8", "expected an integer 0..=255"),
        ("expected u16", "expected an integer 0..=65535"),
        ("expected u32", "expected an integer 0..=4294967295"),
        ("expected u64", "expected an integer >= 0"),
        ("expected a sequence", "expected an array"),
        ("expected a map", "expected a table"),
    ] {
        if let Some(head) = m.strip_suffix(from) {
            m = format!("{head}{to}");
        }
    }
    if let Some(i) = m.find("expected struct ") {
        m.truncate(i);
        m.push_str("expected a table");
    }
    m
}

#[cfg(test)]
mod tests;
