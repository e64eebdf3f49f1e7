//! The ground-truth file: it round-trips, scoring from it equals scoring from the in-memory
//! scenario, and malformed files give typed errors naming the line.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::trocar::{Detector, DetectorConfig, LineSample};
use nalgebra::Vector3;
use sim::scenario::{Scenario, ScenarioConfig, Truth, TruthState, generate};
use sim::score::{self, Detected, Score};
use sim::truth_file::{
    At, ScenarioStart, ScoreInputError, TruthFile, TruthHeader, TruthLineError, TruthReadError, TruthWriter,
    score_detections, write_scenario,
};
use sim::twin::{SimRobot, TwinConfig, TwinEvent};

const T0_US: u64 = 1_700_000_000_000_000;
const WRONG_TROCAR_M: f64 = 0.03;

fn small_scenario(seed: u64, cycles: usize) -> ScenarioConfig {
    ScenarioConfig {
        seed,
        cycles,
        inside_s: [3.0, 4.0],
        outside_s: [1.5, 2.0],
        trocars_base_m: TwinConfig::default().scenario.trocars_base_m,
        ..Default::default()
    }
}

/// Runs a twin, writing its truth file; returns the file and every sample's truth and events.
fn twin_run(state_every: u64) -> (Vec<u8>, Vec<Truth>, Vec<TwinEvent>, TwinConfig) {
    let config = TwinConfig { scenario: small_scenario(8, 2), ..TwinConfig::default() };
    let mut robot = SimRobot::new(&config).unwrap();
    let mut header = TruthHeader::new(&config.scenario, T0_US, state_every);
    header.twin = Some(config.clone());
    let mut w = TruthWriter::new(Vec::new(), &header).unwrap();
    w.scenario(ScenarioStart { sample: 0, seed: 8 }).unwrap();
    let (mut truths, mut events) = (Vec::new(), Vec::new());
    let mut i = 0u64;
    while let Some(_frames) = robot.on_sync((i % 240) as u8 + 1, T0_US + i * 1000).unwrap() {
        w.sample(T0_US + i * 1000, robot.truth(), robot.events()).unwrap();
        truths.push(*robot.truth());
        events.extend_from_slice(robot.events());
        i += 1;
    }
    (w.finish().unwrap(), truths, events, config)
}

#[test]
fn the_truth_file_round_trips() {
    for state_every in [1, 10, 1000] {
        let (bytes, truths, events, config) = twin_run(state_every);
        let file = TruthFile::read(&bytes[..]).unwrap();
        assert_eq!(file.header().twin.as_ref(), Some(&config));
        assert_eq!(file.header().scenario, config.scenario);
        assert_eq!(file.header().t0_unix_time_us, T0_US);
        assert_eq!(file.samples(), truths.len() as u64);
        assert_eq!(file.events(), &events[..]);
        assert_eq!(file.events().len(), 4);
        assert_eq!(file.scenarios(), &[ScenarioStart { sample: 0, seed: 8 }]);
        // Every state line is bit-exact; every sample multiple of state_every has one.
        for r in file.states() {
            let t = &truths[r.sample as usize];
            assert_eq!((r.t_s, r.state, r.fulcrum_base_m, r.line), (t.t_s, t.state, t.fulcrum_base_m, t.line));
            assert_eq!(r.unix_time_us, T0_US + r.sample * 1000);
        }
        let lines = file.states().len() as u64;
        assert!(lines >= truths.len() as u64 / state_every, "{lines} state lines");
        // The state of every sample is exact; the pivot and the line are interpolated.
        let (mut pivot_err, mut wrist_err) = (0.0_f64, 0.0_f64);
        for (i, t) in truths.iter().enumerate() {
            let r = file.record_at(i as u64).unwrap();
            assert_eq!(r.state, t.state, "sample {i}");
            assert_eq!(file.state_at(i as u64), Some(t.state));
            assert_eq!(r.fulcrum_base_m.is_some(), t.fulcrum_base_m.is_some());
            if let (Some(a), Some(b)) = (r.fulcrum_base_m, t.fulcrum_base_m) {
                pivot_err = pivot_err.max((a - b).norm());
            }
            wrist_err = wrist_err.max((r.line.wrist_base_m - t.line.wrist_base_m).norm());
            if state_every == 1 {
                assert_eq!(r.line, t.line);
            }
        }
        assert!(file.record_at(truths.len() as u64).is_none());
        eprintln!(
            "state_every {state_every}: {lines} state lines, pivot within {pivot_err:e} m, wrist {wrist_err:e} m"
        );
        match state_every {
            1 => assert_eq!((pivot_err, wrist_err), (0.0, 0.0)),
            // Linear interpolation over 10 ms: about 10 µm at the kinks of the pivot's path
            // (start and end of the manipulation), up to millimetres for the wrist where the
            // scenario's free motion has kinks.
            10 => assert!(pivot_err < 2e-5 && wrist_err < 2e-3, "{pivot_err} {wrist_err}"),
            _ => assert!(pivot_err > 1e-6, "1 s decimation cannot be exact: {pivot_err}"),
        }
        // Written twice, the same bytes.
        assert_eq!(twin_run(state_every).0, bytes);
    }
}

/// A detector's output for `scenario`: the real detector on the measured lines, plus a false
/// detection while outside and a wrong trocar just after an insertion.
fn detections(scenario: &Scenario) -> Vec<Detected> {
    let mut detector = Detector::new(&DetectorConfig::default()).unwrap();
    let mut out: Vec<Detected> = scenario
        .measured
        .iter()
        .map(|l| {
            let e = detector.step(&LineSample::new(l.wrist_base_m, l.axis_base));
            Detected { inside: e.state.is_inside(), fulcrum_base_m: e.fulcrum_base_m }
        })
        .collect();
    let far = Some(Vector3::new(0.0, 0.5, 0.0));
    // 50 ms of a false detection at the start (outside), and a wrong trocar later.
    for d in &mut out[100..150] {
        *d = Detected { inside: true, fulcrum_base_m: Some(Vector3::new(0.3, -0.09, 0.0)) };
    }
    let e = scenario.events[2]; // the second insertion
    for d in &mut out[e.sample + 10..e.sample + 60] {
        assert!(!d.inside, "the detector needs longer than 10 ms");
        *d = Detected { inside: true, fulcrum_base_m: far };
    }
    out
}

fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

#[test]
fn scoring_from_the_truth_file_equals_scoring_from_the_scenario() {
    let scenario = generate(&small_scenario(12, 3));
    let detected = detections(&scenario);
    let reference = score::score(&scenario, &detected, WRONG_TROCAR_M);
    eprintln!("reference score: {reference:?}");
    assert_eq!(reference.insertions, 3);
    assert_eq!(reference.false_detections, 2, "outside, and a wrong trocar: {reference:?}");
    assert!(reference.insertions_detected >= 2, "{reference:?}");

    // Full rate: bit-identical, by sample index and by time.
    let bytes = write_scenario(Vec::new(), &scenario, T0_US, 1).unwrap();
    let file = TruthFile::read(&bytes[..]).unwrap();
    let by_sample = detected.iter().enumerate().map(|(i, d)| (At::Sample(i as u64), *d));
    assert_eq!(score_detections(&file, by_sample, WRONG_TROCAR_M).unwrap(), reference);
    // A detection stamped when the TPDOs arrive (SYNC + 250 us) belongs to that SYNC's sample.
    let by_time = detected.iter().enumerate().map(|(i, d)| (At::UnixTimeUs(T0_US + i as u64 * 1000 + 250), *d));
    assert_eq!(score_detections(&file, by_time, WRONG_TROCAR_M).unwrap(), reference);
    // Only the changes, held until the next one: the same.
    let changes: Vec<(At, Detected)> = detected
        .iter()
        .enumerate()
        .filter(|(i, d)| *i == 0 || *i + 1 == detected.len() || detected[i - 1] != **d)
        .map(|(i, d)| (At::Sample(i as u64), *d))
        .collect();
    assert!(changes.len() < detected.len() / 10);
    assert_eq!(score_detections(&file, changes, WRONG_TROCAR_M).unwrap(), reference);

    // Decimated (10 ms): the same events, delays and false detections; the errors differ by
    // the interpolation of the pivot only.
    let bytes = write_scenario(Vec::new(), &scenario, T0_US, 10).unwrap();
    let file = TruthFile::read(&bytes[..]).unwrap();
    let by_sample = detected.iter().enumerate().map(|(i, d)| (At::Sample(i as u64), *d));
    let s: Score = score_detections(&file, by_sample, WRONG_TROCAR_M).unwrap();
    assert_eq!(
        (s.insertions, s.insertions_detected, s.extractions, s.extractions_detected, s.false_detections),
        (
            reference.insertions,
            reference.insertions_detected,
            reference.extractions,
            reference.extractions_detected,
            reference.false_detections
        )
    );
    assert_eq!(s.insertion_delays_s, reference.insertion_delays_s);
    assert_eq!(s.extraction_delays_s, reference.extraction_delays_s);
    assert_eq!(s.false_detection_samples, reference.false_detection_samples);
    assert!(close(&s.first_errors_m, &reference.first_errors_m, 2e-5));
    assert!((s.rms_error_m - reference.rms_error_m).abs() < 2e-5);
    assert_ne!(s, reference, "decimated pivots are interpolated, not exact");
}

#[test]
fn bad_detection_sequences_are_refused() {
    let scenario = generate(&small_scenario(13, 1));
    let bytes = write_scenario(Vec::new(), &scenario, T0_US, 10).unwrap();
    let file = TruthFile::read(&bytes[..]).unwrap();
    let d = Detected { inside: false, fulcrum_base_m: None };
    assert_eq!(
        score_detections(&file, [(At::Sample(5), d), (At::Sample(3), d)], 0.03),
        Err(ScoreInputError::OutOfOrder { index: 1, sample: 3, previous: 5 })
    );
    assert_eq!(
        score_detections(&file, [(At::UnixTimeUs(T0_US - 1), d)], 0.03),
        Err(ScoreInputError::BeforeStart { index: 0 })
    );
    // Past the end: ignored, nothing scored.
    let s = score_detections(&file, [(At::Sample(u64::MAX), d)], 0.03).unwrap();
    assert_eq!((s.insertions, s.insertions_detected), (1, 0));
    assert_eq!(file.sample_at_unix_time_us(T0_US), Some(0));
    assert_eq!(file.sample_at_unix_time_us(T0_US + 1999), Some(1));
    assert_eq!(file.sample_at_unix_time_us(u64::MAX), Some(file.samples() - 1));
}

/// A small valid file and its lines.
fn valid_lines() -> Vec<String> {
    let scenario = generate(&small_scenario(14, 1));
    let bytes = write_scenario(Vec::new(), &scenario, T0_US, 500).unwrap();
    String::from_utf8(bytes).unwrap().lines().map(str::to_owned).collect()
}

fn read(lines: &[String]) -> Result<TruthFile, TruthReadError> {
    TruthFile::read(lines.join("\n").as_bytes())
}

/// Index of the first line containing `pat`.
fn find(lines: &[String], pat: &str) -> usize {
    lines.iter().position(|l| l.contains(pat)).unwrap()
}

#[track_caller]
fn expect_line_error(lines: &[String], line: u64, check: impl Fn(&TruthLineError) -> bool) {
    match read(lines) {
        Err(e @ TruthReadError::Line { .. }) => {
            assert_eq!(e.line(), Some(line), "{e}");
            assert!(e.to_string().starts_with(&format!("truth file line {line}: ")), "{e}");
            let TruthReadError::Line { kind, .. } = &e else { unreachable!() };
            assert!(check(kind), "unexpected kind: {e}");
        }
        other => panic!("expected an error at line {line}, got {other:?}"),
    }
}

#[test]
fn malformed_truth_files_give_typed_errors_with_line_numbers() {
    let ok = valid_lines();
    assert!(read(&ok).is_ok());
    let ins = find(&ok, "\"insertion\"");
    let first_state = find(&ok, "\"type\":\"state\"");

    let mut l = ok.clone();
    l[ins] = "{not json".into();
    expect_line_error(&l, ins as u64 + 1, |k| matches!(k, TruthLineError::Json(_)));

    let mut l = ok.clone();
    l[0] = l[0].replace("\"version\":1", "\"version\":2");
    expect_line_error(&l, 1, |k| matches!(k, TruthLineError::Version { found: 2 }));

    let mut l = ok.clone();
    l[0] = l[0].replace("comanip-truth", "other");
    expect_line_error(&l, 1, |k| matches!(k, TruthLineError::Format { .. }));

    let l = ok[1..].to_vec();
    expect_line_error(&l, 1, |k| matches!(k, TruthLineError::HeaderPlacement));

    let mut l = ok.clone();
    l[ins] = set_field(&l[ins], "trocar", "9");
    expect_line_error(&l, ins as u64 + 1, |k| matches!(k, TruthLineError::Trocar { index: 9, trocars: 4 }));

    let mut l = ok.clone();
    l[first_state] = l[first_state].replace("\"wrist_base_m\"", "\"wrist\"");
    expect_line_error(
        &l,
        first_state as u64 + 1,
        |k| matches!(k, TruthLineError::Json(e) if e.to_string().contains("wrist")),
    );

    // The state line at the insertion sample is missing: the next state line contradicts it.
    let mut l = ok.clone();
    l.remove(ins + 1);
    expect_line_error(&l, ins as u64 + 2, |k| matches!(k, TruthLineError::Inconsistent(_)));

    // Two state lines swapped: the sample goes backwards.
    let mut l = ok.clone();
    l.swap(first_state + 1, first_state + 2);
    expect_line_error(&l, first_state as u64 + 3, |k| matches!(k, TruthLineError::Order(_)));
    // The first state line is not sample 0.
    let mut l = ok.clone();
    l.remove(first_state);
    expect_line_error(&l, first_state as u64 + 1, |k| matches!(k, TruthLineError::Order(_)));

    // A state line outside with a fulcrum.
    let mut l = ok.clone();
    l[first_state] = l[first_state].replace("\"wrist_base_m\"", "\"fulcrum_base_m\":[0,0,0],\"wrist_base_m\"");
    expect_line_error(&l, first_state as u64 + 1, |k| matches!(k, TruthLineError::Fulcrum));

    let mut l = ok.clone();
    let last = l.len() - 1;
    l[last] = l[last].replace("\"events\":2", "\"events\":3");
    expect_line_error(&l, last as u64 + 1, |k| {
        matches!(k, TruthLineError::EndCounts { said_events: 3, events: 2, .. })
    });

    let mut l = ok.clone();
    l.push(ok[first_state].clone());
    expect_line_error(&l, l.len() as u64, |k| matches!(k, TruthLineError::AfterEnd));

    let l = ok[..ok.len() - 1].to_vec();
    assert!(matches!(read(&l), Err(TruthReadError::MissingEnd { last_line }) if last_line == l.len() as u64));

    assert!(matches!(TruthFile::read(&b""[..]), Err(TruthReadError::Empty)));
    let mut bytes = ok.join("\n").into_bytes();
    bytes.splice(0..0, b"\xff\xfe\n".iter().copied());
    match TruthFile::read(&bytes[..]) {
        Err(TruthReadError::Line { line: 1, kind: TruthLineError::NotUtf8 }) => {}
        other => panic!("{other:?}"),
    }
    // Blank lines are skipped and do not shift the numbering of later lines.
    let mut l = ok.clone();
    l.insert(1, String::new());
    l[ins + 1] = "garbage".into();
    expect_line_error(&l, ins as u64 + 2, |k| matches!(k, TruthLineError::Json(_)));
}

/// `line` with the integer value of `"key":` replaced by `value`.
fn set_field(line: &str, key: &str, value: &str) -> String {
    let pat = format!("\"{key}\":");
    let start = line.find(&pat).unwrap() + pat.len();
    let end = start + line[start..].find([',', '}']).unwrap();
    format!("{}{}{}", &line[..start], value, &line[end..])
}

#[test]
fn the_writer_refuses_events_of_another_sample_and_non_finite_values() {
    let cfg = small_scenario(1, 1);
    let mut w = TruthWriter::new(Vec::new(), &TruthHeader::new(&cfg, T0_US, 10)).unwrap();
    let truth = Truth {
        t_s: 0.0,
        state: TruthState::Outside,
        fulcrum_base_m: None,
        line: LineSample::new(Vector3::new(0.4, 0.0, 0.3), Vector3::new(0.0, 0.0, -1.0)),
    };
    let e = TwinEvent { sample: 5, t_s: 0.005, unix_time_us: T0_US, trocar: 0, insertion: true };
    assert!(w.sample(T0_US, &truth, &[e]).is_err());
    let bad = Truth { t_s: f64::NAN, ..truth };
    assert!(w.sample(T0_US, &bad, &[]).is_err());
    assert_eq!(w.samples(), 0);
    w.sample(T0_US, &truth, &[]).unwrap();
    let file = TruthFile::read(&w.finish().unwrap()[..]).unwrap();
    assert_eq!(file.samples(), 1);
    assert!(TruthWriter::new(Vec::new(), &TruthHeader::new(&cfg, T0_US, 0)).is_err());
}
