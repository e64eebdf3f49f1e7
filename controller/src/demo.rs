//! The built-in simulated robot: the detector over the simulated surgeon, with the state
//! changes printed next to the ground truth.

use estimator::trocar::{Detector, DetectorConfig, LineSample, TrocarState};
use sim::scenario::{ScenarioConfig, generate};
use sim::score::{self, Detected, Score};

/// A fulcrum farther than this from the true trocar (metres) is a wrong-trocar detection.
pub const WRONG_TROCAR_M: f64 = 0.03;

/// One state change of the detector.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Change {
    /// Time, seconds since the start of the scenario.
    pub t_s: f64,
    /// New state.
    pub state: TrocarState,
    /// Fulcrum, metres, robot base frame, when inside.
    pub fulcrum_base_m: Option<[f64; 3]>,
    /// Distance from that fulcrum to the true pivot, metres, when both exist.
    pub error_m: Option<f64>,
}

/// Runs `detector_cfg` over the scenario `scenario_cfg`, calling `on_change` at each state
/// change (and at each true event, `on_truth`), and returns the score.
pub fn run(
    detector_cfg: &DetectorConfig,
    scenario_cfg: &ScenarioConfig,
    mut on_change: impl FnMut(&Change),
    mut on_truth: impl FnMut(f64, usize, bool),
) -> Result<Score, estimator::trocar::ConfigError> {
    let scenario = generate(scenario_cfg);
    let mut detector = Detector::new(detector_cfg)?;
    let mut detected = Vec::with_capacity(scenario.measured.len());
    let mut prev = TrocarState::Outside;
    let mut events = scenario.events.iter().peekable();
    for (i, line) in scenario.measured.iter().enumerate() {
        while let Some(e) = events.next_if(|e| e.sample <= i) {
            on_truth(e.t_s, e.trocar, e.insertion);
        }
        let est = detector.step(&LineSample::new(line.wrist_base_m, line.axis_base));
        if est.state != prev {
            let truth = &scenario.truth[i];
            on_change(&Change {
                t_s: truth.t_s,
                state: est.state,
                fulcrum_base_m: est.fulcrum_base_m.map(|f| [f.x, f.y, f.z]),
                error_m: match (est.fulcrum_base_m, truth.fulcrum_base_m) {
                    (Some(f), Some(t)) => Some((f - t).norm()),
                    _ => None,
                },
            });
            prev = est.state;
        }
        detected.push(Detected { inside: est.state.is_inside(), fulcrum_base_m: est.fulcrum_base_m });
    }
    Ok(score::score(&scenario, &detected, WRONG_TROCAR_M))
}
