//! Conversions between the calibration files (`hw_io::calib_files`) and estimator types.

use estimator::calib::ours::{OursResult, ResidualStats};
use estimator::calib::{KinematicNoise, Observation, Setup};
use hw_io::calib_files::{
    CALIB_FILE_VERSION, DATASET_FORMAT, DatasetFile, NoiseJson, ObservationJson, PipelineResultJson, ResidualJson,
    SelectionStageJson, TransformJson,
};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

/// File transform → isometry (metres).
pub fn isometry(t: &TransformJson) -> Isometry3<f64> {
    let [w, x, y, z] = t.quaternion_wxyz;
    Isometry3::from_parts(
        Translation3::from(Vector3::from(t.translation_m)),
        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
    )
}

/// Isometry → file transform.
pub fn transform_json(t: &Isometry3<f64>) -> TransformJson {
    let q = t.rotation;
    TransformJson { translation_m: t.translation.vector.into(), quaternion_wxyz: [q.w, q.i, q.j, q.k] }
}

/// A parsed dataset file → setup, observations and optional noise model (the file's
/// selection rule, [`DatasetFile::selection_rule`], checked by `parse_dataset`; an invalid one
/// here falls back to the default and is refused by `prepare`).
pub fn dataset(d: &DatasetFile) -> (Setup, Vec<Observation>, Option<KinematicNoise>) {
    let selection = d
        .selection_rule()
        .unwrap_or(estimator::calib::SelectionRule { min_visible_shaft_px: f64::NAN, ..Default::default() });
    let setup = Setup {
        intrinsics: d.intrinsics,
        hand_eye: isometry(&d.hand_eye),
        right_eye: d.right_eye.as_ref().map(isometry),
        selection,
        shaft_extent: d.shaft_extent.unwrap_or_default(),
    };
    let obs = d
        .observations
        .iter()
        .map(|o| Observation {
            ecm_joints: o.ecm_joints,
            psm_joints: o.psm_joints,
            tool_point_m: o.tool_point_m,
            line_px: o.line_px,
            eye: o.eye,
        })
        .collect();
    let noise = d.noise_model.map(|n| KinematicNoise { rot_rad: n.rot_rad, trans_m: n.trans_m, pixel_px: n.pixel_px });
    (setup, obs, noise)
}

/// Setup, observations and noise model → dataset file.
pub fn dataset_json(setup: &Setup, obs: &[Observation], noise: Option<KinematicNoise>) -> DatasetFile {
    DatasetFile {
        format: DATASET_FORMAT.into(),
        version: CALIB_FILE_VERSION,
        intrinsics: setup.intrinsics,
        hand_eye: transform_json(&setup.hand_eye),
        right_eye: setup.right_eye.as_ref().map(transform_json),
        noise_model: noise.map(|n| NoiseJson { rot_rad: n.rot_rad, trans_m: n.trans_m, pixel_px: n.pixel_px }),
        min_shaft_px: None,
        selection: Some(setup.selection),
        shaft_extent: (setup.shaft_extent != estimator::calib::ShaftExtent::default()).then_some(setup.shaft_extent),
        observations: obs
            .iter()
            .map(|o| ObservationJson {
                ecm_joints: o.ecm_joints,
                psm_joints: o.psm_joints,
                tool_point_m: o.tool_point_m,
                line_px: o.line_px,
                eye: o.eye,
            })
            .collect(),
    }
}

fn selection_json(o: &OursResult) -> Option<SelectionStageJson> {
    match (&o.selection, &o.selection_refused) {
        (Some(s), _) => Some(SelectionStageJson {
            applied: true,
            selected: s.selected,
            plain: s.plain,
            left_out: s.left_out,
            shift_sigmas: s.shift_sigmas,
            refused: None,
            move_statistic: s.move_statistic.map(|(x, _)| x),
            move_limit: s.move_statistic.map(|(_, l)| l),
            accepted_on_likelihood: s.accepted_on_likelihood,
        }),
        (None, Some(e)) => {
            let test = e.move_statistic();
            Some(SelectionStageJson {
                applied: false,
                selected: 0,
                plain: 0,
                left_out: 0,
                shift_sigmas: e.shift_sigmas().unwrap_or(0.0),
                refused: Some(e.to_string()),
                move_statistic: test.map(|(x, _)| x),
                move_limit: test.map(|(_, l)| l),
                accepted_on_likelihood: false,
            })
        }
        (None, None) => None,
    }
}

fn residual_json(r: &ResidualStats) -> ResidualJson {
    ResidualJson { count: r.count, rms_px: r.rms_px, median_px: r.median_px, max_px: r.max_px, inliers: r.inliers }
}

/// One pipeline's result entry.
pub fn result_json(
    pipeline: &str,
    pose: &Isometry3<f64>,
    residuals: &ResidualStats,
    ours: Option<&OursResult>,
    solve_ms: f64,
) -> PipelineResultJson {
    let m = pose.to_homogeneous();
    let mut transform = [[0.0; 4]; 4];
    for (i, row) in transform.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = m[(i, j)];
        }
    }
    let tj = transform_json(pose);
    PipelineResultJson {
        pipeline: pipeline.into(),
        transform,
        quaternion_wxyz: tj.quaternion_wxyz,
        translation_m: tj.translation_m,
        residuals: residual_json(residuals),
        covariance: ours.map(|o| {
            let mut c = [[0.0; 6]; 6];
            for (i, row) in c.iter_mut().enumerate() {
                for (j, v) in row.iter_mut().enumerate() {
                    *v = o.covariance[(i, j)];
                }
            }
            c
        }),
        ambiguity_ratio: None,
        log_likelihood_ratio: ours.map(|o| o.log_likelihood_ratio),
        solve_ms,
        selection_stage: ours.and_then(selection_json),
        noise_scale: ours.and_then(|o| o.noise_scale),
        searched_on: ours.map(|o| o.searched_on),
        cover_searched: ours.map(|o| o.cover_searched),
    }
}

#[cfg(test)]
mod tests {
    use estimator::calib::ours::{OursResult, ResidualStats, SelectionSummary};
    use estimator::calib::selection::SelectionError;
    use nalgebra::{Isometry3, Matrix6};

    fn result(selection: Option<SelectionSummary>, selection_refused: Option<SelectionError>) -> OursResult {
        OursResult {
            pose: Isometry3::identity(),
            covariance: Matrix6::identity(),
            residuals: ResidualStats { count: 0, rms_px: 0.0, median_px: 0.0, max_px: 0.0, inliers: 0 },
            scale: 1.0,
            alternative: Isometry3::identity(),
            log_likelihood_ratio: 10.0,
            iterations: 1,
            guard_kept: 0,
            guard_from: None,
            selection,
            selection_refused,
            noise_scale: None,
            searched_on: 0,
            cover_searched: false,
        }
    }

    /// The result file says why an applied stage can be over its move limit (the likelihood
    /// override), and keeps the move test's figures of a stage the shafts refused after it
    /// passed the test.
    #[test]
    fn the_selection_stage_entry_keeps_the_override_and_the_statistic() {
        let summary = SelectionSummary {
            selected: 700,
            plain: 20,
            left_out: 9,
            shift_sigmas: 6.0,
            accepted_on_likelihood: true,
            moving_step: None,
            move_test_measured: false,
            move_statistic: Some((40.0, 22.457_744)),
        };
        let applied = super::selection_json(&result(Some(summary), None)).unwrap();
        assert!(applied.applied && applied.accepted_on_likelihood);
        assert_eq!((applied.move_statistic, applied.move_limit), (Some(40.0), Some(22.457_744)));
        let text = serde_json::to_string(&applied).unwrap();
        assert!(text.contains("\"accepted_on_likelihood\":true"), "{text}");
        let plain =
            super::selection_json(&result(Some(SelectionSummary { accepted_on_likelihood: false, ..summary }), None));
        let text = serde_json::to_string(&plain.unwrap()).unwrap();
        assert!(!text.contains("accepted_on_likelihood"), "{text}");

        let shafts = SelectionError::ShaftsNotExplained {
            behind: 30,
            off_shaft: 2,
            observations: 729,
            sigmas: 3.5,
            move_statistic: Some((5.0, 22.457_744)),
        };
        let refused = super::selection_json(&result(None, Some(shafts))).unwrap();
        assert!(!refused.applied && !refused.accepted_on_likelihood);
        assert_eq!((refused.move_statistic, refused.move_limit), (Some(5.0), Some(22.457_744)));
        assert_eq!(refused.shift_sigmas, 3.5);
        assert!(refused.refused.as_deref().is_some_and(|r| r.contains("30 of 729")), "{:?}", refused.refused);

        let ran =
            SelectionError::RanAway { sigmas: f64::INFINITY, statistic: 58.1, dof: 6, limit: 22.46, measured: false };
        let refused = super::selection_json(&result(None, Some(ran))).unwrap();
        assert_eq!((refused.move_statistic, refused.move_limit, refused.shift_sigmas), (Some(58.1), Some(22.46), 0.0));
        let none = super::selection_json(&result(None, Some(SelectionError::NoModel))).unwrap();
        assert_eq!((none.move_statistic, none.move_limit), (None, None));
    }

    /// Our pipeline's selection-stage summary survives a JSON round trip whether or not the
    /// moving-covariance step's jackknife standard error was computed (serde_json writes a
    /// non-finite number as `null`, which an `f64` cannot read back: the error is an `Option`,
    /// finite when present), and a summary written before it was optional still reads.
    #[test]
    fn the_selection_summary_survives_a_json_round_trip() {
        let base = SelectionSummary {
            selected: 700,
            plain: 20,
            left_out: 9,
            shift_sigmas: 1.25,
            accepted_on_likelihood: false,
            moving_step: None,
            move_test_measured: false,
            move_statistic: Some((4.2, 22.457_744)),
        };
        for moving_step in [None, Some((0.3, None, false)), Some((5.0, Some(0.9), true))] {
            let s = SelectionSummary { moving_step, ..base };
            let text = serde_json::to_string(&s).unwrap();
            let back: SelectionSummary = serde_json::from_str(&text).unwrap();
            assert_eq!(back, s, "{text}");
        }
        let not_computed = serde_json::to_string(&SelectionSummary { moving_step: Some((0.3, None, false)), ..base });
        assert!(not_computed.unwrap().contains("\"moving_step\":[0.3,null,false]"));
        // The earlier form, a number where the standard error was computed.
        let old = r#"{"selected":700,"plain":20,"left_out":9,"shift_sigmas":1.25,"moving_step":[5.0,0.9,true]}"#;
        let back: SelectionSummary = serde_json::from_str(old).unwrap();
        assert_eq!(back.moving_step, Some((5.0, Some(0.9), true)));
        // What the earlier `f64` could not read back: its infinite value, written as `null`.
        assert!(serde_json::from_str::<(f64, f64, bool)>("[5.0,null,false]").is_err());
    }
}
