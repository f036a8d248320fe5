//! Thermal behaviour of a large CNC feed axis: a lumped thermal network, the true
//! positioning error field it causes, and a simulated laser interferometer.
//!
//! Pure and synchronous: no clock, no I/O. Time advances only through
//! [`ThermalMachine::step`], so an 8-hour run takes as long as its arithmetic; for a
//! seed and the same sequence of steps the results are identical.
//!
//! # Network
//!
//! Every node is first order, integrated exactly over a step (inputs held constant),
//! so any step size is stable:
//!
//! - ambient: `mean + daily_amplitude * sin(2 pi (t + phase) / 1 day) + drift * t`
//!   plus a slow seeded random wander (Ornstein-Uhlenbeck);
//! - bed and column follow ambient with their own time constants;
//! - ball screw follows the bed plus a rise proportional to the axis load
//!   `speed / full_speed * duty`; the motor follows ambient plus its own rise.
//!
//! - with `spindle` (the shop plant), the spindle head follows ambient plus a rise
//!   proportional to the spindle load.
//!
//! Sensors (`ambient`, `bed`, `column`, `screw`, `motor`, and `extra` and `spindle`
//! with those effects) read their node through a first-order lag with Gaussian noise.
//! [`Plant`] names the presets: `ideal` (exactly the straight-line model below) and
//! `shop` (what it cannot express).
//!
//! # Error field
//!
//! Actual minus commanded position, um, for the base physics:
//!
//! ```text
//! err(P) = a * (T_screw - T_ref) * (P - P_ref) / 1000 + a * L_col * (T_column - T_ref) / 1000
//! ```
//!
//! with `a` the expansion coefficient in um/m/K, `P_ref` the screw's fixed bearing
//! (the reference position; error there is the column part only) and `L_col` the
//! column's lever into the axis, mm. In the gateway's terms this is exactly
//! `K0 = a L_col (T_column - T_ref)` and `tan(beta) = a (T_screw - T_ref)` with
//! `P0 = P_ref` ([`ThermalMachine::true_model`]). The [`Effects`] add what this
//! straight-line model cannot express.

use crate::SimRng;
use compgate_core::measure::{Measurements, TempColumn};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

const DAY_S: f64 = 86_400.0;

/// Ambient temperature of the workshop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AmbientParams {
    /// Daily mean, degC.
    pub mean_degc: f64,
    /// Amplitude of the daily sine, K.
    pub daily_amplitude_degc: f64,
    /// Time added to `t` before the sine, s (-21600 starts at the daily minimum).
    pub phase_s: f64,
    /// Linear drift, K per hour.
    pub drift_degc_per_h: f64,
    /// Standard deviation of the random wander, K (0 = none).
    pub wander_degc: f64,
    /// Correlation time of the wander, s.
    pub wander_tau_s: f64,
}

impl Default for AmbientParams {
    fn default() -> Self {
        Self {
            mean_degc: 20.0,
            daily_amplitude_degc: 3.0,
            phase_s: -DAY_S / 4.0,
            drift_degc_per_h: 0.1,
            wander_degc: 0.1,
            wander_tau_s: 3600.0,
        }
    }
}

/// The machine: geometry, network and instruments. `Default` is the default scenario:
/// a 2 m steel axis in a workshop whose ambient rises ~5 K over the first 8 hours.
#[derive(Debug, Clone, PartialEq)]
pub struct ThermalParams {
    /// Axis travel, mm (positions 0..=axis_length_mm).
    pub axis_length_mm: f64,
    /// Linear expansion coefficient, um per m per K (steel ~11.5).
    pub expansion_um_per_m_per_degc: f64,
    /// Temperature at which the error field is zero, degC.
    pub ref_degc: f64,
    /// Fixed bearing of the screw: the reference position, mm.
    pub ref_position_mm: f64,
    /// Lever of the column's growth into the axis direction, mm.
    pub column_lever_mm: f64,
    /// Workshop ambient.
    pub ambient: AmbientParams,
    /// Bed time constant behind ambient, s.
    pub bed_tau_s: f64,
    /// Column time constant behind ambient, s.
    pub column_tau_s: f64,
    /// Screw time constant behind the bed, s.
    pub screw_tau_s: f64,
    /// Motor time constant behind ambient, s.
    pub motor_tau_s: f64,
    /// Steady rise of the screw over the bed at load 1, K.
    pub screw_rise_degc: f64,
    /// Steady rise of the motor over ambient at load 1, K.
    pub motor_rise_degc: f64,
    /// Speed at which load is 1 (with duty 1), mm/s.
    pub full_speed_mm_per_s: f64,
    /// Lag of every sensor, s (0 = none).
    pub sensor_tau_s: f64,
    /// Sensor noise, K (standard deviation; 0 = none).
    pub sensor_noise_degc: f64,
    /// Interferometer noise, um (standard deviation; 0 = none).
    pub interferometer_noise_um: f64,
}

impl Default for ThermalParams {
    fn default() -> Self {
        Self {
            axis_length_mm: 2000.0,
            expansion_um_per_m_per_degc: 11.5,
            ref_degc: 20.0,
            ref_position_mm: 0.0,
            column_lever_mm: 800.0,
            ambient: AmbientParams::default(),
            bed_tau_s: 4.0 * 3600.0,
            column_tau_s: 3.0 * 3600.0,
            screw_tau_s: 1800.0,
            motor_tau_s: 1200.0,
            screw_rise_degc: 6.0,
            motor_rise_degc: 15.0,
            full_speed_mm_per_s: 200.0,
            sensor_tau_s: 20.0,
            sensor_noise_degc: 0.02,
            interferometer_noise_um: 0.3,
        }
    }
}

/// `thermal_lag`: the structure (column and screw, as far as the error is concerned)
/// follows what its sensor reads with a further first-order lag.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThermalLagParams {
    /// Lag of the structure behind the sensed node, s.
    pub tau_s: f64,
}

/// `nonlinear_position`: the screw's rise over the bed is largest mid-travel (where the
/// nut runs most), bending the error curve: `um_per_degc * rise * 4 x (1 - x)`,
/// `x = P / axis_length`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NonlinearPositionParams {
    /// Bow at mid-travel per K of screw rise over the bed, um/K.
    pub um_per_degc: f64,
}

/// `reversal`: the error approaching in the positive direction minus the error
/// approaching in the negative direction is `b_um`, half of it on each side; a
/// backlash, the table lagging behind on both sides, makes it negative.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReversalParams {
    /// Reversal value, um: err(+) - err(-), the sign of ISO 230-2's B_i and of
    /// diagnose's `b_um`.
    pub b_um: f64,
}

/// `pitch_periodic`: periodic pitch error of the screw, `amplitude * sin(2 pi P / period)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PitchPeriodicParams {
    /// Period along the axis, mm.
    pub period_mm: f64,
    /// Amplitude, um.
    pub amplitude_um: f64,
}

/// `motion_heating`: a node no sensor sees (guideway, nut) heated by axis load,
/// adding `um_per_degc * rise` to the error everywhere.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionHeatingParams {
    /// Time constant of the hidden node, s.
    pub tau_s: f64,
    /// Steady rise at load 1, K.
    pub rise_degc: f64,
    /// Error per K of rise, um/K.
    pub um_per_degc: f64,
}

/// `extra_sensor`: a heat source cycling on and off (hydraulics, coolant) warms a
/// part of the structure, seen only by sensor `extra`, adding `um_per_degc * (T_extra
/// - ambient)` to the error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtraSensorParams {
    /// Time constant of the warmed part, s.
    pub tau_s: f64,
    /// Rise of the source over ambient while on, K.
    pub rise_degc: f64,
    /// Period of the on/off cycle (half on, half off), s.
    pub period_s: f64,
    /// Error per K of the part's rise over ambient, um/K.
    pub um_per_degc: f64,
}

/// `spindle`: the spindle head, a lump of its own heated by the spindle's load
/// ([`Motion::spindle_load`]), seen by sensor `spindle`; its growth shifts the tool
/// along the axis by `k0_um_per_degc * (T_spindle - ambient)` everywhere and tilts the
/// column by `slope_um_per_m_per_degc` per K, so the shift grows along the axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpindleParams {
    /// Time constant of the head, s.
    pub tau_s: f64,
    /// Steady rise over ambient at spindle load 1, K.
    pub rise_degc: f64,
    /// Shift per K of the head's rise, um/K.
    pub k0_um_per_degc: f64,
    /// Tilt per K of the head's rise: extra error per m of position, um/m/K.
    pub slope_um_per_m_per_degc: f64,
}

/// Optional effects beyond the straight-line model; `None` = off.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Effects {
    /// `thermal_lag`.
    pub thermal_lag: Option<ThermalLagParams>,
    /// `nonlinear_position`.
    pub nonlinear_position: Option<NonlinearPositionParams>,
    /// `reversal`.
    pub reversal: Option<ReversalParams>,
    /// `pitch_periodic`.
    pub pitch_periodic: Option<PitchPeriodicParams>,
    /// `motion_heating`.
    pub motion_heating: Option<MotionHeatingParams>,
    /// `extra_sensor`.
    pub extra_sensor: Option<ExtraSensorParams>,
    /// The spindle head (not a diagnose effect name: physics of the shop plant).
    pub spindle: Option<SpindleParams>,
}

/// An effect name that [`Effects::from_names`] does not know.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown effect `{0}`; known: {known}", known = Effects::NAMES.join(", "))]
pub struct UnknownEffect(pub String);

impl Effects {
    /// The effect names, as the diagnose vocabulary spells them.
    pub const NAMES: [&'static str; 6] = [
        "thermal_lag",
        "nonlinear_position",
        "reversal",
        "pitch_periodic",
        "motion_heating",
        "extra_sensor",
    ];

    /// Switches on the named effects with their default parameters:
    /// `thermal_lag` tau 1800 s; `nonlinear_position` 2 um/K; `reversal` b -4 um (a 4 um backlash);
    /// `pitch_periodic` 10 mm, 1.5 um; `motion_heating` tau 2400 s, 4 K at load 1,
    /// 3 um/K; `extra_sensor` tau 900 s, 8 K on half of a 2 h cycle, 2 um/K.
    pub fn from_names<S: AsRef<str>>(names: &[S]) -> Result<Self, UnknownEffect> {
        let mut e = Self::default();
        for name in names {
            match name.as_ref().trim() {
                "thermal_lag" => e.thermal_lag = Some(ThermalLagParams { tau_s: 1800.0 }),
                "nonlinear_position" => {
                    e.nonlinear_position = Some(NonlinearPositionParams { um_per_degc: 2.0 })
                }
                "reversal" => e.reversal = Some(ReversalParams { b_um: -4.0 }),
                "pitch_periodic" => {
                    e.pitch_periodic = Some(PitchPeriodicParams {
                        period_mm: 10.0,
                        amplitude_um: 1.5,
                    })
                }
                "motion_heating" => {
                    e.motion_heating = Some(MotionHeatingParams {
                        tau_s: 2400.0,
                        rise_degc: 4.0,
                        um_per_degc: 3.0,
                    })
                }
                "extra_sensor" => {
                    e.extra_sensor = Some(ExtraSensorParams {
                        tau_s: 900.0,
                        rise_degc: 8.0,
                        period_s: 2.0 * 3600.0,
                        um_per_degc: 2.0,
                    })
                }
                "" => {}
                other => return Err(UnknownEffect(other.to_string())),
            }
        }
        Ok(e)
    }

    /// Names of the effects that are on, in [`Self::NAMES`] order, then `spindle`
    /// (the shop plant's head, no diagnose effect of its own).
    pub fn names(&self) -> Vec<&'static str> {
        let mut names = self.diagnose_names();
        if self.spindle.is_some() {
            names.push("spindle");
        }
        names
    }

    /// Names of the diagnose effects that are on, in [`Self::NAMES`] order.
    pub fn diagnose_names(&self) -> Vec<&'static str> {
        let on = [
            self.thermal_lag.is_some(),
            self.nonlinear_position.is_some(),
            self.reversal.is_some(),
            self.pitch_periodic.is_some(),
            self.motion_heating.is_some(),
            self.extra_sensor.is_some(),
        ];
        Self::NAMES
            .iter()
            .zip(on)
            .filter_map(|(n, on)| on.then_some(*n))
            .collect()
    }
}

/// Which simulated machine: the one the patent model describes exactly, or a shop
/// machine it cannot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Plant {
    /// Exactly the model's form: K0 from the column, tan(beta) from the screw.
    Ideal,
    /// Several lumps with their own time constants: the structure lags its sensors
    /// (`thermal_lag` 1200 s), a nut/guideway no sensor sees warms with the axis'
    /// travel (`motion_heating`), the spindle head warms with the spindle and shifts
    /// and tilts the tool (`spindle`, sensor `spindle`), and the screw's rise bows the
    /// error curve (`nonlinear_position`), over the ambient's daily swing and drift.
    #[default]
    Shop,
}

impl Plant {
    /// The names, as `--plant` spells them.
    pub const NAMES: [&'static str; 2] = ["ideal", "shop"];

    /// The preset of a name.
    pub fn from_name(name: &str) -> Option<Self> {
        match name.trim() {
            "ideal" => Some(Plant::Ideal),
            "shop" => Some(Plant::Shop),
            _ => None,
        }
    }

    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Plant::Ideal => "ideal",
            Plant::Shop => "shop",
        }
    }

    /// Parameters and effects of the preset.
    pub fn build(self) -> (ThermalParams, Effects) {
        match self {
            Plant::Ideal => (ThermalParams::default(), Effects::default()),
            Plant::Shop => (
                ThermalParams::default(),
                Effects {
                    thermal_lag: Some(ThermalLagParams { tau_s: 1200.0 }),
                    nonlinear_position: Some(NonlinearPositionParams { um_per_degc: 1.0 }),
                    motion_heating: Some(MotionHeatingParams {
                        tau_s: 2400.0,
                        rise_degc: 4.0,
                        um_per_degc: 3.0,
                    }),
                    spindle: Some(SpindleParams {
                        tau_s: 1500.0,
                        rise_degc: 12.0,
                        k0_um_per_degc: 1.5,
                        slope_um_per_m_per_degc: 2.0,
                    }),
                    ..Effects::default()
                },
            ),
        }
    }
}

/// Axis motion during a step: the load that heats screw and motor.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Motion {
    /// Feed speed while moving, mm/s.
    pub speed_mm_per_s: f64,
    /// Fraction of the step spent moving, 0..=1.
    pub duty: f64,
    /// Spindle load, 0..=1 (heats the spindle head, with that effect).
    pub spindle_load: f64,
}

impl Motion {
    /// Standing still.
    pub const STOPPED: Motion = Motion {
        speed_mm_per_s: 0.0,
        duty: 0.0,
        spindle_load: 0.0,
    };

    /// The axis moving at `speed_mm_per_s` for `duty` of the time, spindle off.
    pub const fn axis(speed_mm_per_s: f64, duty: f64) -> Self {
        Motion {
            speed_mm_per_s,
            duty,
            spindle_load: 0.0,
        }
    }

    /// Distance travelled in `dt_s`, mm.
    pub fn travel_mm(&self, dt_s: f64) -> f64 {
        self.speed_mm_per_s.abs() * self.duty.clamp(0.0, 1.0) * dt_s
    }
}

/// The straight-line model the base physics obeys exactly (no sensor lag, no effects):
/// `K0 = k0_um_per_degc * (T_column - ref)`, `tan(beta) = tan_beta_per_degc * (T_screw
/// - ref)`, reference position `p0_mm`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueModel {
    /// K0 per K of `column`, um/K.
    pub k0_um_per_degc_column: f64,
    /// tan(beta) per K of `screw`, 1/K (mm/mm/K).
    pub tan_beta_per_degc_screw: f64,
    /// Temperature where both are zero, degC.
    pub ref_degc: f64,
    /// Reference position, mm.
    pub p0_mm: f64,
}

/// Index of each node in the state vector.
const AMB: usize = 0;
const BED: usize = 1;
const COL: usize = 2;
const SCREW: usize = 3;
const MOTOR: usize = 4;
const EXTRA: usize = 5;
const SPINDLE: usize = 6;

/// The simulated machine.
#[derive(Debug, Clone)]
pub struct ThermalMachine {
    params: ThermalParams,
    effects: Effects,
    rng: SimRng,
    t_s: f64,
    /// Ambient wander, K.
    wander_degc: f64,
    /// Node temperatures (AMB..=SPINDLE; EXTRA and SPINDLE unused without their
    /// effect).
    node_degc: [f64; 7],
    /// The interferometer's own noise source: measuring never changes the machine.
    meas_rng: SimRng,
    /// Distance the axis travelled since `t = 0`, mm (its position is a triangle
    /// wave of it over the travel).
    travel_total_mm: f64,
    /// Lagged column and screw as the error sees them (`thermal_lag`).
    struct_col_degc: f64,
    struct_screw_degc: f64,
    /// Hidden node's rise (`motion_heating`), K.
    hidden_rise_degc: f64,
    /// Lagged sensor values without noise, per sensor.
    sensed_degc: Vec<f64>,
    /// What [`Self::sensors_degc`] returns: lagged values plus this step's noise.
    sensors: Vec<(&'static str, f64)>,
}

fn relax(value: f64, target: f64, dt_s: f64, tau_s: f64) -> f64 {
    if tau_s <= 0.0 {
        return target;
    }
    target + (value - target) * (-dt_s / tau_s).exp()
}

fn normal(rng: &mut SimRng, sd: f64) -> f64 {
    match Normal::new(0.0, sd) {
        Ok(n) if sd > 0.0 => n.sample(rng),
        _ => 0.0,
    }
}

impl ThermalMachine {
    /// A machine at `t = 0`, every node at the ambient temperature then.
    pub fn new(params: ThermalParams, effects: Effects, seed: u64) -> Self {
        let mut m = Self {
            params,
            effects,
            rng: SimRng::seed_from_u64(seed),
            t_s: 0.0,
            wander_degc: 0.0,
            node_degc: [0.0; 7],
            meas_rng: SimRng::seed_from_u64(seed ^ 0x1A5E_5EED),
            travel_total_mm: 0.0,
            struct_col_degc: 0.0,
            struct_screw_degc: 0.0,
            hidden_rise_degc: 0.0,
            sensed_degc: Vec::new(),
            sensors: Vec::new(),
        };
        let amb = m.ambient_degc();
        m.node_degc = [amb; 7];
        m.struct_col_degc = amb;
        m.struct_screw_degc = amb;
        let names = m.sensor_names();
        m.sensed_degc = vec![amb; names.len()];
        m.sensors = names.into_iter().map(|n| (n, amb)).collect();
        m.add_sensor_noise();
        m
    }

    /// The parameters.
    pub fn params(&self) -> &ThermalParams {
        &self.params
    }

    /// The effects.
    pub fn effects(&self) -> &Effects {
        &self.effects
    }

    /// Simulated time, s.
    pub fn t_s(&self) -> f64 {
        self.t_s
    }

    /// Sensor names, in the order of [`Self::sensors_degc`].
    pub fn sensor_names(&self) -> Vec<&'static str> {
        let mut n = vec!["ambient", "bed", "column", "screw", "motor"];
        if self.effects.extra_sensor.is_some() {
            n.push("extra");
        }
        if self.effects.spindle.is_some() {
            n.push("spindle");
        }
        n
    }

    fn sensor_node(&self, i: usize) -> usize {
        match i {
            0..=4 => [AMB, BED, COL, SCREW, MOTOR][i],
            5 if self.effects.extra_sensor.is_some() => EXTRA,
            _ => SPINDLE,
        }
    }

    /// The axis' actual position, mm: it runs back and forth over the travel as the
    /// duty moves it (a triangle wave of the distance travelled).
    pub fn axis_position_mm(&self) -> (f64, i8) {
        let l = self.params.axis_length_mm.max(1e-9);
        let s = self.travel_total_mm % (2.0 * l);
        if s < l {
            (s, 1)
        } else {
            (2.0 * l - s, -1)
        }
    }

    /// Distance travelled since `t = 0`, mm.
    pub fn travel_total_mm(&self) -> f64 {
        self.travel_total_mm
    }

    /// Ambient at the current time (deterministic part plus wander), degC.
    pub fn ambient_degc(&self) -> f64 {
        let a = &self.params.ambient;
        a.mean_degc
            + a.daily_amplitude_degc
                * (std::f64::consts::TAU * (self.t_s + a.phase_s) / DAY_S).sin()
            + a.drift_degc_per_h * self.t_s / 3600.0
            + self.wander_degc
    }

    /// True node temperatures: ambient, bed, column, screw, motor, degC.
    pub fn node_temperatures_degc(&self) -> [(&'static str, f64); 5] {
        [
            ("ambient", self.node_degc[AMB]),
            ("bed", self.node_degc[BED]),
            ("column", self.node_degc[COL]),
            ("screw", self.node_degc[SCREW]),
            ("motor", self.node_degc[MOTOR]),
        ]
    }

    /// Advances the machine by `dt_s` with the axis moving as `motion` throughout.
    pub fn step(&mut self, dt_s: f64, motion: &Motion) {
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return;
        }
        let p = &self.params;
        let load = if p.full_speed_mm_per_s > 0.0 {
            motion.speed_mm_per_s.abs() / p.full_speed_mm_per_s * motion.duty.clamp(0.0, 1.0)
        } else {
            0.0
        };
        // Ambient wander: exact Ornstein-Uhlenbeck update.
        let a = p.ambient;
        if a.wander_degc > 0.0 && a.wander_tau_s > 0.0 {
            let decay = (-dt_s / a.wander_tau_s).exp();
            let sd = a.wander_degc * (1.0 - decay * decay).sqrt();
            self.wander_degc = self.wander_degc * decay + normal(&mut self.rng, sd);
        }
        self.t_s += dt_s;
        self.travel_total_mm += motion.travel_mm(dt_s);
        let amb = self.ambient_degc();
        let p = &self.params;
        let n = &mut self.node_degc;
        n[AMB] = amb;
        n[BED] = relax(n[BED], amb, dt_s, p.bed_tau_s);
        n[COL] = relax(n[COL], amb, dt_s, p.column_tau_s);
        n[SCREW] = relax(
            n[SCREW],
            n[BED] + p.screw_rise_degc * load,
            dt_s,
            p.screw_tau_s,
        );
        n[MOTOR] = relax(
            n[MOTOR],
            amb + p.motor_rise_degc * load,
            dt_s,
            p.motor_tau_s,
        );
        if let Some(x) = self.effects.extra_sensor {
            let on = x.period_s > 0.0 && (self.t_s / x.period_s).fract() < 0.5;
            let source = amb + if on { x.rise_degc } else { 0.0 };
            n[EXTRA] = relax(n[EXTRA], source, dt_s, x.tau_s);
        } else {
            n[EXTRA] = amb;
        }
        if let Some(sp) = self.effects.spindle {
            let source = amb + sp.rise_degc * motion.spindle_load.clamp(0.0, 1.0);
            n[SPINDLE] = relax(n[SPINDLE], source, dt_s, sp.tau_s);
        } else {
            n[SPINDLE] = amb;
        }
        let lag_s = self.effects.thermal_lag.map_or(0.0, |l| l.tau_s);
        self.struct_col_degc = relax(self.struct_col_degc, n[COL], dt_s, lag_s);
        self.struct_screw_degc = relax(self.struct_screw_degc, n[SCREW], dt_s, lag_s);
        if let Some(h) = self.effects.motion_heating {
            self.hidden_rise_degc = relax(self.hidden_rise_degc, h.rise_degc * load, dt_s, h.tau_s);
        }
        let nodes: Vec<f64> = (0..self.sensed_degc.len())
            .map(|i| self.node_degc[self.sensor_node(i)])
            .collect();
        let tau_s = self.params.sensor_tau_s;
        for (s, node) in self.sensed_degc.iter_mut().zip(nodes) {
            *s = relax(*s, node, dt_s, tau_s);
        }
        self.add_sensor_noise();
    }

    fn add_sensor_noise(&mut self) {
        let sd = self.params.sensor_noise_degc;
        for (i, (_, v)) in self.sensors.iter_mut().enumerate() {
            *v = self.sensed_degc[i] + normal(&mut self.rng, sd);
        }
    }

    /// Sensor readings after the last step: lagged node temperature plus noise, degC.
    pub fn sensors_degc(&self) -> &[(&'static str, f64)] {
        &self.sensors
    }

    /// One sensor's reading by name.
    pub fn sensor_degc(&self, name: &str) -> Option<f64> {
        self.sensors.iter().find(|(n, _)| *n == name).map(|s| s.1)
    }

    /// The straight-line model of the base physics.
    pub fn true_model(&self) -> TrueModel {
        let a_um_per_mm = self.params.expansion_um_per_m_per_degc / 1000.0;
        TrueModel {
            k0_um_per_degc_column: a_um_per_mm * self.params.column_lever_mm,
            tan_beta_per_degc_screw: a_um_per_mm * 1e-3,
            ref_degc: self.params.ref_degc,
            p0_mm: self.params.ref_position_mm,
        }
    }

    /// True positioning error (actual minus commanded) at `pos_mm`, approached in
    /// direction `dir` (+1/-1; 0 = unknown, no reversal part), um.
    pub fn true_error_um(&self, pos_mm: f64, dir: i8) -> f64 {
        let p = &self.params;
        let a_um_per_mm = p.expansion_um_per_m_per_degc / 1000.0;
        let mut err_um =
            a_um_per_mm * (self.struct_screw_degc - p.ref_degc) * (pos_mm - p.ref_position_mm)
                + a_um_per_mm * p.column_lever_mm * (self.struct_col_degc - p.ref_degc);
        let e = &self.effects;
        if let Some(nl) = e.nonlinear_position {
            let x = if p.axis_length_mm > 0.0 {
                pos_mm / p.axis_length_mm
            } else {
                0.0
            };
            let rise = self.struct_screw_degc - self.node_degc[BED];
            err_um += nl.um_per_degc * rise * 4.0 * x * (1.0 - x);
        }
        if let Some(r) = e.reversal {
            err_um += f64::from(dir.signum()) * r.b_um / 2.0;
        }
        if let Some(pp) = e.pitch_periodic {
            if pp.period_mm > 0.0 {
                err_um += pp.amplitude_um * (std::f64::consts::TAU * pos_mm / pp.period_mm).sin();
            }
        }
        if let Some(h) = e.motion_heating {
            err_um += h.um_per_degc * self.hidden_rise_degc;
        }
        if let Some(x) = e.extra_sensor {
            err_um += x.um_per_degc * (self.node_degc[EXTRA] - self.node_degc[AMB]);
        }
        if let Some(sp) = e.spindle {
            let rise = self.node_degc[SPINDLE] - self.node_degc[AMB];
            err_um += rise * (sp.k0_um_per_degc + sp.slope_um_per_m_per_degc * pos_mm / 1000.0);
        }
        err_um
    }

    /// The laser interferometer: true error plus measurement noise, um. Its noise has
    /// a source of its own, so how often one measures never changes the machine.
    pub fn measure(&mut self, pos_mm: f64, dir: i8) -> f64 {
        let sd = self.params.interferometer_noise_um;
        self.true_error_um(pos_mm, dir) + normal(&mut self.meas_rng, sd)
    }
}

/// One phase of a duty cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Phase {
    /// What the phase is, for plots and logs.
    pub name: &'static str,
    /// Duration, s.
    pub duration_s: f64,
    /// Axis motion throughout.
    pub motion: Motion,
}

/// A sequence of phases; after the last one the machine stands still.
#[derive(Debug, Clone, PartialEq)]
pub struct DutyCycle {
    /// The phases, in order.
    pub phases: Vec<Phase>,
}

impl DutyCycle {
    /// The default scenario for `hours`: warm-up (1/8), heavy steady machining (3/8),
    /// cool-down at standstill (2/8), medium machining again (2/8), over the ambient
    /// swing of the day. The spindle runs with the machining (load 0.5, 0.9, 0, 0.6).
    pub fn scenario(hours: f64) -> Self {
        let h_s = hours.max(0.0) * 3600.0;
        let m = |speed_mm_per_s, duty: f64| Motion {
            speed_mm_per_s,
            duty,
            spindle_load: (duty + 0.1).min(1.0),
        };
        Self {
            phases: vec![
                Phase {
                    name: "warm-up",
                    duration_s: h_s / 8.0,
                    motion: m(100.0, 0.5),
                },
                Phase {
                    name: "steady",
                    duration_s: h_s * 3.0 / 8.0,
                    motion: m(200.0, 0.8),
                },
                Phase {
                    name: "cool-down",
                    duration_s: h_s * 2.0 / 8.0,
                    motion: Motion::STOPPED,
                },
                Phase {
                    name: "medium",
                    duration_s: h_s * 2.0 / 8.0,
                    motion: m(150.0, 0.6),
                },
            ],
        }
    }

    /// A commissioning measurement run of `hours`: blocks of machining at several
    /// axis and spindle loads and standstill, so that screw, structure and spindle
    /// temperatures vary apart.
    pub fn commissioning(hours: f64) -> Self {
        let block_s = 1.5 * 3600.0;
        let loads = [
            (200.0, 0.9, 0.3),
            (0.0, 0.0, 0.0),
            (120.0, 0.5, 1.0),
            (200.0, 0.6, 0.6),
            (0.0, 0.0, 0.8),
            (60.0, 0.8, 0.0),
            (0.0, 0.0, 0.0),
        ];
        Self::cycling(hours, block_s, &loads)
    }

    /// A commissioning run for the gateway's recorder, `hours` long: 40-minute
    /// blocks cycling through nine combinations of axis load, spindle load and
    /// standstill (a 6-hour cycle), so that every few hours of the record excite
    /// every lump apart. Blocked cross-validation holds hours out at a time; with the
    /// 1.5-hour blocks of [`Self::commissioning`] a held-out block could show
    /// combinations the rest never did.
    pub fn recording(hours: f64) -> Self {
        let block_s = 40.0 * 60.0;
        let loads = [
            (200.0, 0.9, 0.2),
            (0.0, 0.0, 0.9),
            (120.0, 0.5, 0.6),
            (0.0, 0.0, 0.0),
            (200.0, 0.6, 1.0),
            (60.0, 0.8, 0.0),
            (0.0, 0.0, 0.5),
            (150.0, 0.9, 0.8),
            (0.0, 0.0, 0.0),
        ];
        Self::cycling(hours, block_s, &loads)
    }

    /// `hours` of blocks of `block_s` cycling through `loads` (axis speed mm/s, duty,
    /// spindle load): machining where the duty is above 0, standstill otherwise; the
    /// last block is cut short at the end.
    fn cycling(hours: f64, block_s: f64, loads: &[(f64, f64, f64)]) -> Self {
        let mut phases = Vec::new();
        let mut left_s = hours.max(0.0) * 3600.0;
        for &(speed_mm_per_s, duty, spindle_load) in loads.iter().cycle() {
            if left_s <= 0.0 {
                break;
            }
            let d = left_s.min(block_s);
            phases.push(Phase {
                name: if duty > 0.0 {
                    "machining"
                } else {
                    "standstill"
                },
                duration_s: d,
                motion: Motion {
                    speed_mm_per_s,
                    duty,
                    spindle_load,
                },
            });
            left_s -= d;
        }
        Self { phases }
    }

    /// Total duration, s.
    pub fn duration_s(&self) -> f64 {
        self.phases.iter().map(|p| p.duration_s).sum()
    }

    /// The phase at `t_s` (`None` after the end).
    pub fn phase_at(&self, t_s: f64) -> Option<&Phase> {
        let mut start_s = 0.0;
        for p in &self.phases {
            if t_s < start_s + p.duration_s {
                return Some(p);
            }
            start_s += p.duration_s;
        }
        None
    }

    /// Motion at `t_s`.
    pub fn motion_at(&self, t_s: f64) -> Motion {
        self.phase_at(t_s).map_or(Motion::STOPPED, |p| p.motion)
    }
}

/// How a measurement run samples the error.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepPlan {
    /// Target positions, mm, in ascending order; each sweep visits them up, then down.
    pub targets_mm: Vec<f64>,
    /// Time between the starts of two sweeps, s.
    pub every_s: f64,
    /// Time at each target (move and settle), s; [`measurement_run`] steps the
    /// machine on this grid.
    pub dwell_s: f64,
    /// Bidirectional runs per sweep (ISO 230-2 asks for 5).
    pub runs: usize,
}

impl SweepPlan {
    /// `n` targets over the axis the ISO 230-2 way, `P_i = (i - 1) p + r_i`: the
    /// ends fixed, interior targets shifted by up to +/- 5 % of the spacing (a fixed
    /// low-discrepancy sequence, to 0.1 mm) so that no periodic error of the screw
    /// hides by sampling at its zeros. One run every `every_s`.
    pub fn irregular(axis_length_mm: f64, n: usize, every_s: f64) -> Self {
        let mut plan = Self::even(axis_length_mm, n, every_s);
        let last = plan.targets_mm.len() - 1;
        let spacing_mm = axis_length_mm / last as f64;
        for (i, p) in plan.targets_mm.iter_mut().enumerate() {
            if i > 0 && i < last {
                let r = ((i as f64 * 0.618_033_988_75).fract() - 0.5) * 0.1 * spacing_mm;
                *p = ((*p + r) * 10.0).round() / 10.0;
            }
        }
        plan
    }

    /// `n` equally spaced targets over the axis, one run every `every_s`.
    pub fn even(axis_length_mm: f64, n: usize, every_s: f64) -> Self {
        let n = n.max(2);
        Self {
            targets_mm: (0..n)
                .map(|i| axis_length_mm * i as f64 / (n - 1) as f64)
                .collect(),
            every_s,
            dwell_s: 4.0,
            runs: 1,
        }
    }
}

/// A measurement series in the columns of the measured-error CSV
/// (`t_s,pos_mm,dir,travel_mm,err_um,T_<sensor>...`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Series {
    /// Sensor names (without `T_`), in column order.
    pub sensor_names: Vec<&'static str>,
    /// Time, s.
    pub t_s: Vec<f64>,
    /// Position, mm.
    pub pos_mm: Vec<f64>,
    /// Direction of approach, +1/-1.
    pub dir: Vec<i8>,
    /// Distance travelled since the previous row, mm.
    pub travel_mm: Vec<f64>,
    /// Interferometer reading, um.
    pub err_um: Vec<f64>,
    /// One column per sensor, degC.
    pub temps_degc: Vec<Vec<f64>>,
}

impl Series {
    /// Number of rows.
    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    /// True without rows.
    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }

    fn push(&mut self, m: &ThermalMachine, pos_mm: f64, dir: i8, travel_mm: f64, err_um: f64) {
        self.t_s.push(m.t_s());
        self.pos_mm.push(pos_mm);
        self.dir.push(dir);
        self.travel_mm.push(travel_mm);
        self.err_um.push(err_um);
        for (col, (_, v)) in self.temps_degc.iter_mut().zip(m.sensors_degc()) {
            col.push(*v);
        }
    }
}

/// Runs `machine` through `cycle`, measuring with the interferometer as `plan` says.
/// The machine steps on a fixed grid of `plan.dwell_s` and always runs the duty
/// cycle: a sweep only samples the error field, one target per step, so how often one
/// measures never changes the machine. `travel_mm` is the machining travel since the
/// previous row (the sweep's own slow moves heat nothing worth counting).
pub fn measurement_run(
    machine: &mut ThermalMachine,
    cycle: &DutyCycle,
    plan: &SweepPlan,
) -> Series {
    let mut s = Series {
        sensor_names: machine.sensor_names(),
        temps_degc: vec![Vec::new(); machine.sensor_names().len()],
        ..Series::default()
    };
    let end_s = cycle.duration_s();
    let step_s = plan.dwell_s.max(1e-3);
    let targets: Vec<(f64, i8)> = (0..plan.runs.max(1))
        .flat_map(|_| {
            let up = plan.targets_mm.iter().map(|&p| (p, 1i8));
            let down = plan.targets_mm.iter().rev().map(|&p| (p, -1i8));
            up.chain(down)
        })
        .collect();
    let mut travel_mm = 0.0;
    let mut next_sweep_s = 0.0;
    let mut sweep_at: Option<usize> = None;
    let mut k: u64 = 0;
    while machine.t_s() < end_s - 1e-9 {
        let t0 = k as f64 * step_s;
        if sweep_at.is_none() && !targets.is_empty() && t0 + 1e-9 >= next_sweep_s {
            sweep_at = Some(0);
            next_sweep_s += plan.every_s.max(step_s);
        }
        let motion = cycle.motion_at(t0);
        machine.step(step_s, &motion);
        k += 1;
        travel_mm += motion.travel_mm(step_s);
        if let Some(i) = sweep_at {
            let (pos_mm, dir) = targets[i];
            let err_um = machine.measure(pos_mm, dir);
            s.push(machine, pos_mm, dir, travel_mm, err_um);
            travel_mm = 0.0;
            sweep_at = (i + 1 < targets.len()).then_some(i + 1);
        }
    }
    s
}

/// A measurement series in the measured-error CSV's form, whose columns these already
/// are.
impl From<&Series> for Measurements {
    fn from(s: &Series) -> Self {
        Self {
            t_s: s.t_s.clone(),
            pos_mm: s.pos_mm.clone(),
            err_um: s.err_um.clone(),
            dir: s.dir.clone(),
            travel_mm: s.travel_mm.clone(),
            temps: s
                .sensor_names
                .iter()
                .zip(&s.temps_degc)
                .map(|(name, degc)| TempColumn {
                    name: (*name).to_string(),
                    degc: degc.clone(),
                })
                .collect(),
            ignored_columns: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet() -> ThermalParams {
        ThermalParams {
            ambient: AmbientParams {
                daily_amplitude_degc: 0.0,
                drift_degc_per_h: 0.0,
                wander_degc: 0.0,
                ..AmbientParams::default()
            },
            sensor_noise_degc: 0.0,
            sensor_tau_s: 0.0,
            interferometer_noise_um: 0.0,
            ..ThermalParams::default()
        }
    }

    fn node(m: &ThermalMachine, name: &str) -> f64 {
        m.node_temperatures_degc()
            .iter()
            .find(|(n, _)| *n == name)
            .map(|n| n.1)
            .unwrap_or(f64::NAN)
    }

    const FULL: Motion = Motion::axis(200.0, 1.0);

    /// The default reversal is a 4 um backlash: err(+) - err(-) = b_um = -4 um, the
    /// sign diagnose reports (the simulator said b 4 um where diagnose found -3.97).
    #[test]
    fn reversal_b_is_the_error_in_plus_minus_the_error_in_minus() {
        let m = ThermalMachine::new(quiet(), Effects::from_names(&["reversal"]).unwrap(), 1);
        let b_um = m.true_error_um(500.0, 1) - m.true_error_um(500.0, -1);
        assert!((b_um - -4.0).abs() < 1e-12, "{b_um}");
        assert_eq!(m.effects.reversal.map(|r| r.b_um), Some(b_um));
    }

    #[test]
    fn steady_state_rises_and_time_constant() {
        let mut m = ThermalMachine::new(quiet(), Effects::default(), 1);
        assert!((node(&m, "screw") - 20.0).abs() < 1e-12);
        // One screw time constant at full load: 1 - 1/e of the 6 K rise.
        m.step(1800.0, &FULL);
        let expect = 6.0 * (1.0 - (-1.0f64).exp());
        assert!(
            (node(&m, "screw") - 20.0 - expect).abs() < 1e-9,
            "{}",
            node(&m, "screw")
        );
        // Steady state after many constants, whatever the step size.
        for _ in 0..2000 {
            m.step(37.0, &FULL);
        }
        assert!((node(&m, "screw") - 26.0).abs() < 1e-6);
        assert!((node(&m, "motor") - 35.0).abs() < 1e-6);
        assert!((node(&m, "bed") - 20.0).abs() < 1e-9);
        // Half the duty, half the rise.
        for _ in 0..2000 {
            m.step(60.0, &Motion { duty: 0.5, ..FULL });
        }
        assert!((node(&m, "screw") - 23.0).abs() < 1e-6);
    }

    #[test]
    fn bed_follows_a_step_of_ambient_with_its_time_constant() {
        let mut p = quiet();
        p.ambient.drift_degc_per_h = 0.0;
        let mut m = ThermalMachine::new(p, Effects::default(), 1);
        // Move ambient by hand: a drift of 3600 K/h for 1 s is a +1 K step.
        m.params.ambient.drift_degc_per_h = 3600.0;
        m.step(1.0, &Motion::STOPPED);
        m.params.ambient.drift_degc_per_h = 0.0;
        m.params.ambient.mean_degc += 1.0;
        let b0 = node(&m, "bed");
        m.step(4.0 * 3600.0, &Motion::STOPPED);
        let rise = node(&m, "bed") - b0;
        // 1 K step, one time constant: 63.2 % of the remaining gap.
        let gap = 21.0 - b0;
        assert!(
            (rise / gap - (1.0 - (-1.0f64).exp())).abs() < 1e-6,
            "{rise} {gap}"
        );
    }

    #[test]
    fn expansion_is_11_5_um_per_m_per_k() {
        let mut m = ThermalMachine::new(quiet(), Effects::default(), 1);
        m.struct_screw_degc = 21.0;
        m.struct_col_degc = 20.0;
        // 1 K over 2 m: 23 um at the far end, 0 at the fixed bearing.
        assert!((m.true_error_um(2000.0, 1) - 23.0).abs() < 1e-9);
        assert!(m.true_error_um(0.0, 1).abs() < 1e-12);
        m.struct_col_degc = 22.0;
        // Column: 2 K x 800 mm x 11.5 um/m/K = 18.4 um everywhere.
        assert!((m.true_error_um(0.0, -1) - 18.4).abs() < 1e-9);
        let t = m.true_model();
        assert!((t.k0_um_per_degc_column - 9.2).abs() < 1e-12);
        assert!((t.tan_beta_per_degc_screw - 11.5e-6).abs() < 1e-18);
    }

    #[test]
    fn default_scenario_swings_ambient_by_at_least_4_k() {
        let mut m = ThermalMachine::new(ThermalParams::default(), Effects::default(), 7);
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for _ in 0..(8 * 360) {
            m.step(10.0, &Motion::STOPPED);
            lo = lo.min(m.ambient_degc());
            hi = hi.max(m.ambient_degc());
        }
        assert!(hi - lo >= 4.0, "swing {}", hi - lo);
    }

    #[test]
    fn deterministic_for_a_seed_and_noisy_sensors() {
        let run = |seed| {
            let mut m = ThermalMachine::new(ThermalParams::default(), Effects::default(), seed);
            for _ in 0..100 {
                m.step(10.0, &FULL);
            }
            (m.sensors_degc().to_vec(), m.measure(1000.0, 1))
        };
        assert_eq!(run(3), run(3));
        assert_ne!(run(3), run(4));
        let (sensors, _) = run(3);
        let names: Vec<_> = sensors.iter().map(|s| s.0).collect();
        assert_eq!(names, ["ambient", "bed", "column", "screw", "motor"]);
    }

    #[test]
    fn sensor_lag_and_noise() {
        let mut p = quiet();
        p.sensor_tau_s = 60.0;
        let mut m = ThermalMachine::new(p.clone(), Effects::default(), 1);
        m.step(60.0, &FULL);
        // The screw node moved; its sensor lags behind it.
        let lag = node(&m, "screw") - m.sensor_degc("screw").unwrap_or(f64::NAN);
        assert!(lag > 0.01, "lag {lag}");
        p.sensor_noise_degc = 0.05;
        let mut m = ThermalMachine::new(p, Effects::default(), 1);
        let mut v = Vec::new();
        for _ in 0..2000 {
            m.step(1.0, &Motion::STOPPED);
            v.push(m.sensor_degc("bed").unwrap_or(f64::NAN) - node(&m, "bed"));
        }
        let sd = (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        assert!((sd - 0.05).abs() < 0.005, "sd {sd}");
    }

    #[test]
    fn each_effect_switches_on_alone() {
        let base = |effects: Effects| {
            let mut m = ThermalMachine::new(quiet(), effects, 1);
            for _ in 0..60 {
                m.step(60.0, &FULL);
            }
            m
        };
        let plain = base(Effects::default());
        for name in Effects::NAMES {
            let e = Effects::from_names(&[name]).unwrap_or_default();
            assert_eq!(e.names(), vec![name]);
            let m = base(e);
            let diff = |pos_mm: f64, dir: i8| {
                m.true_error_um(pos_mm, dir) - plain.true_error_um(pos_mm, dir)
            };
            match name {
                "thermal_lag" => assert!(diff(2000.0, 1) < -1.0, "{}", diff(2000.0, 1)),
                "nonlinear_position" => {
                    assert!(diff(0.0, 1).abs() < 1e-9 && diff(2000.0, 1).abs() < 1e-9);
                    assert!(diff(1000.0, 1) > 1.0);
                }
                "reversal" => {
                    assert!((diff(500.0, 1) + 2.0).abs() < 1e-9);
                    assert!((diff(500.0, -1) - 2.0).abs() < 1e-9);
                }
                "pitch_periodic" => {
                    assert!((diff(2.5, 1) - 1.5).abs() < 1e-9);
                    assert!(diff(5.0, 1).abs() < 1e-9);
                }
                "motion_heating" => {
                    let d = diff(700.0, 1);
                    assert!((diff(1300.0, -1) - d).abs() < 1e-9 && d > 1.0, "{d}");
                    assert!(m.sensor_names().len() == 5);
                }
                "extra_sensor" => {
                    assert!(diff(700.0, 1) > 1.0);
                    assert_eq!(m.sensor_names().last(), Some(&"extra"));
                    assert!(m.sensor_degc("extra").unwrap_or(0.0) > 21.0);
                }
                _ => unreachable!(),
            }
        }
        assert!(Effects::from_names(&["nope"]).is_err());
    }

    #[test]
    fn measurement_run_rows_and_travel() {
        let mut m = ThermalMachine::new(ThermalParams::default(), Effects::default(), 2);
        let cycle = DutyCycle::scenario(2.0);
        let plan = SweepPlan::even(2000.0, 5, 1800.0);
        let s = measurement_run(&mut m, &cycle, &plan);
        // 4 sweeps of 5 targets up and down.
        assert_eq!(s.len(), 4 * 10);
        assert_eq!(s.temps_degc.len(), 5);
        assert!(s.temps_degc.iter().all(|c| c.len() == s.len()));
        assert!(s.t_s.windows(2).all(|w| w[1] >= w[0]));
        assert_eq!(&s.dir[..10], &[1, 1, 1, 1, 1, -1, -1, -1, -1, -1]);
        // Between sweeps the axis machined: 1800 s x 100 mm/s x 0.5 for the warm-up,
        // and it went on machining during the sweep (4 s per target).
        assert!(s.travel_mm[10] > 80_000.0, "{}", s.travel_mm[10]);
        assert!((s.travel_mm[1] - 200.0).abs() < 1e-9, "{}", s.travel_mm[1]);
        // The screw warmed up: the far end's error grew.
        let far: Vec<f64> = (0..s.len())
            .filter(|&i| s.pos_mm[i] == 2000.0)
            .map(|i| s.err_um[i])
            .collect();
        assert!(far.last().unwrap_or(&0.0) - far[0] > 20.0, "{far:?}");
    }

    #[test]
    fn sampling_more_often_does_not_change_the_machine() {
        let (params, effects) = Plant::Shop.build();
        let cycle = DutyCycle::scenario(3.0);
        let run = |every_s| {
            let mut m = ThermalMachine::new(params.clone(), effects, 4);
            let plan = SweepPlan::irregular(2000.0, 9, every_s);
            measurement_run(&mut m, &cycle, &plan)
        };
        let (a, b) = (run(600.0), run(120.0));
        assert!(b.len() > 4 * a.len());
        // Every row of the sparse run is in the dense one, with the same sensors
        // and the same error (the noise of the interferometer aside).
        let mut common = 0;
        for i in 0..a.len() {
            let j = (0..b.len())
                .find(|&j| b.t_s[j] == a.t_s[i] && b.pos_mm[j] == a.pos_mm[i])
                .unwrap_or_else(|| panic!("row {i} at {} s missing", a.t_s[i]));
            for c in 0..a.temps_degc.len() {
                assert_eq!(a.temps_degc[c][i], b.temps_degc[c][j]);
            }
            assert!((a.err_um[i] - b.err_um[j]).abs() < 3.0, "{i}");
            common += 1;
        }
        assert_eq!(common, a.len());
    }

    #[test]
    fn the_spindle_head_warms_with_the_spindle_and_shifts_the_tool() {
        let (_, mut effects) = Plant::Shop.build();
        effects.thermal_lag = None;
        let spin = Motion {
            spindle_load: 1.0,
            ..Motion::STOPPED
        };
        let mut m = ThermalMachine::new(quiet(), effects, 1);
        let e0 = m.true_error_um(1000.0, 1);
        for _ in 0..200 {
            m.step(60.0, &spin);
        }
        // 12 K at load 1 after many time constants; the axis did not move.
        assert!((m.sensor_degc("spindle").unwrap_or(0.0) - 32.0).abs() < 0.05);
        assert_eq!(m.travel_total_mm(), 0.0);
        // 12 K x (1.5 um/K + 2 um/m/K x 1 m) = 42 um at 1000 mm.
        let d = m.true_error_um(1000.0, 1) - e0;
        assert!((d - 42.0).abs() < 0.2, "{d}");
        // Plant names round-trip.
        for n in Plant::NAMES {
            assert_eq!(Plant::from_name(n).map(Plant::name), Some(n));
        }
    }

    #[test]
    fn irregular_targets_see_the_pitch_error() {
        let plan = SweepPlan::irregular(2000.0, 9, 600.0);
        let t = &plan.targets_mm;
        assert_eq!((t[0], t[8]), (0.0, 2000.0));
        assert!(t.windows(2).all(|w| w[1] > w[0]));
        assert!(t.iter().skip(1).take(7).all(|p| p % 250.0 != 0.0), "{t:?}");
        let e = Effects::from_names(&["pitch_periodic"]).unwrap_or_default();
        let m = ThermalMachine::new(quiet(), e, 1);
        let plain = ThermalMachine::new(quiet(), Effects::default(), 1);
        let seen = t
            .iter()
            .map(|&p| (m.true_error_um(p, 1) - plain.true_error_um(p, 1)).abs())
            .fold(0.0, f64::max);
        assert!(seen > 0.5, "{seen}");
    }
}
