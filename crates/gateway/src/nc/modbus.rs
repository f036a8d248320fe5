//! The Modbus NC target: the NC axis module's register map (`compgate_ncproto`) over
//! Modbus TCP with the REQ/DONE/ERROR/STATE handshake and a job timeout; the read-back
//! is [`Guarded`](super::Guarded)'s. Only the registers the map documents are read
//! (see the table "What the gateway's writer touches" in `compgate_ncproto`).

use std::time::Duration;

use compgate_ncproto::{self as ncmap, JobState, JobStatus};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use super::{Job, JobIds, JobReport, NcError, NcSnapshot, NcWriter};
use crate::config::keys::secs;
use crate::config::problem::Problems;
use crate::source::modbus::{Backoff, LinkSpec, ModbusLink};
use crate::source::plan::RegisterKind;

fn f64_at(regs: &[u16], base: u16, addr: u16) -> Result<f64, NcError> {
    let i = usize::from(addr - base);
    regs.get(i..i + 4)
        .and_then(|r| <[u16; 4]>::try_from(r).ok())
        .map(ncmap::regs_to_f64)
        .ok_or_else(|| NcError::Protocol(format!("register {addr} missing from read-back")))
}

/// FB3-style job client over Modbus TCP.
#[derive(Debug)]
pub struct ModbusNcWriter {
    link: ModbusLink,
    unit_id: u8,
    job_timeout: Duration,
    job_ids: JobIds,
}

impl ModbusNcWriter {
    /// A writer on `link` addressing unit `unit_id`.
    pub fn new(link: ModbusLink, unit_id: u8, job_timeout: Duration) -> Self {
        Self {
            link,
            unit_id,
            job_timeout,
            job_ids: JobIds::default(),
        }
    }

    async fn read_holding(&mut self, start: u16, count: u16) -> Result<Vec<u16>, NcError> {
        Ok(self
            .link
            .read(self.unit_id, RegisterKind::Holding, start, count)
            .await?)
    }

    /// `STATE ..= JOB_ID_DONE`: the state and, once a job ended, its result, in one
    /// read (the job's end needs no second request).
    async fn handshake(&mut self) -> Result<(JobState, Vec<u16>), NcError> {
        let r = self
            .read_holding(ncmap::STATE, ncmap::JOB_ID_DONE - ncmap::STATE + 1)
            .await?;
        let v = r.first().copied().unwrap_or(u16::MAX);
        let s = JobState::from_u16(v).ok_or_else(|| NcError::Protocol(format!("STATE = {v}")))?;
        Ok((s, r))
    }

    /// Waits until `done(state)` or the deadline; the module is polled briefly
    /// because a job takes one or two IPO cycles. Returns the last handshake read.
    /// `sent`: whether the job has been handed over (for the timeout's message).
    async fn wait_state(
        &mut self,
        deadline: Instant,
        job_id: u16,
        sent: bool,
        done: impl Fn(JobState) -> bool,
    ) -> Result<Vec<u16>, NcError> {
        loop {
            let (s, regs) = self.handshake().await?;
            if done(s) {
                return Ok(regs);
            }
            if Instant::now() >= deadline {
                return Err(NcError::JobTimeout {
                    job_id,
                    timeout: self.job_timeout,
                    state: Some(s),
                    sent,
                });
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }

    async fn run_job(&mut self, job: &Job, job_id: u16, deadline: Instant) -> Result<(), NcError> {
        // A job left unacknowledged by an earlier run (crash, timeout) is cleared
        // first; a busy module is waited for, never interrupted.
        if self.handshake().await?.0 != JobState::Idle {
            self.link.write(self.unit_id, ncmap::REQ, &[0]).await?;
            self.wait_state(deadline, job_id, false, |s| s == JobState::Idle)
                .await?;
        }
        let mut block = vec![job_id, job.pairs.len() as u16];
        for (var_id, value) in &job.pairs {
            block.push(*var_id);
            block.extend_from_slice(&ncmap::f64_to_regs(*value));
        }
        self.link.write(self.unit_id, ncmap::JOB_ID, &block).await?;
        // From here a lost reply does not mean the module did not act: REQ = 1 may
        // have reached it.
        let handed_over = |e: NcError| match e {
            NcError::Link(cause) => NcError::HandedOver { job_id, cause },
            e => e,
        };
        self.link
            .write(self.unit_id, ncmap::REQ, &[1])
            .await
            .map_err(|cause| NcError::HandedOver { job_id, cause })?;
        let r = self
            .wait_state(deadline, job_id, true, |s| {
                matches!(s, JobState::Done | JobState::Error)
            })
            .await
            .map_err(handed_over)?;
        let reg = |a: u16| r[usize::from(a - ncmap::STATE)];
        // Acknowledge before judging, so the module is idle whatever happens next.
        self.link
            .write(self.unit_id, ncmap::REQ, &[0])
            .await
            .map_err(|cause| NcError::HandedOver { job_id, cause })?;
        if reg(ncmap::JOB_ID_DONE) != job_id {
            return Err(NcError::Protocol(format!(
                "JOB_ID_DONE = {}, expected {job_id}",
                reg(ncmap::JOB_ID_DONE)
            )));
        }
        let status = JobStatus::from_u16(reg(ncmap::STATUS))
            .ok_or_else(|| NcError::Protocol(format!("STATUS = {}", reg(ncmap::STATUS))))?;
        if reg(ncmap::ERROR) != 0 || status != JobStatus::Ok {
            let index = reg(ncmap::ERROR_INDEX);
            return Err(NcError::Refused {
                job_id,
                status,
                index,
                var: job.var_at(index),
            });
        }
        Ok(())
    }
}

impl NcWriter for ModbusNcWriter {
    async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
        job.check_pair_count()?;
        let job_id = self.job_ids.issue();
        let started = Instant::now();
        let deadline = started + self.job_timeout;
        match tokio::time::timeout_at(deadline, self.run_job(job, job_id, deadline)).await {
            Ok(Ok(())) => Ok(JobReport {
                job_id,
                elapsed: started.elapsed(),
            }),
            Ok(Err(e)) => Err(e),
            Err(_) => {
                // Cut off mid-request: the stream may hold a late reply.
                self.link.disconnect();
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
        let base = ncmap::READBACK;
        // Two requests: 136..139 are not in the map, and a module serving exactly the
        // map refuses a read that spans them.
        let rb = self.read_holding(base, ncmap::RB_VALUES_LEN).await?;
        let flags = self
            .read_holding(ncmap::RB_FLAGS, ncmap::RB_FLAGS_LEN)
            .await?;
        let u = |a: u16| {
            flags
                .get(usize::from(a - ncmap::RB_FLAGS))
                .copied()
                .unwrap_or(0)
        };
        Ok(NcSnapshot {
            sd43900_mm: f64_at(&rb, base, ncmap::RB_SD43900)?,
            sd43910: f64_at(&rb, base, ncmap::RB_SD43910)?,
            sd43920_mm: f64_at(&rb, base, ncmap::RB_SD43920)?,
            md32760: f64_at(&rb, base, ncmap::RB_MD32760)?,
            max_ax_velo_mm_per_min: f64_at(&rb, base, ncmap::RB_MAX_AX_VELO)?,
            md32450_mm: f64_at(&rb, base, ncmap::RB_MD32450)?,
            position_mm: Some(f64_at(&rb, base, ncmap::RB_POSITION)?),
            applied_comp_mm: Some(f64_at(&rb, base, ncmap::RB_APPLIED_COMP)?),
            target_comp_mm: Some(f64_at(&rb, base, ncmap::RB_TARGET_COMP)?),
            md32750: Some(u(ncmap::RB_MD32750)),
            referenced: Some(u(ncmap::RB_REFERENCED) != 0),
        })
    }
}

/// `[targets.NAME]` with `kind = "modbus"` (or the older `[nc_modules.NAME]`): an
/// NC axis module reached over Modbus TCP (one axis per module; see
/// `compgate_ncproto`).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ModbusTargetConfig {
    /// `host:port` of the module's Modbus TCP interface. Required; at most
    /// 300 characters. Port 0 only for `compgate demo` and `compgate sim` in a file
    /// with `[sim]`: the simulated plant binds a free port and writes it in.
    #[schemars(length(max = 300))]
    pub address: String,
    /// Modbus unit id, 0..=255 (Modbus TCP). Required.
    pub unit_id: u8,
    /// Seconds one Modbus request may take. Default 1.0; 0.001..=3600.
    #[serde(default = "default_nc_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub timeout_s: f64,
    /// Seconds a TCP connect may take. Default 2.0; 0.001..=3600.
    #[serde(default = "default_connect_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub connect_timeout_s: f64,
    /// Seconds the whole job (the running gateway's check of what the NC holds, REQ
    /// .. DONE/ERROR and the read-back) may take. Default 2.0; 0.001..=3600.
    #[serde(default = "default_job_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub job_timeout_s: f64,
}

impl ModbusTargetConfig {
    /// `timeout_s` as a [`Duration`].
    pub fn timeout(&self) -> Duration {
        secs(self.timeout_s)
    }
    /// `connect_timeout_s` as a [`Duration`].
    pub fn connect_timeout(&self) -> Duration {
        secs(self.connect_timeout_s)
    }
    /// `job_timeout_s` as a [`Duration`].
    pub fn job_timeout(&self) -> Duration {
        secs(self.job_timeout_s)
    }

    /// `address` is `host:port`, every time > 0.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        out.host_port(&k("address"), &self.address);
        out.positive(&k("timeout_s"), self.timeout_s, "seconds");
        out.positive(&k("connect_timeout_s"), self.connect_timeout_s, "seconds");
        out.positive(&k("job_timeout_s"), self.job_timeout_s, "seconds");
    }

    /// The writer of the module's one axis (not connected yet; connects on first use
    /// and reconnects with a backoff of 0.5 s doubling to 10 s). The module carries
    /// one axis, so `axis_name` and `axis_number` select nothing.
    pub fn build(&self, _axis_name: &str, _axis_number: u16) -> Result<ModbusNcWriter, NcError> {
        Ok(self.writer())
    }

    /// The module's job writer (not connected yet).
    pub fn writer(&self) -> ModbusNcWriter {
        let link = ModbusLink::new(
            LinkSpec::Tcp {
                address: self.address.clone(),
                connect_timeout: self.connect_timeout(),
            },
            self.timeout(),
            Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
        );
        ModbusNcWriter::new(link, self.unit_id, self.job_timeout())
    }
}

fn default_nc_timeout_s() -> f64 {
    1.0
}
fn default_connect_timeout_s() -> f64 {
    2.0
}
fn default_job_timeout_s() -> f64 {
    2.0
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use super::*;

    // The NC target shares the field's link: a module that accepts and closes at once
    // is retried with the growing backoff, not once per read-back.
    #[tokio::test]
    async fn a_module_that_accepts_and_closes_is_retried_with_a_growing_backoff() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let accepts = Arc::new(AtomicUsize::new(0));
        let counted = accepts.clone();
        let peer = tokio::spawn(async move {
            while let Ok((stream, _)) = listener.accept().await {
                counted.fetch_add(1, Ordering::SeqCst);
                drop(stream);
            }
        });
        let cfg = ModbusTargetConfig {
            address: address.clone(),
            unit_id: 1,
            timeout_s: 1.0,
            connect_timeout_s: 1.0,
            job_timeout_s: 1.0,
        };
        let mut writer = cfg.writer();
        let closed = format!("NC link: connection closed by the peer at {address}");
        let end = Instant::now() + Duration::from_secs(2);
        let mut hinted = false;
        while Instant::now() < end {
            let error = writer.read_snapshot().await.unwrap_err().to_string();
            assert!(error.starts_with(&closed), "{error}");
            // Before any reply: most likely a module that takes one connection at a
            // time, already held by another client.
            if error.starts_with(&format!("{closed} before it answered")) {
                assert!(error.contains("one connection at a time"), "{error}");
                hinted = true;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(
            hinted,
            "no error said the module may take one connection at a time"
        );
        // Attempts at 0, 0.5 and 1.5 s.
        let accepts = accepts.load(Ordering::SeqCst);
        assert!((2..6).contains(&accepts), "{accepts} connects in 2 s");
        peer.abort();
    }

    /// One Modbus TCP frame from `from`: MBAP header and PDU.
    async fn frame(from: &mut tokio::net::TcpStream) -> Option<Vec<u8>> {
        use tokio::io::AsyncReadExt;
        let mut head = [0u8; 7];
        from.read_exact(&mut head).await.ok()?;
        let len = usize::from(u16::from_be_bytes([head[4], head[5]]));
        let mut pdu = vec![0u8; len.saturating_sub(1)];
        from.read_exact(&mut pdu).await.ok()?;
        Some([&head[..], &pdu].concat())
    }

    // The reply to the write that raises REQ was lost (a switch, a busy gateway): the
    // module took the job, and the error read as a link that failed before anything
    // was written ("NC link: no reply within 500ms"). It now says the values may have
    // landed.
    #[tokio::test]
    async fn a_lost_reply_to_the_job_request_says_the_values_may_have_landed() {
        use compgate_plc::nc::{NcAxis, NcAxisModule};
        use tokio::io::AsyncWriteExt;
        let module = NcAxisModule::new(NcAxis::default());
        let (upstream, shutdown) = module.serve_loopback().await.unwrap();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        // Forwards every frame, and drops the replies to a write of 1 to REQ.
        let proxy = tokio::spawn(async move {
            let (mut client, _) = listener.accept().await.unwrap();
            let mut nc = tokio::net::TcpStream::connect(upstream).await.unwrap();
            while let Some(request) = frame(&mut client).await {
                nc.write_all(&request).await.unwrap();
                let reply = frame(&mut nc).await.unwrap();
                let address = u16::from_be_bytes([request[8], request[9]]);
                let raises_req = address == ncmap::REQ
                    && match request[7] {
                        6 => request[10..12] == [0, 1],
                        16 => request[13..15] == [0, 1],
                        _ => false,
                    };
                if !raises_req {
                    client.write_all(&reply).await.unwrap();
                }
            }
        });
        let cfg = ModbusTargetConfig {
            address,
            unit_id: 1,
            timeout_s: 0.2,
            connect_timeout_s: 1.0,
            job_timeout_s: 1.0,
        };
        let mut writer = cfg.writer();
        let job = Job {
            pairs: vec![(ncmap::var::SD43900, 0.123)],
        };
        let error = writer.write_job(&job).await.unwrap_err();
        assert!(matches!(error, NcError::HandedOver { .. }), "{error:?}");
        assert!(
            error
                .to_string()
                .ends_with("the values may have landed; check with `compgate nc read`"),
            "{error}"
        );
        assert_eq!(module.state().sd43900_mm, 0.123, "the job landed");
        proxy.abort();
        shutdown.cancel();
    }
}
