//! `compgate-commission`: the offline commissioning tools. They read files (and, for
//! `backlash`, talk to the NC) and write reports; none needs the service running.
//!
//! - [`calibrate`]: the patent's step S1, least-squares fit of K0(T) and tan(beta)(T)
//!   (pure part in `calibrate::fit`), model file, plot.
//! - [`iso230`]: ISO 230-2 evaluation (A, B, R, E, M) of bidirectional runs.
//! - [`diagnose`]: where model and measurement disagree, which effect is missing, the
//!   model with it added, and how much the gap shrinks.
//! - [`backlash`]: backlash of a full-closed-loop axis from the servo trace of encoder
//!   and scale (seed formulas, plateau extraction, MD32450 write).
//! - [`volumetric`]: online volumetric compensation of a 5-axis AC-head machine.
//!
//! Each tool keeps its math pure (no I/O, no clap), its command (arguments, files, the
//! NC client) in `command`, and what it shows and writes (text, CSV, SVG) in `report`
//! (diagnose: `output`). They share:
//!
//! - [`args`]: range checks of numeric command-line flags, naming the flag;
//! - [`plot`]: the one way to draw an SVG chart (also used by the root package's
//!   scenario);
//! - [`lsq`]: linear least squares by column-scaled SVD (calibrate, diagnose);
//! - [`stats`]: mean, standard deviation, golden-section search;
//! - [`table`]: Markdown and fixed-width plain-text tables of the reports.
//!
//! The `synth` feature adds `diagnose::synth`, synthetic measurements (it pulls in
//! rand); tests and examples enable it.

pub mod args;
pub mod backlash;
pub mod calibrate;
pub mod diagnose;
pub mod iso230;
pub mod lsq;
pub mod plot;
pub mod stats;
pub mod table;
pub mod volumetric;
