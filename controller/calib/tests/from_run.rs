//! `comanip-calib from-run` on a short run of `simrobot generate --frames`: the endoscope
//! joints decoded from the bus and the tool axis from fulcrumd's own replay match the run's
//! ground truth at each frame's time, and the command writes its report.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::process::Command;

use comanip_calib::bus_run::read_run;
use estimator::kinematics::Achilles;

#[path = "../../tests/support/workspace_bin.rs"]
mod support;
use support::workspace_bin;

#[test]
fn bus_joints_match_the_frames_truth_and_the_report_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let twin = dir.path().join("twin.toml");
    std::fs::write(&twin, "[scenario]\ncycles = 1\ninside_s = [6.0, 6.5]\noutside_s = [1.0, 1.2]\n").unwrap();
    let endo = dir.path().join("endoscope.toml");
    std::fs::write(
        &endo,
        "[camera.intrinsics]\nfx = 200.0\nfy = 200.0\ncx = 159.5\ncy = 119.5\nskew = 0.0\nwidth = 320\nheight = 240\n\
         distortion = [-0.08, 0.01, 0.0, 0.0, 0.0]\n[tissue]\nplane_z_m = 0.27\nextent_m = 0.40\ntexture_px = 256\n\
         [realism]\nsecond_instrument = false\n",
    )
    .unwrap();
    let run = dir.path().join("run");
    let o = Command::new(workspace_bin("sim", "simrobot"))
        .args(["generate", "--frames", "--fps", "8", "--seed", "3", "--out"])
        .arg(&run)
        .arg("--config")
        .arg(&twin)
        .arg("--endoscope-config")
        .arg(&endo)
        .output()
        .unwrap();
    assert!(o.status.success(), "generate: {}", String::from_utf8_lossy(&o.stderr));

    let cfg = controller::config::Config::default();
    let data = read_run(&run, &cfg).unwrap();
    assert!(data.frames.len() >= 20, "{} usable frames of {}", data.frames.len(), data.listed);
    assert_eq!(data.frames.len() + data.no_cycle + data.no_ecm + data.outside, data.listed);
    // The run's ground truth per frame: the endoscope's and the tool arm's true joints.
    let truth: Vec<serde_json::Value> = std::fs::read_to_string(run.join("frames/truth.jsonl"))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let arm = Achilles::new(&cfg.kinematics).unwrap();
    let arr =
        |v: &serde_json::Value| -> Vec<f64> { v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect() };
    for f in &data.frames {
        let t = truth.iter().find(|t| t["index"].as_u64() == Some(f.index as u64)).unwrap();
        let ecm = arr(&t["ecm_joints"]);
        for (k, (got, want)) in f.ecm_joints.iter().zip(&ecm).enumerate() {
            // Encoder resolution plus at most 10 ms of interpolation of a slow arm.
            let tol = if k == 2 { 2e-4 } else { 2e-3 };
            assert!((got - want).abs() < tol, "frame {}: ecm joint {k}: {got} vs {want}", f.index);
        }
        let q: [f64; 6] = arr(&t["tool_joints"]).try_into().unwrap();
        let axis = arm.forward(&q).unwrap().axis_base;
        // The arm's model error (1 mrad offsets, 0.5 mm links) and a millisecond of motion.
        assert!(axis.angle(&f.axis_b) < 0.01, "frame {}: tool axis {:.4} rad off", f.index, axis.angle(&f.axis_b));
    }

    let out = dir.path().join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_comanip-calib"))
        .args(["from-run", "--run"])
        .arg(&run)
        .arg("--out-dir")
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "from-run: {}", String::from_utf8_lossy(&o.stderr));
    let md = std::fs::read_to_string(out.join("from-run.md")).unwrap();
    assert!(md.contains("| truth | both |") && md.contains("| ours |") && md.contains("| paper |"), "{md}");
}
