//! fulcrumd ignores the endoscope-holder arm's encoder nodes on its bus (`bus.other_node_ids`,
//! `docs/can-protocol.md`): the same simulated run, as a candump log with and without them,
//! gives sample for sample the same estimates, no health flag, no bad frame; their frames are
//! counted as frames of other nodes.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use controller::config::Config;
use controller::replay::{LogReplay, replay_candump_reader};
use hw_io::can::candump::CandumpWriter;
use hw_io::can::{CanFrame, SYNC_COB_ID, SyncSource, TimedFrame};
use hw_io::ipc::OutputState;
use sim::twin::{SimRobot, TwinConfig};

/// A candump log of a whole simulated run, as `simrobot generate` writes it, and the number
/// of the endoscope arm's frames in it.
fn bus_log(endoscope: bool) -> (Vec<u8>, u64) {
    let mut cfg = TwinConfig::default();
    cfg.scenario.cycles = 2;
    cfg.scenario.inside_s = [4.0, 5.0];
    cfg.scenario.outside_s = [1.5, 2.0];
    cfg.endoscope_arm.enabled = endoscope;
    let mut robot = SimRobot::new(&cfg).unwrap();
    let mut w = CandumpWriter::new(Vec::new(), "vcan0").unwrap();
    let mut sync = SyncSource::new();
    let mut ecm = 0;
    for i in 0u64.. {
        let t_us = 1_700_000_000_000_000 + i * 1000;
        let counter = sync.next_counter();
        let Some(frames) = robot.on_sync(counter, t_us).unwrap() else { break };
        w.write(&TimedFrame { frame: CanFrame::new_standard(SYNC_COB_ID, &[counter]).unwrap(), unix_time_us: t_us })
            .unwrap();
        for f in &frames {
            w.write(f).unwrap();
            ecm += u64::from(cfg.endoscope_arm.node_ids.contains(&((f.frame.id().raw() & 0x7F) as u8)));
        }
    }
    (w.into_inner(), ecm)
}

fn replay(log: &[u8], cfg: &Config) -> LogReplay {
    replay_candump_reader(log, cfg).unwrap()
}

#[test]
fn estimates_are_identical_with_and_without_the_endoscope_nodes() {
    let (with, ecm_frames) = bus_log(true);
    let (without, none) = bus_log(false);
    assert_eq!(none, 0);
    assert!(ecm_frames > 2000, "{ecm_frames} endoscope frames: the scenario happened");
    let cfg = Config::default();
    assert_eq!(cfg.bus.other_node_ids, [4, 5], "the default configuration expects the endoscope arm");
    let a = replay(&with, &cfg);
    let b = replay(&without, &cfg);
    assert_eq!(a.cycles.len(), b.cycles.len());
    assert!(a.cycles.len() > 10_000);
    for (k, (x, y)) in a.cycles.iter().zip(&b.cycles).enumerate() {
        assert_eq!(x.input, y.input, "cycle {k}: acquisition");
        assert_eq!(x.output, y.output, "cycle {k}: estimate");
        assert!(x.input.flags.is_empty(), "cycle {k}: health {:?}", x.input.flags);
    }
    let inside = a.cycles.iter().filter(|c| c.output.state == OutputState::Inside).count();
    assert!(inside > 3000, "the detector found the trocars ({inside} cycles inside)");
    let (s, s0) = (a.acquisition, b.acquisition);
    assert_eq!(s.other_node_frames, ecm_frames, "every endoscope frame counted as another node's");
    assert_eq!(s0.other_node_frames, 0);
    for (name, v) in [
        ("unknown_id_frames", s.unknown_id_frames),
        ("wrong_dlc_frames", s.wrong_dlc_frames),
        ("malformed_frames", s.malformed_frames),
        ("foreign_node_frames", s.foreign_node_frames),
        ("duplicate_tpdos", s.duplicate_tpdos),
        ("emcy_frames", s.emcy_frames),
        ("incomplete_cycles", s.incomplete_cycles),
    ] {
        assert_eq!(v, 0, "{name}");
    }
    assert_eq!(s.frames, s0.frames + ecm_frames);

    // Without the list they are foreign nodes: counted as such, and still harmless.
    let mut bare = Config::default();
    bare.bus.other_node_ids.clear();
    let c = replay(&with, &bare);
    assert_eq!(c.acquisition.foreign_node_frames, ecm_frames);
    assert!(c.cycles.iter().zip(&b.cycles).all(|(x, y)| x.output == y.output));
}

#[test]
fn other_node_ids_are_validated() {
    for (text, bad) in [("[4, 4]", true), ("[2]", true), ("[0]", true), ("[4, 5, 9]", false), ("[]", false)] {
        let toml_text = format!("[bus]\nother_node_ids = {text}\n");
        let r = Config::from_toml(&toml_text, std::path::Path::new("t.toml"));
        assert_eq!(r.is_err(), bad, "{text}: {r:?}");
        if let Err(e) = r {
            assert!(e.to_string().contains("bus.other_node_ids"), "{e}");
        }
    }
}
