//! The structural check: the layered TOML tree against the JSON Schema of
//! [`Config`](super::Config) ([`json_schema`](super::schema::json_schema)).
//!
//! Every key is looked at, so every unknown key, wrong type, out-of-range integer,
//! unknown enum value and missing required key of the whole file is found in one
//! pass, each with its path. A table tagged by one of its keys (`transport` of a
//! device, `kind` of a scaling) is checked against the schema of its tag's value
//! only, so a key of another transport is reported as such.
//!
//! The schema is the subset of JSON Schema that `schemars` writes for the config
//! structs: `$ref` into `$defs`, `allOf`, `oneOf` (tagged tables and documented enum
//! values), `anyOf` (an optional value), `type`, `properties`, `required`,
//! `additionalProperties`, `enum`, `const`, `minimum`, `exclusiveMinimum`, `maximum`,
//! `maxLength` and `items`.
//!
//! # Ranges
//!
//! Every numeric key's range and every text key's longest length is declared once,
//! on its field (`#[schemars(range(min = .., max = ..))]`, a key that must be > 0
//! `#[schemars(range(max = ..), extend("exclusiveMinimum" = 0.0))]`,
//! `#[schemars(length(max = ..))]`), so the JSON Schema carries it and this walker
//! checks it: a value outside (integer or float, `nan` included) or a text longer
//! than allowed is reported with its key and the range, e.g.
//!
//! ```text
//! devices.ain1.timeout_s: invalid value: floating point `1e-320`, expected a number 0.001..=3600
//! devices.ain1.serial_path: invalid value: a string of 1048576 characters, expected a string of at most 1024 characters
//! ```

use serde_json::Value as Json;

use super::keys::Seg;
use crate::nc::number;

/// What kind of structural problem a [`Finding`] is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    /// A key the schema does not know: reported, then ignored.
    Unknown,
    /// A value of the wrong type where text is expected (an environment value may be
    /// meant as text).
    NotText,
    /// Anything else: the entry holding it cannot be read.
    Broken,
}

/// One structural problem.
#[derive(Debug, Clone)]
pub(crate) struct Finding {
    /// The key.
    pub path: Vec<Seg>,
    /// What is wrong, in the operator's words.
    pub message: String,
    /// How it affects the entry.
    pub kind: Kind,
}

/// Every structural problem of `tree` under `schema`, in the order of the keys.
pub(crate) fn check(schema: &Json, tree: &toml::Value) -> Vec<Finding> {
    let mut w = Walker {
        root: schema,
        out: Vec::new(),
    };
    w.walk(schema, tree, &mut Vec::new());
    w.out
}

/// The schema of one place, with references, `allOf` and the chosen `oneOf` branch
/// merged in.
#[derive(Default)]
struct View<'s> {
    types: Vec<&'s str>,
    props: Vec<(&'s str, &'s Json)>,
    required: Vec<&'s str>,
    closed: bool,
    additional: Option<&'s Json>,
    values: Option<Vec<&'s Json>>,
    min: Option<f64>,
    /// `exclusiveMinimum`: the value must be above it.
    above: Option<f64>,
    max: Option<f64>,
    max_len: Option<u64>,
    items: Option<&'s Json>,
    tag: Option<Tag<'s>>,
}

/// The tag of a tagged table.
struct Tag<'s> {
    key: &'s str,
    /// The instance's tag value when it names a branch.
    chosen: Option<String>,
    /// Every allowed value, in schema order.
    values: Vec<String>,
    /// The keys of every branch, by tag value.
    branch_keys: Vec<(String, Vec<&'s str>)>,
}

struct Walker<'s> {
    root: &'s Json,
    out: Vec<Finding>,
}

impl<'s> Walker<'s> {
    fn resolve(&self, mut s: &'s Json) -> &'s Json {
        for _ in 0..32 {
            let Some(r) = s.get("$ref").and_then(Json::as_str) else {
                break;
            };
            let target = r.strip_prefix('#').and_then(|ptr| self.root.pointer(ptr));
            match target {
                Some(t) if s.as_object().is_some_and(|o| o.len() == 1) => s = t,
                _ => break,
            }
        }
        s
    }

    fn view(&self, s: &'s Json, inst: Option<&toml::Value>) -> View<'s> {
        let mut v = View::default();
        self.merge(&mut v, s, inst, 0);
        v
    }

    fn merge(&self, v: &mut View<'s>, s: &'s Json, inst: Option<&toml::Value>, depth: usize) {
        if depth > 32 {
            return;
        }
        let s = self.resolve(s);
        let Some(o) = s.as_object() else {
            return;
        };
        if let Some(r) = o.get("$ref").and_then(Json::as_str) {
            if let Some(t) = r.strip_prefix('#').and_then(|p| self.root.pointer(p)) {
                self.merge(v, t, inst, depth + 1);
            }
        }
        match o.get("type") {
            Some(Json::String(t)) => v.types = vec![t.as_str()],
            Some(Json::Array(ts)) => {
                v.types = ts
                    .iter()
                    .filter_map(Json::as_str)
                    .filter(|t| *t != "null")
                    .collect()
            }
            _ => {}
        }
        if let Some(Json::Object(props)) = o.get("properties") {
            for (k, p) in props {
                if !v.props.iter().any(|(n, _)| n == k) {
                    v.props.push((k.as_str(), p));
                }
            }
        }
        if let Some(Json::Array(req)) = o.get("required") {
            for r in req.iter().filter_map(Json::as_str) {
                if !v.required.contains(&r) {
                    v.required.push(r);
                }
            }
        }
        for key in ["additionalProperties", "unevaluatedProperties"] {
            match o.get(key) {
                Some(Json::Bool(false)) => v.closed = true,
                Some(a @ Json::Object(_)) => v.additional = Some(a),
                _ => {}
            }
        }
        if let Some(c) = o.get("const") {
            v.values = Some(vec![c]);
        }
        if let Some(Json::Array(e)) = o.get("enum") {
            v.values = Some(e.iter().collect());
        }
        if let Some(m) = o.get("minimum").and_then(Json::as_f64) {
            v.min = Some(m);
        }
        if let Some(m) = o.get("exclusiveMinimum").and_then(Json::as_f64) {
            v.above = Some(m);
        }
        if let Some(m) = o.get("maximum").and_then(Json::as_f64) {
            v.max = Some(m);
        }
        if let Some(m) = o.get("maxLength").and_then(Json::as_u64) {
            v.max_len = Some(m);
        }
        if let Some(i) = o.get("items") {
            v.items = Some(i);
        }
        if let Some(Json::Array(all)) = o.get("allOf") {
            for a in all {
                self.merge(v, a, inst, depth + 1);
            }
        }
        if let Some(Json::Array(any)) = o.get("anyOf") {
            // An optional value: the branches other than `null`.
            let branches: Vec<&Json> = any
                .iter()
                .filter(|b| b.get("type").and_then(Json::as_str) != Some("null"))
                .collect();
            let pick = branches
                .iter()
                .find(|b| inst.is_some_and(|i| type_fits(&self.view(b, None).types, i)))
                .or(branches.first());
            if let Some(b) = pick {
                self.merge(v, b, inst, depth + 1);
            }
        }
        if let Some(Json::Array(one)) = o.get("oneOf") {
            self.one_of(v, one, inst, depth);
        }
    }

    /// Documented enum values (every branch a constant), or a table tagged by the
    /// one key whose value is a constant in every branch.
    fn one_of(&self, v: &mut View<'s>, one: &'s [Json], inst: Option<&toml::Value>, depth: usize) {
        let branches: Vec<View<'s>> = one.iter().map(|b| self.view(b, None)).collect();
        if branches
            .iter()
            .all(|b| b.props.is_empty() && b.values.is_some())
        {
            let mut values = Vec::new();
            for b in &branches {
                values.extend(b.values.iter().flatten().copied());
                for t in &b.types {
                    if !v.types.contains(t) {
                        v.types.push(t);
                    }
                }
            }
            v.values = Some(values);
            return;
        }
        let tag_key = branches.first().and_then(|first| {
            first.props.iter().map(|(k, _)| *k).find(|k| {
                branches.iter().all(|b| {
                    b.props
                        .iter()
                        .any(|(n, p)| n == k && self.view(p, None).values.is_some())
                })
            })
        });
        let Some(tag_key) = tag_key else {
            return;
        };
        let tag_of = |b: &View<'s>| -> String {
            b.props
                .iter()
                .find(|(n, _)| *n == tag_key)
                .and_then(|(_, p)| self.view(p, None).values)
                .and_then(|vals| vals.first().and_then(|x| x.as_str()).map(str::to_string))
                .unwrap_or_default()
        };
        let values: Vec<String> = branches.iter().map(tag_of).collect();
        let given = inst
            .and_then(|i| i.as_table())
            .and_then(|t| t.get(tag_key))
            .and_then(|x| x.as_str());
        let chosen = given.and_then(|g| values.iter().position(|x| x == g));
        let branch_keys = branches
            .iter()
            .zip(&values)
            .map(|(b, val)| (val.clone(), b.props.iter().map(|(k, _)| *k).collect()))
            .collect();
        if v.types.is_empty() {
            v.types = vec!["object"];
        }
        match chosen {
            Some(i) => self.merge(v, &one[i], inst, depth + 1),
            None => {
                // No branch: every branch's keys are known, only the tag is required.
                for b in &branches {
                    for (k, p) in &b.props {
                        if !v.props.iter().any(|(n, _)| n == k) {
                            v.props.push((k, p));
                        }
                    }
                    v.closed |= b.closed;
                }
                if !v.required.contains(&tag_key) {
                    v.required.push(tag_key);
                }
            }
        }
        v.tag = Some(Tag {
            key: tag_key,
            chosen: chosen.map(|i| values[i].clone()),
            values,
            branch_keys,
        });
    }

    fn push(&mut self, path: &[Seg], message: String, kind: Kind) {
        self.out.push(Finding {
            path: path.to_vec(),
            message,
            kind,
        });
    }

    fn walk(&mut self, s: &'s Json, inst: &toml::Value, path: &mut Vec<Seg>) {
        let v = self.view(s, Some(inst));
        if !v.types.is_empty() && !type_fits(&v.types, inst) {
            let kind = if v.types.contains(&"string") {
                Kind::NotText
            } else {
                Kind::Broken
            };
            self.push(
                path,
                format!(
                    "invalid type: {}, expected {}",
                    describe(inst),
                    expected(&v)
                ),
                kind,
            );
            return;
        }
        if let Some(values) = &v.values {
            if !values.iter().any(|x| json_eq(x, inst)) {
                let message = match inst {
                    toml::Value::String(s) => {
                        format!("unknown value `{s}`, expected {}", one_of_text(values))
                    }
                    other => format!(
                        "invalid type: {}, expected {}",
                        describe(other),
                        one_of_text(values)
                    ),
                };
                self.push(path, message, Kind::Broken);
                return;
            }
        }
        match inst {
            toml::Value::Integer(_) | toml::Value::Float(_) => {
                let x = match inst {
                    toml::Value::Integer(i) => *i as f64,
                    toml::Value::Float(f) => *f,
                    _ => f64::NAN,
                };
                // `nan` is outside every declared range.
                let out = (x.is_nan() && (v.min.is_some() || v.above.is_some() || v.max.is_some()))
                    || v.min.is_some_and(|m| x < m)
                    || v.above.is_some_and(|m| x <= m)
                    || v.max.is_some_and(|m| x > m);
                if out {
                    let register = match (path.last(), inst) {
                        (Some(Seg::Key(k)), toml::Value::Integer(i)) if k == "address" => {
                            six_digit_register(*i)
                        }
                        _ => None,
                    };
                    self.push(
                        path,
                        format!(
                            "invalid value: {}, expected {}{}",
                            describe(inst),
                            expected(&v),
                            register.unwrap_or_default()
                        ),
                        Kind::Broken,
                    );
                }
            }
            toml::Value::String(s) => {
                let n = s.chars().count();
                if let Some(max) = v.max_len.filter(|m| n as u64 > *m) {
                    // Not the text itself: it may be megabytes long.
                    self.push(
                        path,
                        format!(
                            "invalid value: a string of {n} characters, expected a string of at \
                             most {max} characters"
                        ),
                        Kind::Broken,
                    );
                }
            }
            toml::Value::Array(a) => {
                if let Some(items) = v.items {
                    for (i, x) in a.iter().enumerate() {
                        path.push(Seg::Index(i));
                        self.walk(items, x, path);
                        path.pop();
                    }
                }
            }
            toml::Value::Table(t) => self.table(&v, t, path),
            _ => {}
        }
    }

    fn table(&mut self, v: &View<'s>, t: &toml::Table, path: &mut Vec<Seg>) {
        let mut keys: Vec<&String> = t.keys().collect();
        keys.sort();
        let own: Vec<&str> = v.props.iter().map(|(k, _)| *k).collect();
        let mut explained: Vec<&str> = Vec::new();
        for key in keys {
            let value = &t[key.as_str()];
            path.push(Seg::Key(key.clone()));
            if let Some((_, p)) = v.props.iter().find(|(k, _)| *k == key.as_str()) {
                let tag_bad = v
                    .tag
                    .as_ref()
                    .is_some_and(|tag| tag.key == key.as_str() && tag.chosen.is_none());
                if tag_bad {
                    let tag = v.tag.as_ref().map(|t| t.values.clone()).unwrap_or_default();
                    let message = match value {
                        toml::Value::String(s) => format!(
                            "unknown value `{s}`, expected one of {}",
                            backticked_list(tag.iter().map(String::as_str))
                        ),
                        other => format!(
                            "invalid type: {}, expected one of {}",
                            describe(other),
                            backticked_list(tag.iter().map(String::as_str))
                        ),
                    };
                    self.push(path, message, Kind::Broken);
                } else {
                    self.walk(p, value, path);
                }
            } else if let Some(a) = v.additional {
                self.walk(a, value, path);
            } else if v.closed {
                let (message, meant) = unknown_key(key, &own, v.tag.as_ref());
                if let Some(m) = meant {
                    explained.push(m);
                }
                self.push(path, message, Kind::Unknown);
            }
            path.pop();
        }
        for r in &v.required {
            if t.contains_key(*r) || explained.contains(r) {
                continue;
            }
            path.push(Seg::Key(r.to_string()));
            let message = match &v.tag {
                Some(Tag {
                    key,
                    chosen: Some(val),
                    ..
                }) if key != r => format!("required with {key} = \"{val}\""),
                _ => "required key is missing".to_string(),
            };
            self.push(path, message, Kind::Broken);
            path.pop();
        }
    }
}

/// The message for an unknown key, and the key it probably meant.
fn unknown_key<'k>(key: &str, own: &[&'k str], tag: Option<&Tag<'k>>) -> (String, Option<&'k str>) {
    if let Some(tag) = tag {
        let Tag {
            key: tag_key,
            chosen,
            branch_keys,
            ..
        } = tag;
        let of = |k: &str| -> Vec<String> {
            branch_keys
                .iter()
                .filter(|(_, keys)| keys.contains(&k))
                .map(|(val, _)| format!("\"{val}\""))
                .collect()
        };
        if let Some(val) = chosen {
            let owners = of(key);
            if !owners.is_empty() {
                return (
                    format!(
                        "unknown key (not used by {tag_key} = \"{val}\"; only for {tag_key} = {})",
                        owners.join(" or ")
                    ),
                    None,
                );
            }
            if let Some(best) = closest(key, own) {
                return (format!("unknown key; did you mean `{best}`?"), Some(best));
            }
            let others: Vec<&str> = branch_keys
                .iter()
                .flat_map(|(_, keys)| keys.iter().copied())
                .filter(|k| !own.contains(k))
                .collect();
            if let Some(best) = closest(key, &others) {
                return (
                    format!(
                        "unknown key; did you mean `{best}`? (only for {tag_key} = {}, not \"{val}\")",
                        of(best).join(" or ")
                    ),
                    None,
                );
            }
        }
    }
    if let Some(best) = closest(key, own) {
        return (format!("unknown key; did you mean `{best}`?"), Some(best));
    }
    let message = if own.is_empty() {
        "unknown key; this table takes no keys".to_string()
    } else {
        format!(
            "unknown key; expected one of {}",
            backticked_list(own.iter().copied())
        )
    };
    (message, None)
}

/// The candidate closest to `name` when it is close enough to be a typo.
///
/// Close enough: at most a third of the letters differ (at least 2 may), or half of
/// them when the first three letters agree (`retry` -> `retries`).
pub(crate) fn closest<'c>(name: &str, candidates: &[&'c str]) -> Option<&'c str> {
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

/// Levenshtein distance ignoring case.
pub(crate) fn edit_distance(a: &str, b: &str) -> usize {
    strsim::levenshtein(&a.to_lowercase(), &b.to_lowercase())
}

fn backticked_list<'a>(names: impl Iterator<Item = &'a str>) -> String {
    names
        .map(|n| format!("`{n}`"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn one_of_text(values: &[&Json]) -> String {
    let names: Vec<String> = values
        .iter()
        .map(|x| match x {
            Json::String(s) => s.clone(),
            other => other.to_string(),
        })
        .collect();
    format!(
        "one of {}",
        backticked_list(names.iter().map(String::as_str))
    )
}

fn type_fits(types: &[&str], inst: &toml::Value) -> bool {
    types.is_empty()
        || types.iter().any(|t| {
            matches!(
                (*t, inst),
                ("integer", toml::Value::Integer(_))
                    | ("number", toml::Value::Integer(_) | toml::Value::Float(_))
                    | ("string", toml::Value::String(_))
                    | ("boolean", toml::Value::Boolean(_))
                    | ("object", toml::Value::Table(_))
                    | ("array", toml::Value::Array(_))
            )
        })
}

fn json_eq(x: &Json, inst: &toml::Value) -> bool {
    match (x, inst) {
        (Json::String(a), toml::Value::String(b)) => a == b,
        (Json::Bool(a), toml::Value::Boolean(b)) => a == b,
        (Json::Number(a), toml::Value::Integer(b)) => a.as_i64() == Some(*b),
        (Json::Number(a), toml::Value::Float(b)) => a.as_f64() == Some(*b),
        _ => false,
    }
}

/// A note for a register number from a manual's 6-digit numbering (`400002`: holding
/// register 2), which no 16-bit address takes.
fn six_digit_register(value: i64) -> Option<String> {
    let (table, base) = match value {
        300_001..=365_536 => ("input", 300_001),
        400_001..=465_536 => ("holding", 400_001),
        _ => return None,
    };
    Some(format!(
        "; {value} looks like a 6-digit register number of a device manual ({table} \
         register {}): addresses here are 0-based PDU addresses, so that register is \
         address = {} with register = \"{table}\"",
        value - base + 1,
        value - base
    ))
}

/// The value as serde would name it: `string "x"`, `integer `5``, ...
fn describe(inst: &toml::Value) -> String {
    match inst {
        toml::Value::String(s) => format!("string {s:?}"),
        toml::Value::Integer(i) => format!("integer `{i}`"),
        toml::Value::Float(f) => format!("floating point `{}`", number(*f)),
        toml::Value::Boolean(b) => format!("boolean `{b}`"),
        toml::Value::Datetime(d) => format!("date-time `{d}`"),
        toml::Value::Array(_) => "an array".to_string(),
        toml::Value::Table(_) => "a table".to_string(),
    }
}

/// What the schema wants, in the operator's words.
fn expected(v: &View<'_>) -> String {
    if let Some(values) = &v.values {
        return one_of_text(values);
    }
    let texts: Vec<String> = v
        .types
        .iter()
        .map(|t| match *t {
            "integer" => format!("an integer{}", range_text(v)),
            "number" => format!("a number{}", range_text(v)),
            "string" => match v.max_len {
                Some(max) => format!("a string of at most {max} characters"),
                None => "a string".to_string(),
            },
            "boolean" => "a boolean".to_string(),
            "object" => "a table".to_string(),
            "array" => "an array".to_string(),
            other => other.to_string(),
        })
        .collect();
    texts.join(" or ")
}

/// ` lo..=hi`, ` > lo and <= hi`, ` >= lo`, ` > lo`, ` <= hi` or nothing: the
/// words the stages' validation uses for the same range.
fn range_text(v: &View<'_>) -> String {
    match (v.min, v.above, v.max) {
        (_, Some(lo), Some(hi)) => format!(" > {} and <= {}", number(lo), number(hi)),
        (_, Some(lo), None) => format!(" > {}", number(lo)),
        (Some(lo), None, Some(hi)) => format!(" {}..={}", number(lo), number(hi)),
        (Some(lo), None, None) => format!(" >= {}", number(lo)),
        (None, None, Some(hi)) => format!(" <= {}", number(hi)),
        (None, None, None) => String::new(),
    }
}
