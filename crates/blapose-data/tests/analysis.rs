// temporary analysis (to be removed)
use blapose_core::bones::bone_lengths;
use blapose_core::layouts::KeypointLayout;
use blapose_core::skeleton::{BONE_NAMES, JOINT_NAMES, SYMMETRIC_BONE_PAIRS};
use blapose_data::h36m::*;
use std::time::Instant;

fn median(v: &mut Vec<f32>) -> f32 { let n = v.len()/2; *v.select_nth_unstable_by(n, |a,b| a.total_cmp(b)).1 }

#[test]
#[ignore]
fn analysis() {
    let root = blapose_data::test_data_root("h36m", "analysis").unwrap();
    let t = Instant::now();
    let poses = load_poses(&root, &ALL_SUBJECTS).unwrap();
    println!("all poses: {:?}, {} seqs", t.elapsed(), poses.values().map(|m| m.len()).sum::<usize>());
    let t = Instant::now();
    let det = load_detections(&root, &ALL_SUBJECTS).unwrap();
    println!("all dets: {:?}", t.elapsed());
    let cams = load_cameras(&root).unwrap();
    for (s, acts) in &poses {
        let mut all: Vec<[f32;16]> = vec![];
        for p in acts.values() { for f in p { all.push(bone_lengths(f)); } }
        let n = all.len() as f64;
        let mut line = format!("{s}: ");
        let mut means=[0.0f64;16];
        for b in 0..16 {
            let m = all.iter().map(|l| l[b] as f64).sum::<f64>()/n;
            let sd = (all.iter().map(|l| (l[b] as f64-m).powi(2)).sum::<f64>()/n).sqrt();
            means[b]=m;
            line += &format!("{}={:.1}±{:.3} ", BONE_NAMES[b], m*1000.0, sd*1000.0);
        }
        println!("{line}");
        let lr: Vec<String> = SYMMETRIC_BONE_PAIRS.iter().map(|&(r,l)| format!("{:.2}", (means[r]-means[l])*1000.0)).collect();
        println!("  r-l mm: {lr:?}");
    }
    // frame count check
    for (s, acts) in &det { for (a, cs) in acts { for (c, d) in cs {
        let n = poses.get(s).and_then(|m| m.get(a)).map(|p| p.len());
        if n != Some(d.len()) { println!("mismatch {s}/{a}/{c}: det {} poses {:?}", d.len(), n); }
    }}}
    // per-joint medians for converted SH on test subjects; fit neck fraction on train
    let mut num=0.0f64; let mut den=0.0f64;
    let mut spine_num=0.0f64; let mut spine_den=0.0f64; let mut head_num=0.0f64; let mut head_den=0.0f64;
    let mut per_joint: Vec<Vec<f32>> = vec![vec![];17];
    let mut coco_err: Vec<Vec<f32>> = vec![vec![];17];
    for (s, acts) in &det {
        let test = TEST_SUBJECTS.contains(&s.as_str());
        for (a, cs) in acts { for (c, d) in cs {
            let cam = cams.get(s, c).unwrap();
            let p = &poses[s][a];
            for (t, f) in d.iter().enumerate().step_by(if test {1} else {5}) {
                if t >= p.len() { break; }
                let gt = cam.project_world_pose_to_pixels(&p[t]);
                let conv = KeypointLayout::Sh16.to_h36m17(f).unwrap();
                // neck: gt9 - th ≈ a (head - th)
                let th = conv[8]; let hd = conv[10];
                for i in 0..2 {
                    let u = (hd[i]-th[i]) as f64; let v = (gt[9][i]-th[i]) as f64;
                    if !test { num += u*v; den += u*u; }
                    // coco spine on gt: spine - pelvis ≈ f (thorax - pelvis) with pelvis=midhips, thorax=midshoulders
                    let pel = 0.5*(gt[1][i]+gt[4][i]) as f64; let thx = 0.5*(gt[11][i]+gt[14][i]) as f64;
                    if !test { spine_num += (thx-pel)*(gt[7][i] as f64-pel); spine_den += (thx-pel).powi(2);
                    head_num += (gt[9][i] as f64-thx)*(gt[10][i] as f64-thx); head_den += (gt[9][i] as f64 - thx).powi(2);}
                }
                if test {
                    for j in 0..17 { per_joint[j].push(((conv[j][0]-gt[j][0]).powi(2)+(conv[j][1]-gt[j][1]).powi(2)).sqrt()); }
                    let coco: Vec<[f32;2]> = vec![gt[9],gt[9],gt[9],gt[9],gt[9],gt[11],gt[14],gt[12],gt[15],gt[13],gt[16],gt[4],gt[1],gt[5],gt[2],gt[6],gt[3]];
                    let cc = KeypointLayout::Coco17.to_h36m17(&coco).unwrap();
                    for j in 0..17 { coco_err[j].push(((cc[j][0]-gt[j][0]).powi(2)+(cc[j][1]-gt[j][1]).powi(2)).sqrt()); }
                }
            }
        }}
    }
    println!("neck fraction fit {:.4}, coco spine {:.4}, coco head {:.4}", num/den, spine_num/spine_den, head_num/head_den);
    for j in 0..17 { println!("{:12} sh16 median {:.2} px   coco-synth median {:.2}", JOINT_NAMES[j], median(&mut per_joint[j]), median(&mut coco_err[j])); }
}
