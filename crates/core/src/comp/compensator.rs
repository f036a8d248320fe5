//! From temperatures to what to write: limits, deadband, bad-input policy.

use super::{CompError, CompParams, Dynamics, ThermalModel};

/// Safety limits of one axis' compensation.
///
/// Every value must be finite and >= 0 ([`Limits::validate`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Limits {
    /// Largest |K0| ever written, mm.
    pub max_abs_k0_mm: f64,
    /// Largest |tan(beta)| ever written, mm/mm.
    pub max_abs_tan_beta: f64,
    /// Largest change of K0 in one write, mm.
    pub max_step_k0_mm: f64,
    /// Largest change of tan(beta) in one write, mm/mm.
    pub max_step_tan_beta: f64,
    /// No write while K0 changed less than this (and tan(beta) less than its
    /// deadband, and P0 not at all), mm.
    pub deadband_k0_mm: f64,
    /// No write while tan(beta) changed less than this (and K0 less than its
    /// deadband, and P0 not at all), mm/mm.
    pub deadband_tan_beta: f64,
}

impl Limits {
    /// Checks every field; returns every problem at once.
    pub fn validate(&self) -> Result<(), Vec<CompError>> {
        let fields = [
            ("max_abs_k0_mm", self.max_abs_k0_mm),
            ("max_abs_tan_beta", self.max_abs_tan_beta),
            ("max_step_k0_mm", self.max_step_k0_mm),
            ("max_step_tan_beta", self.max_step_tan_beta),
            ("deadband_k0_mm", self.deadband_k0_mm),
            ("deadband_tan_beta", self.deadband_tan_beta),
        ];
        let errors: Vec<CompError> = fields
            .iter()
            .filter(|(_, v)| !(v.is_finite() && *v >= 0.0))
            .map(|&(field, _)| CompError::InvalidLimit { field })
            .collect();
        if errors.is_empty() {
            Ok(())
        } else {
            Err(errors)
        }
    }
}

/// What to do while an input the model uses is bad.
#[derive(Debug, Clone, PartialEq)]
pub enum BadInputPolicy {
    /// Leave the NC's parameters as they are.
    Hold,
    /// Move K0 and tan(beta) towards zero at these rates (P0 stays): with no
    /// trustworthy temperature, no compensation is the neutral state. A rate of 0
    /// (or less) keeps that parameter.
    RampToZero {
        /// K0 rate, mm/s.
        k0_mm_per_s: f64,
        /// tan(beta) rate, (mm/mm)/s.
        tan_beta_per_s: f64,
    },
}

/// The outcome of one [`AxisCompensator::decide`].
#[derive(Debug, Clone, PartialEq)]
pub enum Decision {
    /// Write these parameters.
    Write {
        /// The limited parameter set.
        params: CompParams,
        /// An absolute or step limit cut the model's value.
        clamped: bool,
    },
    /// The change is below the deadband: nothing to write.
    WithinDeadband,
    /// Inputs are bad and the policy is `Hold` (or the ramp has nothing left to
    /// do): nothing to write. Empty `bad_inputs` means the model produced a
    /// non-finite value from finite inputs.
    Hold {
        /// Indices of the bad inputs the model uses, ascending.
        bad_inputs: Vec<usize>,
    },
    /// Inputs are bad and the policy is `RampToZero`: write this one step.
    Ramp {
        /// The baseline moved one step towards zero.
        params: CompParams,
        /// Indices of the bad inputs the model uses, ascending.
        bad_inputs: Vec<usize>,
    },
}

/// The model's last value where it is beyond an absolute limit: the axis gets the
/// limit instead, and a commissioning engineer must hear of it (a wrong model, or a
/// limit set too tight).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BeyondLimit {
    /// The model's K0 in mm, when |K0| > `max_abs_k0_mm`.
    pub k0_mm: Option<f64>,
    /// The model's tan(beta), when |tan(beta)| > `max_abs_tan_beta`.
    pub tan_beta: Option<f64>,
}

impl BeyondLimit {
    fn of(target: &CompParams, l: &Limits) -> Option<Self> {
        let k0_mm = (target.k0_mm.abs() > l.max_abs_k0_mm).then_some(target.k0_mm);
        let tan_beta = (target.tan_beta.abs() > l.max_abs_tan_beta).then_some(target.tan_beta);
        (k0_mm.is_some() || tan_beta.is_some()).then_some(Self { k0_mm, tan_beta })
    }
}

/// Decides, update by update, what to write into one axis' SD43900/43910/43920.
///
/// The baseline is what the NC holds: set at start-up ([`Self::set_baseline`]) and
/// after each accepted write ([`Self::confirm`]). [`Self::decide`] never changes it,
/// so a failed write is simply decided again next time from the same baseline.
///
/// Limits are applied in this order: absolute clamp, then the step limit from the
/// baseline. A baseline outside the absolute limits is therefore left step by step
/// (never jumping more than one step), so the written value may stay outside the
/// absolute limits for a few updates; it never moves away from them.
#[derive(Debug, Clone)]
pub struct AxisCompensator {
    model: ThermalModel,
    limits: Limits,
    policy: BadInputPolicy,
    /// Inputs the model references (cached: checked on every decision).
    inputs: Vec<usize>,
    baseline: Option<CompParams>,
    last_decide_s: Option<f64>,
    /// Lagged inputs and motion heat (empty: the plain model).
    dynamics: Dynamics,
    /// Where the last decision's model value was beyond an absolute limit.
    beyond_limit: Option<BeyondLimit>,
}

impl AxisCompensator {
    /// A compensator without a baseline: its first decision writes without step
    /// limit and deadband.
    pub fn new(model: ThermalModel, limits: Limits, policy: BadInputPolicy) -> Self {
        Self {
            inputs: model.inputs(),
            model,
            limits,
            policy,
            baseline: None,
            last_decide_s: None,
            dynamics: Dynamics::default(),
            beyond_limit: None,
        }
    }

    /// With lagged inputs (model inputs beyond the real ones) and motion heat.
    pub fn with_dynamics(mut self, dynamics: Dynamics) -> Self {
        self.dynamics = dynamics;
        self
    }

    /// The lags and motion heat.
    pub fn dynamics(&self) -> &Dynamics {
        &self.dynamics
    }

    /// The NC's actual position at `now_s` (for the motion heat term).
    pub fn on_position(&mut self, now_s: f64, pos_mm: f64) {
        self.dynamics.on_position(now_s, pos_mm);
    }

    /// Sets what the NC holds now (read at start-up).
    pub fn set_baseline(&mut self, params: CompParams) {
        self.baseline = Some(params);
    }

    /// Decides at `now_s` what to write for `temps_degc` (indexed like the model's
    /// inputs; `None` = that input is bad). Inputs the model does not use do not
    /// matter; a used input that is `None`, not finite or missing from the slice is
    /// bad, and the model is then not evaluated at all.
    pub fn decide(&mut self, now_s: f64, temps_degc: &[Option<f64>]) -> Decision {
        let dt_s = self
            .last_decide_s
            .map_or(0.0, |t0_s| (now_s - t0_s).max(0.0));
        self.last_decide_s = Some(now_s);
        self.beyond_limit = None;
        // Lagged inputs fill their slots after the real ones.
        let lagged;
        let temps_degc = if self.dynamics.lags().is_empty() {
            temps_degc
        } else {
            let mut t = temps_degc.to_vec();
            self.dynamics.apply_lags(now_s, &mut t);
            lagged = t;
            &lagged[..]
        };

        let mut bad_inputs: Vec<usize> = self
            .inputs
            .iter()
            .copied()
            .filter(|&i| {
                !temps_degc
                    .get(i)
                    .copied()
                    .flatten()
                    .is_some_and(f64::is_finite)
            })
            .collect();
        if !bad_inputs.is_empty() {
            // A lagged slot is bad because its source is: name the source, a real
            // input the caller can map to its channel.
            for i in &mut bad_inputs {
                if let Some(l) = self.dynamics.lags().iter().find(|l| l.slot == *i) {
                    *i = l.source;
                }
            }
            bad_inputs.sort_unstable();
            bad_inputs.dedup();
            return self.on_bad_inputs(dt_s, bad_inputs);
        }
        // Unused inputs may be None: NaN is never read by the model.
        let temps: Vec<f64> = temps_degc.iter().map(|t| t.unwrap_or(f64::NAN)).collect();
        let mut target = self.model.params(&temps);
        let (k0_mm, tan_beta) = self.dynamics.motion_terms();
        target.k0_mm += k0_mm;
        target.tan_beta += tan_beta;
        if !target.is_finite() {
            return Decision::Hold { bad_inputs };
        }
        self.beyond_limit = BeyondLimit::of(&target, &self.limits);
        self.limit(target)
    }

    /// Where the model's value at the last [`Self::decide`] was beyond an absolute
    /// limit (whether that decision wrote or found the limit held already); `None`
    /// when it was within them or the model was not evaluated (bad inputs).
    pub fn beyond_limit(&self) -> Option<BeyondLimit> {
        self.beyond_limit
    }

    /// The NC accepted `written`: it becomes the baseline.
    pub fn confirm(&mut self, written: CompParams) {
        self.baseline = Some(written);
    }

    /// What the NC holds, as far as this compensator knows.
    pub fn baseline(&self) -> Option<CompParams> {
        self.baseline
    }

    /// The thermal model.
    pub fn model(&self) -> &ThermalModel {
        &self.model
    }

    /// The limits.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// The bad-input policy.
    pub fn policy(&self) -> &BadInputPolicy {
        &self.policy
    }

    fn limit(&self, target: CompParams) -> Decision {
        let l = &self.limits;
        let base = self.baseline;
        let (k0_mm, k0_clamped) = limit_one(
            target.k0_mm,
            base.map(|b| b.k0_mm),
            l.max_abs_k0_mm,
            l.max_step_k0_mm,
        );
        let (tan_beta, tan_clamped) = limit_one(
            target.tan_beta,
            base.map(|b| b.tan_beta),
            l.max_abs_tan_beta,
            l.max_step_tan_beta,
        );
        let params = CompParams {
            k0_mm,
            tan_beta,
            p0_mm: target.p0_mm,
        };
        if let Some(b) = base {
            if within(k0_mm - b.k0_mm, l.deadband_k0_mm)
                && within(tan_beta - b.tan_beta, l.deadband_tan_beta)
                && params.p0_mm == b.p0_mm
            {
                return Decision::WithinDeadband;
            }
        }
        Decision::Write {
            params,
            clamped: k0_clamped || tan_clamped,
        }
    }

    fn on_bad_inputs(&self, dt_s: f64, bad_inputs: Vec<usize>) -> Decision {
        let (k0_mm_per_s, tan_beta_per_s) = match self.policy {
            BadInputPolicy::Hold => return Decision::Hold { bad_inputs },
            BadInputPolicy::RampToZero {
                k0_mm_per_s,
                tan_beta_per_s,
            } => (k0_mm_per_s, tan_beta_per_s),
        };
        // Without a (sane) baseline there is nothing to ramp from.
        let Some(b) = self.baseline.filter(CompParams::is_finite) else {
            return Decision::Hold { bad_inputs };
        };
        // The step limit also caps the ramp, e.g. after a long pause between updates.
        let k0_mm = toward_zero(
            b.k0_mm,
            (k0_mm_per_s * dt_s).min(self.limits.max_step_k0_mm),
        );
        let tan_beta = toward_zero(
            b.tan_beta,
            (tan_beta_per_s * dt_s).min(self.limits.max_step_tan_beta),
        );
        if k0_mm == b.k0_mm && tan_beta == b.tan_beta {
            return Decision::Hold { bad_inputs };
        }
        Decision::Ramp {
            params: CompParams {
                k0_mm,
                tan_beta,
                p0_mm: b.p0_mm,
            },
            bad_inputs,
        }
    }
}

/// Clamps to ±`max_abs`, then to `base ± max_step`; true if either cut the value.
fn limit_one(target: f64, base: Option<f64>, max_abs: f64, max_step: f64) -> (f64, bool) {
    // Written out rather than f64::clamp, which panics on NaN or inverted bounds.
    let mut v = if target > max_abs {
        max_abs
    } else if target < -max_abs {
        -max_abs
    } else {
        target
    };
    let mut clamped = v != target;
    if let Some(b) = base {
        if v > b + max_step {
            v = b + max_step;
            clamped = true;
        } else if v < b - max_step {
            v = b - max_step;
            clamped = true;
        }
    }
    (v, clamped)
}

/// A change inside the deadband; an exact zero change always is (deadband 0).
fn within(change: f64, deadband: f64) -> bool {
    change == 0.0 || change.abs() < deadband
}

/// `v` moved towards zero by `step`, stopping at zero.
fn toward_zero(v: f64, step: f64) -> f64 {
    if step.is_nan() || step <= 0.0 {
        v
    } else if v.abs() <= step {
        0.0
    } else {
        v - step.copysign(v)
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Affine, Term};
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    /// K0 = 0.004 mm/degC * (T0 - 20), tan = 0.00001 /degC * (T1 - 20), P0 = 10.
    fn model() -> ThermalModel {
        ThermalModel {
            k0_mm: Affine {
                offset: 0.0,
                terms: vec![Term {
                    input: 0,
                    ref_degc: 20.0,
                    coeff: 0.004,
                }],
            },
            tan_beta: Affine {
                offset: 0.0,
                terms: vec![Term {
                    input: 1,
                    ref_degc: 20.0,
                    coeff: 0.000_01,
                }],
            },
            p0_mm: 10.0,
        }
    }

    fn limits() -> Limits {
        Limits {
            max_abs_k0_mm: 0.5,
            max_abs_tan_beta: 0.01,
            max_step_k0_mm: 0.02,
            max_step_tan_beta: 0.000_02,
            deadband_k0_mm: 0.001,
            deadband_tan_beta: 0.000_001,
        }
    }

    fn hold() -> AxisCompensator {
        AxisCompensator::new(model(), limits(), BadInputPolicy::Hold)
    }

    fn ramp() -> AxisCompensator {
        AxisCompensator::new(
            model(),
            limits(),
            BadInputPolicy::RampToZero {
                k0_mm_per_s: 0.001,
                tan_beta_per_s: 0.000_001,
            },
        )
    }

    fn params(k0_mm: f64, tan_beta: f64) -> CompParams {
        CompParams {
            k0_mm,
            tan_beta,
            p0_mm: 10.0,
        }
    }

    fn written(d: &Decision) -> CompParams {
        match d {
            Decision::Write { params, .. } | Decision::Ramp { params, .. } => *params,
            other => panic!("expected a write, got {other:?}"),
        }
    }

    #[test]
    fn first_decision_writes_without_step_limit() {
        let mut c = hold();
        // K0 = 0.004 * 30 = 0.12 (6 steps of 0.02 at once), tan = 0.00001 * 5.
        let d = c.decide(0.0, &[Some(50.0), Some(25.0)]);
        let p = written(&d);
        assert!(close(p.k0_mm, 0.12));
        assert!(close(p.tan_beta, 0.000_05));
        assert_eq!(p.p0_mm, 10.0);
        assert!(matches!(d, Decision::Write { clamped: false, .. }));
        // Deciding does not make it the baseline.
        assert_eq!(c.baseline(), None);
    }

    #[test]
    fn absolute_limit_clamps() {
        let mut c = hold();
        // K0 = 0.004 * 200 = 0.8 -> 0.5; tan = 0.00001 * -1100 = -0.011 -> -0.01.
        let d = c.decide(0.0, &[Some(220.0), Some(-1080.0)]);
        assert_eq!(
            d,
            Decision::Write {
                params: params(0.5, -0.01),
                clamped: true
            }
        );
        let beyond = c.beyond_limit().expect("beyond both limits");
        assert!(close(beyond.k0_mm.unwrap(), 0.8));
        assert!(close(beyond.tan_beta.unwrap(), -0.011));
        // Within the limits again: nothing beyond.
        c.decide(1.0, &[Some(30.0), Some(20.0)]);
        assert_eq!(c.beyond_limit(), None);
    }

    #[test]
    fn step_limit_from_baseline_and_retry_until_confirmed() {
        let mut c = hold();
        c.set_baseline(params(0.1, 0.0));
        // Target K0 0.2: one step of 0.02 from 0.1.
        let temps = [Some(70.0), Some(20.0)];
        let d = c.decide(0.0, &temps);
        assert!(matches!(d, Decision::Write { clamped: true, .. }));
        assert!(close(written(&d).k0_mm, 0.12));
        // Not confirmed (write failed): the same step again.
        assert!(close(written(&c.decide(10.0, &temps)).k0_mm, 0.12));
        c.confirm(written(&d));
        assert_eq!(c.baseline(), Some(written(&d)));
        assert!(close(written(&c.decide(20.0, &temps)).k0_mm, 0.14));
        // Downwards too: baseline 0.14, target 0 -> 0.12.
        c.confirm(params(0.14, 0.0));
        let d = c.decide(30.0, &[Some(20.0), Some(20.0)]);
        assert!(close(written(&d).k0_mm, 0.12));
    }

    #[test]
    fn step_limit_on_tan_beta() {
        let mut c = hold();
        c.set_baseline(params(0.0, 0.0));
        // tan target 0.00001 * 10 = 0.0001 -> one step 0.00002.
        let d = c.decide(0.0, &[Some(20.0), Some(30.0)]);
        assert!(close(written(&d).tan_beta, 0.000_02));
        assert!(matches!(d, Decision::Write { clamped: true, .. }));
    }

    #[test]
    fn deadband() {
        let mut c = hold();
        // Target K0 = 0.004 * 5 = 0.02, tan 0.
        let temps = [Some(25.0), Some(20.0)];
        c.set_baseline(params(0.0195, 0.0));
        assert_eq!(c.decide(0.0, &temps), Decision::WithinDeadband);
        c.set_baseline(params(0.02, 0.0));
        assert_eq!(c.decide(0.0, &temps), Decision::WithinDeadband);
        // K0 beyond its deadband.
        c.set_baseline(params(0.018, 0.0));
        assert!(close(written(&c.decide(0.0, &temps)).k0_mm, 0.02));
        // K0 within, tan beyond: both must be within to skip.
        c.set_baseline(params(0.02, 0.000_002));
        assert!(matches!(c.decide(0.0, &temps), Decision::Write { .. }));
        // P0 differs: write even though K0 and tan match.
        c.set_baseline(CompParams {
            p0_mm: 0.0,
            ..params(0.02, 0.0)
        });
        assert_eq!(written(&c.decide(0.0, &temps)).p0_mm, 10.0);
    }

    #[test]
    fn zero_deadband_skips_only_identical_values() {
        let mut c = AxisCompensator::new(
            model(),
            Limits {
                deadband_k0_mm: 0.0,
                deadband_tan_beta: 0.0,
                ..limits()
            },
            BadInputPolicy::Hold,
        );
        let temps = [Some(25.0), Some(20.0)];
        c.set_baseline(params(0.02, 0.0));
        assert_eq!(c.decide(0.0, &temps), Decision::WithinDeadband);
        c.set_baseline(params(0.019_999, 0.0));
        assert!(close(written(&c.decide(0.0, &temps)).k0_mm, 0.02));
    }

    #[test]
    fn clamped_value_still_obeys_deadband() {
        let mut c = hold();
        // Target K0 0.8 clamped to 0.5; the NC holds 0.4995: change 0.0005 < 0.001.
        c.set_baseline(params(0.4995, 0.0));
        assert_eq!(
            c.decide(0.0, &[Some(220.0), Some(20.0)]),
            Decision::WithinDeadband
        );
        // Held at the limit, the model is still beyond it: the caller must know.
        let beyond = c.beyond_limit().expect("beyond the K0 limit");
        assert!(close(beyond.k0_mm.unwrap(), 0.8) && beyond.tan_beta.is_none());
        // A step limit alone is not beyond a limit; bad inputs evaluate nothing.
        c.set_baseline(params(0.1, 0.0));
        assert!(matches!(
            c.decide(1.0, &[Some(70.0), Some(20.0)]),
            Decision::Write { clamped: true, .. }
        ));
        assert_eq!(c.beyond_limit(), None);
        c.decide(2.0, &[Some(220.0), Some(20.0)]);
        c.decide(3.0, &[None, Some(20.0)]);
        assert_eq!(c.beyond_limit(), None);
    }

    #[test]
    fn baseline_beyond_absolute_limit_is_left_step_by_step() {
        let mut c = hold();
        c.set_baseline(params(0.8, 0.0));
        // Target 0.8 clamped to 0.5, but one step from 0.8 is 0.78.
        let d = c.decide(0.0, &[Some(220.0), Some(20.0)]);
        assert!(close(written(&d).k0_mm, 0.78));
        assert!(matches!(d, Decision::Write { clamped: true, .. }));
    }

    #[test]
    fn unused_inputs_do_not_matter() {
        let mut c = hold();
        let d = c.decide(0.0, &[Some(25.0), Some(20.0), None, Some(f64::NAN)]);
        assert!(close(written(&d).k0_mm, 0.02));
    }

    #[test]
    fn bad_used_input_holds() {
        let mut c = hold();
        c.set_baseline(params(0.1, 0.0));
        assert_eq!(
            c.decide(0.0, &[Some(25.0), None]),
            Decision::Hold {
                bad_inputs: vec![1]
            }
        );
        // Not finite counts as bad; a slice too short lacks input 1.
        assert_eq!(
            c.decide(1.0, &[Some(f64::INFINITY), None]),
            Decision::Hold {
                bad_inputs: vec![0, 1]
            }
        );
        assert_eq!(
            c.decide(2.0, &[Some(25.0)]),
            Decision::Hold {
                bad_inputs: vec![1]
            }
        );
        assert_eq!(c.baseline(), Some(params(0.1, 0.0)));
    }

    #[test]
    fn non_finite_model_holds() {
        let mut m = model();
        m.k0_mm.terms[0].coeff = f64::INFINITY;
        let mut c = AxisCompensator::new(m, limits(), BadInputPolicy::Hold);
        // inf * 0 = NaN at the reference temperature.
        assert_eq!(
            c.decide(0.0, &[Some(20.0), Some(20.0)]),
            Decision::Hold { bad_inputs: vec![] }
        );
    }

    #[test]
    fn ramp_to_zero_from_baseline() {
        let mut c = ramp();
        c.set_baseline(params(0.1, 0.0001));
        // Good inputs at t=0: a normal decision (K0 0.1 -> target 0.1: deadband).
        assert_eq!(
            c.decide(0.0, &[Some(45.0), Some(30.0)]),
            Decision::WithinDeadband
        );
        // Input 0 bad at t=10: 10 s * 0.001 = 0.01, 10 s * 0.000001 = 0.00001.
        let d = c.decide(10.0, &[None, Some(30.0)]);
        let Decision::Ramp {
            params: p,
            bad_inputs,
        } = d
        else {
            panic!("expected a ramp, got {d:?}");
        };
        assert_eq!(bad_inputs, vec![0]);
        assert!(close(p.k0_mm, 0.09));
        assert!(close(p.tan_beta, 0.000_09));
        assert_eq!(p.p0_mm, 10.0);
        // Not confirmed: the next ramp starts from the same baseline.
        assert!(close(written(&c.decide(20.0, &[None, None])).k0_mm, 0.09));
        c.confirm(p);
        assert!(close(written(&c.decide(30.0, &[None, None])).k0_mm, 0.08));
    }

    #[test]
    fn ramp_stops_at_zero_then_holds() {
        let mut c = ramp();
        c.set_baseline(params(-0.005, 0.000_003));
        c.decide(0.0, &[None, None]);
        // 10 s: step 0.01 > 0.005 -> 0, not +0.005; tan 0.00001 > 0.000003 -> 0.
        let p = written(&c.decide(10.0, &[None, None]));
        assert_eq!((p.k0_mm, p.tan_beta), (0.0, 0.0));
        c.confirm(p);
        assert_eq!(
            c.decide(20.0, &[None, None]),
            Decision::Hold {
                bad_inputs: vec![0, 1]
            }
        );
    }

    #[test]
    fn ramp_step_is_capped_by_max_step() {
        let mut c = ramp();
        c.set_baseline(params(0.3, 0.0));
        c.decide(0.0, &[None, None]);
        // 1000 s * 0.001 = 1 mm, capped at 0.02.
        assert!(close(written(&c.decide(1000.0, &[None, None])).k0_mm, 0.28));
    }

    #[test]
    fn ramp_needs_a_baseline_and_elapsed_time() {
        let mut c = ramp();
        assert!(matches!(
            c.decide(0.0, &[None, None]),
            Decision::Hold { .. }
        ));
        c.set_baseline(params(0.1, 0.0));
        // Same instant as the previous decision: nothing to ramp yet.
        assert!(matches!(
            c.decide(0.0, &[None, None]),
            Decision::Hold { .. }
        ));
    }

    #[test]
    fn validate_limits() {
        assert_eq!(limits().validate(), Ok(()));
        let bad = Limits {
            max_abs_k0_mm: -1.0,
            deadband_tan_beta: f64::NAN,
            ..limits()
        };
        assert_eq!(
            bad.validate(),
            Err(vec![
                CompError::InvalidLimit {
                    field: "max_abs_k0_mm"
                },
                CompError::InvalidLimit {
                    field: "deadband_tan_beta"
                },
            ])
        );
    }

    /// Deterministic pseudo-random numbers (Knuth's MMIX LCG).
    struct Lcg(u64);

    impl Lcg {
        /// Uniform in [lo, hi).
        fn next(&mut self, lo: f64, hi: f64) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let unit = (self.0 >> 11) as f64 / (1u64 << 53) as f64;
            lo + unit * (hi - lo)
        }
    }

    /// Step limits hold up to rounding of `baseline ± step`.
    fn step_ok(new: f64, old: f64, max_step: f64) -> bool {
        (new - old).abs() <= max_step * (1.0 + 1e-9) + 1e-15
    }

    #[test]
    fn property_writes_respect_limits() {
        let mut rng = Lcg(42);
        let mut writes = 0;
        let mut ramps = 0;
        for case in 0..200 {
            let l = Limits {
                max_abs_k0_mm: rng.next(0.01, 1.0),
                max_abs_tan_beta: rng.next(1e-4, 1e-2),
                max_step_k0_mm: rng.next(0.001, 0.1),
                max_step_tan_beta: rng.next(1e-6, 1e-4),
                deadband_k0_mm: rng.next(0.0, 0.002),
                deadband_tan_beta: rng.next(0.0, 2e-6),
            };
            let m = ThermalModel {
                k0_mm: Affine {
                    offset: rng.next(-0.2, 0.2),
                    terms: vec![Term {
                        input: 0,
                        ref_degc: 20.0,
                        coeff: rng.next(-0.05, 0.05),
                    }],
                },
                tan_beta: Affine {
                    offset: rng.next(-1e-3, 1e-3),
                    terms: vec![Term {
                        input: 1,
                        ref_degc: 20.0,
                        coeff: rng.next(-1e-3, 1e-3),
                    }],
                },
                p0_mm: 0.0,
            };
            let policy = if case % 2 == 0 {
                BadInputPolicy::Hold
            } else {
                BadInputPolicy::RampToZero {
                    k0_mm_per_s: rng.next(0.0, 0.01),
                    tan_beta_per_s: rng.next(0.0, 1e-5),
                }
            };
            let mut c = AxisCompensator::new(m, l.clone(), policy);
            c.set_baseline(CompParams {
                k0_mm: rng.next(-l.max_abs_k0_mm, l.max_abs_k0_mm),
                tan_beta: rng.next(-l.max_abs_tan_beta, l.max_abs_tan_beta),
                p0_mm: 0.0,
            });
            let mut now_s = 0.0;
            for _ in 0..50 {
                now_s += rng.next(0.1, 100.0);
                let t0 = rng.next(-50.0, 150.0);
                let t1 = rng.next(-50.0, 150.0);
                let temps = [
                    (rng.next(0.0, 1.0) > 0.2).then_some(t0),
                    (rng.next(0.0, 1.0) > 0.2).then_some(t1),
                ];
                let Some(base) = c.baseline() else {
                    panic!("baseline was set");
                };
                let d = c.decide(now_s, &temps);
                let p = match &d {
                    Decision::Write { params, .. } => {
                        writes += 1;
                        *params
                    }
                    Decision::Ramp { params, .. } => {
                        ramps += 1;
                        // A ramp never moves away from zero.
                        assert!(params.k0_mm.abs() <= base.k0_mm.abs());
                        assert!(params.tan_beta.abs() <= base.tan_beta.abs());
                        *params
                    }
                    Decision::WithinDeadband | Decision::Hold { .. } => continue,
                };
                assert!(p.k0_mm.abs() <= l.max_abs_k0_mm, "{d:?} {l:?}");
                assert!(p.tan_beta.abs() <= l.max_abs_tan_beta, "{d:?} {l:?}");
                assert!(step_ok(p.k0_mm, base.k0_mm, l.max_step_k0_mm), "{d:?}");
                assert!(
                    step_ok(p.tan_beta, base.tan_beta, l.max_step_tan_beta),
                    "{d:?}"
                );
                // Some writes fail and are not confirmed.
                if rng.next(0.0, 1.0) > 0.1 {
                    c.confirm(p);
                }
            }
        }
        // The generator really exercised both paths.
        assert!(writes > 1000, "{writes}");
        assert!(ramps > 100, "{ramps}");
    }

    #[test]
    fn lagged_inputs_and_motion_heat_reach_the_parameters() {
        use super::super::{Dynamics, InputLag, MotionHeat};
        // K0 = 0.004 * (lag(T0) - 20); input 2 is T0 through a 100 s lag.
        let mut m = model();
        m.k0_mm.terms[0].input = 2;
        let dynamics = Dynamics::new(
            vec![InputLag {
                source: 0,
                slot: 2,
                tau_s: 100.0,
            }],
            Some(MotionHeat {
                tau_s: 1000.0,
                ref_mm_per_s: 0.0,
                k0_mm_per_mm_per_s: 0.001,
                tan_beta_per_mm_per_s: 0.0,
            }),
        );
        let mut c = AxisCompensator::new(m, limits(), BadInputPolicy::Hold).with_dynamics(dynamics);
        let k0 = |d: Decision| match d {
            Decision::Write { params, .. } => params.k0_mm,
            other => panic!("{other:?}"),
        };
        // At rest and 20 degC: nothing.
        assert!(close(k0(c.decide(0.0, &[Some(20.0), Some(20.0)])), 0.0));
        // T0 steps to 21 degC: after one time constant the lag has 63 %.
        let got = k0(c.decide(100.0, &[Some(21.0), Some(20.0)]));
        assert!(close(got, 0.004 * (1.0 - (-1.0f64).exp())), "{got}");
        // 1000 mm of travel in one step: h = 1 mm/s -> K0 += 0.001 mm.
        c.on_position(100.0, 0.0);
        c.on_position(100.0, 1000.0);
        c.confirm(CompParams::default());
        let got = k0(c.decide(100.0, &[Some(21.0), Some(20.0)]));
        assert!(close(got, 0.004 * (1.0 - (-1.0f64).exp()) + 0.001), "{got}");
        // A bad source makes its lagged slot bad: hold, naming the source.
        assert_eq!(
            c.decide(110.0, &[None, Some(20.0)]),
            Decision::Hold {
                bad_inputs: vec![0]
            }
        );
    }
}
