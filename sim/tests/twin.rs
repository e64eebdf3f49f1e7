//! The simulated robot on the bus: what the controller decodes from its frames, its ground
//! truth and events, endless mode, node faults from the config, and the statistics of the
//! motion against the configuration.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::kinematics::Achilles;
use hw_io::can::{JointAssembler, Message, NodeId, SyncSource, TimedFrame};
use nalgebra::Vector3;
use sim::encoders::EmcyInjection;
use sim::robot::IkError;
use sim::scenario::{ScenarioConfig, TruthState};
use sim::twin::{ModelErrorConfig, SimRobot, TwinConfig, TwinError, TwinEvent};

/// A short scenario (about 6 s per cycle) so that debug-built tests stay fast.
fn small(cycles: usize, seed: u64) -> TwinConfig {
    let mut c = TwinConfig::default();
    c.scenario.seed = seed;
    c.scenario.cycles = cycles;
    c.scenario.inside_s = [2.0, 3.0];
    c.scenario.outside_s = [1.2, 1.8];
    c
}

/// Unix time of the first SYNC, microseconds (the `generate` epoch).
const T0_US: u64 = 1_700_000_000_000_000;

/// Runs the twin to the end (or `max` samples), calling `each` with the frames of every SYNC.
fn run(robot: &mut SimRobot, max: u64, mut each: impl FnMut(&SimRobot, u64, &[TimedFrame])) -> u64 {
    let mut sync = SyncSource::new();
    let mut n = 0;
    while n < max {
        let t_us = T0_US + n * 1000;
        let Some(frames) = robot.on_sync(sync.next_counter(), t_us).unwrap() else { break };
        each(robot, t_us, &frames);
        n += 1;
    }
    n
}

/// Largest wrist (metres) and axis (radians) error of the line the controller computes from
/// the frames (assembler, counts to radians, nominal forward kinematics) against `target`.
fn decoded_errors(config: &TwinConfig, target: impl Fn(&SimRobot) -> (Vector3<f64>, Vector3<f64>)) -> (f64, f64) {
    let mut robot = SimRobot::new(config).unwrap();
    let nominal = Achilles::new(&config.kinematics).unwrap();
    let mut assembler = JointAssembler::from_config(&config.encoder).unwrap();
    let (mut wrist, mut axis) = (0.0_f64, 0.0_f64);
    run(&mut robot, u64::MAX, |robot, _, frames| {
        assembler.start_cycle();
        for f in frames {
            // The endoscope arm's TPDOs (nodes 4 and 5, every 10th SYNC) are not the tool arm's.
            if let Ok(msg @ Message::Tpdo { node, .. }) = Message::decode(&f.frame)
                && config.encoder.node_ids.contains(&node.get())
            {
                assembler.accept(&msg).unwrap();
            }
        }
        let q = config.encoder.counts_to_rad(&assembler.counts().unwrap());
        let pose = nominal.forward(&q).unwrap();
        let (w, a) = target(robot);
        wrist = wrist.max((pose.wrist_base_m - w).norm());
        axis = axis.max(pose.axis_base.dot(&a).clamp(-1.0, 1.0).acos());
    });
    (wrist, axis)
}

fn truth_line(robot: &SimRobot) -> (Vector3<f64>, Vector3<f64>) {
    (robot.truth().line.wrist_base_m, robot.truth().line.axis_base)
}

#[test]
fn without_model_error_the_decoded_line_is_the_truth_within_quantisation() {
    let config = TwinConfig { model_error: ModelErrorConfig::zero(), ..small(1, 3) };
    let (wrist_m, axis_rad) = decoded_errors(&config, truth_line);
    eprintln!("no model error: wrist within {wrist_m:e} m, axis within {axis_rad:e} rad");
    // One count is 2π / 2^17 = 48 µrad per joint; rounding gives half of it, over a
    // 0.6 m arm some 15 µm at the wrist.
    assert!(wrist_m < 5e-5, "wrist off by {wrist_m} m");
    assert!(axis_rad < 2e-4, "axis off by {axis_rad} rad");
    assert!(wrist_m > 1e-7, "no quantisation at all? {wrist_m} m");
}

#[test]
fn with_the_default_model_error_the_decoded_line_is_biased() {
    let config = small(1, 3);
    assert_ne!(config.model_error, ModelErrorConfig::zero(), "the default has a calibration error");
    let (wrist_m, axis_rad) = decoded_errors(&config, truth_line);
    eprintln!("default model error: wrist off by up to {wrist_m:e} m, axis by {axis_rad:e} rad");
    assert!(wrist_m > 2e-4, "±0.5 mm / ±1 mrad should bias the wrist by a fraction of a millimetre: {wrist_m} m");
    assert!(wrist_m < 5e-3, "bias {wrist_m} m is too large for ±0.5 mm / ±1 mrad");
    assert!(axis_rad > 1e-4, "axis bias {axis_rad} rad");
}

#[test]
fn measurement_noise_option_moves_the_arm_along_the_measured_line() {
    let config = TwinConfig { model_error: ModelErrorConfig::zero(), measurement_noise: true, ..small(1, 4) };
    // The decoded line follows the scenario's noisy measured line ...
    let measured = |r: &SimRobot| {
        let k = (r.sample().unwrap() - r.scenario_start_sample()) as usize;
        let m = r.scenario().measured[k];
        (m.wrist_base_m, m.axis_base)
    };
    let (wrist_m, _) = decoded_errors(&config, measured);
    assert!(wrist_m < 5e-5, "decoded line off the measured line by {wrist_m} m");
    // ... which is off the truth by the configured noise (0.1 mm per axis, one sigma).
    let (wrist_m, _) = decoded_errors(&config, truth_line);
    assert!(wrist_m > 2e-4, "noise not applied: {wrist_m} m");
}

#[test]
fn a_finite_scenario_ends_and_its_events_are_reported_once_at_their_sample() {
    let config = small(2, 5);
    let mut robot = SimRobot::new(&config).unwrap();
    let scenario = robot.scenario().clone();
    let mut events: Vec<TwinEvent> = Vec::new();
    let mut states = Vec::new();
    let n = run(&mut robot, u64::MAX, |r, t_us, frames| {
        let tool_tpdo =
            |f: &&TimedFrame| matches!(Message::decode(&f.frame), Ok(Message::Tpdo { node, .. }) if node.get() <= 3);
        assert_eq!(frames.iter().filter(tool_tpdo).count(), 3);
        assert!(frames.iter().all(|f| f.unix_time_us == t_us + 100), "frames stamped SYNC + 100 us latency");
        for e in r.events() {
            assert_eq!(e.unix_time_us, t_us);
            events.push(*e);
        }
        states.push(r.truth().state);
    });
    assert_eq!(n as usize, scenario.truth.len());
    assert!(robot.is_done());
    assert_eq!(robot.on_sync(1, 0).unwrap(), None);
    assert_eq!(events.len(), 4);
    for (e, s) in events.iter().zip(&scenario.events) {
        assert_eq!((e.sample as usize, e.trocar, e.insertion), (s.sample, s.trocar, s.insertion));
        assert!((e.t_s - e.sample as f64 * 0.001).abs() < 1e-9);
        // The event's sample is the first sample of the new state.
        let before = states[e.sample as usize - 1];
        let after = states[e.sample as usize];
        if e.insertion {
            assert_eq!((before, after), (TruthState::Outside, TruthState::Inside { index: e.trocar }));
        } else {
            assert_eq!((before, after), (TruthState::Inside { index: e.trocar }, TruthState::Outside));
        }
    }
    assert_eq!(robot.samples_done(), n);
    assert_eq!(robot.nodes().tpdos_sent(0), n);
}

#[test]
fn endless_mode_goes_on_with_the_next_seed_continuously() {
    let config = TwinConfig { endless: true, ..small(1, 10) };
    let mut robot = SimRobot::new(&config).unwrap();
    let first_len = robot.scenario().truth.len() as u64;
    let mut seeds = vec![robot.scenario_seed()];
    let mut starts = vec![0];
    let mut events: Vec<TwinEvent> = Vec::new();
    let mut prev: Option<(Vector3<f64>, Vector3<f64>)> = None;
    let (mut max_step, mut max_turn) = (0.0_f64, 0.0_f64);
    let mut transition_samples = 0;
    run(&mut robot, 3 * first_len, |r, _, _| {
        if r.scenario_seed() != *seeds.last().unwrap() {
            seeds.push(r.scenario_seed());
            starts.push(r.scenario_start_sample());
        }
        if r.in_transition() {
            transition_samples += 1;
            assert_eq!(r.truth().state, TruthState::Outside);
            assert_eq!(r.truth().fulcrum_base_m, None);
        }
        let (w, a) = truth_line(r);
        if let Some((pw, pa)) = prev {
            max_step = max_step.max((w - pw).norm());
            max_turn = max_turn.max((a - pa).norm());
        }
        prev = Some((w, a));
        events.extend_from_slice(r.events());
        assert!((r.truth().t_s - r.sample().unwrap() as f64 * 0.001).abs() < 1e-9, "t_s is run time");
    });
    assert!(seeds.len() >= 3, "seeds {seeds:?}");
    assert_eq!(&seeds[..3], &[10, 11, 12]);
    assert_eq!(starts[0], 0);
    assert!(starts[1] > first_len, "a transition precedes the second scenario");
    assert!(transition_samples >= 500, "{transition_samples} transition samples");
    // Continuous everywhere, transitions included: under 2 mm and 0.01 per 1 ms sample.
    assert!(max_step < 0.002, "wrist jumps {max_step} m");
    assert!(max_turn < 0.01, "axis jumps {max_turn}");
    // Events carry run sample indices, increasing, alternating insertion / extraction.
    assert!(events.len() >= 4);
    for (k, w) in events.windows(2).enumerate() {
        assert!(w[1].sample > w[0].sample);
        assert_eq!(w[0].insertion, k % 2 == 0);
    }
    assert!(events.iter().any(|e| e.sample > starts[1]));
}

#[test]
fn node_faults_of_the_config_count_from_the_first_sync() {
    let mut config = small(1, 6);
    config.nodes[1].dropout_windows_us = vec![[10_000, 20_000]];
    config.nodes[2].emcy =
        vec![EmcyInjection { at_us: 5_000, duration_us: 3_000, code: 0x7305, register: 1, vendor: [0; 5] }];
    config.nodes[0].latency_us = 300;
    let mut robot = SimRobot::new(&config).unwrap();
    let mut emcys = Vec::new();
    let mut missing_node2 = Vec::new();
    run(&mut robot, 100, |_, t_us, frames| {
        let rel = t_us - T0_US;
        let mut node2 = false;
        for f in frames {
            match Message::decode(&f.frame) {
                Ok(Message::Emcy { node, code, .. }) => emcys.push((rel, node.get(), code)),
                Ok(Message::Tpdo { node, .. }) => {
                    node2 |= node == NodeId::new(2).unwrap();
                    let latency = if node.get() == 1 { 300 } else { 100 };
                    assert_eq!(f.unix_time_us, t_us + latency);
                }
                _ => {}
            }
        }
        if !node2 {
            missing_node2.push(rel);
        }
    });
    assert_eq!(emcys, vec![(5_000, 3, 0x7305), (8_000, 3, 0)]);
    assert_eq!(missing_node2, (10..20).map(|k| k * 1000).collect::<Vec<u64>>());
}

#[test]
fn an_unreachable_line_is_an_error_and_nothing_advances() {
    let mut config = small(1, 7);
    config.scenario.trocars_base_m = vec![[1.5, 0.0, 0.0]];
    let mut robot = SimRobot::new(&config).unwrap();
    // The start pose is reachable; the way to the trocar 1.5 m away is not.
    let mut t_us = 0;
    let err = loop {
        match robot.on_sync(1, t_us) {
            Ok(Some(_)) => t_us += 1000,
            Ok(None) => panic!("the scenario ended without an error"),
            Err(e) => break e,
        }
    };
    let done = robot.samples_done();
    assert!(done > 0);
    let TwinError::Ik { sample, source: IkError::NotConverged { .. } } = err else { panic!("{err:?}") };
    assert_eq!(sample, done, "the error names the sample");
    assert!(err.to_string().starts_with(&format!("sample {done}: inverse kinematics")), "{err}");
    // Retrying fails the same way at the same sample: nothing advanced.
    assert_eq!(robot.on_sync(2, t_us + 1000).unwrap_err(), err);
    assert_eq!(robot.samples_done(), done);
    assert_eq!(robot.nodes().tpdos_sent(0), done);
}

/// Angle between two unit vectors, radians.
fn angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b))
}

struct Stats {
    inside_s: Vec<f64>,
    outside_s: Vec<f64>,
    max_rate_rad_s: f64,
    mean_rate_rad_s: f64,
}

fn statistics(scenario: ScenarioConfig) -> Stats {
    let config = TwinConfig { scenario, ..TwinConfig::default() };
    let mut robot = SimRobot::new(&config).unwrap();
    let mut events: Vec<TwinEvent> = Vec::new();
    let mut prev_axis: Option<Vector3<f64>> = None;
    let (mut max_rate, mut sum_rate, mut n_inside) = (0.0_f64, 0.0, 0usize);
    run(&mut robot, u64::MAX, |r, _, _| {
        events.extend_from_slice(r.events());
        let axis = r.truth().line.axis_base;
        if let (Some(p), TruthState::Inside { .. }) = (prev_axis, r.truth().state) {
            let rate = angle(&p, &axis) / 0.001;
            max_rate = max_rate.max(rate);
            sum_rate += rate;
            n_inside += 1;
        }
        prev_axis = Some(axis);
    });
    let mut s = Stats { inside_s: vec![], outside_s: vec![], max_rate_rad_s: max_rate, mean_rate_rad_s: 0.0 };
    s.mean_rate_rad_s = sum_rate / n_inside as f64;
    for w in events.windows(2) {
        let dt = w[1].t_s - w[0].t_s;
        if w[0].insertion {
            assert_eq!(w[0].trocar, w[1].trocar, "extraction from the trocar inserted into");
            s.inside_s.push(dt);
        } else {
            assert_ne!(w[0].trocar, w[1].trocar, "the next cycle goes to another trocar");
            s.outside_s.push(dt);
        }
    }
    s
}

#[test]
fn motion_statistics_match_the_configuration() {
    let mut cfg = TwinConfig::default().scenario;
    cfg.cycles = 4;
    cfg.seed = 21;
    cfg.inside_s = [3.0, 5.0];
    cfg.outside_s = [1.6, 2.6];
    let s = statistics(cfg.clone());
    eprintln!(
        "inside {:?} s, outside {:?} s, axis speed inside: max {:.3} rad/s, mean {:.3} rad/s",
        s.inside_s, s.outside_s, s.max_rate_rad_s, s.mean_rate_rad_s
    );
    assert_eq!(s.inside_s.len(), 4);
    assert_eq!(s.outside_s.len(), 3);
    // Inside time = inside_s, minus the approach (3 cm at 8-16 cm/s: 0.19-0.38 s), plus the
    // way out from the final depth (2-14 cm: 0.13-1.75 s).
    for &t in &s.inside_s {
        assert!((cfg.inside_s[0] - 0.3..=cfg.inside_s[1] + 1.6).contains(&t), "inside {t} s");
    }
    // Outside time = outside_s plus the last 3 cm out and the first 3 cm in (0.38-0.75 s).
    for &t in &s.outside_s {
        assert!((cfg.outside_s[0] + 0.3..=cfg.outside_s[1] + 0.8).contains(&t), "outside {t} s");
    }
    // Angular speed of the axis while inside: pitch and yaw are sums of three sinusoids of
    // amplitude at most A / 1.8 and frequency at most f_max, so at most
    // sqrt(2) · 3 · A / 1.8 · 2π f_max.
    let a = cfg.pivot_amplitude_deg.to_radians();
    let bound = 2f64.sqrt() * 3.0 * a / 1.8 * std::f64::consts::TAU * cfg.pivot_frequency_hz[1];
    assert!(s.max_rate_rad_s <= bound * 1.01, "max {} rad/s above the bound {bound}", s.max_rate_rad_s);
    assert!(s.max_rate_rad_s > 0.1 * bound, "max {} rad/s: hardly any pivoting", s.max_rate_rad_s);
    // Half the amplitude: the same random draws, so exactly half the angular speed.
    let half = statistics(ScenarioConfig { pivot_amplitude_deg: cfg.pivot_amplitude_deg / 2.0, ..cfg });
    let ratio = half.mean_rate_rad_s / s.mean_rate_rad_s;
    assert!((ratio - 0.5).abs() < 0.01, "mean angular speed ratio {ratio}");
    assert_eq!(half.inside_s, s.inside_s);
}
