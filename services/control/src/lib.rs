//! control: Pose + FlowEstimate in, CoilCommand out. The loop logic (`ControlLoop`) is free of
//! ports so it is tested directly and reused by in-process runs; `run` wires it to iceoryx2.
//! Safety: invalid, non-finite, out-of-canal or physically impossible poses never drive the
//! coils; the loop holds the orientation field briefly, then goes safe (zero currents).
//!
//! Files by concern: `config` (the `[control]` table), `setup` (its checks and the loop a
//! scenario describes), `control_loop` (the step as a pipeline of stages), `latency` (the
//! predictors that feed it the state at actuation time), `telemetry` (the recording and the run
//! logs), `service` (the process).

pub mod coil_gains;
pub mod config;
pub mod control_loop;
pub mod controllers;
pub mod latency;
pub mod observer;
pub mod operator;
pub mod reference;
pub mod rig3d;
pub mod service;
pub mod setup;
mod telemetry;

pub use config::{ControlConfig, SlewYieldConfig};
pub use control_loop::{ControlLoop, Decision};
pub use service::{run, FLOW_LOST_AFTER};
pub use setup::{build_loop, check_config, prepare, ControlSetup};
