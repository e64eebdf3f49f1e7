//! The endoscope-holder arm on the bus and in the world: its nodes answer exactly every 10th
//! SYNC with its joints, the motion is deterministic by seed, the tool arm's frames are
//! unchanged by it, and the default placement keeps the instrument in the endoscope's view.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use hw_io::can::{Message, SyncSource, TimedFrame};
use sim::endoscope::{InstrumentGeometry, StereoRenderer};
use sim::endoscope_arm::EndoscopeArmConfig;
use sim::twin::{SimRobot, TwinConfig};
use sim::world::{DEFAULT_KEEP_NS, World, default_endoscope_config};

const T0_US: u64 = 1_700_000_000_000_000;

fn small(cycles: usize, seed: u64) -> TwinConfig {
    let mut c = TwinConfig::default();
    c.scenario.seed = seed;
    c.scenario.cycles = cycles;
    c.scenario.inside_s = [2.0, 3.0];
    c.scenario.outside_s = [1.2, 1.8];
    c
}

fn run(robot: &mut SimRobot, max: u64, mut each: impl FnMut(&SimRobot, u8, u64, &[TimedFrame])) -> u64 {
    let mut sync = SyncSource::new();
    let mut n = 0;
    while n < max {
        let t_us = T0_US + n * 1000;
        let counter = sync.next_counter();
        let Some(frames) = robot.on_sync(counter, t_us).unwrap() else { break };
        each(robot, counter, t_us, &frames);
        n += 1;
    }
    n
}

#[test]
fn nodes_answer_exactly_every_tenth_sync_with_the_joints() {
    let cfg = small(1, 3);
    let e = cfg.endoscope_arm.clone();
    let mut robot = SimRobot::new(&cfg).unwrap();
    let (mut answered, mut syncs, mut beats) = (0u64, 0u64, [0u64; 2]);
    let rev = std::f64::consts::TAU / f64::from(e.counts_per_rev);
    let n = run(&mut robot, u64::MAX, |robot, counter, t_us, frames| {
        syncs += 1;
        let mut counts: [Option<[i32; 2]>; 2] = [None, None];
        for f in frames {
            match Message::decode(&f.frame).unwrap() {
                Message::Tpdo { node, counts: c } if node.get() == e.node_ids[0] => counts[0] = Some(c),
                Message::Tpdo { node, counts: c } if node.get() == e.node_ids[1] => counts[1] = Some(c),
                Message::Tpdo { node, .. } => assert!((1..=3).contains(&node.get()), "node {node}"),
                Message::Heartbeat { node, .. } if e.node_ids.contains(&node.get()) => {
                    assert_eq!(counter % 10, 5, "endoscope heartbeats away from its TPDOs");
                    beats[usize::from(node.get() == e.node_ids[1])] += 1;
                }
                _ => {}
            }
            assert!(f.unix_time_us >= t_us, "stamped after its SYNC");
        }
        assert_eq!(robot.endoscope_tpdos_sent(), counter.is_multiple_of(10));
        match counts {
            [Some(a), Some(b)] => {
                assert_eq!(counter % 10, 0, "TPDOs at counter {counter}");
                answered += 1;
                let q = e.counts_to_joints(&[a[0], a[1], b[0], b[1]]);
                let truth = robot.endoscope_joints().unwrap();
                for j in 0..4 {
                    let quantum = if j == 2 { 1.0 / f64::from(e.insertion_counts_per_m) } else { rev };
                    assert!((q[j] - truth[j]).abs() <= quantum / 2.0 + 1e-12, "joint {j}: {} vs {}", q[j], truth[j]);
                }
            }
            [None, None] => assert_ne!(counter % 10, 0, "no TPDOs at counter {counter}"),
            _ => panic!("only one endoscope node answered at counter {counter}"),
        }
    });
    assert!(n > 4000, "the scenario ran ({n} samples)");
    assert_eq!(answered, syncs / 10, "exactly every 10th SYNC");
    assert_eq!(robot.endoscope_nodes().unwrap().tpdos_sent(), 2 * answered);
    // One heartbeat per node per 100 ms.
    let expected = n.div_ceil(100);
    assert!(beats.iter().all(|&b| b.abs_diff(expected) <= 1), "{beats:?} heartbeats, {n} samples");
}

#[test]
fn the_tool_arms_frames_do_not_change_and_off_means_off() {
    let on = small(1, 5);
    let mut off = on.clone();
    off.endoscope_arm.enabled = false;
    let collect = |cfg: &TwinConfig| {
        let mut robot = SimRobot::new(cfg).unwrap();
        let mut frames = Vec::new();
        run(&mut robot, 3000, |_, _, _, f| frames.extend_from_slice(f));
        frames
    };
    let with = collect(&on);
    let without = collect(&off);
    let ecm = |f: &&TimedFrame| {
        matches!(Message::decode(&f.frame),
            Ok(Message::Tpdo { node, .. } | Message::Heartbeat { node, .. }) if node.get() >= 4)
    };
    assert!(without.iter().filter(ecm).count() == 0);
    assert_eq!(with.iter().filter(ecm).count(), 2 * 300 + 2 * 30, "2 TPDOs per 10 SYNCs, 2 heartbeats per 100");
    let tool: Vec<_> = with.iter().filter(|f| !ecm(f)).copied().collect();
    assert_eq!(tool, without, "the tool arm's frames are the same with the endoscope arm on the bus");
}

#[test]
fn motion_is_deterministic_by_seed() {
    let joints = |seed: u64| {
        let mut cfg = small(1, 2);
        cfg.endoscope_arm.seed = seed;
        let mut robot = SimRobot::new(&cfg).unwrap();
        let mut q = Vec::new();
        run(&mut robot, 20_000, |r, _, _, _| q.push(r.endoscope_joints().unwrap()));
        q
    };
    let a = joints(7);
    assert_eq!(a, joints(7));
    assert_ne!(a, joints(8));
    // It held and it moved: some samples equal their predecessor, some not.
    let moving = a.windows(2).filter(|w| w[0] != w[1]).count();
    assert!(moving > 500 && moving < a.len() - 5000, "{moving} moving samples of {}", a.len());
}

#[test]
fn a_clashing_node_id_is_refused() {
    let mut cfg = TwinConfig::default();
    cfg.endoscope_arm.node_ids = [2, 6];
    let err = SimRobot::new(&cfg).unwrap_err().to_string();
    assert!(err.contains("endoscope_arm.node_ids"), "{err}");
    let toml_text = "[endoscope_arm]\ntransmission_type = 7\n";
    let cfg: TwinConfig = toml::from_str(toml_text).unwrap();
    assert!(SimRobot::new(&cfg).unwrap_err().to_string().contains("transmission_type"));
    let cfg: TwinConfig = toml::from_str("[endoscope_arm]\nnode_ids = [9, 10]\n").unwrap();
    assert_eq!(cfg.endoscope_arm, EndoscopeArmConfig { node_ids: [9, 10], ..Default::default() });
}

/// Share of samples (every 33 ms) where the instrument's tip is in the left image, in front
/// of the tissue, over whole default scenarios.
fn tip_in_view_share(seed: u64) -> (f64, f64) {
    let mut cfg = TwinConfig::default();
    cfg.scenario.seed = seed;
    cfg.scenario.cycles = 4;
    let geom = InstrumentGeometry::default();
    let rcfg = default_endoscope_config();
    let mut small_cfg = rcfg.clone();
    small_cfg.tissue.texture_px = 16;
    small_cfg.tissue.grid = 2;
    let renderer = StereoRenderer::new(small_cfg, geom.mesh().unwrap()).unwrap();
    let mut world = World::new(&cfg, &geom, DEFAULT_KEEP_NS).unwrap();
    let mut robot = SimRobot::new(&cfg).unwrap();
    let (mut seen, mut total, mut inside, mut seen_inside) = (0u64, 0u64, 0u64, 0u64);
    run(&mut robot, u64::MAX, |robot, _, t_us, _| {
        let s = world.record(t_us * 1000, robot).unwrap();
        let s = &s;
        if !s.sample.is_multiple_of(33) {
            return;
        }
        let eye = renderer.eye_poses(&s.ecm_joints)[0];
        let tip = world.tip_in_ecm(s, &geom);
        let visible = tip.z < rcfg.tissue.plane_z_m - 0.01 && renderer.project_world(&eye, &tip).is_some();
        let is_inside = matches!(robot.truth().state, sim::scenario::TruthState::Inside { .. });
        total += 1;
        seen += u64::from(visible);
        inside += u64::from(is_inside);
        seen_inside += u64::from(visible && is_inside);
    });
    (seen as f64 / total as f64, seen_inside as f64 / inside.max(1) as f64)
}

#[test]
fn the_default_placement_keeps_the_tip_in_view_most_of_the_time() {
    for seed in 1..=3 {
        let (all, inside) = tip_in_view_share(seed);
        eprintln!(
            "seed {seed}: tip in the left image in {:.1} % of the samples, {:.1} % of those inside a trocar",
            all * 100.0,
            inside * 100.0
        );
        assert!(all > 0.7 && inside > 0.9, "seed {seed}: {all}");
    }
}

#[test]
fn the_world_puts_the_instrument_tip_at_the_scenarios_tip_and_interpolates() {
    let cfg = small(1, 4);
    let geom = InstrumentGeometry::default();
    let mut world = World::new(&cfg, &geom, 5_000_000).unwrap();
    let mut robot = SimRobot::new(&cfg).unwrap();
    let t_b_e = cfg.endoscope_arm.rcm_in_tool_base().unwrap();
    let l = cfg.scenario.instrument_length_m;
    let mut recorded = Vec::new();
    run(&mut robot, 3000, |robot, _, t_us, _| {
        let s = world.record(t_us * 1000, robot).unwrap();
        // The rendered jaw pivot is the scenario's true tip P + L·z, seen from {e}.
        let line = robot.truth().line;
        let tip_b = line.wrist_base_m + line.axis_base * l;
        let tip_e = t_b_e.inverse() * nalgebra::Point3::from(tip_b);
        assert!((world.tip_in_ecm(&s, &geom) - tip_e.coords).norm() < 1e-9, "sample {}", s.sample);
        // The instrument's z axis is the tool axis.
        let z_e = s.instrument_in_ecm.rotation * nalgebra::Vector3::z();
        assert!((z_e - t_b_e.inverse().rotation * line.axis_base).norm() < 1e-9);
        assert_eq!(s.ecm_joints, robot.endoscope_joints().unwrap());
        recorded.push(s);
    });
    // Only the kept span (5 ms) is remembered.
    let first = world.history().next().unwrap().t_ns;
    assert_eq!(first, recorded[recorded.len() - 6].t_ns);
    let (a, b) = (&recorded[2994], &recorded[2995]);
    assert!(world.covers(a.t_ns, b.t_ns) && !world.covers(recorded[0].t_ns, b.t_ns));
    // Halfway between two samples: halfway joints and poses; outside the kept span, the ends.
    let mid = world.scene_at((a.t_ns + b.t_ns) / 2).unwrap();
    for j in 0..4 {
        assert!((mid.ecm_joints[j] - (a.ecm_joints[j] + b.ecm_joints[j]) / 2.0).abs() < 1e-12);
    }
    let pa = a.instrument_in_ecm.translation.vector;
    let pb = b.instrument_in_ecm.translation.vector;
    assert!((mid.instrument.pose_world.translation.vector - (pa + pb) / 2.0).norm() < 1e-12);
    assert_eq!(world.scene_at(a.t_ns).unwrap().instrument.pose_world, a.instrument_in_ecm);
    let last = recorded.last().unwrap();
    assert_eq!(world.scene_at(last.t_ns + 1_000_000_000).unwrap().ecm_joints, last.ecm_joints);
    assert_eq!(world.scene_at(0).unwrap().ecm_joints, world.history().next().unwrap().ecm_joints);
    assert!(matches!(world.record(0, &robot), Err(sim::world::WorldError::Order { .. })));
    // No endoscope arm, no world.
    let mut off = cfg.clone();
    off.endoscope_arm.enabled = false;
    assert!(World::new(&off, &geom, 0).is_err());
}
