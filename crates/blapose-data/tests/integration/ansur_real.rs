//! ANSUR II on the real CSVs (skipped with a message when absent).

use blapose_data::ansur::{load_ansur, Sex};

#[test]
fn both_tables_load_with_plausible_values() {
    let Some(root) =
        blapose_data::test_data_root("ansur2/ANSUR_II_MALE_Public.csv", "ANSUR II test")
    else {
        return;
    };
    let t = load_ansur(&root).expect("load ANSUR II");
    let males = t.records.iter().filter(|r| r.sex == Sex::Male).count();
    let females = t.records.iter().filter(|r| r.sex == Sex::Female).count();
    assert_eq!((males, females), (4082, 1986), "README counts");
    // 108 CSV columns = id + 93 measurements + Gender + 13 demographic columns
    assert_eq!(t.columns.len(), 93);
    for name in [
        "stature",
        "acromionradialelength",
        "radialestylionlength",
        "biacromialbreadth",
        "tragiontopofhead",
    ] {
        assert!(t.column_index(name).is_some(), "missing column {name}");
    }
    let mean = |sex: Sex, col: &str| {
        let i = t.column_index(col).expect("column");
        let v: Vec<f64> = t
            .records
            .iter()
            .filter(|r| r.sex == sex)
            .map(|r| r.values[i] as f64)
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    let (m, f) = (mean(Sex::Male, "stature"), mean(Sex::Female, "stature"));
    println!("mean stature: male {m:.0} mm, female {f:.0} mm");
    assert!(
        (1700.0..1800.0).contains(&m) && (1580.0..1680.0).contains(&f),
        "{m} {f}"
    );
    // upper arm (acromion-radiale) ~ 30-35 cm
    let ua = mean(Sex::Male, "acromionradialelength");
    assert!((300.0..360.0).contains(&ua), "{ua}");
    assert!(t
        .records
        .iter()
        .all(|r| r.values.iter().all(|v| v.is_finite() && *v > 0.0)));
}
