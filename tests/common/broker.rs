//! A real Mosquitto broker on a free loopback port, and a subscriber collecting what
//! arrives.
#![allow(dead_code)]
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};

fn mosquitto() -> PathBuf {
    for p in ["/usr/sbin/mosquitto", "/usr/bin/mosquitto"] {
        if Path::new(p).exists() {
            return p.into();
        }
    }
    "mosquitto".into()
}

/// A running mosquitto; dropping it kills it.
pub struct Broker {
    pub port: u16,
    conf: PathBuf,
    child: Option<Child>,
}

impl Broker {
    pub fn start(dir: &Path) -> Self {
        Self::start_with(dir, "")
    }

    /// [`start`](Self::start) with `extra` lines at the end of its configuration.
    pub fn start_with(dir: &Path, extra: &str) -> Self {
        let port = super::free_port();
        Self::start_conf(dir, port, &Self::conf_text(dir, port, extra))
    }

    /// The configuration [`start_with`](Self::start_with) writes.
    pub fn conf_text(dir: &Path, port: u16, extra: &str) -> String {
        // Persistence keeps the test subscriber's session (and the QoS 1 messages
        // queued for it) across a stop/start, so it misses nothing published
        // before it reconnects. `user root`: started as root, mosquitto would
        // otherwise switch to its own user, which cannot write the test's directory.
        format!(
            "listener {port} 127.0.0.1\nallow_anonymous true\npersistence true\npersistence_location {}/\nuser root\n{extra}\n",
            dir.display()
        )
    }

    /// A broker on `port` (which `text` must name) run with the configuration `text`,
    /// written into `dir`.
    pub fn start_conf(dir: &Path, port: u16, text: &str) -> Self {
        let conf = dir.join("mosquitto.conf");
        std::fs::write(&conf, text).unwrap();
        let mut b = Broker {
            port,
            conf,
            child: None,
        };
        b.restart();
        b
    }

    /// Starts the broker again on the same port (after `stop`).
    pub fn restart(&mut self) {
        let child = Command::new(mosquitto())
            .arg("-c")
            .arg(&self.conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto runs (./test.sh installs the mosquitto package)");
        let child = self.child.insert(child);
        super::process::wait_listening(child, self.port, 2.0, "mosquitto");
    }

    /// SIGTERM: mosquitto saves its persistence file and exits. SIGKILL after 5 s:
    /// a bridge that cannot connect can leave it spinning deaf to SIGTERM, and a
    /// failed test would hang in this drop.
    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = Command::new("kill")
                .args(["-TERM", &c.id().to_string()])
                .status();
            let deadline = std::time::Instant::now() + Duration::from_secs(5);
            while c.try_wait().ok().flatten().is_none() {
                if std::time::Instant::now() > deadline {
                    let _ = c.kill();
                    break;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            let _ = c.wait();
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Messages received: (topic, payload).
pub type Received = Arc<Mutex<Vec<(String, serde_json::Value)>>>;

/// Subscribes to `filter` with QoS 1, re-subscribing after every reconnect.
pub fn subscribe(port: u16, filter: &str) -> (Received, tokio::task::JoinHandle<()>) {
    let got: Received = Arc::default();
    let sink = got.clone();
    let filter = filter.to_string();
    let task = tokio::spawn(async move {
        let mut opts = MqttOptions::new("test-subscriber", "127.0.0.1", port);
        opts.set_keep_alive(Duration::from_secs(5));
        opts.set_clean_session(false);
        let (client, mut events) = AsyncClient::new(opts, 64);
        loop {
            match events.poll().await {
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    client
                        .subscribe(filter.clone(), QoS::AtLeastOnce)
                        .await
                        .unwrap();
                }
                Ok(Event::Incoming(Packet::Publish(p))) => {
                    let v = serde_json::from_slice(&p.payload).expect("payload is JSON");
                    sink.lock().unwrap().push((p.topic.clone(), v));
                }
                Ok(_) => {}
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    });
    (got, task)
}

/// The retained message on `topic` now, as a client subscribing afresh gets it
/// (`None` when none comes within 2 s).
pub async fn retained(port: u16, topic: &str) -> Option<serde_json::Value> {
    static PROBES: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = PROBES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let mut opts = MqttOptions::new(format!("retained-probe-{n}"), "127.0.0.1", port);
    opts.set_clean_session(true);
    let (client, mut events) = AsyncClient::new(opts, 8);
    let got = tokio::time::timeout(Duration::from_secs(2), async {
        loop {
            match events.poll().await {
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    client.subscribe(topic, QoS::AtLeastOnce).await.unwrap();
                }
                Ok(Event::Incoming(Packet::Publish(p))) if p.retain => {
                    return serde_json::from_slice(&p.payload).ok();
                }
                Ok(_) => {}
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    })
    .await
    .ok()
    .flatten();
    let _ = client.try_disconnect();
    got
}
