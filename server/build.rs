//! Locates the default weights under `models/` at the repository root so the
//! binary can embed them with `include_bytes!`.
//!
//! A checkout without the files (weights not trained or not copied yet) still
//! builds: the `blapose_embedded_*` cfgs stay unset, the server then requires
//! `--weights` / `--bigru-weights` (and `--rectified-*`, or
//! `--no-camera-aware`; without the lifter it serves none unless
//! `--lifter-weights` names one), and cargo prints a warning so nobody ships such a
//! binary by accident.

use std::path::PathBuf;

const FILES: [(&str, &str, &str); 5] = [
    (
        "bone_length_gru.safetensors",
        "blapose_embedded_gru",
        "BLAPOSE_EMBEDDED_GRU",
    ),
    (
        "bone_length_bigru.safetensors",
        "blapose_embedded_bigru",
        "BLAPOSE_EMBEDDED_BIGRU",
    ),
    (
        "bone_length_gru_rectified.safetensors",
        "blapose_embedded_gru_rectified",
        "BLAPOSE_EMBEDDED_GRU_RECTIFIED",
    ),
    (
        "bone_length_bigru_rectified.safetensors",
        "blapose_embedded_bigru_rectified",
        "BLAPOSE_EMBEDDED_BIGRU_RECTIFIED",
    ),
    (
        "lifter_videopose27_causal.safetensors",
        "blapose_embedded_lifter",
        "BLAPOSE_EMBEDDED_LIFTER",
    ),
];

fn main() {
    let manifest =
        PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").unwrap_or_else(|_| ".".into()));
    let models = manifest.join("../models");
    println!("cargo:rerun-if-changed={}", models.display());
    for (file, cfg, env) in FILES {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
        let path = models.join(file);
        println!("cargo:rerun-if-changed={}", path.display());
        if path.is_file() {
            println!("cargo:rustc-cfg={cfg}");
            println!("cargo:rustc-env={env}={}", path.display());
        } else {
            println!(
                "cargo:warning=no default weights at {}: this blapose-server binary needs explicit weights flags",
                path.display()
            );
        }
    }
}
