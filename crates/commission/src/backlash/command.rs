//! `compgate backlash` on the command line: the arguments, the servo client that runs
//! the programme and uploads the trace over Modbus TCP, the MD32450 write and the
//! report files.

use std::path::PathBuf;
use std::time::Duration;

use compgate_ncproto::{self as ncmap, var};

use compgate_gateway::nc::{Guarded, Job, ModbusNcWriter, NcWriter, StopSignals};
use compgate_gateway::source::modbus::{Backoff, LinkSpec, ModbusLink};
use compgate_gateway::source::plan::RegisterKind;
use compgate_gateway::source::SourceError;

use compgate_ncproto::servo::TraceConfig;

use super::input::read_trace;
use super::math::{extract, Backlash, Extraction, Points, Procedure, Trace};
use super::report::{report, write_csv, write_svg};
use super::{BacklashError, Outcome};
use crate::args::check_f64;

/// Largest |position| a point may have, mm: beyond any machine's travel.
const PLAUSIBLE_MM: f64 = 100_000.0;

/// Arguments of `compgate backlash`.
#[derive(Debug, Clone, clap::Args)]
pub struct BacklashArgs {
    /// Axis name, for the report and file names.
    #[arg(long, default_value = "X1")]
    pub axis: String,
    /// Point A, mm: approached positively; the trace starts here.
    #[arg(long, allow_negative_numbers = true, default_value_t = 10.0)]
    pub a: f64,
    /// Point B, mm: above A.
    #[arg(long, allow_negative_numbers = true, default_value_t = 60.0)]
    pub b: f64,
    /// Point C, mm: below B (negative move).
    #[arg(long, allow_negative_numbers = true, default_value_t = 30.0)]
    pub c: f64,
    /// Point D, mm: above C (positive move).
    #[arg(long, allow_negative_numbers = true, default_value_t = 60.0)]
    pub d: f64,
    /// Feed v of every move, mm/min.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1000.0)]
    pub feed: f64,
    /// Dwell S at every point, s.
    #[arg(long, allow_negative_numbers = true, default_value_t = 2.0)]
    pub dwell: f64,
    /// Servo trace sample period, ms.
    #[arg(long, allow_negative_numbers = true, default_value_t = 2.0)]
    pub period_ms: f64,
    /// Write the result (mean of F1 and F2) to MD32450 through the FB3 job and verify
    /// the read-back.
    #[arg(long)]
    pub write: bool,
    /// NC axis module, host:port (Modbus TCP).
    #[arg(long, value_name = "ADDRESS")]
    pub nc: Option<String>,
    /// Modbus unit id of the NC axis module.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1)]
    pub unit: u8,
    /// Directory for the position-time SVG and the trace CSV.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Run against an in-process simulated axis instead of --nc.
    #[arg(long)]
    pub sim: bool,
    /// Analyse a servo trace recorded on a control instead of running the test:
    /// CSV with t_s, encoder_mm, scale_mm and optionally command_mm. The points,
    /// feed and dwell flags describe the programme that was run.
    #[arg(long, value_name = "FILE.csv")]
    pub trace: Option<PathBuf>,
    /// Simulated axis: backlash, um.
    #[arg(long, allow_negative_numbers = true, default_value_t = 20.0)]
    pub sim_backlash_um: f64,
    /// Simulated axis: measurement noise (standard deviation) of encoder and scale, um.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.3)]
    pub sim_noise_um: f64,
    /// Simulated axis: drive-train elasticity time constant, ms (table lag = v * tau);
    /// 0..=25 at the simulated Kv of 20 1/s, beyond 12.5 the loop overshoots.
    #[arg(long, allow_negative_numbers = true, default_value_t = 8.0)]
    pub sim_elastic_ms: f64,
    /// Simulated axis: noise seed.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1)]
    pub sim_seed: u64,
    /// Simulated axis: machine seconds per wall-clock second.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1000.0)]
    pub sim_speed: f64,
}

impl Default for BacklashArgs {
    fn default() -> Self {
        Self {
            axis: "X1".into(),
            a: 10.0,
            b: 60.0,
            c: 30.0,
            d: 60.0,
            feed: 1000.0,
            dwell: 2.0,
            period_ms: 2.0,
            write: false,
            nc: None,
            unit: 1,
            out: None,
            sim: false,
            trace: None,
            sim_backlash_um: 20.0,
            sim_noise_um: 0.3,
            sim_elastic_ms: 8.0,
            sim_seed: 1,
            sim_speed: 1000.0,
        }
    }
}

impl Procedure {
    /// The procedure of `args`.
    pub fn from_args(args: &BacklashArgs) -> Self {
        Self {
            points: Points {
                a_mm: args.a,
                b_mm: args.b,
                c_mm: args.c,
                d_mm: args.d,
            },
            feed_mm_per_min: args.feed,
            dwell_s: args.dwell,
            period_s: args.period_ms / 1000.0,
        }
    }
}

/// Register I/O on the NC axis module's servo block.
struct ServoClient {
    link: ModbusLink,
    unit: u8,
}

impl ServoClient {
    async fn read(&mut self, start: u16, count: u16) -> Result<Vec<u16>, BacklashError> {
        Ok(self
            .link
            .read(self.unit, RegisterKind::Holding, start, count)
            .await?)
    }

    async fn write(&mut self, start: u16, words: &[u16]) -> Result<(), BacklashError> {
        Ok(self.link.write(self.unit, start, words).await?)
    }

    async fn status(&mut self) -> Result<Vec<u16>, BacklashError> {
        self.read(ncmap::SERVO_STATUS, ncmap::SERVO_STATUS_LEN)
            .await
    }
}

fn reg(status: &[u16], address: u16) -> u16 {
    status
        .get(usize::from(address - ncmap::SERVO_STATUS))
        .copied()
        .unwrap_or(0)
}

fn f64_reg(status: &[u16], address: u16) -> f64 {
    let at = usize::from(address - ncmap::SERVO_STATUS);
    status
        .get(at..at + 4)
        .and_then(|r| <[u16; 4]>::try_from(r).ok())
        .map_or(f64::NAN, ncmap::regs_to_f64)
}

fn link_to(address: &str) -> ModbusLink {
    ModbusLink::new(
        LinkSpec::Tcp {
            address: address.to_string(),
            connect_timeout: Duration::from_secs(3),
        },
        Duration::from_secs(2),
        Backoff::new(Duration::from_millis(100), Duration::from_secs(2)),
    )
}

/// Waits for the programme and the trace; real time bounds the wait at the
/// programme's own duration (`move_s`) plus a margin. Returns the final status.
async fn wait_programme(
    nc: &mut ServoClient,
    cfg: &TraceConfig,
    move_s: f64,
) -> Result<Vec<u16>, BacklashError> {
    let deadline =
        tokio::time::Instant::now() + Duration::from_secs_f64(move_s + cfg.record_s + 30.0);
    loop {
        let status = nc.status().await?;
        match reg(&status, ncmap::MV_STATE) {
            3 => {
                return Err(BacklashError::Refused {
                    what: "move programme",
                    code: reg(&status, ncmap::MV_STATUS),
                })
            }
            2 if reg(&status, ncmap::TR_STATE) == 4 => return Ok(status),
            2 if reg(&status, ncmap::TR_STATE) <= 1 => {
                return Err(BacklashError::Timeout(format!(
                    "the programme ended but the trace never triggered (scale rising through {} mm)",
                    cfg.threshold_mm
                )))
            }
            _ => {}
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(BacklashError::Timeout(format!(
                "programme step {}, trace state {} after {:.0} s",
                reg(&status, ncmap::MV_STEP),
                reg(&status, ncmap::TR_STATE),
                move_s + cfg.record_s + 30.0
            )));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Uploads the trace `status` reports complete, page by page.
async fn upload_trace(
    nc: &mut ServoClient,
    status: &[u16],
    cfg: &TraceConfig,
) -> Result<Trace, BacklashError> {
    let count = ncmap::regs_to_u32([
        reg(status, ncmap::TR_COUNT),
        reg(status, ncmap::TR_COUNT + 1),
    ]);
    let per_page = u32::from(ncmap::TR_PAGE_SAMPLES);
    let mut trace = Trace {
        period_s: cfg.period_s,
        ..Trace::default()
    };
    for page in 0..count.div_ceil(per_page) {
        let page_u16 = u16::try_from(page).map_err(|_| {
            BacklashError::Extraction(format!("{count} samples exceed the page index"))
        })?;
        nc.write(ncmap::TR_PAGE, &[page_u16]).await?;
        let w = nc.read(ncmap::TR_WINDOW, ncmap::TR_WINDOW_LEN).await?;
        let in_page = (count - page * per_page).min(per_page) as usize;
        for k in 0..in_page {
            let f = |at: usize| ncmap::regs_to_f64([w[at], w[at + 1], w[at + 2], w[at + 3]]);
            trace.encoder_mm.push(f(8 * k));
            trace.scale_mm.push(f(8 * k + 4));
        }
    }
    Ok(trace)
}

/// After `cause` ended the wait: if the programme still runs, aborts it
/// (`MV_CMD = 2`) on a connection of its own (the test's may hold a cut request or a
/// reconnect backoff) and says where the axis stopped, or that it could not be
/// stopped.
async fn abort_programme(address: &str, unit: u8, cause: BacklashError) -> BacklashError {
    let mut nc = ServoClient {
        link: link_to(address),
        unit,
    };
    let running = match nc.status().await {
        Ok(status) => reg(&status, ncmap::MV_STATE) == 1,
        // Unknown: abort anyway, the write says whether the NC is reachable.
        Err(_) => true,
    };
    if !running {
        return cause;
    }
    let abort = match nc.write(ncmap::MV_CMD, &[2]).await {
        Ok(()) => match nc.status().await {
            Ok(status) if reg(&status, ncmap::MV_STATE) == 1 => format!(
                "THE NC STILL RUNS THE MOVE PROGRAMME after MV_CMD = 2 (abort): stop the axis at \
                 the machine; the scale reads {:.3} mm",
                f64_reg(&status, ncmap::SCALE_POS)
            ),
            Ok(status) => format!(
                "the move programme was aborted (MV_STATE {}); the scale reads {:.3} mm",
                reg(&status, ncmap::MV_STATE),
                f64_reg(&status, ncmap::SCALE_POS)
            ),
            Err(e) => format!("MV_CMD = 2 (abort) was sent; reading the axis after failed: {e}"),
        },
        Err(e) => format!(
            "ABORTING THE MOVE PROGRAMME FAILED ({e}): the axis may still be moving; stop it at the machine"
        ),
    };
    BacklashError::Aborted {
        cause: Box::new(cause),
        abort,
    }
}

/// Runs the test on the NC axis module at `address` and returns everything measured.
pub async fn run_on(address: &str, args: &BacklashArgs) -> Result<Outcome, BacklashError> {
    let procedure = Procedure::from_args(args);
    procedure.validate(None)?;
    prepare_out(args, &[])?;
    let mut nc = ServoClient {
        link: link_to(address),
        unit: args.unit,
    };
    // The axis limits and the highest feed come from the NC; check them before moving.
    // The first contact says what --nc must be: an S7 PLC or an OPC UA server there
    // answered "connection closed" or "no reply", as if the module were busy.
    let status = nc.status().await.map_err(|e| match e {
        BacklashError::Link(cause @ (SourceError::Connect(_) | SourceError::ConnectTimeout)) => {
            BacklashError::Unreachable {
                address: address.to_string(),
                cause,
            }
        }
        BacklashError::Link(cause) => BacklashError::FirstContact {
            address: address.to_string(),
            cause,
        },
        e => e,
    })?;
    let rb = nc.read(ncmap::READBACK, ncmap::READBACK_LEN).await?;
    let at = usize::from(ncmap::RB_MAX_AX_VELO - ncmap::READBACK);
    let max_feed = rb
        .get(at..at + 4)
        .and_then(|r| <[u16; 4]>::try_from(r).ok())
        .map_or(f64::NAN, ncmap::regs_to_f64);
    procedure.validate(Some((
        f64_reg(&status, ncmap::AXIS_MIN),
        f64_reg(&status, ncmap::AXIS_MAX),
        max_feed,
    )))?;
    if reg(&status, ncmap::MV_STATE) == 1 {
        return Err(BacklashError::Refused {
            what: "move programme",
            code: 5,
        });
    }

    // Arm the trace first, so it is waiting when the axis arrives at A.
    let cfg = procedure.trace_config();
    let mut words = vec![cfg.trigger as u16, 0];
    for v in [cfg.period_s, cfg.record_s, cfg.threshold_mm, cfg.delay_s] {
        words.extend_from_slice(&ncmap::f64_to_regs(v));
    }
    words.push(1);
    nc.write(ncmap::TR_TRIGGER, &words).await?;
    let status = nc.status().await?;
    if reg(&status, ncmap::TR_STATUS) != 0 {
        return Err(BacklashError::Refused {
            what: "servo trace",
            code: reg(&status, ncmap::TR_STATUS),
        });
    }

    // The programme and its start in one write.
    let steps = procedure.program();
    let mut words = vec![1, steps.len() as u16];
    for s in &steps {
        for v in [s.target_mm, s.feed_mm_per_min, s.dwell_s] {
            words.extend_from_slice(&ncmap::f64_to_regs(v));
        }
    }
    let mut stop = StopSignals::register();
    // A lost reply to the start does not mean the programme did not start.
    if let Err(e) = nc.write(ncmap::MV_CMD, &words).await {
        return Err(abort_programme(address, args.unit, e).await);
    }
    tracing::info!(axis = %args.axis, nc = address, "backlash test programme started");

    // Wait for the programme and the trace; real time bounds the wait at the
    // programme's own duration plus a margin.
    let move_s: f64 = {
        let mut from = f64_reg(&status, ncmap::SCALE_POS);
        let mut total = 0.0;
        for s in &steps {
            total += (s.target_mm - from).abs() / (s.feed_mm_per_min / 60.0) + 1.0 + s.dwell_s;
            from = s.target_mm;
        }
        total
    };
    // The axis moves until the programme ends: a signal (Ctrl-C, the unit stopped, a
    // closed SSH session) or a failed wait must not leave it running unattended. A
    // signal during the upload after it ends the test as well.
    let measured = tokio::select! {
        r = async {
            let status = wait_programme(&mut nc, &cfg, move_s).await?;
            let trace = upload_trace(&mut nc, &status, &cfg).await?;
            Ok((status, trace))
        } => r,
        signal = stop.recv() => Err(BacklashError::Signal(signal)),
    };
    let (status, trace) = match measured {
        Ok(measured) => measured,
        Err(e) => return Err(abort_programme(address, args.unit, e).await),
    };
    let machine_time_s =
        f64_reg(&status, ncmap::MV_END_TIME_S) - f64_reg(&status, ncmap::MV_START_TIME_S);

    let points = extract(&trace, &procedure, Extraction::Plateau)
        .map_err(|e| keep_trace_on_refusal(args, &trace, e))?;
    let backlash = Backlash::from_points(&points);
    let files = write_files(args, &trace, &points)?;

    let mut md32450_written_mm = None;
    if args.write {
        if backlash.disagreement_mm().is_some() {
            return Err(BacklashError::Disagree {
                f1_um: backlash.f1_mm * 1000.0,
                f2_um: backlash.f2_mm * 1000.0,
                tol_um: backlash.tolerance_mm() * 1000.0,
            });
        }
        let value = backlash.md32450_mm();
        if !(0.0..=compgate_ncproto::MD32450_LIMIT_MM).contains(&value) {
            return Err(BacklashError::Invalid(vec![format!(
                "MD32450 = {value} mm is outside 0 ..= {} mm; not written",
                compgate_ncproto::MD32450_LIMIT_MM
            )]));
        }
        // A stop asked for since the upload (extraction and files take a moment)
        // writes nothing.
        if let Some(signal) = stop.pending() {
            return Err(BacklashError::Signal(signal));
        }
        // The guard checks the read-back bit for bit, as for every job.
        let mut writer = Guarded::new(
            ModbusNcWriter::new(link_to(address), args.unit, Duration::from_secs(5)),
            vec![var::MD32450],
            Duration::from_secs(5),
        );
        writer
            .write_job(&Job {
                pairs: vec![(var::MD32450, value)],
            })
            .await?;
        md32450_written_mm = Some(value);
        if let Some(signal) = stop.pending() {
            tracing::warn!(
                "{signal} during the MD32450 job: the job was finished first (MD32450 = {value} mm written)"
            );
        }
    }

    Ok(Outcome {
        procedure,
        trace_config: cfg,
        trace,
        points,
        backlash,
        md32450_written_mm,
        machine_time_s,
        trace_file: None,
        files,
    })
}

/// A refused trace is still written to `--out` (it was recorded: nothing is lost, and
/// it shows why); the refusal is returned, with the file named.
fn keep_trace_on_refusal(args: &BacklashArgs, trace: &Trace, e: BacklashError) -> BacklashError {
    let Some((_, csv)) = out_files(args) else {
        return e;
    };
    match (e, write_csv(&csv, trace)) {
        (BacklashError::Extraction(why), Ok(())) => {
            BacklashError::Extraction(format!("{why} (trace kept in {})", csv.display()))
        }
        (e, _) => e,
    }
}

fn file_stem(axis: &str) -> String {
    axis.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}

/// The files `--out` receives: the SVG and the trace CSV.
fn out_files(args: &BacklashArgs) -> Option<(PathBuf, PathBuf)> {
    let dir = args.out.as_ref()?;
    let stem = file_stem(&args.axis);
    Some((
        dir.join(format!("backlash_{stem}.svg")),
        dir.join(format!("backlash_{stem}_trace.csv")),
    ))
}

/// Creates `--out` and checks its files against `inputs` before anything is read or
/// moved: a trace given as `--trace` must not be overwritten by its own re-export.
fn prepare_out(args: &BacklashArgs, inputs: &[&std::path::Path]) -> Result<(), BacklashError> {
    let (Some(dir), Some((svg, csv))) = (&args.out, out_files(args)) else {
        return Ok(());
    };
    compgate_core::outputs::make_dir("--out", dir)?;
    Ok(compgate_core::outputs::check(inputs, &[&svg, &csv])?)
}

/// Writes the SVG and the trace CSV into `--out` (made by [`prepare_out`]), if given.
fn write_files(
    args: &BacklashArgs,
    trace: &Trace,
    points: &[super::math::PointValue; 3],
) -> Result<Vec<PathBuf>, BacklashError> {
    let Some((svg, csv)) = out_files(args) else {
        return Ok(Vec::new());
    };
    write_svg(&svg, &args.axis, trace, points)?;
    write_csv(&csv, trace)?;
    Ok(vec![svg, csv])
}

/// `compgate backlash --trace FILE.csv`: the analysis of a trace recorded on a
/// control, offline. The procedure flags describe the programme that was run; the
/// sample period comes from the file.
pub fn run_file(args: &BacklashArgs) -> Result<Outcome, BacklashError> {
    let Some(path) = &args.trace else {
        return Err(BacklashError::Invalid(vec!["give --trace FILE.csv".into()]));
    };
    prepare_out(args, &[path])?;
    let trace = read_trace(path)?;
    let procedure = Procedure {
        period_s: trace.period_s,
        ..Procedure::from_args(args)
    };
    // The period comes from the file: a problem with it is the file's, so say where.
    procedure.validate(None).map_err(|e| match e {
        BacklashError::Invalid(problems) => {
            let ms = if trace.period_s >= 0.5 {
                "; `t_s` is in seconds, and a servo trace is sampled every few ms: were \
                 milliseconds written?"
            } else {
                ""
            };
            BacklashError::Invalid(vec![format!(
                "{}: with the sample period of its column `t_s`, {} s: {}{ms}",
                path.display(),
                trace.period_s,
                problems.join("; ")
            )])
        }
        e => e,
    })?;
    let points = extract(&trace, &procedure, Extraction::Plateau)?;
    let backlash = Backlash::from_points(&points);
    let files = write_files(args, &trace, &points)?;
    let n = trace.scale_mm.len();
    Ok(Outcome {
        procedure,
        trace_config: TraceConfig {
            period_s: trace.period_s,
            record_s: n as f64 * trace.period_s,
            ..TraceConfig::default()
        },
        machine_time_s: (n.saturating_sub(1)) as f64 * trace.period_s,
        trace,
        points,
        backlash,
        md32450_written_mm: None,
        trace_file: Some(path.clone()),
        files,
    })
}

/// Checks everything about the arguments that can be checked offline, before any
/// connection is made.
pub fn check_args(args: &BacklashArgs) -> Result<(), BacklashError> {
    // Flags first, by name: the procedure's own checks below only see the points.
    let flags = [
        ("--a", args.a, -PLAUSIBLE_MM, PLAUSIBLE_MM, "mm"),
        ("--b", args.b, -PLAUSIBLE_MM, PLAUSIBLE_MM, "mm"),
        ("--c", args.c, -PLAUSIBLE_MM, PLAUSIBLE_MM, "mm"),
        ("--d", args.d, -PLAUSIBLE_MM, PLAUSIBLE_MM, "mm"),
        ("--feed", args.feed, 0.0, 1e6, "mm/min"),
        ("--dwell", args.dwell, 0.0, 3600.0, "s"),
        ("--period-ms", args.period_ms, 0.0, 1000.0, "ms"),
        ("--sim-backlash-um", args.sim_backlash_um, 0.0, 1000.0, "um"),
        ("--sim-noise-um", args.sim_noise_um, 0.0, 100.0, "um"),
        ("--sim-elastic-ms", args.sim_elastic_ms, 0.0, 1000.0, "ms"),
        ("--sim-speed", args.sim_speed, 0.0, 1e6, "x"),
    ];
    let mut problems: Vec<String> = flags
        .into_iter()
        .filter_map(|(flag, v, min, max, unit)| check_f64(flag, v, min, max, unit).err())
        .map(|e| e.to_string())
        .collect();
    if let Err(BacklashError::Invalid(p)) = Procedure::from_args(args).validate(None) {
        problems.extend(p);
    }
    match (&args.nc, args.sim, &args.trace) {
        (None, false, None) => {
            problems.push("give --nc ADDRESS or --sim, or --trace FILE.csv".into())
        }
        (Some(_), false, None) | (None, true, None) | (None, false, Some(_)) => {}
        _ => problems.push("--nc, --sim and --trace exclude each other".into()),
    }
    if args.trace.is_some() && args.write {
        problems.push("--write needs --nc: a trace file is analysed offline".into());
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(BacklashError::Invalid(problems))
    }
}

/// `compgate backlash --nc ADDRESS` (or `--trace FILE.csv`): runs the test on the NC
/// (or analyses the file) and returns the report table. (`--sim` is the binary's: it serves the simulated axis, then calls
/// [`run_on`].)
pub async fn run(args: &BacklashArgs) -> Result<String, BacklashError> {
    check_args(args)?;
    if args.trace.is_some() {
        let outcome = run_file(args)?;
        return Ok(report(&args.axis, &outcome, None));
    }
    let Some(address) = &args.nc else {
        return Err(BacklashError::Invalid(vec!["give --nc ADDRESS".into()]));
    };
    let outcome = run_on(address, args).await?;
    Ok(report(&args.axis, &outcome, None))
}
