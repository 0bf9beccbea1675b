//! `gomatch-sim fit-acceptance`: the logistic fit and threshold on small hand-made example
//! sets, the command on tiny reports, and the core's built-in rules equal to the committed
//! fits at each capacity (`models/acceptance/<N>/rule.json`).

use std::path::Path;

use gomatch::acceptance::{
    AcceptanceRule, Evidence, OperatingPoint, FEATURES, FITTED_CAPACITIES, OPERATING_SHARES,
};
use gomatch_sim::eval::fit::{
    fit, run, threshold_for, threshold_keeping, Args, Example, FitOutput, Operating, Scores,
};
use gomatch_sim::eval::{evaluate, read_rule, EvalOptions, Matching, Report};
use gomatch_sim::host::CAPACITY;
use gomatch_sim::protocol::synthetic::synthetic_scene;
use gomatch_sim::protocol::ProtocolParams;

/// Evidence whose pose is right with many, spread, multi-view inliers, or wrong with few.
fn example(i: u32, right: bool) -> Example {
    let (inliers, cells, views) = if right {
        (20 + 7 * (i % 9), 8 + i % 20, 2 + i % 6)
    } else {
        (4 + i % 9, 1 + i % 5, 1 + i % 3)
    };
    let merged = inliers * 2 + 10 * u32::from(!right);
    Example {
        evidence: Evidence {
            merged,
            inliers,
            loose: inliers + i % 4,
            cells,
            bbox_area: cells as f32 / 64.0,
            mean_probability: 0.5 + 0.01 * (i % 10) as f32,
            views,
            in_view: if right { merged - i % 5 } else { merged / 2 },
            view_distance: if right { 0.2 } else { 1.0 } + 0.1 * (i % 3) as f32,
            guided_inliers: if right { 5 * inliers } else { inliers / 2 },
            guided_chance: (i % 3) as f32,
        },
        right,
    }
}

fn examples() -> Vec<Example> {
    let mut all: Vec<Example> = (0..30).map(|i| example(i, true)).collect();
    all.extend((0..12).map(|i| example(i, false)));
    // A wrong pose that looks like a right one.
    all.push(Example {
        right: false,
        ..example(3, true)
    });
    all
}

#[test]
fn the_fit_refuses_the_wrong_training_poses_and_is_deterministic() {
    let examples = examples();
    let rule = fit(&examples, 1e-2, Operating::MaxWrong(0.0)).unwrap();
    let scores = Scores::of(&rule, &examples);
    println!("{rule:?}: {scores:?}");
    assert_eq!(scores.accepted_wrong, 0);
    assert_eq!((scores.candidates, scores.right), (43, 30));
    assert!(scores.accepted >= 20, "{scores:?}");
    assert!(rule.weights.iter().all(|w| w.is_finite()));
    assert_eq!(
        fit(&examples, 1e-2, Operating::MaxWrong(0.0)).unwrap(),
        rule
    );
    // Tolerating one wrong pose in 30 accepts more.
    let tolerant = fit(&examples, 1e-2, Operating::MaxWrong(1.0 / 30.0)).unwrap();
    assert!(tolerant.min_confidence <= rule.min_confidence);
    assert!(Scores::of(&tolerant, &examples).accepted >= scores.accepted);
}

/// Poses under the chance gate have confidence 0 whatever the weights, and the logistic
/// model is fitted without them.
#[test]
fn poses_under_the_chance_gate_stay_out_of_the_logistic_fit() {
    let examples = examples();
    let gated: Vec<Example> = (0..10)
        .map(|i| {
            let mut e = example(i, i % 2 == 0);
            e.evidence.guided_chance = e.evidence.guided_inliers as f32;
            e
        })
        .collect();
    assert!(gated.iter().all(|e| !e.evidence.beyond_chance()));
    let rule = fit(&examples, 1e-2, Operating::MaxWrong(0.0)).unwrap();
    let with_gated = fit(
        &[&examples[..], &gated[..]].concat(),
        1e-2,
        Operating::MaxWrong(0.0),
    )
    .unwrap();
    assert_eq!(
        (with_gated.bias, with_gated.weights),
        (rule.bias, rule.weights)
    );
    assert!(gated
        .iter()
        .all(|e| with_gated.confidence(&e.evidence) == 0.0));
}

#[test]
fn the_threshold_is_the_lowest_confidence_within_the_wrong_share() {
    // Confidence grows with the number of views: views 1 (wrong), 2, 3 (wrong), 4, 5.
    let rule = AcceptanceRule {
        bias: -3.0,
        weights: [0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
        min_confidence: 0.0,
    };
    let by_views = |views: u32, right: bool| Example {
        evidence: Evidence {
            views,
            // Past the chance gate.
            guided_inliers: 10,
            ..Evidence::default()
        },
        right,
    };
    let examples = [
        by_views(1, false),
        by_views(2, true),
        by_views(3, false),
        by_views(4, true),
        by_views(5, true),
    ];
    let confidence = |views| rule.confidence(&by_views(views, true).evidence);
    assert_eq!(threshold_for(&rule, &examples, 0.0), confidence(4));
    assert_eq!(threshold_for(&rule, &examples, 0.3), confidence(2));
    assert_eq!(threshold_for(&rule, &examples, 0.5), confidence(1));
    // Nothing reaches the share: accept only certainty.
    assert_eq!(threshold_for(&rule, &[by_views(9, false)], 0.0), 1.0);
    // Keeping a share of the three right ones (views 2, 4, 5): the highest threshold that
    // accepts that many of them.
    assert_eq!(
        threshold_keeping(&rule, &examples, 1.0 / 3.0),
        confidence(5)
    );
    assert_eq!(threshold_keeping(&rule, &examples, 0.5), confidence(4));
    assert_eq!(threshold_keeping(&rule, &examples, 0.97), confidence(2));
    assert_eq!(threshold_keeping(&rule, &examples, 0.0), 0.0);
    assert_eq!(threshold_keeping(&rule, &[by_views(9, false)], 0.97), 0.0);
    // The default fit keeps at least 97 % of the 30 right training poses: all of them.
    let all = crate::examples();
    let rule = fit(&all, 1e-2, Operating::DEFAULT).unwrap();
    let scores = Scores::of(&rule, &all);
    assert_eq!(scores.accepted - scores.accepted_wrong, 30, "{scores:?}");
}

/// A report of a synthetic scene whose queries carry the given examples.
fn report_with(examples: &[Example]) -> Report {
    let scene = synthetic_scene(1, 0);
    let options = EvalOptions {
        protocol: ProtocolParams::for_localizer(10, examples.len(), 0, CAPACITY),
        localizer: gomatch::LocalizerConfig::new(),
        threads: 1,
        view_features: false,
    };
    let mut report = evaluate(&scene, Matching::Oracle, &options, false).unwrap();
    assert_eq!(report.per_query.len(), examples.len());
    for (q, e) in report.per_query.iter_mut().zip(examples) {
        q.evidence = Some(e.evidence);
        q.features = Some(e.evidence.features());
        q.candidate_right = Some(e.right);
    }
    report
}

#[test]
fn the_command_writes_a_rule_that_eval_reads() {
    let all = examples();
    let dir = std::env::temp_dir().join(format!("gomatch-fit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (train, check, out) = (
        dir.join("a.json"),
        dir.join("b.json"),
        dir.join("rule.json"),
    );
    for (path, part) in [(&train, &all[..10]), (&check, &all[30..36])] {
        std::fs::write(path, serde_json::to_string(&report_with(part)).unwrap()).unwrap();
    }
    let args = Args {
        reports: vec![train.clone()],
        check: vec![check],
        max_wrong: None,
        min_recall: None,
        l2: 1e-2,
        capacity: None,
        out: out.clone(),
    };
    // The ten training examples are all right: the fit still ends with finite weights.
    run(&args).unwrap();
    let written: FitOutput = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(read_rule(&out).unwrap(), written.rule());
    assert_eq!(written.training.candidates, 10);
    assert_eq!(written.training_scenes.len(), 1);
    assert_eq!(written.capacity, CAPACITY);
    assert_eq!(written.checked.map(|c| c.candidates), Some(6));
    // One operating point per share, thresholds rising as the share falls.
    let shares: Vec<f32> = written
        .operating_points
        .iter()
        .map(|p| p.max_wrong)
        .collect();
    assert_eq!(shares, OPERATING_SHARES);
    for pair in written.operating_points.windows(2) {
        assert!(pair[0].min_confidence >= pair[1].min_confidence, "{pair:?}");
    }
    // Reports of another capacity than the one asked for are refused.
    let other = Args {
        capacity: Some(256),
        ..args
    };
    let error = run(&other).unwrap_err().to_string();
    assert!(error.contains("capacity 1024, not 256"), "{error}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Each capacity's built-in rule and operating points are the committed fit at that
/// capacity (`tools/train/refit_acceptance.sh` writes both), fitted for the shipped int8
/// model.
#[test]
fn the_built_in_rules_are_the_committed_fits() {
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models");
    let sums = std::fs::read_to_string(models.join("SHA256SUMS")).unwrap();
    let shipped = sums
        .lines()
        .find_map(|l| l.strip_suffix("  gomatch-int8.bin"))
        .expect("the int8 blob's digest");
    for n in FITTED_CAPACITIES {
        let fitted_for =
            std::fs::read_to_string(models.join(format!("acceptance/{n}/model.sha256")));
        assert_eq!(fitted_for.unwrap().trim(), shipped, "refit the rule at {n}");
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join(format!("../models/acceptance/{n}/rule.json"));
        let written: FitOutput =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        assert_eq!(written.capacity, n);
        assert_eq!(AcceptanceRule::for_capacity(n), read_rule(&path).unwrap());
        assert_eq!(
            OperatingPoint::for_capacity(n).as_slice(),
            written.operating_points
        );
        assert_eq!(written.weights.len(), FEATURES);
    }
}
