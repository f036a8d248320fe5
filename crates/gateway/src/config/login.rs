//! User name and password for a peer that asks for them (an OPC UA server, an MQTT
//! broker), from a file or from two environment variables: never in the
//! configuration, which `validate` prints and the recorder keeps.

use std::fmt;
use std::path::{Path, PathBuf};

/// User name and password; the password never appears in Debug output or logs.
#[derive(Clone, PartialEq)]
pub struct Credentials {
    pub user: String,
    pub password: String,
}

impl fmt::Debug for Credentials {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Credentials")
            .field("user", &self.user)
            .field("password", &"***")
            .finish()
    }
}

/// The keys `credentials_file`, `user_env` and `password_env` of one table.
#[derive(Debug, Clone, Copy)]
pub struct LoginKeys<'a> {
    pub credentials_file: Option<&'a str>,
    pub user_env: Option<&'a str>,
    pub password_env: Option<&'a str>,
}

/// A key of [`LoginKeys`] at fault, and why.
pub type LoginProblem = (&'static str, String);

impl LoginKeys<'_> {
    /// The problems of the keys; when they name a file or variables, also one that
    /// cannot be read now.
    pub fn problems(&self) -> Vec<LoginProblem> {
        let mut out = Vec::new();
        match (self.credentials_file, self.user_env, self.password_env) {
            (Some(_), Some(_), _) | (Some(_), _, Some(_)) => out.push((
                "credentials_file",
                "give the credentials either in a file or in user_env/password_env, not both"
                    .into(),
            )),
            (None, Some(_), None) => out.push(("password_env", "required with user_env".into())),
            (None, None, Some(_)) => out.push(("user_env", "required with password_env".into())),
            _ => {
                if self.credentials_file.is_some_and(|f| f.trim().is_empty()) {
                    out.push(("credentials_file", "must not be empty".into()));
                }
                for (name, v) in [
                    ("user_env", self.user_env),
                    ("password_env", self.password_env),
                ] {
                    if let Some(v) = v.filter(|v| v.is_empty() || v.contains(['=', '\0'])) {
                        out.push((name, format!("`{v}` is not an environment variable name")));
                    }
                }
                if out.is_empty() {
                    out.extend(self.load().err());
                }
            }
        }
        out
    }

    /// The user and password from `credentials_file` or the variables `user_env` and
    /// `password_env`; `None`: anonymous. An error names the key at fault and why,
    /// never what the file or a variable holds.
    pub fn load(&self) -> Result<Option<Credentials>, LoginProblem> {
        if let Some(file) = self.credentials_file {
            let path = state_path(file);
            let fail = |why: String| ("credentials_file", format!("{}: {why}", path.display()));
            let text = std::fs::read_to_string(&path).map_err(|e| fail(e.to_string()))?;
            let mut lines = text.lines();
            let user = lines.next().unwrap_or_default().to_string();
            // A file caught half written has the user and no password line yet: a
            // login with an empty password would be refused. (`user\n\n` gives one.)
            let password = match (user.is_empty(), lines.next()) {
                (false, Some(password)) => password.to_string(),
                (no_user, _) => {
                    let which = if no_user {
                        "the first line (user name) is empty"
                    } else {
                        "the second line (password) is missing"
                    };
                    return Err(fail(format!(
                        "{which}; expected the user name on the first line and the password \
                         on the second"
                    )));
                }
            };
            return Ok(Some(Credentials { user, password }));
        }
        let (Some(u), Some(p)) = (self.user_env, self.password_env) else {
            return Ok(None);
        };
        // VarError's own text would show a value that is not Unicode: the secret.
        let get = |key: &'static str, name: &str| match std::env::var(name) {
            Ok(v) => Ok(v),
            Err(std::env::VarError::NotPresent) => Err((
                key,
                format!(
                    "environment variable {name} is not set (give it to the service, e.g. \
                     with the unit's Environment= or EnvironmentFile=)"
                ),
            )),
            Err(std::env::VarError::NotUnicode(_)) => Err((
                key,
                format!("environment variable {name} is not valid Unicode"),
            )),
        };
        let user = get("user_env", u)?;
        if user.is_empty() {
            return Err((
                "user_env",
                format!("environment variable {u} is empty; expected the user name"),
            ));
        }
        Ok(Some(Credentials {
            user,
            password: get("password_env", p)?,
        }))
    }

    /// `credentials_file` when group or others may read it.
    pub fn readable_by_others(&self) -> Option<PathBuf> {
        use std::os::unix::fs::PermissionsExt;
        let path = self.credentials_file.map(state_path)?;
        let mode = std::fs::metadata(&path).ok()?.permissions().mode();
        (mode & 0o077 != 0).then_some(path)
    }

    /// Logs a WARN when `credentials_file` is readable by group or others; `peer`
    /// names whose credentials they are.
    pub fn warn_if_readable_by_others(&self, peer: &str) {
        if let Some(path) = self.readable_by_others() {
            tracing::warn!(
                file = %path.display(),
                "{peer} credentials file is readable by group or others; chmod 600 it"
            );
        }
    }
}

/// A relative path under `$STATE_DIRECTORY` when set (as the recorder's database).
pub fn state_path(p: &str) -> PathBuf {
    let path = Path::new(p);
    match std::env::var_os("STATE_DIRECTORY") {
        Some(dir) if path.is_relative() => Path::new(&dir).join(path),
        _ => path.to_path_buf(),
    }
}
