//! The A/B calibration's unit tests.

use super::readings::pairs_progress;
use super::*;
use crate::store::Store;

#[test]
fn the_measuring_progress_marks_complete_pairs() {
    let pair = |id: &str| crate::layout::Pair {
        id: id.into(),
        group: "A".into(),
        from: "A1".into(),
        to: "A2".into(),
        direction_deg: 45.0,
        nominal_mm: 10.0,
    };
    let mut have = BTreeMap::new();
    have.insert("A-D1".to_string(), vec![10.0; 5]);
    have.insert("A-D2".to_string(), vec![150.0; 2]);
    let line = pairs_progress(&[pair("A-D1"), pair("A-D2"), pair("B-D1")], &have, 5);
    assert_eq!(line, "A-D1 5/5 ✓ · A-D2 2/5 · B-D1 0/5");
}

#[test]
fn rotation_distances_are_written_without_trailing_zeros() {
    assert_eq!(entry::fmt_rd(40.0), "40");
    assert_eq!(entry::fmt_rd(40.1028949), "40.102895");
    assert_eq!(entry::fmt_rd(39.94284), "39.94284");
}

/// A call of `method` read at the boundary, as the agent reads it.
fn parse_call(method: &str, args: &Value) -> anyhow::Result<AbCall> {
    match crate::jobs::Route::of_method(method).unwrap().parse(args)? {
        crate::jobs::Call::Ab(c) => Ok(c),
        other => panic!("{other:?}"),
    }
}

#[test]
fn start_arguments_are_typed_at_the_boundary() {
    let r = parse_call(
        "klipcal_ab_start",
        &json!({"BED": "60", "extruder": 215, "layout": "Full"}),
    )
    .unwrap();
    assert_eq!(
        r,
        AbCall::Start(StartRequest {
            bed_temp_c: Some(60.0),
            nozzle_temp_c: Some(215.0),
            layout: Some("full".into())
        })
    );
    let e = parse_call("klipcal_ab_start", &json!({"bed": "200"})).unwrap_err();
    assert!(e.to_string().starts_with("BED=200: expected"), "{e}");
    let e = parse_call("klipcal_ab_start", &json!({"layout": "round"})).unwrap_err();
    assert_eq!(e.to_string(), "LAYOUT=round: expected paper or full");
    let apply = |v| parse_call("klipcal_apply", &v).unwrap();
    assert_eq!(
        apply(json!({"FORCE": "1"})),
        AbCall::Apply(ApplyRequest { force: true })
    );
    assert_eq!(
        apply(json!({})),
        AbCall::Apply(ApplyRequest { force: false })
    );
    let measure = |v| match parse_call("klipcal_measure", &v).unwrap() {
        AbCall::Measure(m) => m,
        other => panic!("{other:?}"),
    };
    let m = measure(json!({"pair": "A-D1", "values": "10.02, 10.03,10.01", "value": "10,04"}));
    let texts: Vec<(&str, &str)> = m
        .values
        .iter()
        .map(|i| (i.text.as_str(), i.label.as_str()))
        .collect();
    assert_eq!(
        texts,
        vec![
            ("10.02", "item 1"),
            ("10.03", "item 2"),
            ("10.01", "item 3"),
            ("10,04", "VALUE")
        ]
    );
    // The page's fields: one reading each, named by the field.
    let m = measure(json!({"pair": "A-D1", "values": ["", "10,10"]}));
    assert_eq!(m.values.len(), 1);
    assert_eq!(m.values[0].label, "field 2");
    assert!(m.values[0].comma_is_decimal);
    assert_eq!(
        parse_call("klipcal_soak_choice", &json!({})).unwrap(),
        AbCall::SoakChoice("wait"),
        "the macro's field default is the daemon's"
    );
}

#[test]
fn only_the_automatic_states_resume_by_themselves() {
    assert!(State::Printing.is_automatic());
    assert!(!State::Measuring.is_automatic());
    assert!(State::Cancelled.is_final());
    assert_eq!(State::Measuring.name(), "measuring");
}

fn fixture() -> Store {
    // Written by klipcal 0.1.0 (before the session core): three A/B sessions, measuring,
    // solved and applied, each with five readings per pair.
    let dir = tempfile::tempdir().unwrap();
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/sessions-v0.1.0.sqlite");
    std::fs::copy(&src, dir.path().join("klipcal.sqlite")).unwrap();
    let store = Store::open(dir.path()).unwrap();
    std::mem::forget(dir);
    store
}

#[test]
fn sessions_saved_by_release_0_1_0_load_typed() {
    let store = fixture();
    let mut states = Vec::new();
    for id in 1..=3 {
        let row = store.session(id).unwrap().unwrap();
        let s: Session = serde_json::from_value(row.doc.clone()).unwrap();
        states.push(s.state);
        let r = &s.rounds[0];
        assert_eq!(r.layout.pairs.len(), 4);
        if let Some(sol) = &r.solution {
            // The fixture's readings scale group A by 1.002 and B by 0.998 with a constant
            // shrinkage of 0.1 mm that the differential cancels (seed 000 §2).
            assert!(
                (sol.groups[0].scale - 1.002).abs() < 1e-6,
                "{:?}",
                sol.groups[0]
            );
            assert!(
                (sol.groups[1].scale - 0.998).abs() < 1e-6,
                "{:?}",
                sol.groups[1]
            );
            assert!((sol.stepper_x.rotation_distance_old - 40.0).abs() < 1e-12);
        }
        // Saved back, it keeps the shape release 0.1.0 reads.
        let back = serde_json::to_value(&s).unwrap();
        assert_eq!(
            back["rounds"][0]["solution"],
            row.doc["rounds"][0]["solution"]
        );
        assert_eq!(back["state"], row.doc["state"]);
    }
    assert_eq!(
        states,
        vec![State::Measuring, State::Solved, State::Applied]
    );
    assert!(store.session(2).unwrap().unwrap().doc["rounds"][0]["solution"].is_object());
}
