//! The twin's seeded random streams. Everything stochastic in a run draws from the scenario
//! seed through one of these, each part on its own ChaCha8 stream, so that a change in how much
//! one part draws never shifts another's numbers and a run replays exactly from its seed.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The camera's fixed appearance (background texture, lighting-drift phases), drawn once at
/// start-up.
pub const CAMERA_SETUP: u64 = 1;
/// Per-frame camera noise: frame `seq` draws from stream `FRAME_NOISE_BASE + seq`, so a frame's
/// noise does not depend on how many frames came before it (or were dropped).
pub const FRAME_NOISE_BASE: u64 = 1000;
/// The recirculation vortex's phases and the flow-noise modes' geometry ("flow" in ASCII).
pub const FLOW_DISTURBANCE: u64 = 0x666c_6f77;
/// The flow-noise amplitudes' Ornstein–Uhlenbeck process ("nois" in ASCII).
pub const FLOW_NOISE: u64 = 0x6e6f_6973;
/// Seed offset of the per-coil gain errors ("coil" in ASCII). Unlike the streams above it is
/// XOR-ed into the seed; kept so that existing seeds reproduce the same gains.
const COIL_GAIN_SEED_XOR: u64 = 0x636f_696c;

/// Seeded per-run random source on `stream`.
pub fn run_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    let _: u64 = rng.random();
    rng
}

/// The camera noise of frame `seq`.
pub fn frame_noise_rng(seed: u64, seq: u64) -> ChaCha8Rng {
    run_rng(seed, FRAME_NOISE_BASE + seq)
}

/// The source of the per-coil gain errors.
pub fn coil_gain_rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ COIL_GAIN_SEED_XOR)
}
