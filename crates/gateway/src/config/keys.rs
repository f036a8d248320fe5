//! Key paths: how a key of the configuration is named in problems
//! (`devices.ain1.timeout_s`, `axes.X.k0.terms[1].channel`), and seconds as
//! [`Duration`]s.

use std::borrow::Cow;
use std::time::Duration;

/// Longest key written out in a path: every valid key and name fits. A longer one
/// (a name over the limit, perhaps megabytes) is shown by its first characters and
/// its length, never echoed.
const MAX_SHOWN_KEY_CHARS: usize = 64;

/// A key as written in a dotted path: bare when TOML allows it, else quoted; one
/// longer than 64 characters as `<first 16 characters…, N characters>`.
pub fn key_segment(k: &str) -> Cow<'_, str> {
    let n = k.chars().count();
    if n > MAX_SHOWN_KEY_CHARS {
        let head: String = k.chars().take(16).collect();
        return Cow::Owned(format!("<{}…, {n} characters>", key_segment(&head)));
    }
    if !k.is_empty()
        && k.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        Cow::Borrowed(k)
    } else {
        Cow::Owned(format!("{k:?}"))
    }
}

/// `section.name`, the name quoted when it is not a bare TOML key.
pub fn entry(section: &str, name: &str) -> String {
    format!("{section}.{}", key_segment(name))
}

/// `section.name.field`, the name quoted when it is not a bare TOML key.
pub fn field(section: &str, name: &str, field: &str) -> String {
    format!("{section}.{}.{field}", key_segment(name))
}

/// One level of a key path.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Seg {
    /// A table key.
    Key(String),
    /// An array index.
    Index(usize),
}

/// `devices.ain1.timeout_s`, `axes.X.k0.terms[1].channel`.
pub(crate) fn render(path: &[Seg]) -> String {
    render_with(path, key_segment)
}

/// The path in the `config` crate's expression syntax (keys never quoted).
pub(crate) fn render_expr(path: &[Seg]) -> String {
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
pub(crate) fn is_under(key: &str, prefix: &str) -> bool {
    match key.strip_prefix(prefix) {
        Some(rest) => rest.is_empty() || rest.starts_with('.') || rest.starts_with('['),
        None => prefix.is_empty(),
    }
}

/// The named entry a path lies in: `devices.X`, `sim.channels.X`, `gateway`, ...
pub(crate) fn entry_prefix(path: &[Seg]) -> &[Seg] {
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

/// Converts seconds from the configuration into a [`Duration`].
///
/// Saturating: negative or NaN becomes zero, too large becomes [`Duration::MAX`], so a
/// value that validation would reject never panics here.
pub fn secs(s: f64) -> Duration {
    if s.is_nan() || s <= 0.0 {
        Duration::ZERO
    } else {
        Duration::try_from_secs_f64(s).unwrap_or(Duration::MAX)
    }
}
