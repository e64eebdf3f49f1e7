//! The subscriber's check of fulcrumd's samples (`hw_io::ipc::ReceiveCheck`, what
//! `Subscriber::try_recv` runs on every message): arbitrary 200-byte payloads.

use hw_io::ipc::{FULCRUM_SAMPLE_VERSION, FulcrumSample, HealthFlags, ReceiveCheck};

use crate::Bytes;

/// Size of a [`FulcrumSample`], bytes.
pub const SAMPLE_BYTES: usize = core::mem::size_of::<FulcrumSample>();

/// `data` as a sequence of 200-byte samples (the last zero-padded) through one
/// [`ReceiveCheck`]: each is refused or accepted with its invariants holding (the layout
/// version; a valid sample has finite floats and no invalidating flag).
pub fn run(data: &[u8]) {
    let mut check = ReceiveCheck::default();
    for chunk in data.chunks(SAMPLE_BYTES) {
        let sample = sample_from_bytes(chunk);
        let before = check.counters();
        match check.check(sample) {
            Ok(r) => {
                assert_eq!(r.sample.version, FULCRUM_SAMPLE_VERSION);
                if r.sample.is_valid() {
                    assert!(!r.sample.health().intersects(HealthFlags::INVALIDATING));
                    let s = &r.sample;
                    let scalars = [s.residual_m, s.fulcrum_std_m, s.conditioning];
                    let floats = s
                        .fulcrum_base_m
                        .iter()
                        .chain(&scalars)
                        .chain(&s.wrist_base_m)
                        .chain(&s.axis_base)
                        .chain(&s.joints_rad);
                    for v in floats {
                        assert!(v.is_finite(), "accepted a valid sample with a non-finite float");
                    }
                }
                if let Some(f) = r.sample.fulcrum() {
                    assert!(f.iter().all(|v| v.is_finite()));
                }
                assert!(check.counters().received >= before.received);
            }
            Err(_) => assert!(check.counters().rejected >= before.rejected),
        }
    }
}

/// A sample with the fields of `bytes` (little-endian, the C layout's order; zeros past the end).
pub fn sample_from_bytes(bytes: &[u8]) -> FulcrumSample {
    let mut s = FulcrumSample::invalid(HealthFlags::empty());
    let mut b = Bytes::new(bytes);
    s.version = b.u32();
    s.state = b.u32();
    s.sequence = b.u64();
    s.run_id = b.u64();
    s.timestamp_ns = b.u64();
    s.health = b.u32();
    s.trocar_id = b.u32();
    let fl = |b: &mut Bytes<'_>| f64::from_bits(b.u64());
    s.fulcrum_base_m = [fl(&mut b), fl(&mut b), fl(&mut b)];
    s.residual_m = fl(&mut b);
    s.fulcrum_std_m = fl(&mut b);
    s.conditioning = fl(&mut b);
    s.wrist_base_m = [fl(&mut b), fl(&mut b), fl(&mut b)];
    s.axis_base = [fl(&mut b), fl(&mut b), fl(&mut b)];
    s.joints_rad = core::array::from_fn(|_| fl(&mut b));
    s.window_fill = b.u16();
    s.window_len = b.u16();
    s.fit_lines = b.u16();
    s.reserved = b.u16();
    s.wake_late_ns = b.u32();
    s.prev_cycle_compute_ns = b.u32();
    s
}
