//! End to end: scenario → inverse kinematics on the true arm → virtual encoder nodes →
//! CAN frames → decode and assemble (hw-io) → counts to radians → nominal forward
//! kinematics (estimator) → the scenario's truth line, within quantisation.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::kinematics::{Achilles, AchillesConfig};
use hw_io::can::{EncoderConfig, JointAssembler, Message, SyncSource};
use sim::encoders::VirtualNodes;
use sim::robot::{IkTracker, ModelError, SimulatedArm};
use sim::scenario::{ScenarioConfig, generate};

/// Largest wrist (metres) and axis (degrees) error of the decoded lines against the truth.
fn pipeline(error: ModelError) -> (f64, f64, usize) {
    let scenario = generate(&ScenarioConfig { cycles: 2, ..Default::default() });
    let nominal = AchillesConfig::default();
    let mut tracker = IkTracker::new(SimulatedArm::new(&nominal, error).unwrap());
    let controller_arm = Achilles::new(&nominal).unwrap();
    let encoders = EncoderConfig::default();
    let mut nodes = VirtualNodes::with_defaults(&encoders).unwrap();
    let mut sync = SyncSource::new();
    let mut assembler = JointAssembler::from_config(&encoders).unwrap();
    let period_us = (scenario.config.sample_period_s * 1e6).round() as u64;
    let (mut max_wrist_m, mut max_axis_deg) = (0.0_f64, 0.0_f64);
    for (i, truth) in scenario.truth.iter().enumerate() {
        let q_true = tracker.solve(&truth.line, 0.0).unwrap();
        let counter = sync.next_counter();
        let frames = nodes.on_sync(counter, i as u64 * period_us, &q_true).unwrap();
        assembler.start_cycle();
        for f in &frames {
            if let Ok(msg @ Message::Tpdo { .. }) = Message::decode(&f.frame) {
                assembler.accept(&msg).unwrap();
            }
        }
        let q = encoders.counts_to_rad(&assembler.counts().unwrap());
        let pose = controller_arm.forward(&q).unwrap();
        max_wrist_m = max_wrist_m.max((pose.wrist_base_m - truth.line.wrist_base_m).norm());
        let cos = pose.axis_base.dot(&truth.line.axis_base).clamp(-1.0, 1.0);
        max_axis_deg = max_axis_deg.max(cos.acos().to_degrees());
    }
    (max_wrist_m, max_axis_deg, scenario.truth.len())
}

#[test]
fn scenario_through_the_encoder_bus_matches_the_truth_within_quantisation() {
    let (wrist_m, axis_deg, n) = pipeline(ModelError::zero());
    eprintln!("{n} samples: wrist within {wrist_m:e} m, axis within {axis_deg:e} deg");
    assert!(n > 10_000, "{n} samples");
    assert!(wrist_m < 1e-4, "wrist off by {wrist_m} m");
    assert!(axis_deg < 0.05, "axis off by {axis_deg} deg");
    // Quantisation is visible but small: 2^17 counts per revolution.
    assert!(wrist_m > 1e-7, "no quantisation? {wrist_m} m");
}

#[test]
fn calibration_error_of_the_true_arm_is_seen_by_the_nominal_model() {
    let (wrist_m, _axis_deg, _) = pipeline(ModelError::from_seed(3, 0.002, 0.005));
    assert!(wrist_m > 1e-3, "a 2 mm / 5 mrad model error should bias the line by millimetres, got {wrist_m} m");
}
