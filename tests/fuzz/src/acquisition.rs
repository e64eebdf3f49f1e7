//! The acquisition of cycles: arbitrary CAN frames at arbitrary times into
//! `controller::cycle::Acquisition` + `Estimation`, every output checked, no allocation.
//!
//! Input: a sequence of operations, one byte each (low 3 bits the operation, high 5 bits a
//! time step of `k × 50 µs` taken before it), with their operands after them:
//!
//! | op | operation | operands |
//! | --- | --- | --- |
//! | 0 | `start_cycle` | - |
//! | 1 | `on_frame` of a raw frame | id `u32`, flags (bit 0 extended, bit 1 remote), dlc, 8 data bytes |
//! | 2 | `on_frame_between_cycles` of a raw frame | as 1 |
//! | 3 | `on_bus_error` | - |
//! | 4 | `end_cycle` → `Estimation::process` → checks | sync failed (bit 0) |
//! | 5 | the clock jumps to any instant (backwards too: replayed logs carry any time) | `u64` ns |
//! | 6 | `on_frame` of a well-formed message of one of our nodes | kind, node, 8 bytes |
//! | 7 | as 6, between cycles | as 6 |
//!
//! Ops 6-7 let the fuzzer reach complete cycles (and so the detector) without guessing COB-IDs.

use controller::config::Config;
use controller::cycle::{Acquisition, CycleInput, CycleOutput, Estimation};
use hw_io::can::{CanFrame, Message, NmtState, NodeId};
use hw_io::ipc::{HealthFlags, OutputState, ReceiveCheck};

use crate::Bytes;

/// Runs the operations of `data` (module doc); panics when an output breaks an invariant or
/// when the cycle path allocates (under a counting global allocator: see
/// [`allocation_counting_active`]).
pub fn run(data: &[u8]) {
    let cfg = Config::default();
    let Ok(acq) = Acquisition::new(&cfg.bus.encoder, cfg.health) else {
        panic!("the default configuration builds acquisition");
    };
    // Nodes 4 and 5: the endoscope arm's, as in configs/fulcrumd.toml.
    let mut acq = acq.with_other_nodes(&[4, 5]);
    let Ok(mut est) = Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector) else {
        panic!("the default configuration builds estimation");
    };
    let counting = allocation_counting_active();
    let (allocs, ()) = hw_io::rt_alloc::count_thread_allocs(|| {
        let mut b = Bytes::new(data);
        let mut now_ns: u64 = 0;
        while !b.is_empty() {
            let op = b.u8();
            now_ns = now_ns.saturating_add(u64::from(op >> 3) * 50_000);
            match op & 7 {
                0 => acq.start_cycle(),
                1 => {
                    if let Some(f) = raw_frame(&mut b) {
                        acq.on_frame(&f, now_ns);
                    }
                }
                2 => {
                    if let Some(f) = raw_frame(&mut b) {
                        acq.on_frame_between_cycles(&f, now_ns);
                    }
                }
                3 => acq.on_bus_error(),
                4 => {
                    let input = acq.end_cycle(now_ns, b.u8() & 1 == 1);
                    let output = est.process(&input);
                    check_output(&cfg, &input, &output);
                }
                5 => now_ns = b.u64(),
                _ => {
                    if let Some(f) = message_frame(&mut b) {
                        if op & 7 == 6 {
                            acq.on_frame(&f, now_ns);
                        } else {
                            acq.on_frame_between_cycles(&f, now_ns);
                        }
                    }
                }
            }
        }
    });
    if counting {
        assert_eq!(allocs, 0, "the cycle path allocated {allocs} times");
    }
}

/// True when the global allocator counts this thread's allocations
/// (`hw_io::rt_alloc::RtPoolAllocator`): without it the no-allocation check would pass vacuously,
/// so [`run`] only asserts it when this is true.
pub fn allocation_counting_active() -> bool {
    let (n, ()) = hw_io::rt_alloc::count_thread_allocs(|| {
        std::hint::black_box(Box::new(1u64));
    });
    n > 0
}

fn raw_frame(b: &mut Bytes<'_>) -> Option<CanFrame> {
    let id = b.u32();
    let flags = b.u8();
    let dlc = b.u8();
    let data = b.array::<8>();
    CanFrame::from_parts(id, flags & 1 == 1, flags & 2 == 2, dlc, data).ok()
}

fn message_frame(b: &mut Bytes<'_>) -> Option<CanFrame> {
    let kind = b.u8();
    let node = NodeId::new(1 + b.u8() % 5)?;
    let d = b.array::<8>();
    let msg = match kind % 4 {
        0 | 1 => Message::Tpdo {
            node,
            counts: [i32::from_le_bytes([d[0], d[1], d[2], d[3]]), i32::from_le_bytes([d[4], d[5], d[6], d[7]])],
        },
        2 => {
            let state = [NmtState::Operational, NmtState::PreOperational, NmtState::Stopped, NmtState::BootUp]
                [usize::from(d[0] % 4)];
            Message::Heartbeat { node, state }
        }
        _ => Message::Emcy {
            node,
            code: u16::from_le_bytes([d[0], d[1]]),
            register: d[2],
            vendor: [d[3], d[4], d[5], d[6], d[7]],
        },
    };
    msg.encode().ok()
}

/// The invariants of one cycle's output given its input (also used by the candump replay
/// target): a valid output has a complete, unflagged input, no invalidating flag and finite
/// floats; the fulcrum and trocar id are zero unless inside; the published sample reads back
/// with the same state and passes the subscriber's check.
pub fn check_output(cfg: &Config, input: &CycleInput, out: &CycleOutput) {
    let all = (1u8 << hw_io::can::ENCODER_NODES) - 1;
    if out.state.is_valid() {
        assert!(!out.health.intersects(HealthFlags::INVALIDATING), "valid with invalidating flags {}", out.health);
        assert!(!input.flags.intersects(HealthFlags::INVALIDATING), "valid from a flagged input {}", input.flags);
        assert_eq!(input.received_mask, all, "valid from an incomplete cycle: a stale estimate");
        let scalars = [out.residual_m, out.fulcrum_std_m, out.conditioning];
        let floats = out
            .fulcrum_base_m
            .iter()
            .chain(&scalars)
            .chain(&out.wrist_base_m)
            .chain(&out.axis_base)
            .chain(&out.joints_rad);
        for v in floats {
            assert!(v.is_finite(), "valid output with a non-finite float: {out:?}");
        }
        assert_eq!(out.joints_rad, cfg.bus.encoder.counts_to_rad(&input.counts));
    }
    if out.state != OutputState::Inside {
        assert_eq!(out.fulcrum_base_m, [0.0; 3], "a fulcrum published while not inside");
        assert_eq!(out.trocar_id, 0, "a trocar id published while not inside");
    }
    // Every input flag reaches the output.
    assert!(out.health.contains(input.flags), "flags lost: in {} out {}", input.flags, out.health);
    let sample = out.to_sample();
    assert_eq!(sample.state(), Ok(out.state));
    assert_eq!(sample.is_valid(), out.state.is_valid());
    assert!(ReceiveCheck::default().check(sample).is_ok(), "fulcrumd's own sample refused by a subscriber");
}
