//! Bus-load arithmetic for classic CAN with 11-bit identifiers (see `docs/can-protocol.md`).
//!
//! A base-format data frame with `n` data bytes has `47 + 8n` bits including the 3-bit
//! interframe space; the `34 + 8n` bits from start-of-frame to the end of the CRC are
//! subject to bit stuffing, at worst one stuff bit per 4 bits after the first:
//! `⌊(34 + 8n − 1) / 4⌋` (Davis et al., "Controller Area Network (CAN) schedulability
//! analysis: refuted, revisited and revised", 2007).
//!
//! ```
//! use hw_io::can::bus_load;
//! assert_eq!(bus_load::worst_case_frame_bits(8), 135);
//! assert_eq!(bus_load::worst_case_frame_bits(1), 65);
//! let load = bus_load::encoder_bus_worst_case_load(3, 1_000_000);
//! assert!(load <= bus_load::MAX_LOAD); // 47.2 % <= 60 %
//! // With the endoscope arm's two nodes answering every 10th SYNC (transmission type 10):
//! let load = bus_load::mixed_bus_worst_case_load(3, 2, 10, 1_000_000);
//! assert!((load - 0.500_25).abs() < 1e-9); // 50.0 %
//! ```

use super::protocol::{HEARTBEAT_DLC, SYNC_DLC, TPDO_DLC};

/// Bit rate of the encoder bus, bit/s.
pub const BITRATE_BIT_PER_S: u32 = 1_000_000;
/// SYNC period, microseconds.
pub const SYNC_PERIOD_US: u32 = 1_000;
/// Heartbeat period of each node, microseconds.
pub const HEARTBEAT_PERIOD_US: u32 = 100_000;
/// Highest allowed bus load, as a fraction of the bit rate (60 %).
pub const MAX_LOAD: f64 = 0.60;

/// Bits of a base-format (11-bit ID) data frame without stuff bits, including the 3-bit
/// interframe space: `47 + 8·dlc`. `dlc` above 8 counts as 8.
pub const fn nominal_frame_bits(dlc: u8) -> u32 {
    let n = if dlc > 8 { 8 } else { dlc as u32 };
    47 + 8 * n
}

/// Worst-case stuff bits of a base-format data frame: `⌊(34 + 8·dlc − 1) / 4⌋`.
pub const fn worst_case_stuff_bits(dlc: u8) -> u32 {
    let n = if dlc > 8 { 8 } else { dlc as u32 };
    (34 + 8 * n - 1) / 4
}

/// Worst-case bits of a base-format data frame on the wire, interframe space included.
pub const fn worst_case_frame_bits(dlc: u8) -> u32 {
    nominal_frame_bits(dlc) + worst_case_stuff_bits(dlc)
}

/// Worst-case bits per SYNC period (1 ms): one SYNC, one TPDO1 per node, and the nodes'
/// heartbeats averaged over their 100 ms period.
pub fn encoder_bus_worst_case_bits_per_period(nodes: u32) -> f64 {
    let cyclic = worst_case_frame_bits(SYNC_DLC) + nodes * worst_case_frame_bits(TPDO_DLC);
    let heartbeats = f64::from(nodes * worst_case_frame_bits(HEARTBEAT_DLC)) * f64::from(SYNC_PERIOD_US)
        / f64::from(HEARTBEAT_PERIOD_US);
    f64::from(cyclic) + heartbeats
}

/// Worst-case bus load of the encoder protocol as a fraction of `bitrate_bit_per_s`
/// (0.472 for 3 nodes at 1 Mbit/s).
pub fn encoder_bus_worst_case_load(nodes: u32, bitrate_bit_per_s: u32) -> f64 {
    let bits_per_s = encoder_bus_worst_case_bits_per_period(nodes) * 1e6 / f64::from(SYNC_PERIOD_US);
    bits_per_s / f64::from(bitrate_bit_per_s.max(1))
}

/// Worst-case bits per SYNC period (1 ms) of a bus with `nodes` answering every SYNC and
/// `slow_nodes` answering every `slow_every`-th SYNC (CANopen transmission type
/// `slow_every`, e.g. the endoscope arm's nodes at 10), one TPDO1 each, every node with a
/// heartbeat every 100 ms, averaged. `slow_every` 0 counts as 1.
pub fn mixed_bus_worst_case_bits_per_period(nodes: u32, slow_nodes: u32, slow_every: u32) -> f64 {
    let slow = f64::from(slow_nodes * worst_case_frame_bits(TPDO_DLC)) / f64::from(slow_every.max(1));
    let heartbeats = f64::from((nodes + slow_nodes) * worst_case_frame_bits(HEARTBEAT_DLC)) * f64::from(SYNC_PERIOD_US)
        / f64::from(HEARTBEAT_PERIOD_US);
    f64::from(worst_case_frame_bits(SYNC_DLC) + nodes * worst_case_frame_bits(TPDO_DLC)) + slow + heartbeats
}

/// [`mixed_bus_worst_case_bits_per_period`] as a fraction of `bitrate_bit_per_s` (0.500 25
/// for the tool arm's 3 nodes and the endoscope arm's 2 at type 10, at 1 Mbit/s).
pub fn mixed_bus_worst_case_load(nodes: u32, slow_nodes: u32, slow_every: u32, bitrate_bit_per_s: u32) -> f64 {
    let bits_per_s =
        mixed_bus_worst_case_bits_per_period(nodes, slow_nodes, slow_every) * 1e6 / f64::from(SYNC_PERIOD_US);
    bits_per_s / f64::from(bitrate_bit_per_s.max(1))
}

/// Worst-case bits of the busiest SYNC period, heartbeats aside: the SYNC and the TPDO1 of
/// every node, `nodes` every-SYNC nodes and `slow_nodes` nodes of a slower transmission type
/// whose turn it is (740 bits, 74 % of a 1 ms period at 1 Mbit/s, for 3 + 2).
pub const fn worst_case_peak_bits_per_period(nodes: u32, slow_nodes: u32) -> u32 {
    worst_case_frame_bits(SYNC_DLC) + (nodes + slow_nodes) * worst_case_frame_bits(TPDO_DLC)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The numbers quoted in docs/can-protocol.md.
    #[test]
    fn numbers_in_the_protocol_doc() {
        assert_eq!(nominal_frame_bits(1), 55);
        assert_eq!(worst_case_stuff_bits(1), 10);
        assert_eq!(worst_case_frame_bits(1), 65);
        assert_eq!(nominal_frame_bits(8), 111);
        assert_eq!(worst_case_stuff_bits(8), 24);
        assert_eq!(worst_case_frame_bits(8), 135);
        assert_eq!(worst_case_frame_bits(1) + 3 * worst_case_frame_bits(8), 470);
        assert!((encoder_bus_worst_case_bits_per_period(3) - 471.95).abs() < 1e-9);
        let load = encoder_bus_worst_case_load(3, BITRATE_BIT_PER_S);
        assert!((load - 0.47195).abs() < 1e-9);
        assert!(load <= MAX_LOAD);
    }

    /// The numbers of docs/can-protocol.md with the endoscope arm's two nodes at type 10.
    #[test]
    fn numbers_with_the_endoscope_arm() {
        // Without slow nodes the mixed formula is the encoder bus's.
        assert!(
            (mixed_bus_worst_case_bits_per_period(3, 0, 10) - encoder_bus_worst_case_bits_per_period(3)).abs() < 1e-9
        );
        // 470 + 2 × 135 / 10 = 497 bit/ms cyclic, 5 × 65 / 100 = 3.25 bit/ms of heartbeats.
        assert!((mixed_bus_worst_case_bits_per_period(3, 2, 10) - 500.25).abs() < 1e-9);
        let load = mixed_bus_worst_case_load(3, 2, 10, BITRATE_BIT_PER_S);
        assert!((load - 0.50025).abs() < 1e-9);
        assert!(load <= MAX_LOAD);
        // At every SYNC instead, the two nodes would break the budget (a fifth TPDO per ms).
        assert!(mixed_bus_worst_case_load(3, 2, 1, BITRATE_BIT_PER_S) > MAX_LOAD);
        // The busiest millisecond: SYNC and five TPDOs, 740 bits; with the tool nodes'
        // heartbeats in it too, 935 bits: still within the 1000-bit period.
        assert_eq!(worst_case_peak_bits_per_period(3, 2), 740);
        assert_eq!(worst_case_peak_bits_per_period(3, 2) + 3 * worst_case_frame_bits(HEARTBEAT_DLC), 935);
        assert_eq!(worst_case_peak_bits_per_period(3, 0), 470);
    }

    #[test]
    fn stuffing_bound_matches_a_brute_force_count() {
        // Worst case over all payloads is hard to enumerate; check the bound is reached by
        // the classic pattern (alternating runs of 4 equal bits after the first 5) and never
        // exceeded for a few thousand pseudo-random frames.
        fn stuff_bits(bits: &[u8]) -> u32 {
            let (mut count, mut run, mut last, mut out) = (0u32, 0u32, 2u8, Vec::new());
            for &b in bits {
                if b == last {
                    run += 1;
                } else {
                    last = b;
                    run = 1;
                }
                out.push(b);
                if run == 5 {
                    count += 1;
                    last = 1 - b;
                    run = 1;
                    out.push(last);
                }
            }
            count
        }
        let mut x = 0x1234_5678u32;
        for dlc in 0..=8u8 {
            let len = 34 + 8 * usize::from(dlc);
            for _ in 0..500 {
                let bits: Vec<u8> = (0..len)
                    .map(|_| {
                        x ^= x << 13;
                        x ^= x >> 17;
                        x ^= x << 5;
                        (x & 1) as u8
                    })
                    .collect();
                assert!(stuff_bits(&bits) <= worst_case_stuff_bits(dlc));
            }
            // 5 equal bits, then runs of 4 alternating: each run triggers a stuff bit.
            let mut bits = vec![0u8; 5];
            let mut v = 1u8;
            while bits.len() < len {
                bits.extend(std::iter::repeat_n(v, 4));
                v = 1 - v;
            }
            bits.truncate(len);
            assert_eq!(stuff_bits(&bits), worst_case_stuff_bits(dlc), "dlc {dlc}");
        }
    }
}
