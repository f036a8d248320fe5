//! `compgate-bench cycle`: full poll-filter-compute cycles against the bare request rate.
//!
//! Both sides read the same 64 input registers from the same simulated field module
//! over loopback. The gateway side runs the real code path (`DevicePoller::poll` with
//! its timeout and reconnect wrapper, every channel processor and the readings handed
//! to the observers, one axis decision) twice: as the gateway runs it, the device task
//! handing each sample over a bounded channel to the core task, and in one task, poll
//! then processing. The bare side calls tokio-modbus directly. Rounds alternate so a
//! noisy shared machine slows all sides alike, and the result is a ratio.

use std::fmt::Write as _;
use std::time::{Duration, Instant};

use compgate_commission::table::Markdown;

use compgate_plc::field::{FieldModule, FieldModuleSpec, Profile, TransmitterSpec};
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_modbus::client::{tcp, Reader};
use tokio_util::sync::CancellationToken;

use compgate_gateway::config;
use compgate_gateway::runtime;
use compgate_gateway::source::DeviceSample;

/// Measurements of one side.
#[derive(Debug, Clone, Default)]
pub struct Side {
    /// Cycles per second of each round.
    pub rates_per_s: Vec<f64>,
    /// Every cycle's latency.
    pub latencies: Vec<Duration>,
}

impl Side {
    /// Median of the round rates.
    pub fn median_rate_per_s(&self) -> f64 {
        let mut r = self.rates_per_s.clone();
        r.sort_by(f64::total_cmp);
        r.get(r.len() / 2).copied().unwrap_or(0.0)
    }

    /// Latency percentile (0..=100).
    pub fn percentile(&self, p: f64) -> Duration {
        let mut l = self.latencies.clone();
        l.sort();
        if l.is_empty() {
            return Duration::ZERO;
        }
        let i = ((p / 100.0) * (l.len() - 1) as f64).round() as usize;
        l[i.min(l.len() - 1)]
    }
}

/// The result of a bench run.
#[derive(Debug, Clone, Default)]
pub struct BenchReport {
    /// Channels per cycle.
    pub channels: u16,
    /// Gateway cycles as the gateway runs them: the device task polls and hands each
    /// sample over a bounded channel to the core task, which processes it and decides.
    pub gateway: Side,
    /// Gateway cycles with poll and processing one after the other in one task.
    pub sequential: Side,
    /// Bare tokio-modbus reads.
    pub bare: Side,
    /// The device poller alone (request wrapper and decoding, no channel processing).
    pub poll_only: Side,
    /// Time of the synchronous part alone (64 channel processors + one decision): the
    /// median of the rounds' means.
    pub pipeline_only: Duration,
    /// Channel readings checked (every channel at the end of every gateway round) and
    /// how many of them were `Good`: the bench must measure the filters, not the
    /// hold path of rejected samples.
    pub readings_checked: u64,
    /// Of [`Self::readings_checked`], the `Good` ones.
    pub readings_good: u64,
}

impl BenchReport {
    /// Gateway rate (device task -> core task) over bare rate (medians).
    pub fn ratio(&self) -> f64 {
        self.gateway.median_rate_per_s() / self.bare.median_rate_per_s()
    }

    /// What the gateway adds to one cycle, from the median rates: the time of a
    /// gateway cycle (one task) less that of a bare read, us. Unlike the ratio it does
    /// not depend on how long the bare read takes.
    pub fn overhead_us(&self) -> f64 {
        1e6 / self.sequential.median_rate_per_s() - 1e6 / self.bare.median_rate_per_s()
    }

    /// Share of the checked channel readings that were `Good`.
    pub fn good_share(&self) -> f64 {
        self.readings_good as f64 / self.readings_checked.max(1) as f64
    }

    /// Gateway rate with poll and processing in one task over bare rate (medians).
    pub fn sequential_ratio(&self) -> f64 {
        self.sequential.median_rate_per_s() / self.bare.median_rate_per_s()
    }

    /// A Markdown table, as in the README.
    pub fn table(&self) -> String {
        let mut table = Markdown::new([
            format!("{} channels, loopback", self.channels),
            "cycles/s (median of rounds)".into(),
            "p50 latency".into(),
            "p99 latency".into(),
        ]);
        for (name, side) in [
            ("bare tokio-modbus read", &self.bare),
            (
                "gateway poll+filter+compute (device task -> core task)",
                &self.gateway,
            ),
            (
                "the same in one task, one after the other",
                &self.sequential,
            ),
            ("the device poll alone", &self.poll_only),
        ] {
            table.row([
                name.to_string(),
                format!("{:.0}", side.median_rate_per_s()),
                format!("{:.1} us", side.percentile(50.0).as_secs_f64() * 1e6),
                format!("{:.1} us", side.percentile(99.0).as_secs_f64() * 1e6),
            ]);
        }
        table.row([
            "channel processing + decision alone".to_string(),
            String::new(),
            format!(
                "{:.1} us (median of round means)",
                self.pipeline_only.as_secs_f64() * 1e6
            ),
            String::new(),
        ]);
        let mut s = table.render();
        let _ = writeln!(
            s,
            "\nratio gateway/bare: {:.3} as the gateway runs (device task -> core task), {:.3} in one task",
            self.ratio(),
            self.sequential_ratio()
        );
        let _ = writeln!(
            s,
            "gateway overhead per cycle (one task, from the median rates): {:.2} us",
            self.overhead_us()
        );
        let _ = writeln!(
            s,
            "channel readings good at the end of the rounds: {:.1} %",
            100.0 * self.good_share()
        );
        s
    }
}

/// Servo cycle budgets of a 5-axis NC the volumetric compensation runs inside, us.
const SERVO_CYCLES_US: [f64; 2] = [125.0, 500.0];

/// One line on the volumetric compensator: compensations per second on one core and
/// the share of a servo cycle one compensation takes.
pub fn volumetric_line(seconds: f64) -> String {
    let b = crate::volumetric::bench_per_s(seconds);
    format!(
        "volumetric compensation, one core: {:.0}/s, {:.0} ns each = {:.2}% of a {} us / {:.3}% of a {} us servo cycle (target >= 1,000,000/s)\n",
        b.per_s,
        b.ns_each,
        b.ns_each / (SERVO_CYCLES_US[0] * 10.0),
        SERVO_CYCLES_US[0],
        b.ns_each / (SERVO_CYCLES_US[1] * 10.0),
        SERVO_CYCLES_US[1],
    )
}

/// Distinct polled samples the "processing alone" figure cycles through (about
/// 400 KB of samples at 64 channels: they stay in the second-level cache).
const ALONE_SAMPLES: usize = 256;

/// Errors of the bench.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// Setting up failed.
    #[error("bench setup: {0}")]
    Setup(String),
    /// A read failed during measurement.
    #[error("read failed during the bench: {0}")]
    Read(String),
}

/// The bench's rate limit, degC/s. The bench polls about every 14 us, some 7000
/// times as often as a gateway in service (100 ms). One ADC count (0.07 degC) between
/// two polls must pass the rate check, as it does in service with the example
/// configs' 1 degC/s: at 100 degC/s a quarter of the bench's samples were rejected as
/// implausible, and the figure measured the hold path of a faulty sensor instead of
/// the filters. At 10000 degC/s a bench poll may move 0.14 degC; in service, 1 degC/s
/// at 100 ms lets a poll move 0.1 degC.
const BENCH_MAX_RATE_DEGC_PER_S: f64 = 10_000.0;

fn bench_config(channels: u16, address: &str) -> String {
    let mut t = format!(
        "[gateway]\nstatus_interval_s = 1.0\n\n[devices.ain]\ntransport = \"tcp\"\naddress = \"{address}\"\nunit_id = 1\ntimeout_s = 1.0\npoll_interval_s = 1.0\n\n[nc_modules.nc]\naddress = \"127.0.0.1:1\"\nunit_id = 1\n\n"
    );
    for i in 0..channels {
        let _ = write!(
            t,
            "[channels.T{i:03}]\ndevice = \"ain\"\nregister = \"input\"\naddress = {i}\ndata_type = \"u16\"\n\
             scaling = {{ kind = \"transmitter\", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, current_range = \"4-20\", range_min_degc = -50.0, range_max_degc = 150.0 }}\n\
             filter = {{ median_samples = 5, lowpass_tau_s = 10.0, max_rate_degc_per_s = {BENCH_MAX_RATE_DEGC_PER_S:.1}, max_rejected_samples = 5, stale_after_s = 0.0, valid_min_degc = -40.0, valid_max_degc = 140.0 }}\n\n"
        );
    }
    t.push_str(
        "[axes.X]\nnc_module = \"nc\"\nmd32750 = 3\np0_mm = 0.0\nupdate_interval_s = 1.0\n\
         k0 = { offset_mm = 0.0, terms = [{ channel = \"T000\", ref_degc = 20.0, coeff_mm_per_degc = 0.004 }, { channel = \"T001\", ref_degc = 20.0, coeff_mm_per_degc = 0.001 }] }\n\
         tan_beta = { offset = 0.0, terms = [{ channel = \"T002\", ref_degc = 20.0, coeff_per_degc = 0.0000115 }] }\n",
    );
    t
}

/// Runs the bench: `rounds` alternating rounds of `cycles` each.
pub async fn run(channels: u16, cycles: u32, rounds: u32) -> Result<BenchReport, BenchError> {
    // On a worker thread, like every gateway task; `block_on`'s thread wakes
    // differently and would skew the bare side.
    tokio::spawn(measure(channels, cycles, rounds))
        .await
        .map_err(|e| BenchError::Setup(e.to_string()))?
}

async fn measure(channels: u16, cycles: u32, rounds: u32) -> Result<BenchReport, BenchError> {
    let transmitters = (0..channels)
        .map(|i| {
            let mut t = TransmitterSpec::new(
                Profile::Sine {
                    mean_degc: 22.0,
                    amplitude_degc: 2.0,
                    period_s: 60.0 + f64::from(i),
                },
                -50.0,
                150.0,
            );
            t.noise_degc = 0.02;
            t
        })
        .collect();
    let module = FieldModule::new(FieldModuleSpec::new(transmitters, 1))
        .map_err(|e| BenchError::Setup(e.to_string()))?;
    // The simulated module runs on the gateway's runtime. On a thread of its own it
    // would park between requests, and waking a parked CPU (50-100 us on a virtual
    // machine) would lengthen the bare read and flatter the ratio.
    let listener = TcpListener::bind("127.0.0.1:0")
        .await
        .map_err(|e| BenchError::Setup(e.to_string()))?;
    let addr = listener
        .local_addr()
        .map_err(|e| BenchError::Setup(e.to_string()))?;
    let shutdown = CancellationToken::new();
    let _stop = shutdown.clone().drop_guard();
    tokio::spawn(module.serve_tcp(listener, shutdown.clone()));

    let cfg = config::load_str(&bench_config(channels, &addr.to_string()), "bench")
        .map_err(|e| BenchError::Setup(e.to_string()))?;
    let mut built = runtime::build(&cfg).map_err(|e| BenchError::Setup(e.to_string()))?;
    let runtime::Poller::Modbus(poller) = &mut built
        .devices
        .first_mut()
        .ok_or_else(|| BenchError::Setup("no device".into()))?
        .poller
    else {
        return Err(BenchError::Setup("not a Modbus device".into()));
    };
    if poller.blocks().len() != 1 {
        return Err(BenchError::Setup(format!(
            "expected one merged read, the plan has {}",
            poller.blocks().len()
        )));
    }
    let mut pipeline = built.pipeline;

    let stream = tokio::net::TcpStream::connect(addr)
        .await
        .map_err(|e| BenchError::Setup(e.to_string()))?;
    stream
        .set_nodelay(true)
        .map_err(|e| BenchError::Setup(e.to_string()))?;
    let mut bare = tcp::attach(stream);

    let mut report = BenchReport {
        channels,
        ..BenchReport::default()
    };
    // The channels' new readings, as the core loop hands them to the observers.
    let mut readings = Vec::with_capacity(usize::from(channels));
    // Warm up both paths (connects, allocations, caches).
    for _ in 0..200 {
        let s = poller.poll().await;
        pipeline.ingest(&s, &mut readings);
        let _ = bare.read_input_registers(0, channels).await;
    }
    for _ in 0..rounds {
        // As `runtime::generation` runs it: the device task polls back to back (no
        // poll interval) and sends each sample over the same bounded channel to a
        // core task that owns the pipeline. A cycle's latency runs from the start of
        // its poll to the end of its decision.
        let (tx, mut rx) = mpsc::channel::<DeviceSample>(runtime::SAMPLE_QUEUE);
        let mut core_pipeline = pipeline;
        let mut core_readings = std::mem::take(&mut readings);
        let core = tokio::spawn(async move {
            let mut latencies = Vec::with_capacity(cycles as usize);
            while let Some(sample) = rx.recv().await {
                core_pipeline.ingest(&sample, &mut core_readings);
                std::hint::black_box(&core_readings);
                std::hint::black_box(core_pipeline.decide(0, tokio::time::Instant::now()));
                latencies.push(sample.started.elapsed());
            }
            (core_pipeline, core_readings, latencies)
        });
        let t0 = Instant::now();
        for _ in 0..cycles {
            let sample = poller.poll().await;
            if let Some(e) = &sample.error {
                return Err(BenchError::Read(e.to_string()));
            }
            if tx.send(sample).await.is_err() {
                return Err(BenchError::Setup("core task ended".into()));
            }
        }
        drop(tx);
        let (back, back_readings, latencies) =
            core.await.map_err(|e| BenchError::Setup(e.to_string()))?;
        readings = back_readings;
        report
            .gateway
            .rates_per_s
            .push(f64::from(cycles) / t0.elapsed().as_secs_f64());
        report.gateway.latencies.extend(latencies);
        pipeline = back;
        for ch in 0..pipeline.channel_names.len() {
            report.readings_checked += 1;
            report.readings_good +=
                u64::from(pipeline.reading(ch).is_some_and(|r| r.quality.is_good()));
        }

        let t0 = Instant::now();
        for _ in 0..cycles {
            let c0 = Instant::now();
            let sample = poller.poll().await;
            if let Some(e) = &sample.error {
                return Err(BenchError::Read(e.to_string()));
            }
            pipeline.ingest(&sample, &mut readings);
            std::hint::black_box(&readings);
            let _ = pipeline.decide(0, tokio::time::Instant::now());
            report.sequential.latencies.push(c0.elapsed());
        }
        report
            .sequential
            .rates_per_s
            .push(f64::from(cycles) / t0.elapsed().as_secs_f64());

        let t0 = Instant::now();
        for _ in 0..cycles {
            let c0 = Instant::now();
            std::hint::black_box(poller.poll().await);
            report.poll_only.latencies.push(c0.elapsed());
        }
        report
            .poll_only
            .rates_per_s
            .push(f64::from(cycles) / t0.elapsed().as_secs_f64());

        let t0 = Instant::now();
        for _ in 0..cycles {
            let c0 = Instant::now();
            match bare.read_input_registers(0, channels).await {
                Ok(Ok(regs)) => {
                    std::hint::black_box(regs);
                }
                other => return Err(BenchError::Read(format!("{other:?}"))),
            }
            report.bare.latencies.push(c0.elapsed());
        }
        report
            .bare
            .rates_per_s
            .push(f64::from(cycles) / t0.elapsed().as_secs_f64());
    }
    // The synchronous stages alone, to show where time goes: real samples in turn,
    // each stamped one bare read later than the one before, so the filters see a real
    // `dt`, as in the loop (the same sample again would be `dt = 0`, a shortcut for the
    // low pass). Many distinct samples, as the loop sees: with two alternating ones the
    // branch predictor learns their values and the figure comes out a quarter too low.
    let mut samples = Vec::with_capacity(ALONE_SAMPLES);
    for _ in 0..ALONE_SAMPLES {
        samples.push(poller.poll().await);
    }
    let step = Duration::from_secs_f64(1.0 / report.bare.median_rate_per_s().max(1.0));
    // Median of per-round means, like the rates: one burst of load must not decide it.
    let mut means = Vec::with_capacity(rounds as usize);
    let n = cycles.max(1);
    for _ in 0..rounds.max(1) {
        let t0 = Instant::now();
        for i in 0..n {
            let sample = &mut samples[i as usize % ALONE_SAMPLES];
            sample.started += step * ALONE_SAMPLES as u32;
            pipeline.ingest(std::hint::black_box(sample), &mut readings);
            std::hint::black_box(&readings);
            std::hint::black_box(pipeline.decide(0, tokio::time::Instant::now()));
        }
        means.push(t0.elapsed() / n);
    }
    means.sort();
    report.pipeline_only = means[means.len() / 2];
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    // Checks the bench runs the real path and counts what it measures; no timing
    // assertion (speed belongs in the bench, not in tests).
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn bench_runs_both_sides_over_loopback() {
        let r = run(16, 20, 2).await.unwrap();
        assert_eq!(r.gateway.latencies.len(), 40);
        assert_eq!(r.bare.latencies.len(), 40);
        assert_eq!(r.poll_only.latencies.len(), 40);
        assert_eq!(r.sequential.latencies.len(), 40);
        assert_eq!(r.gateway.rates_per_s.len(), 2);
        assert!(r.ratio().is_finite() && r.ratio() > 0.0);
        assert!(r.overhead_us().is_finite());
        assert!(r.table().contains("| bare tokio-modbus read |"));
        // One ADC count of noise between two polls passes the rate check, as in
        // service: the readings are good, not held after a rejection.
        assert_eq!(r.readings_checked, 32);
        assert!(r.good_share() > 0.9, "{}", r.good_share());
    }
}
