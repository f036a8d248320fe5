//! The thermal model `dKx = K0(T) + tan(beta)(T) * (Px - P0)` and its parameters.

use super::CompError;

/// Steel's thermal expansion, 1/K: the scale of a tan(beta) coefficient, which is
/// the screw's (or the structure's) growth per unit length and kelvin.
pub const STEEL_EXPANSION_PER_K: f64 = 11.5e-6;

/// Largest plausible |tan(beta) coefficient|, 1/K: nearly nine times steel's
/// expansion and four times aluminium's. A sensor that warms less than the screw
/// raises the coefficient by that ratio, which this leaves room for; beyond it no
/// machine structure expands, and the usual cause is `pos_mm` in another unit
/// (inches: 25.4 times too large a slope) or a mistyped number.
pub const MAX_TAN_BETA_PER_K: f64 = 1e-4;

/// One temperature term of an affine function: `coeff * (T[input] - ref_degc)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Term {
    /// Index of the temperature in the model's input slice.
    pub input: usize,
    /// Temperature at which this term is zero, degC.
    pub ref_degc: f64,
    /// Sensitivity per degC: mm/degC for K0, 1/degC for tan(beta).
    pub coeff: f64,
}

/// `offset + sum(coeff * (T[input] - ref_degc))`: one model parameter as a function
/// of the temperatures.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Affine {
    /// Value with every temperature at its reference (mm for K0, mm/mm for tan(beta)).
    pub offset: f64,
    /// Temperature terms.
    pub terms: Vec<Term>,
}

impl Affine {
    /// Evaluates at `temps_degc`. A term whose input is beyond the slice yields NaN
    /// (never a panic); [`ThermalModel::check_inputs`] catches that at build time.
    pub fn eval(&self, temps_degc: &[f64]) -> f64 {
        self.terms.iter().fold(self.offset, |acc, t| {
            let temp_degc = temps_degc.get(t.input).copied().unwrap_or(f64::NAN);
            acc + t.coeff * (temp_degc - t.ref_degc)
        })
    }
}

/// The thermal model of one axis: K0(T) -> SD43900, tan(beta)(T) -> SD43910, and the
/// constant reference position P0 -> SD43920.
#[derive(Debug, Clone, PartialEq)]
pub struct ThermalModel {
    /// Position-independent error K0(T), mm.
    pub k0_mm: Affine,
    /// Slope of the error line tan(beta)(T), mm/mm.
    pub tan_beta: Affine,
    /// Reference position P0 of the axis, mm.
    pub p0_mm: f64,
}

impl ThermalModel {
    /// The parameter set at `temps_degc`.
    pub fn params(&self, temps_degc: &[f64]) -> CompParams {
        CompParams {
            k0_mm: self.k0_mm.eval(temps_degc),
            tan_beta: self.tan_beta.eval(temps_degc),
            p0_mm: self.p0_mm,
        }
    }

    /// The input indices the model's terms reference, ascending, without repeats.
    pub fn inputs(&self) -> Vec<usize> {
        let mut inputs: Vec<usize> = self
            .k0_mm
            .terms
            .iter()
            .chain(&self.tan_beta.terms)
            .map(|t| t.input)
            .collect();
        inputs.sort_unstable();
        inputs.dedup();
        inputs
    }

    /// Checks that every term references one of `n_inputs` temperatures.
    pub fn check_inputs(&self, n_inputs: usize) -> Result<(), CompError> {
        match self.inputs().last() {
            Some(&input) if input >= n_inputs => {
                Err(CompError::InputOutOfRange { input, n_inputs })
            }
            _ => Ok(()),
        }
    }
}

/// The three thermal compensation setting data of one axis.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CompParams {
    /// SD43900 `$SA_TEMP_COMP_ABS_VALUE`: position-independent value K0, mm.
    pub k0_mm: f64,
    /// SD43910 `$SA_TEMP_COMP_SLOPE`: tan(beta), mm/mm.
    pub tan_beta: f64,
    /// SD43920 `$SA_TEMP_COMP_REF_POSITION`: reference position P0, mm.
    pub p0_mm: f64,
}

impl CompParams {
    /// The compensation the NC applies at axis position `px_mm` for the MD32750
    /// `$MA_TEMP_COMP_TYPE` bits: bit 0 adds K0, bit 1 adds `tan(beta) * (Px - P0)`.
    /// Bit 2 (tool direction) does not involve these parameters.
    pub fn dk_mm(&self, px_mm: f64, md32750: u16) -> f64 {
        let mut dk_mm = 0.0;
        if md32750 & 0b01 != 0 {
            dk_mm += self.k0_mm;
        }
        if md32750 & 0b10 != 0 {
            dk_mm += self.tan_beta * (px_mm - self.p0_mm);
        }
        dk_mm
    }

    /// All three values are finite.
    pub fn is_finite(&self) -> bool {
        self.k0_mm.is_finite() && self.tan_beta.is_finite() && self.p0_mm.is_finite()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    /// The worked values of the 840D note: SD43900=0.1, SD43920=10, SD43910=0.0001.
    const NOTE: CompParams = CompParams {
        k0_mm: 0.1,
        tan_beta: 0.0001,
        p0_mm: 10.0,
    };

    #[test]
    fn md32750_bit0_is_position_independent() {
        for x in [0.0, 10.0, 50.0, -300.0] {
            assert!(close(NOTE.dk_mm(x, 1), 0.1));
        }
    }

    #[test]
    fn md32750_bit1_is_the_slope() {
        assert!(close(NOTE.dk_mm(0.0, 2), -0.001));
        assert!(close(NOTE.dk_mm(10.0, 2), 0.0));
        assert!(close(NOTE.dk_mm(50.0, 2), 0.004));
    }

    #[test]
    fn md32750_both_bits() {
        assert!(close(NOTE.dk_mm(0.0, 3), 0.099));
        assert!(close(NOTE.dk_mm(10.0, 3), 0.1));
        assert!(close(NOTE.dk_mm(50.0, 3), 0.104));
    }

    #[test]
    fn md32750_zero_and_tool_bit_add_nothing() {
        assert_eq!(NOTE.dk_mm(50.0, 0), 0.0);
        assert_eq!(NOTE.dk_mm(50.0, 4), 0.0);
        assert!(close(NOTE.dk_mm(50.0, 7), 0.104));
    }

    fn model() -> ThermalModel {
        ThermalModel {
            k0_mm: Affine {
                offset: 0.01,
                terms: vec![
                    Term {
                        input: 0,
                        ref_degc: 20.0,
                        coeff: 0.004,
                    },
                    Term {
                        input: 2,
                        ref_degc: 20.0,
                        coeff: 0.001,
                    },
                ],
            },
            tan_beta: Affine {
                offset: 0.0,
                terms: vec![Term {
                    input: 1,
                    ref_degc: 20.0,
                    coeff: 0.000_011_5,
                }],
            },
            p0_mm: 100.0,
        }
    }

    #[test]
    fn params_from_temperatures() {
        // K0 = 0.01 + 0.004*(25-20) + 0.001*(18-20) = 0.01 + 0.02 - 0.002 = 0.028
        // tan = 0.0000115 * (30-20) = 0.000115
        let p = model().params(&[25.0, 30.0, 18.0]);
        assert!(close(p.k0_mm, 0.028));
        assert!(close(p.tan_beta, 0.000_115));
        assert_eq!(p.p0_mm, 100.0);
        // At the reference temperatures only the offsets remain.
        let p = model().params(&[20.0, 20.0, 20.0]);
        assert!(close(p.k0_mm, 0.01));
        assert_eq!(p.tan_beta, 0.0);
    }

    #[test]
    fn empty_affine_is_its_offset() {
        let a = Affine {
            offset: 0.5,
            terms: vec![],
        };
        assert_eq!(a.eval(&[]), 0.5);
        assert_eq!(Affine::default().eval(&[1.0]), 0.0);
    }

    #[test]
    fn missing_input_is_nan_not_panic() {
        assert!(model().k0_mm.eval(&[25.0]).is_nan());
        assert!(!model().params(&[25.0]).is_finite());
    }

    #[test]
    fn inputs_and_check() {
        assert_eq!(model().inputs(), vec![0, 1, 2]);
        assert_eq!(model().check_inputs(3), Ok(()));
        assert_eq!(
            model().check_inputs(2),
            Err(CompError::InputOutOfRange {
                input: 2,
                n_inputs: 2
            })
        );
        let none = ThermalModel {
            k0_mm: Affine::default(),
            tan_beta: Affine::default(),
            p0_mm: 0.0,
        };
        assert!(none.inputs().is_empty());
        assert_eq!(none.check_inputs(0), Ok(()));
    }
}
