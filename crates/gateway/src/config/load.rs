//! Loading: TOML text + environment overrides layered by the `config` crate, then a
//! structural pass that collects every unknown key, type error and missing key, then
//! [`validate`](super::validate).
//!
//! # Why the structural pass loops
//!
//! serde stops at the first error. To report all of them, the merged tree is
//! deserialized with `serde_path_to_error`, which names the key of the error; the
//! offending key is then taken out of the tree and deserialization retried:
//!
//! - unknown key: reported and removed; nothing else is affected.
//! - wrong type or value: reported and removed; a key with a default then takes it,
//!   a required key turns into "missing", which is not reported twice.
//! - missing required key: reported (unless a misspelling of it was), then filled
//!   with a stand-in of the right type (tried in turn: text, integer, bool, table,
//!   array; an enum gets its first value), so the search goes on and every missing
//!   key of a table is found. Nothing is reported about the stand-ins themselves. If
//!   no stand-in fits, the table holding the key is dropped.
//!
//! Semantic validation still runs on the result, but its findings under an entry
//! (`devices.X`, `axes.Y`, ...) that had a wrong or missing value are dropped (they
//! would describe stand-ins or defaults, not the file), and names of dropped entries,
//! or of every entry of a missing section, count as defined.

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;

use config::{Environment, File, FileFormat, Source};

use super::validate::{validate_assuming, Assumed};
use super::{Config, ConfigError, ConfigProblem, ENV_PREFIX, ENV_SEPARATOR};

/// Loads `path` with overrides from the process environment (`COMPGATE__...`) and
/// validates it. Returns the configuration only when nothing is wrong; otherwise every
/// problem at once.
pub fn load(path: &Path) -> Result<Config, ConfigError> {
    let env = std::env::vars_os().map(|(k, v)| {
        (
            k.to_string_lossy().into_owned(),
            v.to_string_lossy().into_owned(),
        )
    });
    load_with_env(path, env)
}

/// As [`load`], with the environment given explicitly (tests, or a caller that has
/// already filtered it). Only entries named `COMPGATE__...` are used.
pub fn load_with_env(
    path: &Path,
    env: impl IntoIterator<Item = (String, String)>,
) -> Result<Config, ConfigError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Read {
        file: file.clone(),
        message: e.to_string(),
    })?;
    load_str_with_env(&text, &file, env)
}

/// Loads and validates configuration text, e.g. an embedded file. `origin` names it
/// in problems. The process environment is **not** consulted (so tests are not at the
/// mercy of the environment they run in); use [`load_str_with_env`] for that.
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
    let layered = match layered {
        Ok(tree) => tree,
        Err(e) => {
            problems.push(ConfigProblem::new(origin, "(file)", e.to_string()));
            return Err(ConfigError::Invalid(problems));
        }
    };

    let structure = structural_pass(layered, origin, &overrides);
    problems.extend(structure.problems);
    if let Some(cfg) = &structure.config {
        let tainted: BTreeSet<String> = structure
            .touched
            .iter()
            .chain(&structure.dropped)
            .map(|p| render(entry_prefix(p)))
            .collect();
        let mut assumed = Assumed::default();
        for path in structure.touched.iter().chain(&structure.dropped) {
            let (section, name) = match path.as_slice() {
                [Seg::Key(section)] => (section, None),
                [Seg::Key(section), Seg::Key(name)] if structure.dropped.contains(path) => {
                    (section, Some(name))
                }
                _ => continue,
            };
            let names = match section.as_str() {
                "devices" => &mut assumed.devices,
                "channels" => &mut assumed.channels,
                "nc_modules" => &mut assumed.nc_modules,
                _ => continue,
            };
            match name {
                Some(n) => {
                    names.insert(n.clone());
                }
                None => names.any = true,
            }
        }
        problems.extend(
            validate_assuming(cfg, origin, &assumed)
                .into_iter()
                .filter(|p| !tainted.iter().any(|t| is_under(&p.key, t))),
        );
    }
    for p in &mut problems {
        annotate_env(p, &overrides);
    }
    match structure.config {
        Some(cfg) if problems.is_empty() => Ok(cfg),
        None if problems.is_empty() => Err(invalid(ConfigProblem::new(
            origin,
            "(file)",
            "the structure could not be read (no single key to blame)",
        ))),
        _ => Err(ConfigError::Invalid(problems)),
    }
}

// -------------------------------------------------------------------- key paths --

/// One level of a key path.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
enum Seg {
    Key(String),
    Index(usize),
}

/// A key as written in a dotted path: bare when TOML allows it, else quoted.
pub(super) fn key_segment(k: &str) -> Cow<'_, str> {
    if !k.is_empty()
        && k.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        Cow::Borrowed(k)
    } else {
        Cow::Owned(format!("{k:?}"))
    }
}

/// `devices.ain1.timeout_s`, `axes.X.k0.terms[1].channel`.
fn render(path: &[Seg]) -> String {
    render_with(path, key_segment)
}

/// The path in the `config` crate's expression syntax (keys never quoted).
fn render_expr(path: &[Seg]) -> String {
    render_with(path, Cow::Borrowed)
}

fn render_with<'a>(path: &'a [Seg], key: impl Fn(&'a str) -> Cow<'a, str>) -> String {
    let mut s = String::new();
    for seg in path {
        match seg {
            Seg::Key(k) => {
                if !s.is_empty() {
                    s.push('.');
                }
                s.push_str(&key(k));
            }
            Seg::Index(i) => s.push_str(&format!("[{i}]")),
        }
    }
    s
}

/// Whether dotted `key` is `prefix` or lies below it.
fn is_under(key: &str, prefix: &str) -> bool {
    match key.strip_prefix(prefix) {
        Some(rest) => rest.is_empty() || rest.starts_with('.') || rest.starts_with('['),
        None => prefix.is_empty(),
    }
}

/// The named entry a path lies in: `devices.X`, `sim.channels.X`, `gateway`, ...
fn entry_prefix(path: &[Seg]) -> &[Seg] {
    let depth = match path.first() {
        Some(Seg::Key(s))
            if matches!(s.as_str(), "devices" | "channels" | "nc_modules" | "axes") =>
        {
            2
        }
        Some(Seg::Key(s)) if s == "sim" => match path.get(1) {
            Some(Seg::Key(t)) if t == "channels" || t == "nc_modules" => 3,
            _ => 1,
        },
        _ => 1,
    };
    &path[..depth.min(path.len())]
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
    ConfigProblem::new(
        origin,
        key,
        format!("TOML syntax error: {}", e.message().trim()),
    )
}

// ------------------------------------------------------------------ environment --

/// One `COMPGATE__...` variable, its key mapped back onto the file's spelling.
#[derive(Debug)]
struct EnvOverride {
    /// The variable's name as set.
    var: String,
    /// The value as set, before the `config` crate parsed it.
    raw: String,
    /// The key it sets, in the file's spelling.
    path: Vec<Seg>,
    /// The value as the `config` crate parsed it (bool, integer, float or string).
    value: config::Value,
}

/// The `config` crate's [`Environment`] source does the parsing (prefix, `__`
/// separator, value types); its lowercased keys are then matched against the file's
/// keys ignoring case, so `COMPGATE__CHANNELS__T_BED__ADDRESS` sets `channels.T_bed`
/// rather than creating a channel `t_bed`. A level that is a number and meets an array
/// in the file becomes an index.
fn env_overrides(
    env: impl IntoIterator<Item = (String, String)>,
    file: &toml::Table,
    origin: &str,
    problems: &mut Vec<ConfigProblem>,
) -> Vec<EnvOverride> {
    let pattern = format!("{ENV_PREFIX}{ENV_SEPARATOR}").to_lowercase();
    let selected: HashMap<String, String> = env
        .into_iter()
        .filter(|(k, _)| k.to_lowercase().starts_with(&pattern))
        .collect();
    if selected.is_empty() {
        return Vec::new();
    }
    // The same key computation as the Environment source, to find the raw value and
    // the variable's name again.
    let mut by_key: BTreeMap<String, Vec<(&String, &String)>> = BTreeMap::new();
    for (name, raw) in &selected {
        let key = name.to_lowercase()[pattern.len()..].replace(ENV_SEPARATOR, ".");
        by_key.entry(key).or_default().push((name, raw));
    }
    let parsed = Environment::with_prefix(ENV_PREFIX)
        .separator(ENV_SEPARATOR)
        .try_parsing(true)
        .ignore_empty(true)
        .source(Some(selected.clone().into_iter().collect()))
        .collect();
    let parsed = match parsed {
        Ok(p) => p,
        Err(e) => {
            problems.push(ConfigProblem::new(origin, "(environment)", e.to_string()));
            return Vec::new();
        }
    };
    let root = toml::Value::Table(file.clone());
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

/// Maps a lowercased dotted key onto the spelling of the keys in `root`.
fn restore_case(root: &toml::Value, key: &str) -> Result<Vec<Seg>, String> {
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
                            return Err(format!(
                                "`{seg}` matches {} ignoring case; rename them",
                                names.join(" and ")
                            ));
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
                    return Err(format!(
                        "index {i} is beyond the {} elements of {}",
                        a.len(),
                        render(&path)
                    ))
                }
                Err(_) => {
                    return Err(format!(
                        "{} is an array; expected a 0-based index instead of `{seg}`",
                        render(&path)
                    ))
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

/// Says which environment variables touched the key of a problem.
fn annotate_env(p: &mut ConfigProblem, overrides: &[EnvOverride]) {
    let vars: Vec<&str> = overrides
        .iter()
        .filter(|o| {
            let k = render(&o.path);
            is_under(&p.key, &k) || is_under(&k, &p.key)
        })
        .map(|o| o.var.as_str())
        .collect();
    if !vars.is_empty() {
        p.message
            .push_str(&format!(" (environment: {})", vars.join(", ")));
    }
}

// -------------------------------------------------------------- structural pass --

struct Structure {
    config: Option<Config>,
    problems: Vec<ConfigProblem>,
    /// Keys (file indices) whose value was wrong, missing or dropped: semantic
    /// findings below their entries would describe stand-ins, not the file.
    touched: Vec<Vec<Seg>>,
    /// Entries (file indices) removed as a whole: their names count as defined.
    dropped: Vec<Vec<Seg>>,
}

/// Upper bound of deserialization attempts; every attempt removes or fills in a key,
/// so only a pathological file gets near it.
const MAX_ATTEMPTS: usize = 2000;

/// Stand-ins tried, in this order, for a required key that is missing, until one
/// has the right type. Enum keys get the first allowed value instead of `""`.
fn stand_in(i: usize) -> Option<toml::Value> {
    Some(match i {
        0 => toml::Value::String(String::new()),
        1 => toml::Value::Integer(0),
        2 => toml::Value::Boolean(false),
        3 => toml::Value::Table(toml::Table::new()),
        4 => toml::Value::Array(Vec::new()),
        _ => return None,
    })
}

/// The loop described in the module documentation. All bookkeeping uses the file's
/// array indices; `shifts` translates them to the shrinking tree.
struct Pass<'a> {
    tree: toml::Value,
    origin: &'a str,
    overrides: &'a [EnvOverride],
    problems: Vec<ConfigProblem>,
    touched: Vec<Vec<Seg>>,
    dropped: Vec<Vec<Seg>>,
    /// Keys whose problem is already reported (a removed wrong value, a key whose
    /// misspelling was reported): their "missing" is not reported again.
    explained: BTreeSet<Vec<Seg>>,
    /// Keys holding a stand-in -> index of the stand-in in use.
    filled: BTreeMap<Vec<Seg>, usize>,
    /// Array path -> file indices of the elements removed from it.
    shifts: BTreeMap<Vec<Seg>, Vec<usize>>,
    /// Environment values turned back into text.
    coerced: BTreeSet<Vec<Seg>>,
}

fn structural_pass(tree: toml::Value, origin: &str, overrides: &[EnvOverride]) -> Structure {
    let mut pass = Pass {
        tree,
        origin,
        overrides,
        problems: Vec::new(),
        touched: Vec::new(),
        dropped: Vec::new(),
        explained: BTreeSet::new(),
        filled: BTreeMap::new(),
        shifts: BTreeMap::new(),
        coerced: BTreeSet::new(),
    };
    let mut config = None;
    for _ in 0..MAX_ATTEMPTS {
        match serde_path_to_error::deserialize::<_, Config>(pass.tree.clone()) {
            Ok(cfg) => {
                config = Some(cfg);
                break;
            }
            Err(e) => {
                let message = e.inner().message().to_string();
                if !pass.step(e.path(), &message) {
                    break;
                }
            }
        }
    }
    Structure {
        config,
        problems: pass.problems,
        touched: pass.touched,
        dropped: pass.dropped,
    }
}

impl Pass<'_> {
    fn report(&mut self, key: &[Seg], message: String) {
        self.problems
            .push(ConfigProblem::new(self.origin, render(key), message));
    }

    /// Handles one error; false when no progress is possible.
    fn step(&mut self, path: &serde_path_to_error::Path, message: &str) -> bool {
        let Some(current) = segments(path) else {
            self.report(&[], humanize(message));
            return false;
        };
        let at = to_file_indices(&current, &self.shifts);
        // The deepest stand-in the error lies in, if any.
        let in_stand_in = self
            .filled
            .keys()
            .filter(|f| at.starts_with(f))
            .max_by_key(|f| f.len())
            .cloned();

        if let Some(name) = quoted_after(message, "unknown field `") {
            let mut key = at;
            if key.last() != Some(&Seg::Key(name.to_string())) {
                key.push(Seg::Key(name.to_string()));
            }
            if in_stand_in.is_none() {
                self.report(&key, humanize(message));
                let allowed = message
                    .split_once("expected")
                    .map_or(vec![], |(_, t)| backticked(t));
                if let (Some(best), Some((_, parent))) = (closest(name, &allowed), key.split_last())
                {
                    let mut meant = parent.to_vec();
                    meant.push(Seg::Key(best.to_string()));
                    self.explained.insert(meant);
                }
            }
            return self.remove(&key);
        }

        if let Some(name) = quoted_after(message, "missing field `") {
            let mut key = at;
            key.push(Seg::Key(name.to_string()));
            if in_stand_in.is_none() && !self.explained.contains(&key) {
                self.report(&key, humanize(message));
            }
            self.touched.push(key.clone());
            return self.fill(&key, 0);
        }

        if let Some(stand_in) = in_stand_in {
            // The stand-in has the wrong type: an enum gets its first allowed value,
            // anything else the next candidate.
            let target = if self.filled.contains_key(&at) {
                at
            } else {
                stand_in
            };
            let first_variant = message
                .strip_prefix("unknown variant `")
                .and_then(|rest| rest.split_once("expected"))
                .and_then(|(_, allowed)| backticked(allowed).into_iter().next());
            if let Some(variant) = first_variant {
                if self.set(&target, toml::Value::String(variant.to_string())) {
                    self.filled.insert(target, usize::MAX);
                    return true;
                }
            }
            let next = self.filled.get(&target).map_or(0, |i| i.saturating_add(1));
            return self.fill(&target, next);
        }

        // A number or bool from the environment where text is expected: the variable
        // meant the text.
        if message.contains("expected a string") && !self.coerced.contains(&at) {
            if let Some(o) = self.overrides.iter().find(|o| o.path == at) {
                let raw = toml::Value::String(o.raw.clone());
                if self.set(&at, raw) {
                    self.coerced.insert(at);
                    return true;
                }
            }
        }
        self.report(&at, humanize(message));
        self.explained.insert(at.clone());
        self.touched.push(at.clone());
        self.remove(&at)
    }

    /// Puts stand-in `i` at `key`; when none is left, drops the table holding it.
    fn fill(&mut self, key: &[Seg], i: usize) -> bool {
        match stand_in(i) {
            Some(v) => {
                self.filled.insert(key.to_vec(), i);
                self.set(key, v)
            }
            None => {
                let Some((_, parent)) = key.split_last() else {
                    return false;
                };
                self.dropped.push(parent.to_vec());
                self.touched.push(parent.to_vec());
                self.filled.retain(|f, _| !f.starts_with(parent));
                self.remove(parent)
            }
        }
    }

    /// Sets the value at `key` (file indices), creating it in an existing table.
    fn set(&mut self, key: &[Seg], value: toml::Value) -> bool {
        let Some(current) = to_current(key, &self.shifts) else {
            return false;
        };
        let Some((last, parent)) = current.split_last() else {
            return false;
        };
        match (node_mut(&mut self.tree, parent), last) {
            (Some(toml::Value::Table(t)), Seg::Key(k)) => {
                t.insert(k.clone(), value);
                true
            }
            (Some(toml::Value::Array(a)), Seg::Index(i)) if *i < a.len() => {
                a[*i] = value;
                true
            }
            _ => false,
        }
    }

    /// Removes the key at `key` (file indices); remembers removed array elements.
    fn remove(&mut self, key: &[Seg]) -> bool {
        let Some(current) = to_current(key, &self.shifts) else {
            return false;
        };
        let (Some((last, parent)), Some((file_last, file_parent))) =
            (current.split_last(), key.split_last())
        else {
            return false;
        };
        match (node_mut(&mut self.tree, parent), last) {
            (Some(toml::Value::Table(t)), Seg::Key(k)) => t.remove(k).is_some(),
            (Some(toml::Value::Array(a)), Seg::Index(i)) if *i < a.len() => {
                a.remove(*i);
                if let Seg::Index(orig) = file_last {
                    let gone = self.shifts.entry(file_parent.to_vec()).or_default();
                    gone.push(*orig);
                    gone.sort_unstable();
                }
                true
            }
            _ => false,
        }
    }
}

/// The error's path as segments; `None` when serde could not name a level.
fn segments(path: &serde_path_to_error::Path) -> Option<Vec<Seg>> {
    use serde_path_to_error::Segment;
    let mut out = Vec::new();
    for s in path.iter() {
        match s {
            Segment::Map { key } => out.push(Seg::Key(key.clone())),
            Segment::Seq { index } => out.push(Seg::Index(*index)),
            Segment::Enum { .. } => {}
            Segment::Unknown => return None,
        }
    }
    Some(out)
}

/// Translates indices in the current (shrunk) tree back to the file's indices.
fn to_file_indices(path: &[Seg], shifts: &BTreeMap<Vec<Seg>, Vec<usize>>) -> Vec<Seg> {
    let mut out: Vec<Seg> = Vec::with_capacity(path.len());
    for seg in path {
        match seg {
            Seg::Index(i) => {
                let mut idx = *i;
                if let Some(gone) = shifts.get(&out) {
                    for g in gone {
                        if *g <= idx {
                            idx += 1;
                        }
                    }
                }
                out.push(Seg::Index(idx));
            }
            key => out.push(key.clone()),
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

/// Translates the file's indices to the current tree's; `None` when an element on
/// the way was removed.
fn to_current(path: &[Seg], shifts: &BTreeMap<Vec<Seg>, Vec<usize>>) -> Option<Vec<Seg>> {
    let mut out = Vec::with_capacity(path.len());
    for (depth, seg) in path.iter().enumerate() {
        match seg {
            Seg::Index(i) => {
                let gone = shifts.get(&path[..depth]).map_or(&[][..], |g| g.as_slice());
                if gone.contains(i) {
                    return None;
                }
                out.push(Seg::Index(i - gone.iter().filter(|g| **g < *i).count()));
            }
            key => out.push(key.clone()),
        }
    }
    Some(out)
}

/// `name` in messages like "unknown field `name`, expected ...".
fn quoted_after<'m>(message: &'m str, prefix: &str) -> Option<&'m str> {
    message.strip_prefix(prefix)?.split('`').next()
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

/// The candidate closest to `name` when it is close enough to be a typo.
///
/// Close enough: at most a third of the letters differ (at least 2 may), or half of
/// them when the first three letters agree (`retry` -> `retries`).
fn closest<'c>(name: &str, candidates: &[&'c str]) -> Option<&'c str> {
    let len = name.chars().count();
    let head = |s: &str| s.to_lowercase().chars().take(3).collect::<String>();
    candidates
        .iter()
        .map(|c| (edit_distance(name, c), *c))
        .filter(|(d, c)| {
            let limit = if len >= 3 && head(name) == head(c) {
                len.div_ceil(2)
            } else {
                len / 3
            };
            *d <= limit.max(2)
        })
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

fn edit_distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.to_lowercase().chars().collect();
    let b: Vec<char> = b.to_lowercase().chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.iter().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, cb) in b.iter().enumerate() {
            let subst = prev[j] + usize::from(ca != cb);
            cur[j + 1] = subst.min(prev[j + 1] + 1).min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

#[cfg(test)]
mod tests;
