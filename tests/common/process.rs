//! The real `compgate` binary as a child process, with a systemd notify socket the
//! test binds and its stderr collected line by line.
#![allow(dead_code)]
// Test harness: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader};
use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_compgate");

/// Asserts that a finished command succeeded (its output in the message); its
/// standard output.
pub fn assert_success(out: &Output) -> String {
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{}\n{stdout}{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// Waits until `child` listens on 127.0.0.1:`port`; panics after `secs` or when it
/// exits. A child that must bind a port picked beforehand (to be restarted on it)
/// exits when somebody took the port meanwhile, and a connect then reaches that other
/// listener: so the child must still run a moment after the port answers.
pub fn wait_listening(child: &mut Child, port: u16, secs: f64, what: &str) {
    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    let exited = |child: &mut Child| {
        if let Some(st) = child.try_wait().unwrap() {
            panic!("{what} exited ({st}) before listening on port {port}: port taken?");
        }
    };
    while Instant::now() < deadline {
        exited(child);
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            std::thread::sleep(Duration::from_millis(100));
            exited(child);
            return;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = child.kill();
    let _ = child.wait();
    panic!("{what} did not listen on port {port} within {secs} s");
}

/// Sends `sig` (e.g. `TERM`) to process `pid`; panics when `kill` fails.
pub fn signal(pid: u32, sig: &str) {
    let ok = Command::new("kill")
        .args([&format!("-{sig}"), &pid.to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -{sig} {pid}");
}

/// A running `compgate run --config FILE`; dropping it kills it.
pub struct Gateway {
    pub child: Child,
    pub stderr: Arc<Mutex<Vec<String>>>,
    /// Every notify datagram so far; a thread drains the socket so the gateway's
    /// (blocking) sd_notify never waits on the test.
    pub notified: Arc<Mutex<Vec<String>>>,
    /// When each datagram of `notified` arrived, same order.
    pub notified_at: Arc<Mutex<Vec<Instant>>>,
    /// Datagrams `wait_notify` has looked at.
    pub messages: Vec<String>,
}

impl Gateway {
    /// Starts the binary on `config` with `NOTIFY_SOCKET` bound in `dir`.
    pub fn start(dir: &Path, config: &Path, extra_env: &[(&str, &str)]) -> Self {
        Self::start_with_nofile(dir, config, extra_env, None)
    }

    /// [`start`](Self::start), with the child's descriptor limit (`RLIMIT_NOFILE`, soft
    /// and hard) set to `nofile` when given, as systemd's `LimitNOFILE=` would.
    pub fn start_with_nofile(
        dir: &Path,
        config: &Path,
        extra_env: &[(&str, &str)],
        nofile: Option<u64>,
    ) -> Self {
        Self::start_full(dir, config, extra_env, nofile, &[])
    }

    /// [`start`](Self::start) with more arguments of `run` (e.g. `--shadow`).
    pub fn start_with_args(dir: &Path, config: &Path, args: &[&str]) -> Self {
        Self::start_full(dir, config, &[], None, args)
    }

    fn start_full(
        dir: &Path,
        config: &Path,
        extra_env: &[(&str, &str)],
        nofile: Option<u64>,
        args: &[&str],
    ) -> Self {
        let sock: PathBuf = dir.join(format!("notify-{}.sock", std::process::id()));
        let _ = std::fs::remove_file(&sock);
        let notify = UnixDatagram::bind(&sock).expect("bind notify socket");
        notify
            .set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        let mut cmd = match nofile {
            None => Command::new(BIN),
            Some(n) => {
                let mut c = Command::new("sh");
                c.args(["-c", &format!("ulimit -n {n} && exec \"$0\" \"$@\""), BIN]);
                c
            }
        };
        cmd.args(["--log", "info", "run", "--config"])
            .arg(config)
            .args(args)
            .env("NOTIFY_SOCKET", &sock)
            .env_remove("JOURNAL_STREAM")
            .env_remove("RUST_LOG")
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        for (k, v) in extra_env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().expect("spawn compgate");
        let notified = Arc::new(Mutex::new(Vec::new()));
        let sink = notified.clone();
        let notified_at = Arc::new(Mutex::new(Vec::new()));
        let times = notified_at.clone();
        std::thread::spawn(move || {
            let mut buf = vec![0u8; 4096];
            loop {
                match notify.recv(&mut buf) {
                    Ok(n) => {
                        let mut sink = sink.lock().unwrap();
                        times.lock().unwrap().push(Instant::now());
                        sink.push(String::from_utf8_lossy(&buf[..n]).to_string());
                    }
                    Err(e)
                        if e.kind() == std::io::ErrorKind::WouldBlock
                            || e.kind() == std::io::ErrorKind::TimedOut =>
                    {
                        // Stop when the test dropped the gateway.
                        if Arc::strong_count(&sink) == 1 {
                            break;
                        }
                    }
                    Err(_) => break,
                }
            }
        });
        let stderr = Arc::new(Mutex::new(Vec::new()));
        let pipe = child.stderr.take().unwrap();
        let lines = stderr.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(pipe).lines().map_while(Result::ok) {
                lines.lock().unwrap().push(line);
            }
        });
        Gateway {
            child,
            stderr,
            notified,
            notified_at,
            messages: Vec::new(),
        }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn signal(&self, sig: &str) {
        signal(self.pid(), sig);
    }

    /// Receives notify datagrams until one satisfies `pred`; panics after `secs`.
    pub fn wait_notify(&mut self, secs: f64, what: &str, pred: impl Fn(&str) -> bool) -> String {
        let deadline = Instant::now() + Duration::from_secs_f64(secs);
        while Instant::now() < deadline {
            let new: Vec<String> = self.notified.lock().unwrap()[self.messages.len()..].to_vec();
            for msg in new {
                self.messages.push(msg.clone());
                if pred(&msg) {
                    return msg;
                }
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!(
            "timed out after {secs} s waiting for notify {what}; got {:?}\nstderr:\n{}",
            self.messages.iter().rev().take(5).collect::<Vec<_>>(),
            self.stderr_text()
        );
    }

    /// Bytes the gateway wrote to stderr so far (its log), newlines included.
    pub fn stderr_bytes(&self) -> usize {
        self.stderr
            .lock()
            .unwrap()
            .iter()
            .map(|l| l.len() + 1)
            .sum()
    }

    pub fn stderr_text(&self) -> String {
        self.stderr.lock().unwrap().join("\n")
    }

    /// Waits until a stderr line contains `needle`; panics after `secs`.
    pub fn wait_log(&self, secs: f64, needle: &str) -> String {
        self.wait_log_nth(secs, needle, 1)
    }

    /// Waits until `n` stderr lines contain `needle`; the `n`th. Panics after `secs`.
    pub fn wait_log_nth(&self, secs: f64, needle: &str, n: usize) -> String {
        let deadline = Instant::now() + Duration::from_secs_f64(secs);
        while Instant::now() < deadline {
            if let Some(l) = self
                .stderr
                .lock()
                .unwrap()
                .iter()
                .filter(|l| l.contains(needle))
                .nth(n - 1)
            {
                return l.clone();
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!(
            "timed out after {secs} s waiting for line {n} with `{needle}`\nstderr:\n{}",
            self.stderr_text()
        );
    }

    /// The port of the metrics listener, as the gateway logs it once bound. Configs in
    /// tests bind port 0: a port picked by the test and released again can be taken
    /// by any other listener before the gateway binds it.
    pub fn metrics_port(&self, secs: f64) -> u16 {
        let line = self.wait_log(secs, "Prometheus metrics on http://");
        line.split("http://")
            .nth(1)
            .and_then(|rest| rest.split('/').next())
            .and_then(|addr| addr.parse::<std::net::SocketAddr>().ok())
            .map(|a| a.port())
            .unwrap_or_else(|| panic!("no address in the metrics log line: {line}"))
    }

    /// SIGTERM and wait; returns whether it exited successfully.
    pub fn stop(mut self) -> bool {
        self.signal("TERM");
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Some(st) = self.child.try_wait().unwrap() {
                return st.success();
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("gateway did not stop within 10 s after SIGTERM");
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
