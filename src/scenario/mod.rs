//! `compgate scenario`: an ISO 230-3-style thermal test of the simulated machine with
//! the real gateway in the loop.
//!
//! The thermal machine (`compgate_plc::thermal`) runs a duty cycle in simulated time.
//! Its sensor temperatures go to a simulated field I/O module, served over Modbus TCP
//! on loopback; the gateway's own poller, channel processors and compensator
//! ([`compgate_gateway::runtime::build`]) read them and its FB3-style writer puts
//! SD43900/43910/43920 into a simulated NC axis module, which applies them. The
//! interferometer reads `true error - applied compensation`. Time is simulated: each
//! tick steps the machine, polls once and stamps the sample with the simulated
//! instant, so an 8-hour test takes seconds.
//!
//! The same machine (same seed) runs twice: compensation off, then on. Each run ends
//! with an ISO 230-2 test: [`ISO_RUNS`] bidirectional runs back to back over the
//! same targets, evaluated by [`compgate_commission::iso230`]. The duty is a function
//! of time alone; the interferometer only samples the machine.
//!
//! `--plant` picks the machine (`shop`: beyond the patent model; `ideal`: exactly
//! it). `--loop` closes the commissioning loop on the gateway's own records: a
//! recorded run (the service's recorder, the interferometer as a laser channel),
//! `export`, `calibrate`, `diagnose`, then a third run with the diagnosed model.

mod plot;

use std::fmt::Write as _;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use compgate_plc::field::{FieldModule, FieldModuleSpec, Profile, TransmitterSpec};
use compgate_plc::nc::{NcAxis, NcAxisModule};
use compgate_plc::thermal::{
    measurement_run, DutyCycle, Effects, Plant, SweepPlan, ThermalMachine, ThermalParams,
};
use thiserror::Error;
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

use compgate_commission::calibrate::{self, AxisModel};
use compgate_commission::diagnose::{self, ModelFile};
use compgate_commission::plot::{DrawError, PlotError};
use compgate_commission::table::Markdown;
use compgate_core::comp::Decision;
use compgate_core::measure::{MeasureError, Measurements, TempColumn};
use compgate_core::outputs::Staged;
use compgate_gateway::config;
use compgate_gateway::nc::{Job, NcWriter};
use compgate_gateway::runtime::{self, AxisStatus, Observer, SampleReadings, Status};

/// Errors of the scenario.
#[derive(Debug, Error)]
pub enum ScenarioError {
    #[error("--effects: {0}")]
    Effects(String),
    #[error("--plant: unknown plant `{0}`; known: ideal, shop")]
    Plant(String),
    #[error("{0}")]
    Arg(#[from] compgate_commission::args::ArgError),
    #[error(
        "{flag} {got_h}: {:.0} s simulated is shorter than the start-up ({STARTUP_S} s) plus \
         one interferometer sweep ({sweep_s} s): give at least {min_h} h",
        got_h * 3600.0
    )]
    TooShort {
        flag: &'static str,
        got_h: f64,
        sweep_s: f64,
        min_h: f64,
    },
    #[error("loop: {0}")]
    Loop(String),
    #[error("--sample-every-s must be at least {min_s} s, the length of one sweep (got {got_s})")]
    SampleEvery { got_s: f64, min_s: f64 },
    #[error("model: the model reads channel `{channel}`; the machine's sensors are {sensors}")]
    UnknownChannel { channel: String, sensors: String },
    #[error("model: commissioning fit: {0}")]
    Fit(#[source] calibrate::CalibrateError),
    #[error("model: {0}")]
    ModelFile(#[source] calibrate::CalibrateError),
    #[error("{0}")]
    Plot(#[from] compgate_commission::plot::PlotError),
    #[error("setup: {0}")]
    Setup(String),
    #[error("{0}")]
    Output(#[from] compgate_core::outputs::OutputError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Csv {
        path: String,
        #[source]
        source: MeasureError,
    },
    /// `--out` holds outputs of a scenario run of another mode that this run would
    /// leave beside its own (a `model.toml` its report does not name).
    #[error(
        "--out {dir}: holds {files} from another scenario run, which this run does not \
         write and would leave beside its report; use an empty directory or remove them"
    )]
    StaleOutputs { dir: String, files: String },
}

/// `compgate scenario` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct ScenarioArgs {
    /// Simulated hours: at least the start-up and one interferometer sweep (96 s),
    /// at most a week.
    #[arg(long, allow_negative_numbers = true, default_value_t = 8.0)]
    pub hours: f64,
    /// Seed of the machine (noise, ambient wander).
    #[arg(long, allow_negative_numbers = true, default_value_t = 1)]
    pub seed: u64,
    /// The simulated machine: `shop` (several thermal lumps, motion and spindle
    /// heat, a bowed screw: what the patent model cannot express exactly) or `ideal`
    /// (exactly the model's form).
    #[arg(long, default_value = "shop")]
    pub plant: String,
    /// Extra effects on top of the plant, comma separated: thermal_lag,
    /// nonlinear_position, reversal, pitch_periodic, motion_heating, extra_sensor.
    #[arg(long, value_delimiter = ',')]
    pub effects: Vec<String>,
    /// Close the commissioning loop on the gateway's own records: record a
    /// commissioning run (compensation off, interferometer as a channel) with the
    /// recorder, export it, calibrate, diagnose, then run the baseline and the
    /// diagnosed model. Ignores --model.
    #[arg(long = "loop")]
    pub closed_loop: bool,
    /// Simulated hours of the recorded commissioning run (--loop); the same range as
    /// --hours.
    #[arg(long, allow_negative_numbers = true, default_value_t = 24.0)]
    pub record_hours: f64,
    /// Model file (calibrate's or diagnose's output); default: the model calibrate
    /// fits from a 24-hour commissioning run of the same machine.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Sensors of the commissioning fit (without --model).
    #[arg(long, value_delimiter = ',', default_value = "column,screw")]
    pub sensors: Vec<String>,
    /// Output directory: report, CSVs, plots, model.
    #[arg(long)]
    pub out: PathBuf,
    /// Interferometer sweep every this many simulated seconds: at least one sweep's
    /// length (36 s), at most a day.
    #[arg(long, allow_negative_numbers = true, default_value_t = 600.0)]
    pub sample_every_s: f64,
}

/// Simulated seconds per tick: one poll of the field module per tick.
const TICK_S: f64 = 2.0;
/// Interferometer targets per sweep over the axis.
const TARGETS: usize = 9;
/// The first interferometer sweep waits this long, s: the gateway's filters fill and
/// its first writes land (in both runs alike), as on a machine switched on before
/// the test starts.
const STARTUP_S: f64 = 60.0;
/// Longest run `--hours` and `--record-hours` accept: a week of simulated time
/// (about a minute of wall time per run in a release build); beyond it a typo
/// runs for hours.
const MAX_HOURS: f64 = 168.0;
/// Longest `--sample-every-s`: a day.
const MAX_SAMPLE_EVERY_S: f64 = 86_400.0;
/// Bidirectional runs of the closing ISO 230-2 test (the standard's 5).
pub const ISO_RUNS: usize = 5;
/// Temperature range of the simulated PT100 transmitters, degC.
const RANGE_DEGC: (f64, f64) = (0.0, 50.0);

/// Peak-to-peak and RMS of one run.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ErrorStats {
    /// max - min of every interferometer reading, um.
    pub peak_to_peak_um: f64,
    /// RMS of every reading, um.
    pub rms_um: f64,
    /// Largest |reading|, um.
    pub max_abs_um: f64,
}

impl ErrorStats {
    /// Statistics of `err_um`.
    pub fn of(err_um: &[f64]) -> Self {
        let (lo, hi) = err_um
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                (a.min(*v), b.max(*v))
            });
        Self {
            peak_to_peak_um: if err_um.is_empty() { 0.0 } else { hi - lo },
            rms_um: (err_um.iter().map(|v| v * v).sum::<f64>() / err_um.len().max(1) as f64).sqrt(),
            max_abs_um: err_um.iter().map(|v| v.abs()).fold(0.0, f64::max),
        }
    }
}

/// One run (compensation off or on).
#[derive(Debug, Clone, Default)]
pub struct RunData {
    /// The interferometer series, measured error = true error - applied compensation.
    pub series: Measurements,
    /// ISO 230-2 runs after the duty cycle: [`ISO_RUNS`] bidirectional sweeps back
    /// to back.
    pub iso230: Measurements,
    /// Compensation the NC applied at each row of `series`, um.
    pub applied_um: Vec<f64>,
    /// Its statistics.
    pub stats: ErrorStats,
    /// Jobs written and verified.
    pub jobs_ok: u64,
    /// Jobs that failed.
    pub jobs_failed: u64,
    /// Field module polls.
    pub polls: u64,
    /// Wall time of the run.
    pub wall: Duration,
}

/// The scenario's result.
#[derive(Debug, Clone)]
pub struct ScenarioReport {
    /// Simulated hours.
    pub hours: f64,
    /// Effects that were on.
    pub effects: Vec<&'static str>,
    /// Where the model came from.
    pub model_source: String,
    /// The model the gateway ran.
    pub model: AxisModel,
    /// What the commissioning fit warns about ([`calibrate::Fit::warnings`]): the
    /// model was applied all the same, to show what it does.
    pub fit_warnings: Vec<String>,
    /// Ambient max - min over the run, K.
    pub ambient_swing_degc: f64,
    /// Compensation off.
    pub off: RunData,
    /// Compensation on.
    pub on: RunData,
    /// ISO 230-2 evaluation of the closing runs, off and on (`None` if it failed).
    pub iso_off: Option<compgate_commission::iso230::Iso230>,
    /// See `iso_off`.
    pub iso_on: Option<compgate_commission::iso230::Iso230>,
    /// The simulated machine (`ideal`, `shop`).
    pub plant: &'static str,
    /// The closed loop (`--loop`): `on` then ran the baseline model calibrated from
    /// the records, this the diagnosed one.
    pub closed_loop: Option<LoopReport>,
}

/// What the closed loop did and what came of it.
#[derive(Debug, Clone)]
pub struct LoopReport {
    /// Simulated hours recorded.
    pub record_hours: f64,
    /// Records written by the recorder (readings, jobs, NC rows) and dropped.
    pub records: (i64, i64, i64),
    /// Records dropped (queue full or failed commit): must be 0.
    pub dropped: u64,
    /// Rows `export` wrote.
    pub rows: usize,
    /// The `compgate export` command that wrote recorded.csv from record.sqlite, run
    /// in the `--out` directory.
    pub export_command: String,
    /// RMS residual of the baseline fit, um.
    pub baseline_fit_rms_um: f64,
    /// diagnose's verdict.
    pub verdict: String,
    /// The diagnosed model (with what the gateway applies and what it does not).
    pub model: ModelFile,
    /// The run with the diagnosed model.
    pub updated: RunData,
    /// ISO 230-2 of its closing runs.
    pub iso_updated: Option<compgate_commission::iso230::Iso230>,
    /// Wall time of recording, export, calibrate and diagnose.
    pub wall: Duration,
}

impl ScenarioReport {
    /// Peak-to-peak reduction, percent.
    pub fn reduction_pp_percent(&self) -> f64 {
        100.0 * (1.0 - self.on.stats.peak_to_peak_um / self.off.stats.peak_to_peak_um)
    }

    /// RMS reduction, percent.
    pub fn reduction_rms_percent(&self) -> f64 {
        100.0 * (1.0 - self.on.stats.rms_um / self.off.stats.rms_um)
    }

    /// Peak-to-peak reduction of the diagnosed model (--loop), percent.
    pub fn reduction_pp_updated_percent(&self) -> Option<f64> {
        let l = self.closed_loop.as_ref()?;
        Some(100.0 * (1.0 - l.updated.stats.peak_to_peak_um / self.off.stats.peak_to_peak_um))
    }

    /// Simulated time over wall time, both runs.
    pub fn speed_up(&self) -> f64 {
        2.0 * self.hours * 3600.0 / (self.off.wall + self.on.wall).as_secs_f64().max(1e-9)
    }

    /// The report as printed (Markdown table).
    pub fn text(&self) -> String {
        let mut s = String::new();
        let effects = if self.effects.is_empty() {
            "none".to_string()
        } else {
            self.effects.join(", ")
        };
        let _ = writeln!(
            s,
            "scenario: {} h simulated, plant {}, effects: {effects}, ambient swing {:.2} K",
            self.hours, self.plant, self.ambient_swing_degc
        );
        let _ = writeln!(s, "model: {}", self.model_source);
        for w in &self.fit_warnings {
            let _ = writeln!(s, "warning: commissioning fit: {w}");
        }
        let um = |v: f64| format!("{v:.2}");
        let mut error = Markdown::new([
            "thermal positioning error",
            "peak-to-peak (um)",
            "RMS (um)",
            "max abs (um)",
        ]);
        let on_name = if self.closed_loop.is_some() {
            "compensation on, baseline (calibrate)"
        } else {
            "compensation on"
        };
        let mut runs = vec![("compensation off", &self.off), (on_name, &self.on)];
        if let Some(l) = &self.closed_loop {
            runs.push(("compensation on, diagnosed model", &l.updated));
        }
        for (name, r) in runs {
            let st = &r.stats;
            let cells = [um(st.peak_to_peak_um), um(st.rms_um), um(st.max_abs_um)];
            error.row(std::iter::once(name.to_string()).chain(cells));
        }
        error.row([
            if self.closed_loop.is_some() {
                "reduction, baseline"
            } else {
                "reduction"
            }
            .to_string(),
            format!("{:.1} %", self.reduction_pp_percent()),
            format!("{:.1} %", self.reduction_rms_percent()),
            String::new(),
        ]);
        if let Some(l) = &self.closed_loop {
            error.row([
                "reduction, diagnosed model".to_string(),
                format!(
                    "{:.1} %",
                    self.reduction_pp_updated_percent().unwrap_or(0.0)
                ),
                format!(
                    "{:.1} %",
                    100.0 * (1.0 - l.updated.stats.rms_um / self.off.stats.rms_um)
                ),
                String::new(),
            ]);
        }
        s.push('\n');
        s.push_str(&error.render());
        if let (Some(a), Some(b)) = (&self.iso_off, &self.iso_on) {
            let title = format!("ISO 230-2 at the end ({ISO_RUNS} bidirectional runs, um)");
            let mut iso = Markdown::new([title.as_str(), "A", "B", "R", "E", "M"]);
            let mut rows = vec![("compensation off", a), (on_name, b)];
            if let Some(u) = self
                .closed_loop
                .as_ref()
                .and_then(|l| l.iso_updated.as_ref())
            {
                rows.push(("compensation on, diagnosed model", u));
            }
            for (name, r) in rows {
                let cells = [r.a_um, r.b_um, r.r_um, r.e_um, r.m_um].map(um);
                iso.row(std::iter::once(name.to_string()).chain(cells));
            }
            // The title stands in the header row without a leading `|`, as the guide
            // shows it.
            let iso = iso.render();
            s.push('\n');
            s.push_str(iso.strip_prefix("| ").unwrap_or(&iso));
        }
        if let Some(l) = &self.closed_loop {
            s.push_str(&l.text());
        }
        let _ = writeln!(
            s,
            "\ngateway in the loop: {} polls, {} NC jobs written and read back ({} failed)",
            self.on.polls, self.on.jobs_ok, self.on.jobs_failed
        );
        let _ = writeln!(
            s,
            "wall time {:.2} s off + {:.2} s on for 2 x {} h: {:.0} x real time",
            self.off.wall.as_secs_f64(),
            self.on.wall.as_secs_f64(),
            self.hours,
            self.speed_up()
        );
        s
    }
}

impl LoopReport {
    /// The loop's part of the report.
    pub fn text(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "\nclosed loop: {} h commissioning run recorded by the gateway (compensation off, \
             interferometer as channel `{LASER_CHANNEL}`): {} readings, {} NC rows, {} dropped; \
             export: {} rows; calibrate (baseline): RMS residual {:.2} um",
            self.record_hours,
            self.records.0,
            self.records.2,
            self.dropped,
            self.rows,
            self.baseline_fit_rms_um
        );
        let _ = writeln!(
            s,
            "the export again, in this directory: `{}`",
            self.export_command
        );
        let _ = writeln!(s, "diagnose: {}", self.verdict);
        let _ = writeln!(s, "applied online by the gateway (model_diagnosed.toml):");
        if self.model.applied.is_empty() {
            let _ = writeln!(s, "- nothing beyond the baseline");
        }
        for a in &self.model.applied {
            let _ = writeln!(s, "- {a}");
        }
        let _ = writeln!(
            s,
            "written to the model file for the NC, not applied by the gateway:"
        );
        if self.model.effects.is_empty() {
            let _ = writeln!(s, "- none");
        }
        for e in &self.model.effects {
            let _ = writeln!(s, "- {}: {}", e.name, e.carried_by);
        }
        let _ = writeln!(
            s,
            "wall time of record + export + calibrate + diagnose: {:.2} s; diagnosed run {:.2} s",
            self.wall.as_secs_f64(),
            self.updated.wall.as_secs_f64()
        );
        s
    }
}

/// The commissioning measurement: a 24-hour run of the same machine (another seed),
/// fitted by calibrate.
pub fn commissioning_model(
    params: &ThermalParams,
    effects: &Effects,
    seed: u64,
    sensors: &[String],
) -> Result<(AxisModel, calibrate::Fit, Measurements), ScenarioError> {
    let mut machine = ThermalMachine::new(params.clone(), *effects, seed ^ 0x5EED_C0DE);
    let plan = SweepPlan::irregular(params.axis_length_mm, TARGETS, 1800.0);
    let s = measurement_run(&mut machine, &DutyCycle::commissioning(24.0), &plan);
    let m = Measurements::from(&s);
    let fit = calibrate::calibrate(&m, sensors, None).map_err(ScenarioError::Fit)?;
    Ok((AxisModel::from_fit(&fit), fit, m))
}

/// The laser interface of the closed loop: a 16-bit 4-20 mA module whose one
/// transmitter carries the interferometer reading over this range, um.
const LASER_RANGE_UM: (f64, f64) = (-250.0, 750.0);
/// Channel of the interferometer reading in the recording run.
pub const LASER_CHANNEL: &str = "laser_um";

fn gateway_config(
    field: &str,
    nc: &str,
    laser: Option<&str>,
    sensors: &[&str],
    model: &AxisModel,
) -> Result<String, calibrate::ModelError> {
    let mut t = format!(
        "[devices.ain]\ntransport = \"tcp\"\naddress = \"{field}\"\nunit_id = 1\ntimeout_s = 1.0\npoll_interval_s = {TICK_S}\n\n\
         [nc_modules.nc_x]\naddress = \"{nc}\"\nunit_id = 1\ntimeout_s = 1.0\njob_timeout_s = 2.0\n\n"
    );
    for (i, name) in sensors.iter().enumerate() {
        let _ = write!(
            t,
            "[channels.{name}]\ndevice = \"ain\"\nregister = \"input\"\naddress = {i}\ndata_type = \"u16\"\n\
             scaling = {{ kind = \"transmitter\", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, current_range = \"4-20\", range_min_degc = {:.1}, range_max_degc = {:.1} }}\n\
             filter = {{ median_samples = 3, lowpass_tau_s = 20.0, max_rate_degc_per_s = 0.5, max_rejected_samples = 5, stale_after_s = 0.0, valid_min_degc = 1.0, valid_max_degc = 49.0 }}\n\n",
            RANGE_DEGC.0, RANGE_DEGC.1
        );
    }
    if let Some(laser) = laser {
        // The interferometer's reading, unfiltered: each sample belongs to the
        // position the NC reported with it.
        let _ = write!(
            t,
            "[devices.laser]\ntransport = \"tcp\"\naddress = \"{laser}\"\nunit_id = 1\ntimeout_s = 1.0\npoll_interval_s = {TICK_S}\n\n\
             [channels.{LASER_CHANNEL}]\ndevice = \"laser\"\nregister = \"input\"\naddress = 0\ndata_type = \"u16\"\n\
             scaling = {{ kind = \"transmitter\", adc_full_scale_counts = 65535, adc_full_scale_ma = 24.0, current_range = \"4-20\", range_min_degc = {:.1}, range_max_degc = {:.1} }}\n\
             filter = {{ median_samples = 1, lowpass_tau_s = 0.0, max_rate_degc_per_s = 0.0, max_rejected_samples = 5, stale_after_s = 0.0, valid_min_degc = -250.0, valid_max_degc = 750.0 }}\n\n",
            LASER_RANGE_UM.0, LASER_RANGE_UM.1
        );
    }
    // Gateway tuning of the scenario: updates every 10 s, deadbands of 0.2 um (K0)
    // and 0.2 um over the 2 m axis (slope); default step limits.
    let axis = "update_interval_s = 10.0\ndeadband_k0_mm = 0.0002\ndeadband_tan_beta = 0.0000001\n\
         max_step_k0_mm = 0.02\nmax_step_tan_beta = 0.00002\n";
    let fragment = calibrate::model_toml("X", "nc_x", model, "")?;
    // Insert the tuning keys right after the [axes.X] header.
    t.push_str(&fragment.replacen("[axes.X]\n", &format!("[axes.X]\n{axis}"), 1));
    Ok(t)
}

/// Parts of a run that stay the same for off and on.
struct Setup<'a> {
    params: &'a ThermalParams,
    effects: Effects,
    seed: u64,
    hours: f64,
    sample_every_s: f64,
}

/// What one run of the machine does.
struct Mode<'a> {
    /// The model the gateway runs.
    model: &'a AxisModel,
    /// Whether the gateway writes into the NC.
    compensate: bool,
    /// The duty cycle.
    cycle: DutyCycle,
    /// Interferometer sweeps and the closing ISO 230-2 runs (off for a recording run).
    sweeps: bool,
    /// Record through the service's recorder, stamped with simulated time from this
    /// Unix instant, ms; the interferometer reads at the actual position into channel
    /// [`LASER_CHANNEL`].
    record: Option<(&'a compgate_service::record::Recorder, i64)>,
}

fn setup_err(e: impl std::fmt::Display) -> ScenarioError {
    ScenarioError::Setup(e.to_string())
}

/// The NC applies its compensation at `pos_mm` once it has slewed there, mm.
fn applied_at(a: &NcAxis, pos_mm: f64) -> f64 {
    let mut b = a.clone();
    b.motion = compgate_plc::nc::Motion::Stopped;
    b.position_mm = pos_mm;
    for _ in 0..1_000_000 {
        b.ipo_tick();
        if b.applied_comp_mm == b.target_comp_mm() {
            break;
        }
    }
    b.applied_comp_mm
}

async fn run_once(
    s: &Setup<'_>,
    mode: &Mode<'_>,
    progress: &indicatif::ProgressBar,
) -> Result<(RunData, f64), ScenarioError> {
    let wall = Instant::now();
    let mut machine = ThermalMachine::new(s.params.clone(), s.effects, s.seed);
    let sensors = machine.sensor_names();
    for ch in mode.model.channels() {
        if !sensors.contains(&ch.as_str()) {
            return Err(ScenarioError::UnknownChannel {
                channel: ch,
                sensors: sensors.join(", "),
            });
        }
    }
    let transmitters = sensors
        .iter()
        .map(|_| TransmitterSpec::new(Profile::Constant { degc: 20.0 }, RANGE_DEGC.0, RANGE_DEGC.1))
        .collect();
    let field = FieldModule::new(FieldModuleSpec::new(transmitters, s.seed)).map_err(setup_err)?;
    let nc = NcAxisModule::new(NcAxis {
        md32750: 3,
        referenced: true,
        ..NcAxis::default()
    });
    let shutdown = CancellationToken::new();
    let _stop = shutdown.clone().drop_guard();
    let fl = TcpListener::bind("127.0.0.1:0").await.map_err(setup_err)?;
    let nl = TcpListener::bind("127.0.0.1:0").await.map_err(setup_err)?;
    let (fa, na) = (
        fl.local_addr().map_err(setup_err)?,
        nl.local_addr().map_err(setup_err)?,
    );
    tokio::spawn(field.clone().serve_tcp(fl, shutdown.clone()));
    tokio::spawn(nc.clone().serve_tcp(nl, shutdown.clone()));
    let laser = match mode.record {
        Some(_) => {
            let t = TransmitterSpec::new(
                Profile::Constant { degc: 0.0 },
                LASER_RANGE_UM.0,
                LASER_RANGE_UM.1,
            );
            let mut spec = FieldModuleSpec::new(vec![t], s.seed);
            spec.adc_full_scale_counts = u16::MAX;
            let module = FieldModule::new(spec).map_err(setup_err)?;
            let ll = TcpListener::bind("127.0.0.1:0").await.map_err(setup_err)?;
            let la = ll.local_addr().map_err(setup_err)?;
            tokio::spawn(module.clone().serve_tcp(ll, shutdown.clone()));
            Some((module, la.to_string()))
        }
        None => None,
    };

    let text = gateway_config(
        &fa.to_string(),
        &na.to_string(),
        laser.as_ref().map(|l| l.1.as_str()),
        &sensors,
        mode.model,
    )
    .map_err(setup_err)?;
    let cfg = config::load_str(&text, "scenario").map_err(setup_err)?;
    let mut built = runtime::build(&cfg).map_err(setup_err)?;
    let update_every_s = cfg.axes["X"].update_interval_s;
    let mut writer = built
        .nc_modules
        .pop()
        .ok_or_else(|| setup_err("no NC module"))?
        .writer;
    let mut devices = std::mem::take(&mut built.devices);
    let pipeline = &mut built.pipeline;
    let mut readings = SampleReadings {
        channel_names: pipeline.channel_names.clone(),
        ..SampleReadings::default()
    };
    // The recorder stamps with the simulated instant.
    let clock_ms = Arc::new(AtomicI64::new(mode.record.map_or(0, |r| r.1)));
    let mut observer = mode.record.map(|(rec, _)| {
        let c = clock_ms.clone();
        rec.observer_with_clock(Arc::new(move || c.load(Ordering::Relaxed)))
    });
    // Step limits and deadband start from what the NC holds, as in the service.
    let snap = writer.read_snapshot().await.map_err(setup_err)?;
    pipeline.axes[0].comp.set_baseline(snap.thermal());
    let base = Instant::now();

    let end_s = s.hours * 3600.0;
    let plan = SweepPlan::irregular(s.params.axis_length_mm, TARGETS, s.sample_every_s);
    let targets: Vec<(f64, i8)> = plan
        .targets_mm
        .iter()
        .map(|&p| (p, 1))
        .chain(plan.targets_mm.iter().rev().map(|&p| (p, -1)))
        .collect();
    let mut out = RunData::default();
    let empty = Measurements {
        temps: sensors
            .iter()
            .map(|n| TempColumn {
                name: (*n).to_string(),
                degc: Vec::new(),
            })
            .collect(),
        ..Measurements::default()
    };
    out.series = empty.clone();
    out.iso230 = empty;
    // After the duty cycle: ISO_RUNS back-to-back bidirectional runs for iso230.
    let iso_points = if mode.sweeps {
        ISO_RUNS * targets.len()
    } else {
        0
    };
    let mut iso_left = ISO_RUNS;
    let mut sweep_is_iso = false;
    let (mut amb_lo, mut amb_hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut next_sweep_s = STARTUP_S;
    let mut next_update_s = 0.0;
    let mut sweep_at: Option<usize> = None;
    let mut travel_mm = 0.0;
    let mut last_progress_s = 0.0;
    let mut status = Status {
        axes: vec![AxisStatus {
            name: "X".into(),
            ..AxisStatus::default()
        }],
        ..Status::default()
    };
    loop {
        let t0 = machine.t_s();
        if sweep_at.is_none() && t0 >= end_s - 1e-9 {
            if out.iso230.len() >= iso_points || iso_left == 0 {
                break;
            }
            iso_left -= 1;
            sweep_at = Some(0);
            sweep_is_iso = true;
        } else if mode.sweeps && sweep_at.is_none() && t0 + 1e-9 >= next_sweep_s {
            sweep_at = Some(0);
            next_sweep_s += s.sample_every_s;
        }
        // The duty is a function of time alone: measuring only samples the machine.
        let motion = mode.cycle.motion_at(t0);
        machine.step(TICK_S, &motion);
        travel_mm += motion.travel_mm(TICK_S);
        let t_s = machine.t_s();
        let at = tokio::time::Instant::from_std(base + Duration::from_secs_f64(t_s));
        clock_ms.store(
            mode.record.map_or(0, |r| r.1) + (t_s * 1000.0).round() as i64,
            Ordering::Relaxed,
        );
        amb_lo = amb_lo.min(machine.ambient_degc());
        amb_hi = amb_hi.max(machine.ambient_degc());

        // The NC's axis is where the duty moved it; its compensation slews there.
        let (pos_mm, dir) = machine.axis_position_mm();
        let nc_axis = nc.with_state(|a| {
            a.position_mm = pos_mm;
            for _ in 0..1_000_000 {
                a.ipo_tick();
                if a.applied_comp_mm == a.target_comp_mm() {
                    break;
                }
            }
            a.clone()
        });

        // Field modules -> gateway pollers -> channel processors (-> recorder).
        for (i, (_, v)) in machine.sensors_degc().iter().enumerate() {
            field
                .set_temperature_override(i, Some(*v))
                .map_err(setup_err)?;
        }
        if let Some((laser, _)) = &laser {
            // The interferometer at the actual position reads what is left after
            // the NC's compensation.
            let err_um = machine.measure(pos_mm, dir) - nc_axis.applied_comp_mm * 1000.0;
            laser
                .set_temperature_override(0, Some(err_um))
                .map_err(setup_err)?;
        }
        for (d, dev) in devices.iter_mut().enumerate() {
            let mut sample = dev.poller.poll().await;
            sample.started = at;
            pipeline.ingest(&sample, &mut readings.channels);
            out.polls += 1;
            if let Some(o) = observer.as_mut() {
                readings.device = d;
                readings.error.clone_from(&sample.error);
                readings.connects = sample.connects;
                readings.poll_elapsed = sample.elapsed;
                o.on_sample(&readings);
            }
        }

        // The NC's actual position feeds the motion heat term, as the status tick
        // does in the service.
        let snap = writer.read_snapshot().await.map_err(setup_err)?;
        let now_s = pipeline.now_s(at);
        if let Some(pos_mm) = snap.position_mm {
            pipeline.axes[0].comp.on_position(now_s, pos_mm);
        }
        if let Some(o) = observer.as_mut() {
            status.axes[0].nc = Some(snap);
            status.axes[0].nc_reads += 1;
            o.on_status(&status);
        }

        // Compensator -> FB3 job into the NC, every update interval.
        if mode.compensate && t_s + 1e-9 >= next_update_s {
            next_update_s += update_every_s;
            let params = match pipeline.decide(0, at) {
                Decision::Write { params, .. } | Decision::Ramp { params, .. } => Some(params),
                Decision::WithinDeadband | Decision::Hold { .. } => None,
            };
            if let Some(params) = params {
                let result = writer.write_job(&Job::thermal(&params)).await;
                if let Some(o) = observer.as_mut() {
                    o.on_job("X", &params, &result);
                }
                match result {
                    Ok(_) => {
                        pipeline.axes[0].comp.confirm(params);
                        out.jobs_ok += 1;
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "scenario: NC job failed");
                        out.jobs_failed += 1;
                    }
                }
            }
        }

        // Interferometer: one target per tick while a sweep runs; the NC's
        // compensation there is what it applies once it stands at the target.
        if let Some(k) = sweep_at {
            let (target_mm, dir) = targets[k];
            let applied_um = applied_at(&nc_axis, target_mm) * 1000.0;
            let err_um = machine.measure(target_mm, dir) - applied_um;
            let m = if sweep_is_iso {
                &mut out.iso230
            } else {
                out.applied_um.push(applied_um);
                &mut out.series
            };
            m.t_s.push(t_s);
            m.pos_mm.push(target_mm);
            m.dir.push(dir);
            m.travel_mm.push(travel_mm);
            m.err_um.push(err_um);
            for (col, (_, v)) in m.temps.iter_mut().zip(machine.sensors_degc()) {
                col.degc.push(*v);
            }
            travel_mm = 0.0;
            sweep_at = (k + 1 < targets.len()).then_some(k + 1);
        }
        if t_s - last_progress_s >= 60.0 {
            progress.inc((t_s - last_progress_s) as u64);
            last_progress_s = t_s;
        }
    }
    out.stats = ErrorStats::of(&out.series.err_um);
    out.wall = wall.elapsed();
    Ok((out, amb_hi - amb_lo))
}

fn io_err(path: &Path, source: std::io::Error) -> ScenarioError {
    ScenarioError::Io {
        path: path.display().to_string(),
        source,
    }
}

fn stage_csv(staged: &mut Staged, path: &Path, m: &Measurements) -> Result<(), ScenarioError> {
    let mut text = Vec::new();
    m.write(&mut text).map_err(|source| ScenarioError::Csv {
        path: path.display().to_string(),
        source,
    })?;
    staged.write(path, text).map_err(|e| io_err(path, e))
}

fn stage_svg(
    staged: &mut Staged,
    path: &Path,
    svg: Result<String, DrawError>,
) -> Result<(), ScenarioError> {
    let svg = svg.map_err(|e| PlotError {
        path: path.display().to_string(),
        message: e.0,
    })?;
    staged.write(path, svg).map_err(|e| io_err(path, e))
}

/// Runs the scenario on the machine `args.plant` names and writes everything into
/// `args.out`.
pub async fn run(args: &ScenarioArgs) -> Result<ScenarioReport, ScenarioError> {
    let plant =
        Plant::from_name(&args.plant).ok_or_else(|| ScenarioError::Plant(args.plant.clone()))?;
    let (params, effects) = plant.build();
    run_with(args, &params, effects, plant.name()).await
}

/// The effects of `base` with those of `extra` switched on too.
fn merge(base: Effects, extra: Effects) -> Effects {
    Effects {
        thermal_lag: extra.thermal_lag.or(base.thermal_lag),
        nonlinear_position: extra.nonlinear_position.or(base.nonlinear_position),
        reversal: extra.reversal.or(base.reversal),
        pitch_periodic: extra.pitch_periodic.or(base.pitch_periodic),
        motion_heating: extra.motion_heating.or(base.motion_heating),
        extra_sensor: extra.extra_sensor.or(base.extra_sensor),
        spindle: extra.spindle.or(base.spindle),
    }
}

fn progress_bar(len_s: f64) -> indicatif::ProgressBar {
    if std::io::stderr().is_terminal() {
        let pb = indicatif::ProgressBar::new(len_s as u64);
        pb.set_style(
            indicatif::ProgressStyle::with_template(
                "{msg} [{bar:40}] {pos}/{len} simulated s ({eta})",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        pb
    } else {
        indicatif::ProgressBar::hidden()
    }
}

fn stage_model(
    staged: &mut Staged,
    path: &Path,
    model: &AxisModel,
    header: &str,
) -> Result<(), ScenarioError> {
    let text = calibrate::model_toml("X", "nc_x", model, header).map_err(|source| {
        ScenarioError::ModelFile(calibrate::CalibrateError::Model {
            path: path.display().to_string(),
            source: Box::new(source),
        })
    })?;
    staged.write(path, text).map_err(|e| io_err(path, e))
}

/// Removes what SQLite may leave beside a database: at the start a stale WAL would
/// be replayed into a new database of that name.
fn remove_sqlite_sidecars(db: &Path) {
    for ext in ["-wal", "-shm"] {
        let _ = std::fs::remove_file(format!("{}{ext}", db.display()));
    }
}

/// The closed loop up to the diagnosed model: a recorded commissioning run of the
/// same machine on another day (compensation off), `export`, `calibrate`, `diagnose`.
/// Stages record.sqlite, recorded.csv, model.toml (baseline) and
/// model_diagnosed.toml.
async fn commission_from_records(
    args: &ScenarioArgs,
    params: &ThermalParams,
    effects: Effects,
    progress: &indicatif::ProgressBar,
    staged: &mut Staged,
) -> Result<(AxisModel, calibrate::Fit, diagnose::Diagnosis, LoopReport), ScenarioError> {
    use compgate_service::record::{self, export, Recorder};
    let wall = Instant::now();
    let lerr = |e: &dyn std::fmt::Display| ScenarioError::Loop(e.to_string());
    // Recorded and exported under the staged names, so that a failed loop leaves
    // the last good run's files; whatever SQLite leaves beside them goes too.
    let db = staged.path_for(&args.out.join("record.sqlite"));
    let csv = staged.path_for(&args.out.join("recorded.csv"));
    remove_sqlite_sidecars(&db);
    struct Sidecars<'a>(&'a Path);
    impl Drop for Sidecars<'_> {
        fn drop(&mut self) {
            remove_sqlite_sidecars(self.0);
        }
    }
    let _sidecars = Sidecars(&db);
    let rec = Recorder::start(&compgate_gateway::config::RecorderConfig {
        path: db.display().to_string(),
        // The simulation outruns real time: the queue holds the whole run.
        queue_cycles: 1_000_000,
        ..Default::default()
    })
    .map_err(|e| lerr(&e))?;
    // Whole seconds, so `export --since` in Unix seconds is exact.
    let epoch_ms = record::now_unix_ms() / 1000 * 1000;
    let setup = Setup {
        params,
        effects,
        seed: args.seed ^ 0x5EED_C0DE,
        hours: args.record_hours,
        sample_every_s: args.sample_every_s,
    };
    let mode = Mode {
        model: &AxisModel::default(),
        compensate: false,
        cycle: DutyCycle::recording(args.record_hours),
        sweeps: false,
        record: Some((&rec, epoch_ms)),
    };
    progress.set_message("recording     ");
    run_once(&setup, &mode, progress).await?;
    let stats = rec.sender().stats().clone();
    rec.finish();
    let dropped =
        stats.dropped_queue.load(Ordering::Relaxed) + stats.dropped_write.load(Ordering::Relaxed);
    if dropped > 0 {
        return Err(ScenarioError::Loop(format!(
            "the recorder dropped {dropped} records: the loop would fit incomplete data"
        )));
    }
    let records = record::counts(&record::export::open_read_only(&db).map_err(|e| lerr(&e))?)
        .map_err(|e| lerr(&e))?;
    let ex = export::ExportArgs {
        db: db.clone(),
        since: (epoch_ms / 1000).to_string(),
        until: ((epoch_ms as f64 / 1000.0) + args.record_hours * 3600.0 + 1.0).to_string(),
        csv: true,
        out: Some(csv.clone()),
        axis: Some("X".into()),
        err_channel: Some(LASER_CHANNEL.into()),
        step_s: 10.0,
        max_hold_s: 60.0,
        add_applied_comp: false,
    };
    let summary = export::run(&ex).map_err(|e| lerr(&e))?;
    let export_command = format!(
        "compgate export --db record.sqlite --since {} --until {} --csv --axis X \
         --err-channel {LASER_CHANNEL} --step-s {} --max-hold-s {} --out recorded.csv",
        ex.since, ex.until, ex.step_s, ex.max_hold_s
    );
    // What the tools read: the CSV file.
    let m = Measurements::read_path(&csv).map_err(|source| ScenarioError::Csv {
        path: csv.display().to_string(),
        source,
    })?;
    let fit = calibrate::calibrate(&m, &args.sensors, None).map_err(ScenarioError::Fit)?;
    let baseline = AxisModel::from_fit(&fit);
    stage_model(
        staged,
        &args.out.join("model.toml"),
        &baseline,
        &format!(
            "compgate scenario --loop: calibrate on the gateway's recorded {} h commissioning run\nRMS residual {:.3} um, R^2 {:.6}",
            args.record_hours, fit.rms_um, fit.r2
        ),
    )?;
    let d = diagnose::diagnose(
        &m,
        &diagnose::Options {
            sensors: Some(args.sensors.clone()),
            ..Default::default()
        },
    )
    .map_err(|e| lerr(&e))?;
    let model = ModelFile::from_diagnosis(&d);
    let path = args.out.join("model_diagnosed.toml");
    let text = model
        .to_toml(&path.display().to_string())
        .map_err(|e| lerr(&e))?;
    staged.write(&path, text).map_err(|e| io_err(&path, e))?;
    let report = LoopReport {
        record_hours: args.record_hours,
        records,
        dropped,
        rows: summary.rows,
        export_command,
        baseline_fit_rms_um: fit.rms_um,
        verdict: d.verdict.clone(),
        model,
        updated: RunData::default(),
        iso_updated: None,
        wall: wall.elapsed(),
    };
    Ok((baseline, fit, d, report))
}

/// The files every run writes into `--out`.
const COMMON_OUTPUTS: [&str; 7] = [
    "off.csv",
    "on.csv",
    "iso230_off.csv",
    "iso230_on.csv",
    "error_vs_time.svg",
    "error_vs_position.svg",
    "report.md",
];
/// ... and a `--loop` run.
const LOOP_OUTPUTS: [&str; 7] = [
    "record.sqlite",
    "recorded.csv",
    "model.toml",
    "model_diagnosed.toml",
    "on_diagnosed.csv",
    "loop_vs_time.svg",
    "loop_vs_position.svg",
];
/// ... and a run without `--model` (the commissioning fit).
const COMMISSIONING_OUTPUTS: [&str; 2] = ["model.toml", "commissioning.csv"];

/// Refuses an `--out` that holds outputs of another mode this run would not
/// replace: a stale `model.toml` beside a `--model` run's report reads as its
/// model. Nothing is deleted (they may be the user's); the `--model` file itself
/// is an input, not a stale output.
fn check_stale_outputs(args: &ScenarioArgs) -> Result<(), ScenarioError> {
    let ours = output_names(args);
    let input = args
        .model
        .as_deref()
        .and_then(|m| std::fs::canonicalize(m).ok());
    let mut stale: Vec<&str> = LOOP_OUTPUTS
        .into_iter()
        .chain(COMMISSIONING_OUTPUTS)
        .filter(|f| !ours.contains(f))
        .filter(|f| {
            let path = args.out.join(f);
            path.exists() && std::fs::canonicalize(&path).ok() != input
        })
        .collect();
    stale.sort_unstable();
    stale.dedup();
    if stale.is_empty() {
        return Ok(());
    }
    Err(ScenarioError::StaleOutputs {
        dir: args.out.display().to_string(),
        files: stale.join(", "),
    })
}

/// The files a run writes into `--out`, for the check before it starts.
fn output_names(args: &ScenarioArgs) -> Vec<&'static str> {
    let mut names = COMMON_OUTPUTS.to_vec();
    if args.closed_loop {
        names.extend(LOOP_OUTPUTS);
    } else if args.model.is_none() {
        names.extend(COMMISSIONING_OUTPUTS);
    }
    names
}

/// Refuses flags that cannot make a run (before anything runs), naming the flag.
fn check_args(args: &ScenarioArgs) -> Result<(), ScenarioError> {
    use compgate_commission::args::{check_f64, once, sensor_names};
    let sweep_s = TICK_S * (2 * TARGETS) as f64;
    // Whole ten-thousandths of an hour, rounded up: the minimum as printed runs.
    let min_h = ((STARTUP_S + sweep_s) / 3600.0 * 1e4).ceil() / 1e4;
    for (flag, got_h) in [
        ("--hours", args.hours),
        ("--record-hours", args.record_hours),
    ] {
        check_f64(flag, got_h, 0.0, MAX_HOURS, "h")?;
        if got_h < min_h {
            return Err(ScenarioError::TooShort {
                flag,
                got_h,
                sweep_s,
                min_h,
            });
        }
    }
    check_f64(
        "--sample-every-s",
        args.sample_every_s,
        0.0,
        MAX_SAMPLE_EVERY_S,
        "s",
    )?;
    if args.sample_every_s < sweep_s {
        return Err(ScenarioError::SampleEvery {
            got_s: args.sample_every_s,
            min_s: sweep_s,
        });
    }
    sensor_names(&args.sensors)?;
    // Empty items name no effect (`--effects ""` is none), as `Effects::from_names` reads them.
    once(
        "--effects",
        args.effects
            .iter()
            .map(|e| e.trim())
            .filter(|e| !e.is_empty()),
    )?;
    Ok(())
}

/// Runs the scenario on a machine with `params` and `effects` (plus `args.effects`).
/// Every file is staged and renamed into `--out` at the end: a run that fails
/// leaves the last good run's files as they were.
pub async fn run_with(
    args: &ScenarioArgs,
    params: &ThermalParams,
    effects: Effects,
    plant: &'static str,
) -> Result<ScenarioReport, ScenarioError> {
    check_args(args)?;
    let extra =
        Effects::from_names(&args.effects).map_err(|e| ScenarioError::Effects(e.to_string()))?;
    let effects = merge(effects, extra);
    compgate_core::outputs::make_dir("--out", &args.out)?;
    let outputs: Vec<PathBuf> = output_names(args)
        .into_iter()
        .map(|f| args.out.join(f))
        .collect();
    compgate_core::outputs::check(
        &args.model.iter().map(PathBuf::as_path).collect::<Vec<_>>(),
        &outputs.iter().map(PathBuf::as_path).collect::<Vec<_>>(),
    )?;
    check_stale_outputs(args)?;
    let mut staged = Staged::new();
    let record_s = if args.closed_loop {
        args.record_hours * 3600.0
    } else {
        0.0
    };
    let progress = progress_bar(record_s + 3.0 * args.hours * 3600.0);
    let mut closed_loop = None;
    let mut fit_warnings = Vec::new();
    let (model, model_source) = match &args.model {
        _ if args.closed_loop => {
            let (baseline, fit, _, l) =
                commission_from_records(args, params, effects, &progress, &mut staged).await?;
            closed_loop = Some(l);
            fit_warnings = fit.warnings();
            (
                baseline,
                format!(
                    "calibrate on the gateway's own records of a {} h commissioning run (sensors {}; RMS residual {:.2} um), written to model.toml",
                    args.record_hours,
                    args.sensors.join(","),
                    fit.rms_um
                ),
            )
        }
        Some(path) => {
            let (axis, model) = calibrate::load_model(path).map_err(ScenarioError::ModelFile)?;
            (model, format!("{} (axes.{axis})", path.display()))
        }
        None => {
            let (model, fit, m) = commissioning_model(params, &effects, args.seed, &args.sensors)?;
            stage_model(
                &mut staged,
                &args.out.join("model.toml"),
                &model,
                &format!(
                    "compgate scenario: commissioning fit, 24 h run of the same machine\nRMS residual {:.3} um, R^2 {:.6}",
                    fit.rms_um, fit.r2
                ),
            )?;
            stage_csv(&mut staged, &args.out.join("commissioning.csv"), &m)?;
            fit_warnings = fit.warnings();
            (
                model,
                format!(
                    "calibrate on a 24 h commissioning run (sensors {}; RMS residual {:.2} um), written to model.toml",
                    args.sensors.join(","),
                    fit.rms_um
                ),
            )
        }
    };
    let setup = Setup {
        params,
        effects,
        seed: args.seed,
        hours: args.hours,
        sample_every_s: args.sample_every_s,
    };
    let mode = |model, compensate| Mode {
        model,
        compensate,
        cycle: DutyCycle::scenario(args.hours),
        sweeps: true,
        record: None,
    };
    progress.set_message("compensation off");
    let (off, swing) = run_once(&setup, &mode(&model, false), &progress).await?;
    progress.set_message("compensation on ");
    let (on, _) = run_once(&setup, &mode(&model, true), &progress).await?;
    let iso =
        |m: &Measurements| compgate_commission::iso230::evaluate(&m.pos_mm, &m.dir, &m.err_um).ok();
    if let Some(l) = closed_loop.as_mut() {
        progress.set_message("diagnosed model ");
        let (updated, _) = run_once(&setup, &mode(&l.model.axis, true), &progress).await?;
        l.iso_updated = iso(&updated.iso230);
        l.updated = updated;
    }
    progress.finish_and_clear();
    let (iso_off, iso_on) = (iso(&off.iso230), iso(&on.iso230));
    let report = ScenarioReport {
        iso_off,
        iso_on,
        hours: args.hours,
        effects: effects.names(),
        model_source,
        model,
        fit_warnings,
        ambient_swing_degc: swing,
        off,
        on,
        plant,
        closed_loop,
    };
    let out = |f: &str| args.out.join(f);
    stage_csv(&mut staged, &out("off.csv"), &report.off.series)?;
    stage_csv(&mut staged, &out("on.csv"), &report.on.series)?;
    stage_csv(&mut staged, &out("iso230_off.csv"), &report.off.iso230)?;
    stage_csv(&mut staged, &out("iso230_on.csv"), &report.on.iso230)?;
    stage_svg(
        &mut staged,
        &out("error_vs_time.svg"),
        plot::error_vs_time(&report),
    )?;
    stage_svg(
        &mut staged,
        &out("error_vs_position.svg"),
        plot::error_vs_position(&report),
    )?;
    let mut text = report.text();
    if let Some(l) = &report.closed_loop {
        stage_csv(&mut staged, &out("on_diagnosed.csv"), &l.updated.series)?;
        stage_svg(
            &mut staged,
            &out("loop_vs_time.svg"),
            plot::loop_vs_time(&report, l),
        )?;
        stage_svg(
            &mut staged,
            &out("loop_vs_position.svg"),
            plot::loop_vs_position(&report, l),
        )?;
        text.push_str(
            "\n![error against time](error_vs_time.svg)\n\n\
             ![before and after the loop, against time](loop_vs_time.svg)\n\n\
             ![before and after the loop, along the axis](loop_vs_position.svg)\n",
        );
    }
    let path = out("report.md");
    staged.write(&path, &text).map_err(|e| io_err(&path, e))?;
    if args.closed_loop {
        // The new database must not meet the old one's WAL.
        remove_sqlite_sidecars(&out("record.sqlite"));
    }
    staged
        .commit()
        .map_err(|(path, source)| io_err(&path, source))?;
    Ok(report)
}

#[cfg(test)]
mod tests;
