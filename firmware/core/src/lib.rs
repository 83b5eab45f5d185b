//! The coil-driver board's logic, without the standard library or an allocator, so the same code
//! runs on the Teensy and inside the twin's emulated board. It knows nothing of pins or timers:
//! the caller feeds it decoded frames, the time, the emergency-stop input and (where the board
//! has them) the current-sense readings, and drives the H-bridges from [`Board::outputs`].
//!
//! Safety chain, in the order a command meets it:
//! 1. **Configuration**: nothing drives before the host sends a `Config` the board accepts (its
//!    channel count, a supply and watchdog within the hardware's range, every coil's limit
//!    within the driver's rating).
//! 2. **Arm**: the board starts disarmed and only an `Arm` frame carrying the arm key arms it.
//!    `Disarm` turns the outputs off and keeps the configuration.
//! 3. **Emergency stop**: the input pin or an `EStop` frame latches it; only a deliberate `Arm`
//!    (with the pin released) or a reset clears it. Nothing else drives in between.
//! 4. **Clamp**: each channel to its configured limit (and never above the hardware's).
//! 5. **Thermal budget**: per coil, the heat above its continuous rating, ∫(I² − I_c²) dt,
//!    fills a budget; from `DERATE_FROM` of it the allowed current falls linearly to the
//!    continuous current, and a full budget trips the board (outputs off) until it has cooled
//!    below `REARM_BELOW` and the host re-arms.
//! 6. **Watchdog**: no accepted `SetCurrents` for the configured time → outputs off until the
//!    next one.
#![cfg_attr(not(test), no_std)]

use millinav_teensy_protocol::{
    AckStatus, BoardConfig, BoardState, BoardStatus, ChannelStatus, CoilRating, Decoder, Message,
    Packet, MAX_COILS, NOT_MEASURED, STATUS_CLAMPED, STATUS_CONFIG_REFUSED, STATUS_DERATING,
    STATUS_ESTOP_INPUT, STATUS_WATCHDOG,
};

/// PWM duty at 100 %.
pub const PWM_MAX: u16 = u16::MAX;
/// Fraction of the heat budget from which a coil's current is derated.
pub const DERATE_FROM: f32 = 0.8;
/// A thermally tripped board re-arms only when every coil is below this fraction of its budget.
pub const REARM_BELOW: f32 = 0.5;

/// What the hardware can do, fixed in the firmware (the host's `Config` must fit inside).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HardwareLimits {
    /// H-bridge channels on the board.
    pub channels: usize,
    /// The drivers' current rating, mA.
    pub max_channel_ma: u32,
    pub min_supply_mv: u32,
    pub max_supply_mv: u32,
    pub min_watchdog_ms: u16,
    pub max_watchdog_ms: u16,
}

impl HardwareLimits {
    /// A board of `channels` 30 A drivers on a 12–80 V supply, watchdog 20 ms … 2 s.
    pub const fn standard(channels: usize) -> Self {
        Self {
            channels,
            max_channel_ma: 30_000,
            min_supply_mv: 12_000,
            max_supply_mv: 80_000,
            min_watchdog_ms: 20,
            max_watchdog_ms: 2000,
        }
    }
}

/// One H-bridge's drive.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ChannelOutput {
    /// PWM duty, 0 ..= [`PWM_MAX`].
    pub duty: u16,
    /// Direction: true drives positive current.
    pub forward: bool,
}

/// Why a `Config` was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConfigRefusal {
    ChannelCount,
    Supply,
    Watchdog,
    /// This coil's rating (zero resistance, limit above the driver's, continuous above the limit,
    /// no heat budget).
    Coil(usize),
    /// Configuration changes only while not armed.
    WhileArmed,
}

/// The board.
#[derive(Debug, Clone)]
pub struct Board {
    hw: HardwareLimits,
    config: Option<BoardConfig>,
    state: BoardState,
    commanded_ma: [i32; MAX_COILS],
    applied_ma: [i32; MAX_COILS],
    measured_ma: [i32; MAX_COILS],
    /// Heat above the continuous rating, A²·s.
    heat: [f32; MAX_COILS],
    last_command_ms: u64,
    last_tick_ms: Option<u64>,
    watchdog_tripped: bool,
    clamped: bool,
    estop_input: bool,
    config_refused: bool,
    pub rx_errors: u32,
    pub frames_received: u32,
    tx_seq: u32,
}

impl Board {
    pub fn new(hw: HardwareLimits) -> Self {
        Self {
            hw: HardwareLimits {
                channels: hw.channels.min(MAX_COILS),
                ..hw
            },
            config: None,
            state: BoardState::Unconfigured,
            commanded_ma: [0; MAX_COILS],
            applied_ma: [0; MAX_COILS],
            measured_ma: [NOT_MEASURED; MAX_COILS],
            heat: [0.0; MAX_COILS],
            last_command_ms: 0,
            last_tick_ms: None,
            watchdog_tripped: false,
            clamped: false,
            estop_input: false,
            config_refused: false,
            rx_errors: 0,
            frames_received: 0,
            tx_seq: 0,
        }
    }

    pub fn state(&self) -> BoardState {
        self.state
    }

    pub fn config(&self) -> Option<&BoardConfig> {
        self.config.as_ref()
    }

    fn channels(&self) -> usize {
        self.hw.channels
    }

    fn next_seq(&mut self) -> u32 {
        self.tx_seq = self.tx_seq.wrapping_add(1);
        self.tx_seq
    }

    fn zero_outputs(&mut self) {
        self.applied_ma = [0; MAX_COILS];
    }

    /// Checks a configuration against the hardware.
    pub fn check_config(&self, config: &BoardConfig) -> Result<(), ConfigRefusal> {
        if config.coils().len() != self.channels() {
            return Err(ConfigRefusal::ChannelCount);
        }
        if !(self.hw.min_supply_mv..=self.hw.max_supply_mv).contains(&config.supply_mv) {
            return Err(ConfigRefusal::Supply);
        }
        if !(self.hw.min_watchdog_ms..=self.hw.max_watchdog_ms).contains(&config.watchdog_ms) {
            return Err(ConfigRefusal::Watchdog);
        }
        for (k, c) in config.coils().iter().enumerate() {
            if c.resistance_mohm == 0
                || c.max_ma == 0
                || c.max_ma > self.hw.max_channel_ma
                || c.continuous_ma > c.max_ma
                || c.i2t_budget == 0
            {
                return Err(ConfigRefusal::Coil(k));
            }
        }
        Ok(())
    }

    fn configure(&mut self, config: BoardConfig) -> Result<(), ConfigRefusal> {
        if self.state == BoardState::Armed {
            return Err(ConfigRefusal::WhileArmed);
        }
        self.check_config(&config)?;
        self.config = Some(config);
        if self.state == BoardState::Unconfigured {
            self.state = BoardState::Disarmed;
        }
        Ok(())
    }

    fn heat_fraction(&self, k: usize, rating: &CoilRating) -> f32 {
        self.heat[k] / (rating.i2t_budget as f32 / 1000.0)
    }

    /// Arms when it may: configured, e-stop input released, every coil cooled after a trip.
    fn arm(&mut self, now_ms: u64) {
        let Some(config) = self.config else {
            return;
        };
        let cooled = config
            .coils()
            .iter()
            .enumerate()
            .all(|(k, r)| self.heat_fraction(k, r) < REARM_BELOW);
        let may = match self.state {
            BoardState::Unconfigured | BoardState::Armed => false,
            BoardState::Disarmed => true,
            BoardState::EStop => !self.estop_input,
            BoardState::ThermalTrip => cooled,
        };
        if may && !self.estop_input {
            self.state = BoardState::Armed;
            self.commanded_ma = [0; MAX_COILS];
            self.zero_outputs();
            self.last_command_ms = now_ms;
            self.watchdog_tripped = false;
        }
    }

    /// Handles one decoded frame; returns the reply to send (an `Ack` for `SetCurrents`).
    pub fn handle(&mut self, packet: &Packet, now_ms: u64) -> Option<Packet> {
        self.frames_received = self.frames_received.wrapping_add(1);
        match &packet.message {
            Message::Config(config) => {
                let refused = self.configure(*config).is_err();
                self.config_refused = refused;
                None
            }
            Message::Arm => {
                self.arm(now_ms);
                None
            }
            Message::Disarm => {
                if matches!(self.state, BoardState::Armed | BoardState::ThermalTrip) {
                    self.state = BoardState::Disarmed;
                }
                self.zero_outputs();
                None
            }
            Message::EStop => {
                self.state = BoardState::EStop;
                self.zero_outputs();
                None
            }
            Message::SetCurrents { currents_ma, .. } => {
                let status = self.set_currents(currents_ma.as_slice(), now_ms);
                let seq = self.next_seq();
                Some(Packet {
                    seq,
                    message: Message::Ack {
                        acked_seq: packet.seq,
                        status: status as u8,
                    },
                })
            }
            // Board-to-host kinds arriving here are ignored.
            Message::Ack { .. } | Message::Telemetry { .. } | Message::Status(_) => None,
        }
    }

    /// The current a coil may carry now: its limit, derated towards its continuous rating as
    /// its heat budget fills past [`DERATE_FROM`].
    fn allowed_ma(&self, k: usize, rating: &CoilRating) -> u32 {
        let used = self.heat_fraction(k, rating);
        if used <= DERATE_FROM {
            return rating.max_ma;
        }
        let t = ((used - DERATE_FROM) / (1.0 - DERATE_FROM)).clamp(0.0, 1.0);
        let span = rating.max_ma.saturating_sub(rating.continuous_ma) as f32;
        (rating.max_ma as f32 - t * span) as u32
    }

    fn set_currents(&mut self, currents: &[i32], now_ms: u64) -> AckStatus {
        if currents.len() != self.channels() {
            return AckStatus::RejectedCoilCount;
        }
        let Some(config) = self.config else {
            return AckStatus::NotArmed;
        };
        if self.state != BoardState::Armed {
            return AckStatus::NotArmed;
        }
        self.last_command_ms = now_ms;
        self.watchdog_tripped = false;
        let mut clamped = false;
        for (k, (&asked, rating)) in currents.iter().zip(config.coils()).enumerate() {
            self.commanded_ma[k] = asked;
            let limit = self.allowed_ma(k, rating).min(self.hw.max_channel_ma) as i64;
            let applied = i64::from(asked).clamp(-limit, limit);
            clamped |= applied != i64::from(asked);
            self.applied_ma[k] = applied as i32;
        }
        self.clamped = clamped;
        if clamped {
            AckStatus::Clamped
        } else {
            AckStatus::Applied
        }
    }

    /// Advances time: the e-stop input, the watchdog and the heat budgets. `measured_ma` are the
    /// current-sense readings of boards that have them (the heat then follows what flows, not
    /// what was asked).
    pub fn tick(&mut self, now_ms: u64, estop_input: bool, measured_ma: Option<&[i32]>) {
        self.estop_input = estop_input;
        if estop_input {
            self.state = BoardState::EStop;
            self.zero_outputs();
        }
        if let Some(m) = measured_ma {
            for (k, v) in m.iter().take(self.channels()).enumerate() {
                self.measured_ma[k] = *v;
            }
        }
        let dt_s = self
            .last_tick_ms
            .map_or(0.0, |t| now_ms.saturating_sub(t) as f32 / 1000.0);
        self.last_tick_ms = Some(now_ms);
        let Some(config) = self.config else {
            return;
        };
        if self.state == BoardState::Armed
            && now_ms.saturating_sub(self.last_command_ms) > u64::from(config.watchdog_ms)
        {
            self.watchdog_tripped = true;
            self.zero_outputs();
        }
        let mut tripped = false;
        for (k, rating) in config.coils().iter().enumerate() {
            let flowing_ma = match measured_ma {
                Some(_) if self.measured_ma[k] != NOT_MEASURED => self.measured_ma[k],
                _ => self.applied_ma[k],
            };
            let i = flowing_ma as f32 / 1000.0;
            let ic = rating.continuous_ma as f32 / 1000.0;
            self.heat[k] = (self.heat[k] + (i * i - ic * ic) * dt_s).max(0.0);
            tripped |= self.heat_fraction(k, rating) >= 1.0;
        }
        if tripped && self.state == BoardState::Armed {
            self.state = BoardState::ThermalTrip;
            self.zero_outputs();
        }
    }

    /// Feeds bytes from the host link through `decoder` into the board: every whole, valid frame
    /// is handled at `now_ms` and its reply (an `Ack`) handed to `reply`; frames of the wrong
    /// length, CRC, version or payload are dropped by the decoder and counted in `rx_errors`
    /// (reported in `Status`). The firmware's receive path.
    pub fn receive(
        &mut self,
        decoder: &mut Decoder,
        bytes: &[u8],
        now_ms: u64,
        mut reply: impl FnMut(Packet),
    ) {
        decoder.push_with(bytes, |packet| {
            if let Some(answer) = self.handle(&packet, now_ms) {
                reply(answer);
            }
        });
        self.rx_errors = decoder.counters.errors().min(u64::from(u32::MAX)) as u32;
    }

    /// Whether the outputs drive now: armed and the watchdog fed.
    pub fn driving(&self) -> bool {
        self.state == BoardState::Armed && !self.watchdog_tripped
    }

    /// The currents the channels drive now, mA (zero when not [`Self::driving`]).
    pub fn driven_ma(&self) -> [i32; MAX_COILS] {
        if self.driving() {
            self.applied_ma
        } else {
            [0; MAX_COILS]
        }
    }

    /// The H-bridge drives: duty = |I| R / V_supply, zero unless armed and fed.
    pub fn outputs(&self) -> [ChannelOutput; MAX_COILS] {
        let mut out = [ChannelOutput::default(); MAX_COILS];
        let Some(config) = self.config else {
            return out;
        };
        if self.state != BoardState::Armed || self.watchdog_tripped {
            return out;
        }
        for (k, rating) in config.coils().iter().enumerate() {
            let i = self.applied_ma[k];
            // mA × mΩ = µV; the supply in mV × 1000 is µV.
            let volts_uv = u64::from(i.unsigned_abs()) * u64::from(rating.resistance_mohm);
            let supply_uv = u64::from(config.supply_mv) * 1000;
            let duty = (volts_uv * u64::from(PWM_MAX) / supply_uv.max(1)).min(u64::from(PWM_MAX));
            out[k] = ChannelOutput {
                duty: duty as u16,
                forward: i >= 0,
            };
        }
        out
    }

    /// The `Status` telemetry frame.
    pub fn status(&mut self) -> Packet {
        let mut channels = [ChannelStatus::default(); MAX_COILS];
        let mut derating = false;
        let driving = self.driving();
        for (k, ch) in channels.iter_mut().take(self.channels()).enumerate() {
            let thermal = self.config.as_ref().map_or(0.0, |c| {
                let r = &c.coils()[k];
                derating |= self.allowed_ma(k, r) < r.max_ma;
                self.heat_fraction(k, r)
            });
            *ch = ChannelStatus {
                commanded_ma: self.commanded_ma[k],
                applied_ma: if driving { self.applied_ma[k] } else { 0 },
                measured_ma: self.measured_ma[k],
                thermal_permille: (thermal * 1000.0).clamp(0.0, 1000.0) as u16,
            };
        }
        let mut flags = 0;
        for (on, bit) in [
            (self.watchdog_tripped, STATUS_WATCHDOG),
            (self.clamped, STATUS_CLAMPED),
            (derating, STATUS_DERATING),
            (self.estop_input, STATUS_ESTOP_INPUT),
            (self.config_refused, STATUS_CONFIG_REFUSED),
        ] {
            if on {
                flags |= bit;
            }
        }
        let status = BoardStatus::new(
            self.state as u8,
            flags,
            &channels[..self.channels()],
            self.rx_errors,
            self.frames_received,
        )
        .unwrap_or_else(|| {
            BoardStatus::new(
                self.state as u8,
                flags,
                &[],
                self.rx_errors,
                self.frames_received,
            )
            .expect("no channels always fit")
        });
        let seq = self.next_seq();
        Packet {
            seq,
            message: Message::Status(status),
        }
    }
}

#[cfg(test)]
mod tests;
