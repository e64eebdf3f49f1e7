//! Insert/extract sequences: each mode must change state at the right moments, at the right
//! trocar, and the fast mode must be faster than the paper's.

mod common;

use common::*;
use estimator::trocar::{Detector, DetectorConfig, DetectorMode, FastConfig};
use nalgebra::Vector3;
use sim::scenario::{ScenarioConfig, generate};
use sim::score::{Detected, score};

struct Delays {
    insertion_s: Vec<f64>,
    extraction_s: Vec<f64>,
}

/// Runs a scripted sequence and checks every state change; returns the delays.
fn run_scripted(cfg: &DetectorConfig, max_delay_s: f64) -> Delays {
    let trocars = [Vector3::new(0.42, -0.08, 0.02), Vector3::new(0.48, 0.06, 0.04), Vector3::new(0.36, 0.0, 0.0)];
    let (lines, phases, fulcrums) = scripted(&trocars, 6, 3.0, 8.0);
    let mut d = Detector::new(cfg).unwrap();
    let mut delays = Delays { insertion_s: vec![], extraction_s: vec![] };
    let mut phase_start = 0;
    let mut seen_change = false;
    for (i, l) in lines.iter().enumerate() {
        if i > 0 && phases[i] != phases[i - 1] {
            phase_start = i;
            seen_change = false;
        }
        let e = d.step(l);
        let age_s = (i - phase_start) as f64 * 0.001;
        match phases[i] {
            Phase::Inside => {
                if e.state.is_inside() {
                    let err = (e.fulcrum_base_m.unwrap() - fulcrums[i]).norm();
                    assert!(err < 0.005, "{:?}: fulcrum {err} m from the trocar at sample {i}", cfg.mode);
                    if !seen_change {
                        delays.insertion_s.push(age_s);
                        seen_change = true;
                    }
                } else {
                    assert!(!seen_change, "{:?}: spurious extraction at sample {i}", cfg.mode);
                    assert!(age_s < max_delay_s, "{:?}: insertion not detected within {max_delay_s} s", cfg.mode);
                }
            }
            Phase::Outside => {
                if e.state.is_inside() {
                    assert!(!seen_change, "{:?}: false detection while outside at sample {i}", cfg.mode);
                    // Still inside from the previous cycle: allowed only at the start.
                    assert!(phase_start > 0, "{:?}: inside at start-up", cfg.mode);
                    assert!(age_s < max_delay_s, "{:?}: extraction not detected within {max_delay_s} s", cfg.mode);
                } else if !seen_change {
                    if phase_start > 0 {
                        delays.extraction_s.push(age_s);
                    }
                    seen_change = true;
                }
            }
        }
    }
    assert_eq!(delays.insertion_s.len(), 6, "{:?}: every insertion detected", cfg.mode);
    assert_eq!(delays.extraction_s.len(), 5, "{:?}: every extraction detected", cfg.mode);
    delays
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn paper_mode_follows_insertions_and_extractions() {
    run_scripted(&DetectorConfig { mode: DetectorMode::Paper, ..Default::default() }, 3.0);
}

#[test]
fn fast_mode_follows_them_sooner_than_the_paper() {
    let paper = run_scripted(&DetectorConfig { mode: DetectorMode::Paper, ..Default::default() }, 3.0);
    let fast = run_scripted(&DetectorConfig { mode: DetectorMode::Fast, ..Default::default() }, 3.0);
    let (pi, fi) = (mean(&paper.insertion_s), mean(&fast.insertion_s));
    let (pe, fe) = (mean(&paper.extraction_s), mean(&fast.extraction_s));
    eprintln!("insertion: paper {pi:.3} s, fast {fi:.3} s; extraction: paper {pe:.3} s, fast {fe:.3} s");
    assert!(fi < pi, "fast insertion {fi} s not below paper {pi} s");
    assert!(fe < pe, "fast extraction {fe} s not below paper {pe} s");
}

#[test]
fn known_instrument_length_makes_axial_extraction_immediate() {
    // Inside, then the surgeon pulls straight out along the axis: no lateral motion at all.
    let f = Vector3::new(0.42, 0.0, 0.02);
    let (mut lines, _, _) = scripted(&[f], 1, 0.0, 5.0);
    let axis = lines.last().unwrap().axis_base;
    let depth_at_end = (f - lines.last().unwrap().wrist_base_m).dot(&axis);
    let length = 0.30; // tip 0.30 m from the wrist: beyond the fulcrum while depth < 0.30
    let pull_start = lines.len();
    for k in 1..=1500 {
        lines.push(line_through(&f, &axis, depth_at_end + 0.0001 * k as f64)); // 0.1 m/s outwards
    }
    let tip_out_sample = pull_start + ((length - depth_at_end) / 0.0001).ceil() as usize - 1;
    for (length_known, must_detect) in [(Some(length), true), (None, false)] {
        let cfg = DetectorConfig {
            fast: FastConfig { instrument_length_m: length_known, ..Default::default() },
            ..Default::default()
        };
        let mut d = Detector::new(&cfg).unwrap();
        let mut out_at = None;
        for (i, l) in lines.iter().enumerate() {
            let e = d.step(l);
            if i >= pull_start && !e.state.is_inside() && out_at.is_none() {
                out_at = Some(i);
            }
            if i == pull_start - 1 {
                assert!(e.state.is_inside());
            }
        }
        match (must_detect, out_at) {
            (true, Some(i)) => {
                let delay_s = (i as f64 - tip_out_sample as f64) * 0.001;
                assert!((0.0..0.05).contains(&delay_s), "tip-over-fulcrum extraction delay {delay_s} s");
            }
            (false, None) => {} // without the length, an axial pull is invisible: no lines disagree
            (m, o) => panic!("length {length_known:?}: expected detection {m}, got {o:?}"),
        }
    }
}

#[test]
fn trocar_memory_recognises_a_reinsertion_quickly() {
    let trocars = [Vector3::new(0.42, -0.08, 0.02), Vector3::new(0.48, 0.06, 0.04)];
    // Visit A, B, A, B: the second visits are re-insertions into known trocars.
    let (lines, phases, _) = scripted(&trocars, 4, 3.0, 8.0);
    let delays_for = |memory: bool| {
        let cfg = DetectorConfig {
            fast: FastConfig { trocar_memory: memory, instrument_length_m: Some(0.30), ..Default::default() },
            ..Default::default()
        };
        let mut d = Detector::new(&cfg).unwrap();
        let mut delays = vec![];
        let mut start = 0;
        let mut ids = vec![];
        let mut waiting = false;
        for (i, l) in lines.iter().enumerate() {
            if i > 0 && phases[i] != phases[i - 1] && phases[i] == Phase::Inside {
                start = i;
                waiting = true;
            }
            let e = d.step(l);
            if let (true, estimator::trocar::TrocarState::Inside { id }) = (waiting, e.state) {
                delays.push((i - start) as f64 * 0.001);
                ids.push(id);
                waiting = false;
            }
        }
        (delays, ids)
    };
    let (with, ids) = delays_for(true);
    let (without, _) = delays_for(false);
    assert_eq!(with.len(), 4);
    assert_eq!(ids[0], ids[2], "re-insertion into A must get A's id");
    assert_eq!(ids[1], ids[3], "re-insertion into B must get B's id");
    assert_ne!(ids[0], ids[1]);
    for k in 2..4 {
        assert!(with[k] <= 0.1, "re-insertion {k} took {} s with memory", with[k]);
        assert!(with[k] < without[k], "memory must speed re-insertion {k}: {} vs {}", with[k], without[k]);
    }
}

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
