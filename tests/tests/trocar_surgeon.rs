//! The detector against the simulated surgeon: the fast mode sees every insertion and every
//! extraction of `sim`'s scenarios. (The scripted-motion tests of both modes live beside the
//! detectors, in `estimator/src/trocar/{mod,fast,paper,lsq}.rs`.)

use estimator::trocar::{Detector, DetectorConfig};
use sim::scenario::{ScenarioConfig, generate};
use sim::score::{Detected, score};

#[test]
fn fast_mode_detects_every_cycle_of_a_simulated_surgeon() {
    for seed in [11, 12] {
        let scenario = generate(&ScenarioConfig { seed, cycles: 6, ..Default::default() });
        let mut d = Detector::new(&DetectorConfig::default()).unwrap();
        let detected: Vec<Detected> = scenario
            .measured
            .iter()
            .map(|l| {
                let e = d.step(l);
                Detected { inside: e.state.is_inside(), fulcrum_base_m: e.fulcrum_base_m }
            })
            .collect();
        let s = score(&scenario, &detected, 0.03);
        assert_eq!(s.insertions_detected, s.insertions, "seed {seed}: {s:?}");
        assert_eq!(s.extractions_detected, s.extractions, "seed {seed}: {s:?}");
    }
}
