//! `kind = "opcua"`: one axis's SD43900/43910/43920 written through a SINUMERIK-style
//! OPC UA server (route 2, option "Access MyMachine / OPC UA"), with `async-opcua`.
//!
//! The node ids come from templates in the config. The namespace index `{ns}` is looked
//! up by its URI in the server's NamespaceArray at every connect, because a server may
//! order its namespaces differently after a restart or an update. A job is one Write
//! call carrying the values, then one Read (max age 0) that must return them bit for
//! bit. The session is opened on first use; a lost connection or session is dropped and
//! opened anew on the next call, after a capped backoff when connecting fails.

use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use compgate_ncproto::var;
use futures::StreamExt;
use opcua::client::transport::TcpConnector;
use opcua::client::{
    Client, ClientBuilder, IdentityToken, Password, Session, SessionEventLoop, SessionPollResult,
};
use opcua::crypto::SecurityPolicy;
use opcua::types::{
    AttributeId, DataValue, EndpointDescription, MessageSecurityMode, NodeId, NumericRange,
    QualifiedName, ReadValueId, StatusCode, TimestampsToReturn, UserTokenPolicy, VariableId,
    Variant, WriteValue,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio::time::Instant;
use tracing::instrument::WithSubscriber;

use super::config::Place;
use super::{Job, JobIds, JobReport, NcError, NcSnapshot, NcWriter};
use crate::config::keys::secs;
use crate::config::login::{state_path, Credentials, LoginKeys};
use crate::config::problem::{check_host_port, peer_identity, Problems};
use crate::source::modbus::Backoff;
use crate::source::SourceError;

/// Default node-id template of SD43900 (`$SA_TEMP_COMP_ABS_VALUE`). Inferred from
/// Siemens' documented path pattern; browse a real control to confirm it.
pub const DEFAULT_SD43900_NODE: &str =
    "ns={ns};s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_ABS_VALUE[u{axis_number}]";
/// Default node-id template of SD43910 (`$SA_TEMP_COMP_SLOPE`).
pub const DEFAULT_SD43910_NODE: &str =
    "ns={ns};s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_SLOPE[u{axis_number}]";
/// Default node-id template of SD43920 (`$SA_TEMP_COMP_REF_POSITION`).
pub const DEFAULT_SD43920_NODE: &str =
    "ns={ns};s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_REF_POSITION[u{axis_number}]";

/// The placeholders a node-id template may use.
const PLACEHOLDERS: [&str; 3] = ["{ns}", "{axis_number}", "{axis_name}"];

/// The setting data this target writes, in node order.
const VARS: [u16; 3] = [var::SD43900, var::SD43910, var::SD43920];

/// UserAccessLevel bit "CurrentWrite" (OPC UA Part 3, AccessLevelType).
const ACCESS_CURRENT_WRITE: u8 = 0x02;

/// How long a dropped session may take to close politely before its socket is cut.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(2);

/// Security policy of the OPC UA secure channel.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq)]
pub enum OpcuaSecurityPolicy {
    /// No signing, no encryption: for tests on loopback only.
    None,
    /// Basic128Rsa15 (deprecated; older SINUMERIK versions).
    Basic128Rsa15,
    /// Basic256 (deprecated; older SINUMERIK versions).
    Basic256,
    /// Basic256Sha256.
    Basic256Sha256,
    /// Aes128_Sha256_RsaOaep.
    Aes128Sha256RsaOaep,
    /// Aes256_Sha256_RsaPss.
    Aes256Sha256RsaPss,
}

impl OpcuaSecurityPolicy {
    fn to_policy(self) -> SecurityPolicy {
        match self {
            Self::None => SecurityPolicy::None,
            Self::Basic128Rsa15 => SecurityPolicy::Basic128Rsa15,
            Self::Basic256 => SecurityPolicy::Basic256,
            Self::Basic256Sha256 => SecurityPolicy::Basic256Sha256,
            Self::Aes128Sha256RsaOaep => SecurityPolicy::Aes128Sha256RsaOaep,
            Self::Aes256Sha256RsaPss => SecurityPolicy::Aes256Sha256RsaPss,
        }
    }
}

/// Message security mode of the OPC UA secure channel.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq)]
pub enum OpcuaSecurityMode {
    /// Neither signed nor encrypted (only with `security_policy = "None"`).
    None,
    /// Signed.
    Sign,
    /// Signed and encrypted.
    SignAndEncrypt,
}

impl OpcuaSecurityMode {
    fn to_mode(self) -> MessageSecurityMode {
        match self {
            Self::None => MessageSecurityMode::None,
            Self::Sign => MessageSecurityMode::Sign,
            Self::SignAndEncrypt => MessageSecurityMode::SignAndEncrypt,
        }
    }
}

/// An OPC UA target: a SINUMERIK (or any) OPC UA server holding the axis setting data.
/// One table serves every axis of that control; each axis gets its own writer.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct OpcuaTargetConfig {
    /// Endpoint URL of the server, `opc.tcp://HOST:PORT[/PATH]` (a SINUMERIK listens
    /// on port 4840). Required; at most 300 characters.
    #[schemars(length(max = 300))]
    pub endpoint_url: String,
    /// URI of the namespace the node ids live in; its index replaces `{ns}` in the
    /// templates, looked up in the server's NamespaceArray at every connect. Default
    /// `SinumerikVarProvider`; 1..=300 characters.
    #[serde(default = "default_namespace_uri")]
    #[schemars(length(min = 1, max = 300))]
    pub namespace_uri: String,
    /// Node-id template of SD43900 (TEMP_COMP_ABS_VALUE). Must contain `{ns}`; may use
    /// `{axis_number}` (the axis's number on the control, from 1) and `{axis_name}`.
    /// Default `ns={ns};s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_ABS_VALUE[u{axis_number}]`;
    /// at most 500 characters.
    #[serde(default = "default_sd43900_node")]
    #[schemars(length(min = 1, max = 500))]
    pub sd43900_node: String,
    /// Node-id template of SD43910 (TEMP_COMP_SLOPE), as `sd43900_node`. Default
    /// `ns={ns};s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_SLOPE[u{axis_number}]`; at most 500
    /// characters.
    #[serde(default = "default_sd43910_node")]
    #[schemars(length(min = 1, max = 500))]
    pub sd43910_node: String,
    /// Node-id template of SD43920 (TEMP_COMP_REF_POSITION), as `sd43900_node`.
    /// Default `ns={ns};s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_REF_POSITION[u{axis_number}]`;
    /// at most 500 characters.
    #[serde(default = "default_sd43920_node")]
    #[schemars(length(min = 1, max = 500))]
    pub sd43920_node: String,
    /// Security policy of the secure channel: `None`, `Basic128Rsa15`, `Basic256`,
    /// `Basic256Sha256`, `Aes128Sha256RsaOaep` or `Aes256Sha256RsaPss`. Default
    /// `Basic256Sha256`. `None` sends the password in clear: loopback tests only.
    #[serde(default = "default_security_policy")]
    pub security_policy: OpcuaSecurityPolicy,
    /// Message security mode: `None` (only with policy `None`), `Sign` or
    /// `SignAndEncrypt`. Default `SignAndEncrypt`.
    #[serde(default = "default_security_mode")]
    pub security_mode: OpcuaSecurityMode,
    /// Folder of compgate's OPC UA certificates: its own certificate and key (created
    /// on first connect when missing, unless the policy is `None`), `trusted/` and
    /// `rejected/` server certificates. A relative path is taken from
    /// `$STATE_DIRECTORY` (the unit's `StateDirectory=`), else from the working
    /// directory. Default `opcua-pki`; 1..=4096 characters.
    #[serde(default = "default_pki_dir")]
    #[schemars(length(min = 1, max = 4096))]
    pub pki_dir: String,
    /// Trust a server certificate not yet in `trusted/` (and store it there). Default
    /// false: the first connect fails and the certificate lands in `rejected/` until an
    /// administrator moves it to `trusted/`.
    #[serde(default)]
    pub trust_server_certificate: bool,
    /// File holding the user name on its first line and the password on its second
    /// (keep it readable by compgate only); a relative path is taken as `pki_dir` is.
    /// Not with `user_env`/`password_env`. Default none: anonymous unless the two
    /// variables are named; at most 4096 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = 4096))]
    pub credentials_file: Option<String>,
    /// Name of the environment variable holding the user name; requires
    /// `password_env`. Default none; 1..=128 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = 128))]
    pub user_env: Option<String>,
    /// Name of the environment variable holding the password; requires `user_env`.
    /// Default none; 1..=128 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = 128))]
    pub password_env: Option<String>,
    /// Seconds one OPC UA request may take. Default 1.0; 0.001..=3600.
    #[serde(default = "default_request_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub request_timeout_s: f64,
    /// Seconds a connect (endpoints, secure channel, session, namespace lookup) may
    /// take. Default 5.0; 0.001..=3600.
    #[serde(default = "default_connect_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub connect_timeout_s: f64,
    /// Seconds a job (the running gateway's check of what the NC holds, the write and
    /// its read-back; a connect has `connect_timeout_s`) may take. Default 2.0;
    /// 0.001..=3600.
    #[serde(default = "default_job_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub job_timeout_s: f64,
    /// Seconds the server keeps a session without requests (keep-alive reads renew
    /// it); an abandoned session is freed after this. Default 60; 1..=3600.
    #[serde(default = "default_session_timeout_s")]
    #[schemars(range(min = 1.0, max = 3600.0))]
    pub session_timeout_s: f64,
}

impl OpcuaTargetConfig {
    /// A target at `endpoint_url` with every other key at its default.
    pub fn new(endpoint_url: impl Into<String>) -> Self {
        Self {
            endpoint_url: endpoint_url.into(),
            namespace_uri: default_namespace_uri(),
            sd43900_node: default_sd43900_node(),
            sd43910_node: default_sd43910_node(),
            sd43920_node: default_sd43920_node(),
            security_policy: default_security_policy(),
            security_mode: default_security_mode(),
            pki_dir: default_pki_dir(),
            trust_server_certificate: false,
            credentials_file: None,
            user_env: None,
            password_env: None,
            request_timeout_s: default_request_timeout_s(),
            connect_timeout_s: default_connect_timeout_s(),
            job_timeout_s: default_job_timeout_s(),
            session_timeout_s: default_session_timeout_s(),
        }
    }

    /// `request_timeout_s` as a [`Duration`].
    pub fn request_timeout(&self) -> Duration {
        secs(self.request_timeout_s)
    }
    /// `connect_timeout_s` as a [`Duration`].
    pub fn connect_timeout(&self) -> Duration {
        secs(self.connect_timeout_s)
    }
    /// `job_timeout_s` as a [`Duration`].
    pub fn job_timeout(&self) -> Duration {
        secs(self.job_timeout_s)
    }

    /// Whether the target has a node for variable `var_id` (SD43900, SD43910, SD43920).
    pub fn has(&self, var_id: u16) -> bool {
        VARS.contains(&var_id)
    }

    fn templates(&self) -> [(&'static str, &str); 3] {
        [
            ("sd43900_node", &self.sd43900_node),
            ("sd43910_node", &self.sd43910_node),
            ("sd43920_node", &self.sd43920_node),
        ]
    }

    /// The URL is `opc.tcp://host:port[/path]`, every template holds `{ns}` and parses
    /// as a node id, policy and mode agree, the credentials come from one place and can
    /// be read now (as `run` reads them at start, so `validate` as `ExecStartPre=`
    /// catches a missing file or variable), every time > 0.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        if let Err(why) = check_endpoint_url(&self.endpoint_url) {
            out.push(k("endpoint_url"), why);
        }
        if self.namespace_uri.trim().is_empty() {
            out.push(k("namespace_uri"), "must not be empty");
        }
        for (name, template) in self.templates() {
            if let Err(why) = check_template(template) {
                out.push(k(name), why);
            }
        }
        let none_policy = self.security_policy == OpcuaSecurityPolicy::None;
        let none_mode = self.security_mode == OpcuaSecurityMode::None;
        if none_policy != none_mode {
            out.push(
                k("security_mode"),
                format!(
                    "{:?} does not go with security_policy {:?}: mode None goes with policy \
                     None only, and policy None with mode None only",
                    self.security_mode, self.security_policy
                ),
            );
        }
        if self.pki_dir.trim().is_empty() {
            out.push(k("pki_dir"), "must not be empty");
        }
        for (name, why) in self.login().problems() {
            out.push(k(name), why);
        }
        out.positive(&k("request_timeout_s"), self.request_timeout_s, "seconds");
        out.positive(&k("connect_timeout_s"), self.connect_timeout_s, "seconds");
        out.positive(&k("job_timeout_s"), self.job_timeout_s, "seconds");
        if out.positive(&k("session_timeout_s"), self.session_timeout_s, "seconds")
            && self.session_timeout_s < 1.0
        {
            out.push(
                k("session_timeout_s"),
                format!("must be >= 1 (seconds), got {}", self.session_timeout_s),
            );
        }
    }

    /// The node ids of SD43900, SD43910, SD43920 for one axis, `{ns}` left for connect.
    fn axis_nodes(&self, axis_name: &str, axis_number: u16) -> [String; 3] {
        self.templates().map(|(_, template)| {
            template
                .replace("{axis_number}", &axis_number.to_string())
                .replace("{axis_name}", axis_name)
        })
    }

    /// The nodes of axis `axis_name`, number `axis_number` (see [`TargetConfig::places`](super::config::TargetConfig::places)).
    pub fn places(&self, axis_name: &str, axis_number: u16) -> Vec<Place> {
        // The server as `opc.tcp://host:port`, so that two spellings of it meet.
        let server = match self.endpoint_url.split_once("://") {
            Some((scheme, rest)) => {
                let authority = rest.split('/').next().unwrap_or(rest);
                format!(
                    "{}://{}",
                    scheme.to_ascii_lowercase(),
                    peer_identity(authority)
                )
            }
            None => self.endpoint_url.to_ascii_lowercase(),
        };
        self.axis_nodes(axis_name, axis_number)
            .into_iter()
            .map(|node| Place {
                area: format!("node `{node}` of the OPC UA server {server}"),
                bytes: 0..1,
            })
            .collect()
    }

    /// No two setting data, of one axis or of two, resolve to the same node, as
    /// [`Self::build`] fills the templates; `axes` are the (name, axis number) of the
    /// axes on this target, `key` the target's path.
    pub fn validate_axes(&self, key: &str, axes: &[(&str, u16)], out: &mut Problems<'_>) {
        // node id -> (axis, template key) that resolved to it first.
        let mut seen: std::collections::BTreeMap<String, (&str, &str)> = Default::default();
        for &(axis, number) in axes {
            let nodes = self.axis_nodes(axis, number);
            for ((template, _), node) in self.templates().into_iter().zip(nodes) {
                match seen.get(&node) {
                    Some(&(other, other_template)) => out.push(
                        format!("{key}.{template}"),
                        if other == axis {
                            format!(
                                "axis {axis}: {template} and {other_template} both resolve to \
                                 `{node}`: one node would take two setting data"
                            )
                        } else {
                            format!(
                                "axes {other} and {axis} both resolve {} to `{node}`: each \
                                 would overwrite the other's value; put {{axis_number}} or \
                                 {{axis_name}} into the template",
                                if template == other_template {
                                    template.to_string()
                                } else {
                                    format!("{other_template} and {template}")
                                }
                            )
                        },
                    ),
                    None => {
                        seen.insert(node, (axis, template));
                    }
                }
            }
        }
    }

    /// The writer of axis `axis_name`, number `axis_number` on the control (not
    /// connected yet). Reads the credentials now, so a missing file or variable is
    /// reported at start.
    pub fn build(&self, axis_name: &str, axis_number: u16) -> Result<OpcuaNcWriter, NcError> {
        for (name, template) in self.templates() {
            check_template(template)
                .map_err(|why| NcError::OpcuaSetup(format!("{name}: {why}")))?;
        }
        let templates = self.axis_nodes(axis_name, axis_number);
        let credentials = self
            .login()
            .load()
            .map_err(|(name, why)| NcError::OpcuaSetup(format!("{name}: {why}")))?;
        self.login().warn_if_readable_by_others("OPC UA");
        Ok(OpcuaNcWriter {
            spec: Arc::new(Spec {
                endpoint_url: self.endpoint_url.clone(),
                namespace_uri: self.namespace_uri.clone(),
                axis_name: axis_name.to_string(),
                templates,
                policy: self.security_policy.to_policy(),
                mode: self.security_mode.to_mode(),
                pki_dir: state_path(&self.pki_dir),
                trust_server_certificate: self.trust_server_certificate,
                credentials,
                request_timeout: self.request_timeout(),
                connect_timeout: self.connect_timeout(),
                session_timeout_ms: (self.session_timeout_s.clamp(1.0, 3600.0) * 1000.0) as u32,
            }),
            job_timeout: self.job_timeout(),
            conn: None,
            connecting: None,
            backoff: Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
            connect_error: None,
            connects: 0,
            job_ids: JobIds::default(),
        })
    }

    pub fn login(&self) -> LoginKeys<'_> {
        LoginKeys {
            credentials_file: self.credentials_file.as_deref(),
            user_env: self.user_env.as_deref(),
            password_env: self.password_env.as_deref(),
        }
    }
}

/// `endpoint_url` is `opc.tcp://host:port[/path]`.
fn check_endpoint_url(url: &str) -> Result<(), String> {
    let Some(rest) = url.strip_prefix("opc.tcp://") else {
        return Err(format!(
            "`{url}` is not an opc.tcp URL; expected opc.tcp://HOST:PORT, e.g. \
             \"opc.tcp://192.168.214.1:4840\""
        ));
    };
    let authority = rest.split('/').next().unwrap_or_default();
    check_host_port(authority).map_err(|e| format!("`{url}`: {e}"))
}

/// A template holds `{ns}`, no unknown placeholder, and gives a node id once filled.
fn check_template(template: &str) -> Result<(), String> {
    if !template.contains("{ns}") {
        return Err(format!(
            "`{template}` has no {{ns}}: the namespace index is looked up from \
             namespace_uri at connect, never written into the node id"
        ));
    }
    let mut rest = template.to_string();
    for p in PLACEHOLDERS {
        rest = rest.replace(p, "");
    }
    if let Some(start) = rest.find('{') {
        let unknown: String = rest[start..].chars().take_while(|c| *c != '}').collect();
        return Err(format!(
            "`{template}`: unknown placeholder {unknown}}}; known are {}",
            PLACEHOLDERS.join(", ")
        ));
    }
    let sample = template
        .replace("{ns}", "2")
        .replace("{axis_number}", "1")
        .replace("{axis_name}", "X1");
    NodeId::from_str(&sample)
        .map(|_| ())
        .map_err(|_| format!("`{template}` does not give a node id such as `ns=2;s=/NC/...`"))
}

fn default_namespace_uri() -> String {
    "SinumerikVarProvider".into()
}
fn default_sd43900_node() -> String {
    DEFAULT_SD43900_NODE.into()
}
fn default_sd43910_node() -> String {
    DEFAULT_SD43910_NODE.into()
}
fn default_sd43920_node() -> String {
    DEFAULT_SD43920_NODE.into()
}
fn default_security_policy() -> OpcuaSecurityPolicy {
    OpcuaSecurityPolicy::Basic256Sha256
}
fn default_security_mode() -> OpcuaSecurityMode {
    OpcuaSecurityMode::SignAndEncrypt
}
fn default_pki_dir() -> String {
    "opcua-pki".into()
}
fn default_request_timeout_s() -> f64 {
    1.0
}
fn default_connect_timeout_s() -> f64 {
    5.0
}
fn default_job_timeout_s() -> f64 {
    2.0
}
fn default_session_timeout_s() -> f64 {
    60.0
}

/// One open session: its event loop runs on a task of its own until the connection
/// is lost; then `lost` is set and the session is not used again.
struct Connection {
    session: Arc<Session>,
    event_loop: JoinHandle<()>,
    lost: Arc<AtomicBool>,
    /// Node ids of SD43900, SD43910, SD43920 with this session's namespace index.
    nodes: [NodeId; 3],
}

impl Connection {
    /// Closes the session and waits for it (dropping only starts a close that a
    /// process about to exit cuts short, and the OPC UA crates then log errors).
    async fn close(self) {
        if !self.lost.load(Ordering::Relaxed) {
            let _ = tokio::time::timeout(CLOSE_TIMEOUT, self.session.disconnect()).await;
            // Closed: `drop` only stops the event loop.
            self.lost.store(true, Ordering::Relaxed);
        }
    }
}

impl Drop for Connection {
    fn drop(&mut self) {
        let event_loop = self.event_loop.abort_handle();
        if self.lost.load(Ordering::Relaxed) {
            event_loop.abort();
            return;
        }
        // Close the session politely so the server frees it now rather than after
        // its session timeout (a control admits only a few sessions).
        let session = self.session.clone();
        match tokio::runtime::Handle::try_current() {
            Ok(rt) => {
                rt.spawn(async move {
                    let _ = tokio::time::timeout(CLOSE_TIMEOUT, session.disconnect()).await;
                    event_loop.abort();
                });
            }
            Err(_) => event_loop.abort(),
        }
    }
}

/// Drives a session's event loop: reports the first connect (or its failure) on
/// `ready`, and stops at the first loss of the connection, which `lost` then shows.
async fn drive(
    event_loop: SessionEventLoop<TcpConnector>,
    ready: oneshot::Sender<Result<(), StatusCode>>,
    lost: Arc<AtomicBool>,
    endpoint: String,
) {
    let mut ready = Some(ready);
    let stream = event_loop.enter();
    futures::pin_mut!(stream);
    while let Some(event) = stream.next().await {
        match event {
            Ok(SessionPollResult::Reconnected(_)) => {
                if let Some(tx) = ready.take() {
                    let _ = tx.send(Ok(()));
                }
            }
            Ok(SessionPollResult::ConnectionLost(status)) => {
                tracing::warn!(%endpoint, %status, "OPC UA connection lost");
                break;
            }
            Ok(_) => {}
            Err(status) => {
                if let Some(tx) = ready.take() {
                    let _ = tx.send(Err(status));
                }
                break;
            }
        }
    }
    lost.store(true, Ordering::Relaxed);
}

/// A third of the session timeout, at most 10 s.
fn keep_alive_interval(session_timeout_ms: u32) -> Duration {
    Duration::from_millis(u64::from(session_timeout_ms / 3)).min(Duration::from_secs(10))
}

/// Service results after which the session cannot be used any more. Not
/// `BadTimeout`: a control slower than `request_timeout_s` got a new session per job,
/// and the old one's close timed out too, so the sessions piled up on the server until
/// their timeout (review Y). A dead link is found by the keep-alive, which marks the
/// connection lost.
fn is_session_fault(status: StatusCode) -> bool {
    matches!(
        status,
        StatusCode::BadNotConnected
            | StatusCode::BadConnectionClosed
            | StatusCode::BadServerNotConnected
            | StatusCode::BadCommunicationError
            | StatusCode::BadSecureChannelClosed
            | StatusCode::BadSecureChannelIdInvalid
            | StatusCode::BadSessionIdInvalid
            | StatusCode::BadSessionClosed
            | StatusCode::BadSessionNotActivated
            | StatusCode::BadTcpInternalError
            | StatusCode::BadDisconnect
            | StatusCode::BadShutdown
    )
}

/// What a writer connects with; shared with its connecting task.
struct Spec {
    endpoint_url: String,
    namespace_uri: String,
    axis_name: String,
    /// Node-id templates with the axis filled in; `{ns}` left for connect.
    templates: [String; 3],
    policy: SecurityPolicy,
    mode: MessageSecurityMode,
    pki_dir: PathBuf,
    trust_server_certificate: bool,
    credentials: Option<Credentials>,
    request_timeout: Duration,
    connect_timeout: Duration,
    session_timeout_ms: u32,
}

impl Spec {
    fn user_label(&self) -> String {
        match &self.credentials {
            Some(c) => format!("`{}`", c.user),
            None => "anonymous".into(),
        }
    }

    /// A client (it creates the pki folder, and a key pair when a secure policy needs
    /// one and none is there yet).
    fn client(&self) -> Result<Client, NcError> {
        let secure = self.policy != SecurityPolicy::None;
        ClientBuilder::new()
            .application_name("compgate")
            .application_uri("urn:compgate")
            .product_uri("urn:compgate")
            .pki_dir(self.pki_dir.clone())
            .create_sample_keypair(secure)
            .trust_server_certs(self.trust_server_certificate)
            // One try per connect: compgate's own backoff paces the retries, and a new
            // session re-reads the namespace index.
            .session_retry_limit(0)
            .request_timeout(self.request_timeout)
            .session_timeout(self.session_timeout_ms)
            // Keep-alive reads renew the session well within its timeout; three missed
            // in a row close it, so a dead peer is noticed between jobs.
            .keep_alive_interval(keep_alive_interval(self.session_timeout_ms))
            .max_failed_keep_alive_count(3)
            .client()
            .map_err(|errors| NcError::OpcuaSetup(format!("OPC UA client: {}", errors.join("; "))))
    }
}

/// SD43900/43910/43920 of one axis over OPC UA (see the module docs).
pub struct OpcuaNcWriter {
    spec: Arc<Spec>,
    job_timeout: Duration,
    conn: Option<Connection>,
    /// A connect under way. It runs on a task of its own, so a caller that gives up
    /// (a job timeout) does not throw it away: the next call takes it over.
    connecting: Option<JoinHandle<Result<Connection, NcError>>>,
    backoff: Backoff,
    /// Why the last connect failed, named while the backoff waits.
    connect_error: Option<SourceError>,
    connects: u64,
    job_ids: JobIds,
}

impl Drop for OpcuaNcWriter {
    fn drop(&mut self) {
        if let Some(task) = self.connecting.take() {
            task.abort();
        }
    }
}

impl fmt::Debug for OpcuaNcWriter {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OpcuaNcWriter")
            .field("endpoint_url", &self.spec.endpoint_url)
            .field("axis", &self.spec.axis_name)
            .field(
                "user",
                &self.spec.credentials.as_ref().map(|c| c.user.as_str()),
            )
            .field("connected", &self.is_connected())
            .field("connects", &self.connects)
            .finish()
    }
}

impl OpcuaNcWriter {
    /// The user name and password it logs in with, read when it was built.
    pub fn credentials(&self) -> Option<&Credentials> {
        self.spec.credentials.as_ref()
    }

    /// True while a session is open.
    pub fn is_connected(&self) -> bool {
        self.conn
            .as_ref()
            .is_some_and(|c| !c.lost.load(Ordering::Relaxed))
    }

    /// Sessions opened so far.
    pub fn connects(&self) -> u64 {
        self.connects
    }

    /// The node ids of SD43900, SD43910, SD43920 as the open session resolved them.
    pub fn node_ids(&self) -> Option<[String; 3]> {
        self.conn
            .as_ref()
            .map(|c| c.nodes.clone().map(|n| n.to_string()))
    }

    /// Whether this session's user may write the three setting data, from their
    /// UserAccessLevel (on a SINUMERIK: whether the user holds SeaWrite).
    pub async fn may_write(&mut self) -> Result<bool, NcError> {
        self.ensure_connected().await?;
        let (session, nodes) = self.session()?;
        let reads: Vec<ReadValueId> = nodes
            .iter()
            .map(|n| read_id(n.clone(), AttributeId::UserAccessLevel))
            .collect();
        let values = match session.read(&reads, TimestampsToReturn::Neither, 0.0).await {
            Ok(v) => v,
            Err(e) => return Err(self.service_fault("read of UserAccessLevel", e)),
        };
        check_count(&values, nodes.len(), "read of UserAccessLevel")?;
        let mut all = true;
        for (node, dv) in nodes.iter().zip(&values) {
            good(dv, node, "read of UserAccessLevel")?;
            let level = match &dv.value {
                Some(Variant::Byte(b)) => *b,
                other => {
                    return Err(NcError::Protocol(format!(
                        "UserAccessLevel of {node} is {}, expected a Byte",
                        shown(other)
                    )))
                }
            };
            all &= level & ACCESS_CURRENT_WRITE != 0;
        }
        Ok(all)
    }

    fn user_label(&self) -> String {
        self.spec.user_label()
    }

    fn session(&self) -> Result<(Arc<Session>, [NodeId; 3]), NcError> {
        self.conn
            .as_ref()
            .map(|c| (c.session.clone(), c.nodes.clone()))
            .ok_or_else(|| SourceError::Transport("OPC UA session not open".into()).into())
    }

    /// Opens a session unless one is open and alive; backs off after failures.
    async fn ensure_connected(&mut self) -> Result<(), NcError> {
        if self
            .conn
            .as_ref()
            .is_some_and(|c| c.lost.load(Ordering::Relaxed))
        {
            self.conn = None;
        }
        if self.conn.is_some() {
            return Ok(());
        }
        let task = match &mut self.connecting {
            Some(task) => task,
            None => {
                if let Some(wait) = self.backoff.remaining(Instant::now()) {
                    return Err(match &self.connect_error {
                        Some(cause) => SourceError::BackingOffAfter {
                            cause: Box::new(cause.clone()),
                            next_attempt_in: wait,
                        },
                        None => SourceError::BackingOff(wait),
                    }
                    .into());
                }
                let spec = self.spec.clone();
                self.connecting.insert(tokio::spawn(async move {
                    tokio::time::timeout(spec.connect_timeout, open(spec.clone()))
                        .await
                        .unwrap_or_else(|_| Err(SourceError::ConnectTimeout.into()))
                }))
            }
        };
        // Awaiting through `&mut` leaves the task in place if this call is cancelled.
        let result = task.await;
        self.connecting = None;
        match result {
            Ok(Ok(conn)) => {
                self.backoff.reset();
                self.connect_error = None;
                self.connects += 1;
                tracing::info!(
                    endpoint = %self.spec.endpoint_url,
                    axis = %self.spec.axis_name,
                    user = %self.user_label(),
                    nodes = ?conn.nodes.iter().map(|n| n.to_string()).collect::<Vec<_>>(),
                    "OPC UA session open"
                );
                self.conn = Some(conn);
                Ok(())
            }
            Ok(Err(e)) => {
                self.backoff.failed(Instant::now());
                self.connect_error = Some(match &e {
                    NcError::Link(cause) => cause.clone(),
                    other => SourceError::Connect(other.to_string()),
                });
                Err(e)
            }
            Err(join) => {
                self.backoff.failed(Instant::now());
                Err(SourceError::Connect(format!("OPC UA connect task: {join}")).into())
            }
        }
    }

    /// Maps a failed service call; a fault of the connection or session drops it, so
    /// the next call opens a new one.
    fn service_fault(&mut self, service: &'static str, e: opcua::types::Error) -> NcError {
        let status = e.status();
        let node = self.conn.as_ref().map_or_else(
            || self.spec.templates[0].clone(),
            |c| c.nodes[0].to_string(),
        );
        let lost = self
            .conn
            .as_ref()
            .is_some_and(|c| c.lost.load(Ordering::Relaxed));
        if lost || is_session_fault(status) {
            self.conn = None;
        }
        match status {
            StatusCode::BadTimeout => SourceError::Timeout(self.spec.request_timeout).into(),
            StatusCode::BadUserAccessDenied => NcError::OpcuaAccessDenied {
                node,
                user: self.user_label(),
            },
            s if is_session_fault(s) => {
                SourceError::Transport(format!("OPC UA {service}: {}", s)).into()
            }
            s => NcError::OpcuaStatus {
                service,
                target: format!("for axis {}", self.spec.axis_name),
                status: s.to_string(),
            },
        }
    }

    async fn read_values(&mut self, idx: &[usize]) -> Result<Vec<f64>, NcError> {
        let (session, nodes) = self.session()?;
        let reads: Vec<ReadValueId> = idx
            .iter()
            .map(|&i| read_id(nodes[i].clone(), AttributeId::Value))
            .collect();
        // Max age 0: the value the NC holds now, not a cached one.
        let values = match session.read(&reads, TimestampsToReturn::Neither, 0.0).await {
            Ok(v) => v,
            Err(e) => return Err(self.service_fault("read", e)),
        };
        check_count(&values, idx.len(), "read")?;
        idx.iter()
            .zip(&values)
            .map(|(&i, dv)| {
                good(dv, &nodes[i], "read").map_err(|e| named_node(e, i))?;
                match &dv.value {
                    Some(Variant::Double(v)) => Ok(*v),
                    other => Err(NcError::Protocol(format!(
                        "{} holds {}, expected a Double",
                        nodes[i],
                        shown(other)
                    ))),
                }
            })
            .collect()
    }

    async fn run_job(&mut self, pairs: &[(usize, f64)]) -> Result<(), NcError> {
        let (session, nodes) = self.session()?;
        let writes: Vec<WriteValue> = pairs
            .iter()
            .map(|&(i, v)| WriteValue {
                node_id: nodes[i].clone(),
                attribute_id: AttributeId::Value as u32,
                index_range: NumericRange::None,
                // No timestamps: servers may refuse a write that sets them.
                value: DataValue::value_only(Variant::Double(v)),
            })
            .collect();
        let results = match session.write(&writes).await {
            Ok(r) => r,
            Err(e) => return Err(self.service_fault("write", e)),
        };
        check_count(&results, writes.len(), "write")?;
        for (&(i, _), status) in pairs.iter().zip(&results) {
            if status.is_good() {
                continue;
            }
            return Err(if *status == StatusCode::BadUserAccessDenied {
                NcError::OpcuaAccessDenied {
                    node: nodes[i].to_string(),
                    user: self.user_label(),
                }
            } else {
                named_node(
                    NcError::OpcuaStatus {
                        service: "write",
                        target: format!("of {}", nodes[i]),
                        status: status.to_string(),
                    },
                    i,
                )
            });
        }
        Ok(())
    }
}

impl NcWriter for OpcuaNcWriter {
    async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
        let mut pairs = Vec::with_capacity(job.pairs.len());
        for &(var_id, value) in &job.pairs {
            let name = super::var_name(var_id);
            let Some(i) = VARS.iter().position(|v| *v == var_id) else {
                return Err(NcError::InvalidJob(format!(
                    "{name} has no node on an OPC UA target (SD43900, SD43910, SD43920 only)"
                )));
            };
            if pairs.iter().any(|&(j, _)| j == i) {
                return Err(NcError::InvalidJob(format!("{name} twice")));
            }
            if !value.is_finite() {
                return Err(NcError::InvalidJob(format!(
                    "{name} = {value}: not a finite number"
                )));
            }
            pairs.push((i, value));
        }
        if pairs.is_empty() {
            return Err(NcError::InvalidJob("no pairs".into()));
        }
        let job_id = self.job_ids.issue();
        // A (re)connect has its own timeout and is not part of the job: a control whose
        // secure handshake takes longer than a job must still get connected.
        self.ensure_connected().await?;
        let started = Instant::now();
        match tokio::time::timeout(self.job_timeout, self.run_job(&pairs)).await {
            Ok(Ok(())) => Ok(JobReport {
                job_id,
                elapsed: started.elapsed(),
            }),
            // The write request went out and its answer did not come: the server may
            // still apply it.
            Ok(Err(NcError::Link(SourceError::Timeout(timeout)))) => Err(NcError::JobTimeout {
                job_id,
                timeout,
                state: None,
                sent: true,
            }),
            Ok(Err(e)) => Err(e),
            Err(_) => {
                // The server may still answer (or apply) the cut-off request: a new
                // session starts clean, and the job counts as not written.
                self.conn = None;
                Err(NcError::JobTimeout {
                    job_id,
                    timeout: self.job_timeout,
                    state: None,
                    sent: true,
                })
            }
        }
    }

    async fn read_snapshot(&mut self) -> Result<NcSnapshot, NcError> {
        self.ensure_connected().await?;
        let v = self.read_values(&[0, 1, 2]).await?;
        Ok(NcSnapshot {
            sd43900_mm: v[0],
            sd43910: v[1],
            sd43920_mm: v[2],
            ..NcSnapshot::default()
        })
    }

    async fn close(&mut self) {
        if let Some(task) = self.connecting.take() {
            task.abort();
        }
        if let Some(conn) = self.conn.take() {
            conn.close().await;
        }
    }
}

/// Connects: endpoints, secure channel, session, then the namespace lookup.
async fn open(spec: Arc<Spec>) -> Result<Connection, NcError> {
    let url = spec.endpoint_url.as_str();
    let endpoint: EndpointDescription = (
        url,
        spec.policy.to_uri(),
        spec.mode,
        UserTokenPolicy::anonymous(),
    )
        .into();
    let identity = match &spec.credentials {
        Some(c) => IdentityToken::UserName(c.user.clone(), Password::new(c.password.clone())),
        None => IdentityToken::Anonymous,
    };
    let user = spec.user_label();
    // With policy None compgate has no certificate, by design; the OPC UA crates log
    // that as ERROR at the client and at every secure channel they set up. Their logs
    // are muted while the client is made and the endpoint connected (whatever fails
    // there is returned, and reported by compgate); the session's own events are not.
    let quiet = spec.policy == SecurityPolicy::None;
    // Reads the pki folder, maybe makes a key pair: off the runtime's threads.
    let mut client = {
        let spec = spec.clone();
        tokio::task::spawn_blocking(move || {
            if quiet {
                tracing::dispatcher::with_default(&tracing::Dispatch::none(), || spec.client())
            } else {
                spec.client()
            }
        })
        .await
        .map_err(|e| NcError::OpcuaSetup(format!("OPC UA client: {e}")))??
    };
    let connect = client.connect_to_matching_endpoint(endpoint, identity);
    let connected = if quiet {
        connect.with_subscriber(tracing::Dispatch::none()).await
    } else {
        connect.await
    };
    let (session, event_loop) = connected.map_err(|e| {
        // The error's text repeats its status first.
        let text = e.to_string();
        let prefix = format!("{}: ", e.status());
        let detail = text.strip_prefix(&prefix).unwrap_or(&text);
        connect_error(url, &user, e.status(), detail)
    })?;
    let lost = Arc::new(AtomicBool::new(false));
    let (tx, rx) = oneshot::channel();
    let task = tokio::spawn(drive(event_loop, tx, lost.clone(), url.to_string()));
    let mut conn = Connection {
        session,
        event_loop: task,
        lost,
        nodes: Default::default(),
    };
    match rx.await {
        Ok(Ok(())) => {}
        Ok(Err(status)) => return Err(connect_error(url, &user, status, "session not activated")),
        Err(_) => {
            return Err(SourceError::Connect(format!("{url}: session event loop ended")).into())
        }
    }
    let ns = namespace_index(&conn.session, &spec.namespace_uri).await?;
    for (slot, template) in conn.nodes.iter_mut().zip(&spec.templates) {
        let id = template.replace("{ns}", &ns.to_string());
        *slot = NodeId::from_str(&id)
            .map_err(|_| NcError::OpcuaSetup(format!("`{id}` is not a node id")))?;
    }
    Ok(conn)
}

fn read_id(node_id: NodeId, attribute: AttributeId) -> ReadValueId {
    ReadValueId {
        node_id,
        attribute_id: attribute as u32,
        index_range: NumericRange::None,
        data_encoding: QualifiedName::null(),
    }
}

/// A value as the server sent it, with its type: `0.5 (Float)`, `no value`.
fn shown(value: &Option<Variant>) -> String {
    match value {
        None => "no value".into(),
        Some(v) => match v.scalar_type_id() {
            Some(t) => format!("{v} ({t})"),
            None => v.to_string(),
        },
    }
}

fn check_count<T>(results: &[T], want: usize, service: &str) -> Result<(), NcError> {
    if results.len() == want {
        Ok(())
    } else {
        Err(NcError::Protocol(format!(
            "OPC UA {service}: {} results for {want} nodes",
            results.len()
        )))
    }
}

/// A status of the node of value `i` names the key it comes from, when the node
/// is not there: that key is what the engineer has to correct.
fn named_node(e: NcError, i: usize) -> NcError {
    match e {
        NcError::OpcuaStatus {
            service,
            target,
            status,
        } if status.starts_with("BadNodeId") => NcError::OpcuaStatus {
            service,
            target: format!(
                "{target} (from {})",
                ["sd43900_node", "sd43910_node", "sd43920_node"][i]
            ),
            status,
        },
        e => e,
    }
}

fn good(dv: &DataValue, node: &NodeId, service: &'static str) -> Result<(), NcError> {
    match dv.status {
        Some(s) if !s.is_good() => Err(NcError::OpcuaStatus {
            service,
            target: format!("of {node}"),
            status: s.to_string(),
        }),
        _ => Ok(()),
    }
}

/// The index of `uri` in the server's NamespaceArray.
async fn namespace_index(session: &Session, uri: &str) -> Result<u16, NcError> {
    let node: NodeId = VariableId::Server_NamespaceArray.into();
    let values = session
        .read(
            &[read_id(node, AttributeId::Value)],
            TimestampsToReturn::Neither,
            0.0,
        )
        .await
        .map_err(|e| SourceError::Connect(format!("reading the NamespaceArray: {}", e.status())))?;
    let uris: Vec<String> = match values.first().and_then(|dv| dv.value.as_ref()) {
        Some(Variant::Array(a)) => a
            .values
            .iter()
            .map(|v| match v {
                Variant::String(s) => s.as_ref().to_string(),
                other => format!("{other:?}"),
            })
            .collect(),
        other => {
            return Err(NcError::Protocol(format!(
                "the server's NamespaceArray is {other:?}, expected an array of strings"
            )))
        }
    };
    uris.iter()
        .position(|u| u == uri)
        .and_then(|i| u16::try_from(i).ok())
        .ok_or_else(|| {
            NcError::OpcuaSetup(format!(
                "namespace_uri `{uri}` is not in the server's NamespaceArray {uris:?}"
            ))
        })
}

/// A failed connect, named by its status; the hints cover what a commissioning
/// engineer meets first.
fn connect_error(url: &str, user: &str, status: StatusCode, detail: &str) -> NcError {
    let hint = match status {
        StatusCode::BadIdentityTokenRejected
        | StatusCode::BadIdentityTokenInvalid
        | StatusCode::BadUserAccessDenied => format!(
            " (the server rejected user {user}: check the user name and password in \
             credentials_file or the variables of user_env and password_env, or that \
             the control admits this user)"
        ),
        StatusCode::BadCertificateUntrusted | StatusCode::BadSecurityChecksFailed => {
            " (a certificate is not trusted yet: move the control's certificate from \
             pki_dir/rejected to pki_dir/trusted, and trust compgate's certificate on the \
             control)"
                .into()
        }
        StatusCode::BadTcpEndpointUrlInvalid | StatusCode::BadSecurityPolicyRejected => {
            " (no endpoint with this security_policy and security_mode)".into()
        }
        _ => String::new(),
    };
    let detail = if detail.is_empty() {
        String::new()
    } else {
        format!(": {detail}")
    };
    SourceError::Connect(format!("{url}: {status}{hint}{detail}")).into()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn problems(cfg: &OpcuaTargetConfig) -> Vec<String> {
        let mut p = Problems::new("t.toml");
        cfg.validate("targets.nc", &mut p);
        p.into_vec().iter().map(|p| p.to_string()).collect()
    }

    fn plain() -> OpcuaTargetConfig {
        OpcuaTargetConfig {
            security_policy: OpcuaSecurityPolicy::None,
            security_mode: OpcuaSecurityMode::None,
            ..OpcuaTargetConfig::new("opc.tcp://127.0.0.1:4840")
        }
    }

    #[test]
    fn defaults_validate() {
        assert_eq!(
            problems(&OpcuaTargetConfig::new("opc.tcp://nc:4840")),
            Vec::<String>::new()
        );
        assert_eq!(problems(&plain()), Vec::<String>::new());
    }

    #[test]
    fn bad_keys_are_named() {
        let cfg = OpcuaTargetConfig {
            endpoint_url: "http://nc:4840".into(),
            sd43910_node: "ns=2;s=/NC/x".into(),
            sd43920_node: "ns={ns};s=/NC/{axis}".into(),
            security_mode: OpcuaSecurityMode::None,
            user_env: Some("U".into()),
            job_timeout_s: 0.0,
            ..OpcuaTargetConfig::new("")
        };
        let p = problems(&cfg).join("\n");
        for key in [
            "targets.nc.endpoint_url",
            "targets.nc.sd43910_node",
            "targets.nc.sd43920_node",
            "targets.nc.security_mode",
            "targets.nc.password_env",
            "targets.nc.job_timeout_s",
        ] {
            assert!(p.contains(key), "{key} missing from:\n{p}");
        }
        assert!(p.contains("{axis}"), "{p}");
        assert!(!p.contains("targets.nc.sd43900_node"), "{p}");
    }

    // While the reconnect waited, the status said only "reconnect backing off": why
    // the server was unreachable was gone.
    #[tokio::test]
    async fn the_wait_before_a_reconnect_names_why_the_last_connect_failed() {
        let at = crate::nc::refused_address();
        let cfg: OpcuaTargetConfig = toml::from_str(&format!(
            "endpoint_url = \"opc.tcp://{at}\"\nsecurity_policy = \"None\"\n\
             security_mode = \"None\"\n"
        ))
        .expect("valid");
        let mut w = cfg.build("X", 1).expect("writer");
        let (first, waiting) = crate::nc::refused_then_waiting(&mut w).await;
        assert!(
            waiting.contains(first.trim_start_matches("NC link: "))
                && waiting.contains("(next attempt in"),
            "first: {first}\nwaiting: {waiting}"
        );
    }

    #[test]
    fn unknown_keys_and_kind_rejected() {
        let err = toml::from_str::<OpcuaTargetConfig>(
            "endpoint_url = \"opc.tcp://nc:4840\"\nkind = \"opcua\"\n",
        )
        .expect_err("kind is not a key of this table");
        assert!(err.to_string().contains("kind"), "{err}");
        let cfg: OpcuaTargetConfig = toml::from_str(
            "endpoint_url = \"opc.tcp://nc:4840\"\nsecurity_policy = \"None\"\n\
             security_mode = \"None\"\n",
        )
        .expect("valid");
        assert_eq!(cfg.security_policy, OpcuaSecurityPolicy::None);
        assert_eq!(cfg.namespace_uri, "SinumerikVarProvider");
    }

    #[test]
    fn build_fills_the_axis_and_hides_the_password() {
        let dir = std::env::temp_dir().join(format!("compgate-opcua-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let file = dir.join("cred");
        std::fs::write(&file, "operator\ns3cret-pw\n").expect("write");
        let cfg = OpcuaTargetConfig {
            credentials_file: Some(file.display().to_string()),
            ..plain()
        };
        let w = cfg.build("Z1", 3).expect("builds");
        assert_eq!(
            w.spec.templates[1],
            "ns={ns};s=/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_SLOPE[u3]"
        );
        let dbg = format!("{w:?} {:?}", w.spec.credentials);
        assert!(dbg.contains("operator"), "{dbg}");
        assert!(!dbg.contains("s3cret"), "{dbg}");
        let _ = std::fs::remove_dir_all(&dir);

        let missing = OpcuaTargetConfig {
            user_env: Some("COMPGATE_TEST_NO_SUCH_USER_VAR".into()),
            password_env: Some("COMPGATE_TEST_NO_SUCH_PW_VAR".into()),
            ..plain()
        };
        let err = missing.build("X1", 1).expect_err("no such variable");
        assert!(
            err.to_string().contains("COMPGATE_TEST_NO_SUCH_USER_VAR"),
            "{err}"
        );
    }

    #[test]
    fn every_key_documents_its_default() {
        let schema = schemars::schema_for!(OpcuaTargetConfig).to_value();
        let props = schema["properties"].as_object().expect("properties");
        assert_eq!(props.len(), 16);
        for (key, p) in props {
            let doc = p["description"].as_str().unwrap_or_default();
            assert!(
                doc.contains("Default") || doc.contains("Required"),
                "{key}: {doc}"
            );
        }
    }

    #[test]
    fn values_of_another_type_are_shown_without_rust_syntax() {
        assert_eq!(shown(&Some(Variant::Float(0.5))), "0.5 (Float)");
        assert_eq!(shown(&None), "no value");
    }

    #[test]
    fn access_denied_says_how_to_grant() {
        let e = NcError::OpcuaAccessDenied {
            node: "ns=3;s=/NC/x".into(),
            user: "`op`".into(),
        };
        let s = e.to_string();
        assert!(
            s.contains("BadUserAccessDenied") && s.contains("SeaWrite"),
            "{s}"
        );
        assert!(s.contains("GiveUserAccess"), "{s}");
    }
}
