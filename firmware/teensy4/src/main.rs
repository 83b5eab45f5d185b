//! millinav coil-driver firmware for a Teensy 4.0 / 4.1.
//!
//! Everything that decides what the coils get lives in `millinav-firmware-core`, the crate the
//! twin's emulated board runs too; this binary only wires it to the hardware:
//! - the host link is the Teensy's USB serial port (`/dev/ttyACM*` on Linux);
//! - eight H-bridges, each a PWM pin (20 kHz, duty = |I|·R / V_supply) and a direction pin;
//! - one driver-enable pin, high only while the board drives;
//! - an emergency-stop input (normally closed to ground: a pressed button or a cut wire reads high
//!   through the pull-up and latches the e-stop);
//! - the LED lights while the board drives.
//!
//! The pin map is in `firmware/FIRMWARE.md`. A panic turns the outputs off and resets the chip,
//! and the board boots unconfigured and disarmed.
#![no_std]
#![no_main]

use millinav_firmware_core::{Board, ChannelOutput, HardwareLimits, PWM_MAX};
use millinav_teensy_protocol::{encode, Decoder, MAX_COILS};
use teensy4_bsp as bsp;

use bsp::board;
use bsp::hal::{flexpwm, gpio, gpt, iomuxc, usbd};
use bsp::pins::common::{
    P10, P11, P12, P14, P15, P16, P17, P18, P19, P2, P3, P4, P5, P6, P7, P8, P9,
};
use usb_device::bus::UsbBusAllocator;
use usb_device::device::{UsbDevice, UsbDeviceBuilder, UsbDeviceState, UsbVidPid};
use usbd_serial::SerialPort;

/// H-bridge channels this board drives.
const CHANNELS: usize = 8;
/// Status telemetry period, ms (the emulated board's too).
const STATUS_PERIOD_MS: u64 = 20;
/// PWM: the IPG clock (150 MHz) counts from −HALF to +HALF, centre-aligned: 20 kHz.
const PWM_HALF_PERIOD: i16 = (board::IPG_FREQUENCY / 20_000 / 2) as i16;
/// PJRC's USB serial identifiers, so the Teensy tools and udev rules recognise the board.
const VID_PID: UsbVidPid = UsbVidPid(0x16C0, 0x0483);
/// Tries to hand a reply to the USB stack before the frame is dropped (the host is not reading).
const WRITE_ATTEMPTS: u32 = 2_000;

/// The e-stop input has a pull-up: an open (pressed or cut) normally-closed switch reads high.
const ESTOP_PIN_CONFIG: iomuxc::Config =
    iomuxc::Config::zero().set_pull_keeper(Some(iomuxc::PullKeeper::Pullup100k));

static EP_MEMORY: usbd::EndpointMemory<2048> = usbd::EndpointMemory::new();
static EP_STATE: usbd::EndpointState = usbd::EndpointState::max_endpoints();

/// Milliseconds since boot from GPT1 free-running at 1 MHz, widened past its 32-bit wrap.
struct Clock {
    gpt: gpt::Gpt1,
    last: u32,
    micros: u64,
}

impl Clock {
    fn new(mut gpt: gpt::Gpt1) -> Self {
        gpt.disable();
        gpt.set_clock_source(gpt::ClockSource::PeripheralClock);
        gpt.set_divider(board::PERCLK_FREQUENCY / 1_000_000);
        gpt.set_mode(gpt::Mode::FreeRunning);
        gpt.set_reset_on_enable(true);
        gpt.enable();
        Self {
            gpt,
            last: 0,
            micros: 0,
        }
    }

    fn now_ms(&mut self) -> u64 {
        let count = self.gpt.count();
        self.micros += u64::from(count.wrapping_sub(self.last));
        self.last = count;
        self.micros / 1000
    }
}

/// Sets one centre-aligned PWM output to `duty` of full scale.
fn set_duty<P, const N: u8, const M: u8>(
    output: &flexpwm::Output<P>,
    submodule: &flexpwm::Submodule<N, M>,
    duty: u16,
) where
    P: iomuxc::flexpwm::Pin<
        Module = iomuxc::consts::Const<N>,
        Submodule = iomuxc::consts::Const<M>,
    >,
{
    let half = (i32::from(PWM_HALF_PERIOD) * i32::from(duty) / i32::from(PWM_MAX)) as i16;
    output.set_turn_on(submodule, -half);
    output.set_turn_off(submodule, half);
}

/// One FlexPWM submodule running at the PWM frequency, outputs independent.
fn start_submodule<const N: u8, const M: u8>(
    pwm: &mut flexpwm::Pwm<N>,
    submodule: &mut flexpwm::Submodule<N, M>,
) {
    submodule.set_debug_enable(true);
    submodule.set_wait_enable(true);
    submodule.set_clock_select(flexpwm::ClockSelect::Ipg);
    submodule.set_prescaler(flexpwm::Prescaler::Prescaler1);
    submodule.set_pair_operation(flexpwm::PairOperation::Independent);
    submodule.set_load_mode(flexpwm::LoadMode::reload_full());
    submodule.set_load_frequency(1);
    submodule.set_initial_count(pwm, -PWM_HALF_PERIOD);
    submodule.set_value(flexpwm::FULL_RELOAD_VALUE_REGISTER, PWM_HALF_PERIOD);
    submodule.set_load_ok(pwm);
    submodule.set_running(pwm, true);
}

/// The eight H-bridges: PWM outputs on FlexPWM 4.2, 2.0, 2.1, 2.2 and 1.3, direction pins,
/// and the drivers' shared enable.
struct Bridges {
    pwm1: flexpwm::Pwm<1>,
    pwm2: flexpwm::Pwm<2>,
    pwm4: flexpwm::Pwm<4>,
    sm1_3: flexpwm::Submodule<1, 3>,
    sm2_0: flexpwm::Submodule<2, 0>,
    sm2_1: flexpwm::Submodule<2, 1>,
    sm2_2: flexpwm::Submodule<2, 2>,
    sm4_2: flexpwm::Submodule<4, 2>,
    ch0: flexpwm::Output<P2>,
    ch1: flexpwm::Output<P3>,
    ch2: flexpwm::Output<P4>,
    ch3: flexpwm::Output<P5>,
    ch4: flexpwm::Output<P6>,
    ch5: flexpwm::Output<P9>,
    ch6: flexpwm::Output<P8>,
    ch7: flexpwm::Output<P7>,
    dir0: gpio::Output<P10>,
    dir1: gpio::Output<P11>,
    dir2: gpio::Output<P12>,
    dir3: gpio::Output<P14>,
    dir4: gpio::Output<P15>,
    dir5: gpio::Output<P16>,
    dir6: gpio::Output<P17>,
    dir7: gpio::Output<P18>,
    enable: gpio::Output<P19>,
}

fn set_pin<P>(pin: &gpio::Output<P>, high: bool) {
    if high {
        pin.set();
    } else {
        pin.clear();
    }
}

impl Bridges {
    /// Drives what the board logic says; the enable pin is high only while `driving`.
    fn apply(&mut self, outputs: &[ChannelOutput; MAX_COILS], driving: bool) {
        if !driving {
            self.enable.clear();
        }
        let o = outputs;
        set_pin(&self.dir0, o[0].forward);
        set_pin(&self.dir1, o[1].forward);
        set_pin(&self.dir2, o[2].forward);
        set_pin(&self.dir3, o[3].forward);
        set_pin(&self.dir4, o[4].forward);
        set_pin(&self.dir5, o[5].forward);
        set_pin(&self.dir6, o[6].forward);
        set_pin(&self.dir7, o[7].forward);
        set_duty(&self.ch0, &self.sm4_2, o[0].duty);
        set_duty(&self.ch1, &self.sm4_2, o[1].duty);
        set_duty(&self.ch2, &self.sm2_0, o[2].duty);
        set_duty(&self.ch3, &self.sm2_1, o[3].duty);
        set_duty(&self.ch4, &self.sm2_2, o[4].duty);
        set_duty(&self.ch5, &self.sm2_2, o[5].duty);
        set_duty(&self.ch6, &self.sm1_3, o[6].duty);
        set_duty(&self.ch7, &self.sm1_3, o[7].duty);
        // New compare values take effect together at the next PWM period.
        self.sm4_2.set_load_ok(&mut self.pwm4);
        self.sm2_0.set_load_ok(&mut self.pwm2);
        self.sm2_1.set_load_ok(&mut self.pwm2);
        self.sm2_2.set_load_ok(&mut self.pwm2);
        self.sm1_3.set_load_ok(&mut self.pwm1);
        if driving {
            self.enable.set();
        }
    }

    fn enable_outputs(&mut self) {
        self.ch0.set_output_enable(&mut self.pwm4, true);
        self.ch1.set_output_enable(&mut self.pwm4, true);
        self.ch2.set_output_enable(&mut self.pwm2, true);
        self.ch3.set_output_enable(&mut self.pwm2, true);
        self.ch4.set_output_enable(&mut self.pwm2, true);
        self.ch5.set_output_enable(&mut self.pwm2, true);
        self.ch6.set_output_enable(&mut self.pwm1, true);
        self.ch7.set_output_enable(&mut self.pwm1, true);
    }
}

/// Hands `bytes` to the USB serial port, polling the device while its buffer is full; drops what
/// does not go out in [`WRITE_ATTEMPTS`] polls (a host that does not read must not stall the
/// board's safety logic).
fn send(
    device: &mut UsbDevice<'static, usbd::BusAdapter>,
    serial: &mut SerialPort<'static, usbd::BusAdapter>,
    mut bytes: &[u8],
) {
    let mut attempts = 0;
    while !bytes.is_empty() && attempts < WRITE_ATTEMPTS {
        match serial.write(bytes) {
            Ok(n) => bytes = &bytes[n..],
            Err(_) => {
                attempts += 1;
                device.poll(&mut [serial]);
            }
        }
    }
}

#[bsp::rt::entry]
fn main() -> ! {
    let board::Resources {
        mut pins,
        mut gpio1,
        mut gpio2,
        gpt1,
        usb,
        flexpwm1,
        flexpwm2,
        flexpwm4,
        ..
    } = board::t40(board::instances());

    // Outputs first, all off: the enable pin low before anything else runs.
    let enable = gpio1.output(pins.p19);
    enable.clear();
    let led = board::led(&mut gpio2, pins.p13);
    led.clear();
    iomuxc::configure(&mut pins.p20, ESTOP_PIN_CONFIG);
    let estop = gpio1.input(pins.p20);

    let (mut pwm1, (_, _, _, mut sm1_3)) = flexpwm1;
    let (mut pwm2, (mut sm2_0, mut sm2_1, mut sm2_2, _)) = flexpwm2;
    let (mut pwm4, (_, _, mut sm4_2, _)) = flexpwm4;
    start_submodule(&mut pwm1, &mut sm1_3);
    start_submodule(&mut pwm2, &mut sm2_0);
    start_submodule(&mut pwm2, &mut sm2_1);
    start_submodule(&mut pwm2, &mut sm2_2);
    start_submodule(&mut pwm4, &mut sm4_2);
    let mut bridges = Bridges {
        pwm1,
        pwm2,
        pwm4,
        sm1_3,
        sm2_0,
        sm2_1,
        sm2_2,
        sm4_2,
        ch0: flexpwm::Output::new_a(pins.p2),
        ch1: flexpwm::Output::new_b(pins.p3),
        ch2: flexpwm::Output::new_a(pins.p4),
        ch3: flexpwm::Output::new_a(pins.p5),
        ch4: flexpwm::Output::new_a(pins.p6),
        ch5: flexpwm::Output::new_b(pins.p9),
        ch6: flexpwm::Output::new_a(pins.p8),
        ch7: flexpwm::Output::new_b(pins.p7),
        dir0: gpio2.output(pins.p10),
        dir1: gpio2.output(pins.p11),
        dir2: gpio2.output(pins.p12),
        dir3: gpio1.output(pins.p14),
        dir4: gpio1.output(pins.p15),
        dir5: gpio1.output(pins.p16),
        dir6: gpio1.output(pins.p17),
        dir7: gpio1.output(pins.p18),
        enable,
    };
    let mut board_logic = Board::new(HardwareLimits::standard(CHANNELS));
    bridges.apply(&board_logic.outputs(), false);
    bridges.enable_outputs();

    let bus = usbd::BusAdapter::with_speed(usb, &EP_MEMORY, &EP_STATE, usbd::Speed::LowFull);
    let bus: &'static UsbBusAllocator<usbd::BusAdapter> =
        cortex_m::singleton!(: UsbBusAllocator<usbd::BusAdapter> = UsbBusAllocator::new(bus))
            .expect("the USB bus is set up once");
    let mut serial = SerialPort::new(bus);
    let mut device = UsbDeviceBuilder::new(bus, VID_PID)
        .manufacturer("millinav")
        .product("millinav coil driver")
        .device_class(usbd_serial::USB_CLASS_CDC)
        .max_packet_size_0(64)
        .build();

    let mut clock = Clock::new(gpt1);
    let mut decoder = Decoder::new();
    let mut usb_configured = false;
    let mut last_status_ms = 0u64;
    loop {
        let now_ms = clock.now_ms();
        if device.poll(&mut [&mut serial]) {
            if device.state() == UsbDeviceState::Configured {
                if !usb_configured {
                    device.bus().configure();
                    usb_configured = true;
                }
                let mut buffer = [0u8; 64];
                if let Ok(n) = serial.read(&mut buffer) {
                    let mut replies = heapless_replies::Replies::new();
                    board_logic.receive(&mut decoder, &buffer[..n], now_ms, |reply| {
                        replies.push(reply)
                    });
                    for reply in replies.iter() {
                        send(&mut device, &mut serial, &encode(reply));
                    }
                }
            } else {
                usb_configured = false;
            }
        }
        board_logic.tick(now_ms, estop.is_set(), None);
        let driving = board_logic.driving();
        bridges.apply(&board_logic.outputs(), driving);
        set_pin(&led, driving);
        if usb_configured && now_ms.saturating_sub(last_status_ms) >= STATUS_PERIOD_MS {
            last_status_ms = now_ms;
            let status = board_logic.status();
            send(&mut device, &mut serial, &encode(&status));
        }
    }
}

/// Replies gathered while a USB packet is decoded (at most a few frames fit in 64 bytes).
mod heapless_replies {
    use millinav_teensy_protocol::Packet;

    const CAPACITY: usize = 8;

    pub struct Replies {
        items: [Option<Packet>; CAPACITY],
        len: usize,
    }

    impl Replies {
        pub fn new() -> Self {
            Self {
                items: [const { None }; CAPACITY],
                len: 0,
            }
        }

        /// Keeps `reply`; beyond the capacity the oldest ones stay and the rest are dropped
        /// (the host counts missing acks).
        pub fn push(&mut self, reply: Packet) {
            if self.len < CAPACITY {
                self.items[self.len] = Some(reply);
                self.len += 1;
            }
        }

        pub fn iter(&self) -> impl Iterator<Item = &Packet> {
            self.items[..self.len].iter().flatten()
        }
    }
}

/// A panic turns every output off (drivers disabled, PWM outputs off) and resets the chip; it
/// boots unconfigured and disarmed, and the host sees the reset in the board's state.
#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    use bsp::ral;
    // SAFETY: the program is ending; nothing else touches these registers again.
    unsafe {
        let gpio1 = ral::gpio::GPIO1::instance();
        // Pin 19 (GPIO1_IO16) is the drivers' enable.
        ral::write_reg!(ral::gpio, gpio1, DR_CLEAR, 1 << 16);
        ral::write_reg!(ral::pwm, ral::pwm::PWM1::instance(), OUTEN, 0);
        ral::write_reg!(ral::pwm, ral::pwm::PWM2::instance(), OUTEN, 0);
        ral::write_reg!(ral::pwm, ral::pwm::PWM4::instance(), OUTEN, 0);
    }
    cortex_m::peripheral::SCB::sys_reset()
}
