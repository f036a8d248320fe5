//! Raw register value -> loop current -> degC, with NAMUR NE43 fault detection.

use super::Reason;

/// Below this loop current a 4-20 mA transmitter signals a fault (NAMUR NE43).
pub const NE43_LOW_MA: f64 = 3.6;
/// Above this loop current a 4-20 mA transmitter signals a fault (NAMUR NE43).
pub const NE43_HIGH_MA: f64 = 21.0;

/// Smallest magnitude of a raw value other than 0 that a sensor produces. A float
/// read in the wrong word order takes its exponent from mantissa bits and lands
/// anywhere in 1e-38..1e38: 23.45 degC as CDAB read as ABCD is -1.6e-23, which every
/// plausible range would let through. No converter or module resolves 1e-6 of its
/// unit.
pub const MIN_RAW_MAGNITUDE: f64 = 1e-6;

/// Output current range of a transmitter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CurrentRange {
    /// 4-20 mA live zero; NAMUR NE43 fault detection applies.
    FourTo20,
    /// 0-20 mA; no fault detection is possible from the current.
    ZeroTo20,
}

/// How a raw register value becomes a temperature.
#[derive(Debug, Clone, PartialEq)]
pub enum Scaling {
    /// A transmitter's loop current read by an ADC.
    ///
    /// `current_ma = raw / adc_full_scale_counts * adc_full_scale_ma`, then the current
    /// range maps linearly onto `range_min_degc..range_max_degc`.
    Transmitter {
        /// ADC counts at full scale (4095 for 12 bit).
        adc_full_scale_counts: f64,
        /// Loop current at the ADC's full scale, mA.
        adc_full_scale_ma: f64,
        /// The transmitter's current range.
        current_range: CurrentRange,
        /// Temperature at the bottom of the current range (4 or 0 mA), degC.
        range_min_degc: f64,
        /// Temperature at 20 mA, degC.
        range_max_degc: f64,
    },
    /// A module that reports an engineering value: `degc = raw * gain + offset_degc`.
    Direct {
        /// Multiplier of the raw value, degC per raw unit.
        gain: f64,
        /// Added after the gain, degC.
        offset_degc: f64,
    },
}

/// One raw value after scaling.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scaled {
    /// Loop current, mA (transmitter scaling with a finite raw value only).
    pub current_ma: Option<f64>,
    /// The temperature, or why there is none (NE43 fault, not finite).
    pub degc: Result<f64, Reason>,
}

/// A scaling as numbers: `current = raw * mul / div`,
/// `degc = base_degc + (current - zero) / span_in * span_out_degc`, NE43 limits (infinite
/// where they do not apply). A direct scaling is `mul = gain`, `base_degc = offset` and
/// neutral values elsewhere (`x / 1`, `x - 0`, `x * 1` are exact), so one formula serves
/// every kind.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Linear {
    pub mul: f64,
    pub div: f64,
    pub zero: f64,
    pub span_in: f64,
    pub span_out_degc: f64,
    pub base_degc: f64,
    pub ne43_low_ma: f64,
    pub ne43_high_ma: f64,
    /// The current is a loop current (a transmitter) and part of the reading.
    pub has_current: bool,
}

impl Scaling {
    /// The scaling as numbers.
    pub(crate) fn linear(&self) -> Linear {
        let no_ne43 = (f64::NEG_INFINITY, f64::INFINITY);
        match *self {
            Self::Transmitter {
                adc_full_scale_counts,
                adc_full_scale_ma,
                current_range,
                range_min_degc,
                range_max_degc,
            } => {
                let (zero, span_in, ne43) = match current_range {
                    CurrentRange::FourTo20 => (4.0, 16.0, (NE43_LOW_MA, NE43_HIGH_MA)),
                    CurrentRange::ZeroTo20 => (0.0, 20.0, no_ne43),
                };
                Linear {
                    mul: adc_full_scale_ma,
                    div: adc_full_scale_counts,
                    zero,
                    span_in,
                    span_out_degc: range_max_degc - range_min_degc,
                    base_degc: range_min_degc,
                    ne43_low_ma: ne43.0,
                    ne43_high_ma: ne43.1,
                    has_current: true,
                }
            }
            Self::Direct { gain, offset_degc } => Linear {
                mul: gain,
                div: 1.0,
                zero: 0.0,
                span_in: 1.0,
                span_out_degc: 1.0,
                base_degc: offset_degc,
                ne43_low_ma: no_ne43.0,
                ne43_high_ma: no_ne43.1,
                has_current: false,
            },
        }
    }

    /// Degrees Celsius per unit of the raw value (one ADC count of a transmitter, one
    /// unit of a direct value times its gain): the scaling's resolution, which the rate
    /// check tolerates as converter noise.
    pub fn degc_per_raw_unit(&self) -> f64 {
        let l = self.linear();
        (l.mul / l.div / l.span_in * l.span_out_degc).abs()
    }

    /// Scales one raw value. NE43 is checked before the temperature is computed:
    /// a fault current carries no temperature. A raw value closer to 0 than
    /// [`MIN_RAW_MAGNITUDE`] (but not 0) is [`Reason::Implausible`]. Currents between 3.6 and 4 mA or
    /// 20 and 21 mA are valid saturated readings and scale linearly (slightly
    /// outside the range); the channel's plausible range decides about them.
    pub fn scale(&self, raw: f64) -> Scaled {
        if !raw.is_finite() {
            return Scaled {
                current_ma: None,
                degc: Err(Reason::NotFinite),
            };
        }
        let l = self.linear();
        let ma = raw * l.mul / l.div;
        if ma < l.ne43_low_ma {
            return fault(ma, Reason::Ne43Low);
        }
        if ma > l.ne43_high_ma {
            return fault(ma, Reason::Ne43High);
        }
        if raw != 0.0 && raw.abs() < MIN_RAW_MAGNITUDE {
            return Scaled {
                current_ma: Some(ma).filter(|_| l.has_current),
                degc: Err(Reason::Implausible),
            };
        }
        let degc = l.base_degc + (ma - l.zero) / l.span_in * l.span_out_degc;
        Scaled {
            current_ma: Some(ma).filter(|ma| l.has_current && ma.is_finite()),
            degc: if degc.is_finite() {
                Ok(degc)
            } else {
                Err(Reason::NotFinite)
            },
        }
    }
}

fn fault(ma: f64, reason: Reason) -> Scaled {
    Scaled {
        current_ma: Some(ma),
        degc: Err(reason),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 24000 counts = 24 mA: one count is one microampere.
    fn pt100(range: CurrentRange) -> Scaling {
        Scaling::Transmitter {
            adc_full_scale_counts: 24000.0,
            adc_full_scale_ma: 24.0,
            current_range: range,
            range_min_degc: -50.0,
            range_max_degc: 150.0,
        }
    }

    fn degc(s: &Scaling, raw: f64) -> f64 {
        match s.scale(raw).degc {
            Ok(v) => v,
            Err(r) => panic!("raw {raw}: {r}"),
        }
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    // Issue 23, trap 2: a CDAB float (23.45 degC) read as ABCD is -1.595e-23, inside
    // every plausible range; it used to be a good reading.
    #[test]
    fn a_float_no_sensor_produces_is_implausible() {
        let direct = Scaling::Direct {
            gain: 1.0,
            offset_degc: 0.0,
        };
        let swapped = f64::from(f32::from_bits(0x999A_41BB));
        assert!((swapped + 1.595e-23).abs() < 1e-26, "{swapped}");
        assert_eq!(direct.scale(swapped).degc, Err(Reason::Implausible));
        assert_eq!(direct.scale(-swapped).degc, Err(Reason::Implausible));
        assert_eq!(direct.scale(0.0).degc, Ok(0.0));
        assert_eq!(direct.scale(1e-6).degc, Ok(1e-6));
    }

    #[test]
    fn one_raw_unit_in_degc() {
        // 1 uA of a 16 mA span over 200 degC.
        assert!(close(
            pt100(CurrentRange::FourTo20).degc_per_raw_unit(),
            0.0125
        ));
        assert!(close(
            pt100(CurrentRange::ZeroTo20).degc_per_raw_unit(),
            0.01
        ));
        let tenths = Scaling::Direct {
            gain: -0.1,
            offset_degc: 5.0,
        };
        assert!(close(tenths.degc_per_raw_unit(), 0.1));
    }

    #[test]
    fn four_to_20_is_linear() {
        let s = pt100(CurrentRange::FourTo20);
        // 4 mA -> -50, 12 mA -> -50 + 8/16*200 = 50, 20 mA -> 150.
        assert!(close(degc(&s, 4000.0), -50.0));
        assert!(close(degc(&s, 12000.0), 50.0));
        assert!(close(degc(&s, 20000.0), 150.0));
        // 8.8 mA -> -50 + 4.8/16*200 = 10.
        assert!(close(degc(&s, 8800.0), 10.0));
        let c = s.scale(8800.0).current_ma.unwrap_or(f64::NAN);
        assert!(close(c, 8.8));
    }

    #[test]
    fn twelve_bit_adc() {
        // 4095 counts = 24 mA: 1365 counts = 8 mA -> -50 + 4/16*200 = 0 degC.
        let s = Scaling::Transmitter {
            adc_full_scale_counts: 4095.0,
            adc_full_scale_ma: 24.0,
            current_range: CurrentRange::FourTo20,
            range_min_degc: -50.0,
            range_max_degc: 150.0,
        };
        assert!(close(degc(&s, 1365.0), 0.0));
        // 2730 counts = 16 mA -> 100 degC.
        assert!(close(degc(&s, 2730.0), 100.0));
    }

    #[test]
    fn ne43_limits() {
        let s = pt100(CurrentRange::FourTo20);
        assert_eq!(s.scale(3599.0).degc, Err(Reason::Ne43Low));
        assert_eq!(s.scale(0.0).degc, Err(Reason::Ne43Low));
        assert_eq!(s.scale(21001.0).degc, Err(Reason::Ne43High));
        // The fault keeps its current for diagnosis.
        assert!(close(s.scale(3599.0).current_ma.unwrap_or(f64::NAN), 3.599));
        // 3.6 mA and 21 mA are saturated but valid: -50 - 0.4/16*200 = -55,
        // -50 + 17/16*200 = 162.5.
        assert!(close(degc(&s, 3600.0), -55.0));
        assert!(close(degc(&s, 21000.0), 162.5));
    }

    #[test]
    fn zero_to_20_has_no_ne43() {
        let s = Scaling::Transmitter {
            adc_full_scale_counts: 20000.0,
            adc_full_scale_ma: 20.0,
            current_range: CurrentRange::ZeroTo20,
            range_min_degc: 0.0,
            range_max_degc: 100.0,
        };
        assert!(close(degc(&s, 0.0), 0.0));
        // 5 mA -> 5/20*100 = 25.
        assert!(close(degc(&s, 5000.0), 25.0));
        // 2 mA would be an NE43 fault on 4-20; here it is 10 degC.
        assert!(close(degc(&s, 2000.0), 10.0));
    }

    #[test]
    fn direct() {
        let s = Scaling::Direct {
            gain: 0.1,
            offset_degc: -2.0,
        };
        // 215 * 0.1 - 2 = 19.5
        assert!(close(degc(&s, 215.0), 19.5));
        assert_eq!(s.scale(215.0).current_ma, None);
    }

    #[test]
    fn not_finite() {
        let s = pt100(CurrentRange::FourTo20);
        assert_eq!(s.scale(f64::NAN).degc, Err(Reason::NotFinite));
        // Infinity is NotFinite, not an NE43 over-current.
        assert_eq!(s.scale(f64::INFINITY).degc, Err(Reason::NotFinite));
        let d = Scaling::Direct {
            gain: 1e308,
            offset_degc: 0.0,
        };
        assert_eq!(d.scale(10.0).degc, Err(Reason::NotFinite));
        // A zero full scale divides by zero: not finite, not a panic.
        let z = Scaling::Transmitter {
            adc_full_scale_counts: 0.0,
            adc_full_scale_ma: 24.0,
            current_range: CurrentRange::ZeroTo20,
            range_min_degc: 0.0,
            range_max_degc: 100.0,
        };
        assert_eq!(z.scale(10.0).degc, Err(Reason::NotFinite));
    }
}
