#[test]
fn write_for_numpy() {
    use blapose_data::npz::*;
    let mut n = Npz::new();
    n.insert("S9/Walking 1", Array::new(vec![2, 17, 3], (0..102).map(|i| i as f32 * 0.5).collect()).unwrap());
    n.insert("fps", Array::new(vec![], vec![50.0]).unwrap());
    write_npz("/tmp/blapose_np_check.npz", &n).unwrap();
}
