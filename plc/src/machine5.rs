//! Simulated 5-axis machine with an AC swivel head and true geometric errors, whose
//! drives close their position loops on (possibly modified) scale feedback.
//!
//! Axes X, Y, Z (mm) move the head; C (swivel, about Z) and A (tilt, about X) are in
//! the head, in degrees. Nominally
//!
//! ```text
//! tip  = (X, Y, Z) + Rz(C) (pivot + Rx(A) (0, 0, -tool_length))
//! axis = Rz(C) Rx(A) (0, 0, 1)
//! ```
//!
//! The machine's true errors come from a function of the five axis positions
//! returning the tip error (mm, actual minus nominal) and the orientation error (a
//! small rotation vector, rad, taking the nominal tool axis to the actual one). This
//! crate does not depend on `compgate`, so a test hands in the gateway's error model
//! as a closure.
//!
//! [`Machine5::move_to`] runs the servo: each cycle the drives read the scales (the
//! true axis positions), pass them through the feedback function (the compensator
//! between scales and drives, or the identity) and move by `gain * (command -
//! feedback)`, until feedback equals the command within a tolerance. It then reports
//! the actual tool pose there.

/// Tip error (mm) and orientation error (rotation vector, rad) at five axis positions.
pub type ErrorFn = dyn Fn(&[f64; 5]) -> ([f64; 3], [f64; 3]) + Send + Sync;

/// Nominal head geometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadGeometry {
    /// Offset from the C axis to the A axis in the C frame, mm.
    pub pivot_mm: [f64; 3],
    /// Distance from the A axis to the tool tip, mm.
    pub tool_length_mm: f64,
}

/// A tool pose in the workpiece frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Tool tip, mm.
    pub tip_mm: [f64; 3],
    /// Unit tool axis (tip towards spindle).
    pub axis: [f64; 3],
}

/// Where the servo settled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settled {
    /// True axis positions (scale values), mm and deg.
    pub axes: [f64; 5],
    /// Actual tool pose there.
    pub pose: Pose,
    /// Servo cycles until feedback matched the command.
    pub cycles: usize,
}

/// Errors of the simulated machine.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Machine5Error {
    /// The loop did not settle within the cycle limit.
    #[error("servo did not settle in {cycles} cycles (remaining {remaining:e})")]
    NotSettled {
        /// Cycles run.
        cycles: usize,
        /// Largest remaining `|command - feedback|`, mm or deg.
        remaining: f64,
    },
}

/// The simulated machine.
pub struct Machine5 {
    geometry: HeadGeometry,
    errors: Box<ErrorFn>,
    /// Loop gain per servo cycle (0 < gain <= 1).
    pub gain: f64,
    /// Settling tolerance on `|command - feedback|`, mm and deg.
    pub tolerance: f64,
    /// Most servo cycles of one move.
    pub max_cycles: usize,
}

impl std::fmt::Debug for Machine5 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Machine5")
            .field("geometry", &self.geometry)
            .field("gain", &self.gain)
            .field("tolerance", &self.tolerance)
            .field("max_cycles", &self.max_cycles)
            .finish_non_exhaustive()
    }
}

impl Machine5 {
    /// A machine with the given geometry and true errors; gain 0.8, tolerance 1e-9,
    /// at most 1000 cycles.
    pub fn new(geometry: HeadGeometry, errors: Box<ErrorFn>) -> Self {
        Self {
            geometry,
            errors,
            gain: 0.8,
            tolerance: 1e-9,
            max_cycles: 1000,
        }
    }

    /// A machine without errors.
    pub fn ideal(geometry: HeadGeometry) -> Self {
        Self::new(geometry, Box::new(|_| ([0.0; 3], [0.0; 3])))
    }

    /// The head geometry.
    pub fn geometry(&self) -> HeadGeometry {
        self.geometry
    }

    /// Nominal pose at axis positions q.
    pub fn nominal_pose(&self, q: &[f64; 5]) -> Pose {
        let g = &self.geometry;
        let (sa, ca) = q[3].to_radians().sin_cos();
        let (sc, cc) = q[4].to_radians().sin_cos();
        let l = g.tool_length_mm;
        let h = [
            g.pivot_mm[0],
            g.pivot_mm[1] + sa * l,
            g.pivot_mm[2] - ca * l,
        ];
        Pose {
            tip_mm: [
                q[0] + cc * h[0] - sc * h[1],
                q[1] + sc * h[0] + cc * h[1],
                q[2] + h[2],
            ],
            axis: [sc * sa, -cc * sa, ca],
        }
    }

    /// Actual pose at axis positions q: the nominal pose with the true errors.
    pub fn actual_pose(&self, q: &[f64; 5]) -> Pose {
        let n = self.nominal_pose(q);
        let (dp, w) = (self.errors)(q);
        let v = n.axis;
        // Rotate the axis by the small rotation vector w (Rodrigues).
        let th = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
        let axis = if th == 0.0 {
            v
        } else {
            let k = [w[0] / th, w[1] / th, w[2] / th];
            let kxv = [
                k[1] * v[2] - k[2] * v[1],
                k[2] * v[0] - k[0] * v[2],
                k[0] * v[1] - k[1] * v[0],
            ];
            let kv = k[0] * v[0] + k[1] * v[1] + k[2] * v[2];
            let (s, c) = th.sin_cos();
            std::array::from_fn(|i| v[i] * c + kxv[i] * s + k[i] * kv * (1.0 - c))
        };
        Pose {
            tip_mm: std::array::from_fn(|i| n.tip_mm[i] + dp[i]),
            axis,
        }
    }

    /// Moves to `command`: the servo drives each axis until `feedback(scales)`
    /// equals the command, then reports the true axis positions and actual pose.
    pub fn move_to(
        &self,
        command: &[f64; 5],
        feedback: impl Fn(&[f64; 5]) -> [f64; 5],
    ) -> Result<Settled, Machine5Error> {
        let mut q = *command;
        let mut remaining = f64::INFINITY;
        for cycles in 0..=self.max_cycles {
            let f = feedback(&q);
            let e: [f64; 5] = std::array::from_fn(|i| command[i] - f[i]);
            remaining = e.iter().fold(0.0, |m, v| m.max(v.abs()));
            if remaining <= self.tolerance {
                return Ok(Settled {
                    axes: q,
                    pose: self.actual_pose(&q),
                    cycles,
                });
            }
            for i in 0..5 {
                q[i] += self.gain * e[i];
            }
        }
        Err(Machine5Error::NotSettled {
            cycles: self.max_cycles,
            remaining,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const G: HeadGeometry = HeadGeometry {
        pivot_mm: [0.0, 0.0, -150.0],
        tool_length_mm: 250.0,
    };

    fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
        (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
    }

    #[test]
    fn ideal_machine_lands_on_the_command() {
        let m = Machine5::ideal(G);
        let u = [100.0, 200.0, 300.0, 30.0, -45.0];
        let s = m.move_to(&u, |q| *q).expect("settles");
        assert_eq!(s.axes, u);
        assert_eq!(s.cycles, 0);
        let n = m.nominal_pose(&u);
        assert!(dist(&s.pose.tip_mm, &n.tip_mm) < 1e-12);
    }

    #[test]
    fn uncompensated_errors_show_in_the_pose() {
        let m = Machine5::new(G, Box::new(|_| ([0.01, 0.0, -0.02], [0.0, 1e-4, 0.0])));
        let u = [0.0, 0.0, 0.0, 0.0, 0.0];
        let s = m.move_to(&u, |q| *q).expect("settles");
        let n = m.nominal_pose(&u);
        assert!((dist(&s.pose.tip_mm, &n.tip_mm) - 0.05f64.sqrt() * 0.1).abs() < 1e-12);
        // Rotation about Y by 1e-4 rad tilts the Z axis towards +X.
        assert!((s.pose.axis[0] - 1e-4).abs() < 1e-10, "{:?}", s.pose.axis);
    }

    #[test]
    fn servo_follows_a_modified_feedback() {
        let m = Machine5::ideal(G);
        let u = [10.0, 20.0, 30.0, 40.0, 50.0];
        // A feedback reading 0.005 high makes the drives stop 0.005 short.
        let s = m.move_to(&u, |q| q.map(|v| v + 0.005)).expect("settles");
        for (q, c) in s.axes.iter().zip(&u) {
            assert!((q - (c - 0.005)).abs() < 1e-8);
        }
        assert!(s.cycles > 1);
        let bad = m.move_to(&u, |q| q.map(|v| -v));
        assert!(matches!(bad, Err(Machine5Error::NotSettled { .. })));
    }
}
