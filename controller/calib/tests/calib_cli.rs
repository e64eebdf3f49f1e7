//! `comanip-calib` end to end on a small simulated dataset: generate → calibrate → result
//! file; malformed inputs give clear errors; a quick sweep writes its table and plots.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::Path;
use std::process::Command;

use hw_io::calib_files::{parse_dataset, parse_result, parse_truth, to_json};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_comanip-calib"))
}

fn run_ok(cmd: &mut Command) -> String {
    let out = cmd.output().expect("run comanip-calib");
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn generate(dir: &Path, sigma: &str) {
    run_ok(
        bin()
            .args(["generate", "--n-e", "2", "--n-t", "2", "--sigma", sigma, "--seed", "4"])
            .arg("--dataset")
            .arg(dir.join("d.json"))
            .arg("--truth")
            .arg(dir.join("t.json")),
    );
}

#[test]
fn generate_then_calibrate_recovers_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path(), "0");
    let d = parse_dataset(&std::fs::read_to_string(dir.path().join("d.json")).unwrap()).unwrap();
    let t = parse_truth(&std::fs::read_to_string(dir.path().join("t.json")).unwrap()).unwrap();
    assert_eq!(d.observations.len() + t.dropped, t.generated);
    let stdout = run_ok(
        bin()
            .arg("calibrate")
            .arg("--dataset")
            .arg(dir.path().join("d.json"))
            .arg("--truth")
            .arg(dir.path().join("t.json"))
            .arg("--out")
            .arg(dir.path().join("r.json")),
    );
    assert!(stdout.contains("paper: e_t") && stdout.contains("ours: e_t"), "{stdout}");
    let r = parse_result(&std::fs::read_to_string(dir.path().join("r.json")).unwrap()).unwrap();
    assert_eq!(r.results.len(), 2);
    for p in &r.results {
        let dt: f64 = (0..3).map(|i| (p.translation_m[i] - t.truth.translation_m[i]).powi(2)).sum::<f64>().sqrt();
        assert!(dt < 1e-9, "{}: {dt} m", p.pipeline);
        // The 4x4 transform carries the same translation, last row 0 0 0 1.
        assert_eq!([p.transform[0][3], p.transform[1][3], p.transform[2][3]], p.translation_m);
        assert_eq!(p.transform[3], [0.0, 0.0, 0.0, 1.0]);
    }
    assert!(r.results[0].covariance.is_none() && r.results[1].covariance.is_some());
}

#[test]
fn wrong_lines_are_listed_in_the_truth_and_stand_out_in_the_residual_plot() {
    let dir = tempfile::tempdir().unwrap();
    let [d, t, r, svg] = ["d.json", "t.json", "r.json", "residuals.svg"].map(|f| dir.path().join(f));
    let stdout = run_ok(
        bin()
            .args(["generate", "--n-e", "3", "--n-t", "3", "--seed", "2", "--wrong-lines", "0.05"])
            .arg("--dataset")
            .arg(&d)
            .arg("--truth")
            .arg(&t),
    );
    let truth = parse_truth(&std::fs::read_to_string(&t).unwrap()).unwrap();
    let data = parse_dataset(&std::fs::read_to_string(&d).unwrap()).unwrap();
    let n = data.observations.len();
    let wrong = truth.wrong_lines.len();
    assert_eq!(wrong, (0.05 * n as f64).round() as usize, "{stdout}");
    assert!(stdout.contains(&format!("({wrong} with a wrong line)")), "{stdout}");
    assert!(truth.wrong_lines.windows(2).all(|w| w[0] < w[1]) && truth.wrong_lines.iter().all(|&i| i < n));
    let stdout = run_ok(
        bin()
            .arg("calibrate")
            .arg("--dataset")
            .arg(&d)
            .arg("--truth")
            .arg(&t)
            .arg("--out")
            .arg(&r)
            .arg("--plot")
            .arg(&svg),
    );
    assert!(stdout.contains(&format!("wrote {}", svg.display())), "{stdout}");
    // Ours is robust to them; the figure's outlier class holds (nearly) exactly the wrong lines.
    let result = parse_result(&std::fs::read_to_string(&r).unwrap()).unwrap();
    let ours = result.results.iter().find(|p| p.pipeline == "ours").unwrap();
    let dt: f64 = (0..3).map(|i| (ours.translation_m[i] - truth.truth.translation_m[i]).powi(2)).sum::<f64>().sqrt();
    assert!(dt < 2e-3, "ours off by {dt} m with {wrong} wrong lines");
    let text = std::fs::read_to_string(&svg).unwrap();
    assert!(text.starts_with("<svg") && text.contains("ours: observed lines by residual"), "not the figure");
    let count = |label: &str| -> usize {
        let at = text.find(label).unwrap_or_else(|| panic!("no legend entry {label:?}"));
        text[at + label.len()..].chars().take_while(char::is_ascii_digit).collect::<String>().parse().unwrap()
    };
    let outliers = count("&gt; 6 robust SD (outlier?): ");
    assert!(outliers + 2 >= wrong && outliers <= wrong + 2, "{outliers} drawn as outliers, {wrong} wrong lines");
    assert_eq!(count("≤ 3 robust SD: ") + count("3-6 robust SD: ") + outliers, n);
    // Both pipelines' histograms.
    assert!(text.contains("paper (RMS") && text.contains("ours (RMS"));

    // A fraction outside 0..=1 is refused with the option's name.
    let out = bin()
        .args(["generate", "--wrong-lines", "1.5"])
        .arg("--dataset")
        .arg(&d)
        .arg("--truth")
        .arg(&t)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--wrong-lines 1.5"));
    // An unwritable figure is a clear error after the result file was written.
    let out = bin()
        .arg("calibrate")
        .arg("--dataset")
        .arg(&d)
        .arg("--out")
        .arg(&r)
        .arg("--plot")
        .arg(dir.path().join("missing-dir/residuals.svg"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot write the residual plot"), "{out:?}");
}

#[test]
fn calibrate_with_opencv_intrinsics_and_one_pipeline() {
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path(), "0.01");
    let d = parse_dataset(&std::fs::read_to_string(dir.path().join("d.json")).unwrap()).unwrap();
    let k = d.intrinsics;
    let yaml = format!(
        "%YAML:1.0\n---\nimage_width: {}\nimage_height: {}\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {}, 0., {}, 0., {}, {}, 0., 0., 1. ]\n",
        k.width, k.height, k.fx, k.cx, k.fy, k.cy
    );
    std::fs::write(dir.path().join("cam.yaml"), yaml).unwrap();
    run_ok(
        bin()
            .arg("calibrate")
            .arg("--pipeline")
            .arg("ours")
            .arg("--dataset")
            .arg(dir.path().join("d.json"))
            .arg("--intrinsics")
            .arg(dir.path().join("cam.yaml"))
            .arg("--out")
            .arg(dir.path().join("r.json")),
    );
    let r = parse_result(&std::fs::read_to_string(dir.path().join("r.json")).unwrap()).unwrap();
    assert_eq!(r.results.len(), 1);
    assert_eq!(r.results[0].pipeline, "ours");
    assert!(r.results[0].log_likelihood_ratio.unwrap() > 1.0 && r.results[0].ambiguity_ratio.is_none());
    // The dataset carries its noise model and selection: the selection-aware stage ran.
    assert!(d.noise_model.is_some() && d.selection.is_some() && d.min_shaft_px.is_none());
    let stage = r.results[0].selection_stage.as_ref().expect("selection stage recorded");
    assert!(stage.applied && stage.refused.is_none(), "{stage:?}");
    assert_eq!(stage.selected + stage.plain + stage.left_out, d.observations.len());
}

#[test]
fn malformed_inputs_fail_with_a_named_field() {
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path(), "0");
    let mut d = parse_dataset(&std::fs::read_to_string(dir.path().join("d.json")).unwrap()).unwrap();
    d.observations[2].line_px[1] = d.observations[2].line_px[0];
    std::fs::write(dir.path().join("bad.json"), to_json(&d)).unwrap();
    let out = bin()
        .arg("calibrate")
        .arg("--dataset")
        .arg(dir.path().join("bad.json"))
        .arg("--out")
        .arg(dir.path().join("r.json"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("observations[2].line_px") && err.contains("coincide"), "{err}");
    // Degenerate: keep a single endoscope pose (of the unmodified dataset).
    let mut d = parse_dataset(&std::fs::read_to_string(dir.path().join("d.json")).unwrap()).unwrap();
    let first = d.observations[0].ecm_joints;
    d.observations.retain(|o| o.ecm_joints == first);
    std::fs::write(dir.path().join("one_view.json"), to_json(&d)).unwrap();
    let out = bin()
        .arg("calibrate")
        .arg("--dataset")
        .arg(dir.path().join("one_view.json"))
        .arg("--out")
        .arg(dir.path().join("r.json"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("fewer than two views"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    std::fs::write(
        dir.path().join("trunc.json"),
        "{\n  \"format\": \"comanip-calib-dataset\",\n  \"version\": 1,\n  \"intrinsics\": 3\n}",
    )
    .unwrap();
    let out = bin()
        .arg("calibrate")
        .arg("--dataset")
        .arg(dir.path().join("trunc.json"))
        .arg("--out")
        .arg(dir.path().join("r.json"))
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("line 4"), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn quick_sweep_writes_table_and_plots() {
    let dir = tempfile::tempdir().unwrap();
    let stdout = run_ok(bin().args(["sweep", "--quick", "--trials", "1"]).arg("--out-dir").arg(dir.path()));
    assert!(stdout.contains("sweep.md"));
    let md = std::fs::read_to_string(dir.path().join("sweep.md")).unwrap();
    assert!(md.contains("| mm | 0.01 | 3⁴×3² | 1× |") && md.contains("| m | 0.01 | 3⁴×3² | 1× |"), "{md}");
    // The in-view selection check: the 3× sensor (same focal length) keeps more of the same
    // 729 combinations than the protocol's camera.
    let kept = |sensor: &str| -> usize {
        let row = md
            .lines()
            .find(|l| l.starts_with(&format!("| m | 0.01 | 3⁴×3² | {sensor} |")))
            .unwrap_or_else(|| panic!("no {sensor} row in {md}"));
        row.split('|').nth(5).unwrap().trim().parse().unwrap()
    };
    assert!(kept("3×") > kept("1×") + 100, "{md}");
    assert!(kept("3×") <= 729);
    for f in ["sigma_mm.svg", "sigma_m.svg", "grid_mm.svg", "grid_m.svg"] {
        let svg = std::fs::read_to_string(dir.path().join(f)).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("ours"), "{f}");
    }
}

fn calibrate(
    dir: &Path,
    dataset: &str,
    pipeline: &str,
    extra: &[&str],
) -> (std::process::Output, hw_io::calib_files::ResultFile) {
    let out = bin()
        .arg("calibrate")
        .arg("--dataset")
        .arg(dir.join(dataset))
        .arg("--out")
        .arg(dir.join("r.json"))
        .args(["--pipeline", pipeline])
        .args(extra)
        .output()
        .unwrap();
    let r = parse_result(&std::fs::read_to_string(dir.join("r.json")).unwrap()).unwrap();
    (out, r)
}

#[test]
fn both_writes_each_result_or_failure_and_exits_non_zero_only_when_all_failed() {
    let dir = tempfile::tempdir().unwrap();
    run_ok(
        bin()
            .args(["generate", "--n-e", "2", "--n-t", "3", "--sigma", "0.01", "--seed", "4"])
            .arg("--dataset")
            .arg(dir.path().join("d.json"))
            .arg("--truth")
            .arg(dir.path().join("t.json")),
    );
    let mut d = parse_dataset(&std::fs::read_to_string(dir.path().join("d.json")).unwrap()).unwrap();
    // Three tool orientations: Eq. 8 is rank-deficient (the paper fails), ours still solves.
    let mut orientations: Vec<[f64; 3]> = Vec::new();
    for o in &d.observations {
        if !orientations.contains(&o.psm_joints) {
            orientations.push(o.psm_joints);
        }
    }
    let three: Vec<[f64; 3]> = vec![orientations[0], orientations[4], orientations[8]];
    let mut three_d = d.clone();
    three_d.observations.retain(|o| three.contains(&o.psm_joints));
    std::fs::write(dir.path().join("three.json"), to_json(&three_d)).unwrap();
    let (out, r) = calibrate(dir.path(), "three.json", "both", &[]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(r.results.iter().map(|p| p.pipeline.as_str()).collect::<Vec<_>>(), ["ours"]);
    assert_eq!(r.failures.len(), 1);
    assert_eq!((r.failures[0].pipeline.as_str(), r.failures[0].kind.as_str()), ("paper", "degenerate"));
    // The paper alone on the same data: every requested pipeline failed, non-zero, recorded.
    let (out, r) = calibrate(dir.path(), "three.json", "paper", &[]);
    assert!(!out.status.success());
    assert!(r.results.is_empty() && r.failures.len() == 1);
    // Degenerate lines (all identical): both fail, typed, non-zero, both recorded.
    let first = d.observations[0].line_px;
    for o in &mut d.observations {
        o.line_px = first;
    }
    std::fs::write(dir.path().join("same.json"), to_json(&d)).unwrap();
    let (out, r) = calibrate(dir.path(), "same.json", "both", &[]);
    assert!(!out.status.success());
    assert!(r.results.is_empty());
    assert_eq!(r.failures.iter().map(|f| f.kind.as_str()).collect::<Vec<_>>(), ["degenerate", "degenerate"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("single pencil"), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn a_selection_stage_that_cannot_model_the_data_fails_loudly_unless_accepted() {
    let dir = tempfile::tempdir().unwrap();
    // The metre reading at σ = 0.03 (30 mm per frame), seed 8: the guarded fit explains the
    // shafts, the selection-aware stage's pose puts some behind the camera (45 of 366). (Seeds
    // were chosen again in session 31: with the search from the cover of rotations every time,
    // seeds 17, 1 and 27 below are answered, or refused for another reason.)
    run_ok(
        bin()
            .args(["generate", "--sigma", "0.03", "--units", "m", "--seed", "8"])
            .arg("--dataset")
            .arg(dir.path().join("wild.json"))
            .arg("--truth")
            .arg(dir.path().join("t.json")),
    );
    let (out, r) = calibrate(dir.path(), "wild.json", "ours", &[]);
    assert!(!out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    assert_eq!(r.failures.len(), 1);
    assert_eq!((r.failures[0].pipeline.as_str(), r.failures[0].kind.as_str()), ("ours", "selection_refused"));
    assert!(r.failures[0].error.contains("behind the camera"), "{}", r.failures[0].error);
    // The unrefined estimate is still in the file, marked.
    assert_eq!(r.results.len(), 1);
    assert!(r.results[0].selection_stage.as_ref().is_some_and(|s| !s.applied && s.refused.is_some()));
    let (out, r) = calibrate(dir.path(), "wild.json", "ours", &["--accept-unrefined"]);
    assert!(out.status.success());
    assert!(r.failures.is_empty() && r.results.len() == 1);
    assert!(String::from_utf8_lossy(&out.stderr).contains("accept-unrefined"));
    // A stricter false-refusal probability raises the test's limit from 27.86 (the default,
    // 1e-4) to the χ²₆ quantile at 1 − 1e-6, 38.26; the result file states both numbers.
    let refused_limit = |r: &hw_io::calib_files::ResultFile| -> Option<f64> {
        let stage = r.results[0].selection_stage.as_ref()?;
        stage.refused.as_ref()?;
        let (x, limit) = (stage.move_statistic?, stage.move_limit?);
        assert!(x > limit, "refused with statistic {x} within its limit {limit}");
        Some(limit)
    };
    // Seed 16: the stage moves from the guarded fit beyond their noise (the move test,
    // statistic 47.9).
    run_ok(
        bin()
            .args(["generate", "--sigma", "0.03", "--units", "m", "--seed", "16"])
            .arg("--dataset")
            .arg(dir.path().join("moved.json"))
            .arg("--truth")
            .arg(dir.path().join("t16.json")),
    );
    let (_, r) = calibrate(dir.path(), "moved.json", "ours", &["--accept-unrefined"]);
    let default_limit = refused_limit(&r).expect("refused at the default, with its limit");
    assert!((default_limit - 27.86).abs() < 0.06, "{default_limit}");
    let (out, r) =
        calibrate(dir.path(), "moved.json", "ours", &["--accept-unrefined", "--false-refusal-probability", "1e-6"]);
    assert!(out.status.success());
    let stage = r.results[0].selection_stage.as_ref().expect("the stage ran");
    let limit = stage.move_limit.expect("its test's limit");
    assert!((limit - 38.26).abs() < 0.06, "{limit}");
    // Not a probability: refused by the command line, nothing run.
    let out = bin()
        .args(["calibrate", "--pipeline", "ours", "--false-refusal-probability", "1.5", "--dataset"])
        .arg(dir.path().join("wild.json"))
        .arg("--out")
        .arg(dir.path().join("never.json"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("strictly between 0 and 1"));
    assert!(!dir.path().join("never.json").exists());
    // The metre reading at σ = 0.03, seed 19: no candidate puts the shafts where an instrument
    // can be; a typed failure, non-zero even with --accept-unrefined, no pose.
    run_ok(
        bin()
            .args(["generate", "--sigma", "0.03", "--units", "m", "--seed", "19"])
            .arg("--dataset")
            .arg(dir.path().join("lost.json"))
            .arg("--truth")
            .arg(dir.path().join("t19.json")),
    );
    let (out, r) = calibrate(dir.path(), "lost.json", "ours", &["--accept-unrefined"]);
    assert!(!out.status.success());
    assert!(r.results.is_empty());
    assert_eq!((r.failures[0].pipeline.as_str(), r.failures[0].kind.as_str()), ("ours", "shafts_not_explained"));
    // A noise model of 1 m per frame on millimetre data: the selection stage cannot model the
    // data; non-zero without --accept-unrefined, the failure recorded.
    generate(dir.path(), "0.01");
    let mut d = parse_dataset(&std::fs::read_to_string(dir.path().join("d.json")).unwrap()).unwrap();
    d.noise_model.as_mut().unwrap().trans_m = 1.0;
    std::fs::write(dir.path().join("absurd.json"), to_json(&d)).unwrap();
    let (out, r) = calibrate(dir.path(), "absurd.json", "ours", &[]);
    assert!(!out.status.success());
    assert_eq!(r.failures.len(), 1);
    assert_eq!(r.failures[0].pipeline.as_str(), "ours");
}

#[test]
fn a_paper_pose_that_puts_the_shafts_where_no_instrument_is_is_a_failure() {
    use sim::calib::{CalibProtocol, NoiseUnits, generate_calibration, random_geometry};
    // Tuning geometry 9000, millimetre reading, σ = 0.01, trial seed 1002: the paper's
    // pipeline lands ≈180° off (its linear start in the mirror's basin), with the shafts
    // behind the camera.
    let g = random_geometry(9000, false).unwrap();
    let p = CalibProtocol {
        geometry: g.geometry,
        n_e: 3,
        n_t: 3,
        sigma: 0.01,
        units: NoiseUnits::Millimetre,
        pixel_sigma_px: 0.0,
        seed: 1002,
    };
    let d = generate_calibration(&p).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let file = comanip_calib::convert::dataset_json(&d.setup, &d.observations, d.noise);
    std::fs::write(dir.path().join("m.json"), to_json(&file)).unwrap();
    // The paper alone: a failure, typed and recorded, non-zero exit; no pose written.
    let (out, r) = calibrate(dir.path(), "m.json", "paper", &[]);
    assert!(!out.status.success());
    assert!(r.results.is_empty(), "{:?}", r.results);
    assert_eq!((r.failures[0].pipeline.as_str(), r.failures[0].kind.as_str()), ("paper", "shafts_not_explained"));
    assert!(r.failures[0].error.contains("behind the camera"), "{}", r.failures[0].error);
    // Both: ours' pose is written and the run succeeds; the paper's failure is recorded.
    let (out, r) = calibrate(dir.path(), "m.json", "both", &[]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(r.results.iter().map(|p| p.pipeline.as_str()).collect::<Vec<_>>(), ["ours"]);
    assert_eq!(r.failures[0].kind, "shafts_not_explained");
}

#[test]
fn estimate_noise_scale_finds_a_noise_model_stated_too_large() {
    // A dataset whose noise model is 20× the noise it was generated with: with
    // --estimate-noise-scale our pipeline's result records the factor it found (≈ 1/20);
    // without, none.
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path(), "0.01");
    let mut d = parse_dataset(&std::fs::read_to_string(dir.path().join("d.json")).unwrap()).unwrap();
    let n = d.noise_model.as_mut().unwrap();
    (n.rot_rad, n.trans_m, n.pixel_px) = (n.rot_rad * 20.0, n.trans_m * 20.0, n.pixel_px * 20.0);
    std::fs::write(dir.path().join("big.json"), to_json(&d)).unwrap();
    let (out, r) = calibrate(dir.path(), "big.json", "ours", &["--estimate-noise-scale", "--accept-unrefined"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let k = r.results[0].noise_scale.expect("the factor is recorded");
    assert!((k * 20.0 - 1.0).abs() < 0.3, "{k}");
    let (out, r) = calibrate(dir.path(), "big.json", "ours", &["--accept-unrefined"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(r.results[0].noise_scale, None);
}

/// `--held-out-seed` draws another held-out set (named in the report), and a held-out set that
/// overlaps the tuning set is refused before anything runs.
#[test]
fn the_held_out_set_can_be_drawn_afresh_and_never_overlaps_the_tuning_set() {
    let dir = tempfile::tempdir().unwrap();
    let args = ["sweep", "--geometries", "1", "--trials", "1", "--held-out-only", "--held-out-seed", "7100"];
    run_ok(bin().args(args).arg("--out-dir").arg(dir.path()));
    let md = std::fs::read_to_string(dir.path().join("generalisation.md")).unwrap();
    assert!(md.contains("held-out geometries: seeds 7100..7101"), "{md}");
    let out = bin()
        .args(["sweep", "--geometries", "5", "--held-out-seed", "9003"])
        .arg("--out-dir")
        .arg(dir.path().join("overlap"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("seeds 9003..9008") && err.contains("overlap"), "{err}");
    assert!(!dir.path().join("overlap").exists(), "nothing written");
}
