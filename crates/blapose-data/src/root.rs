//! Resolving the data root.
//!
//! Human3.6M may not be redistributed, so the data is never part of the
//! repository: binaries take its location from a flag, else the
//! `BLAPOSE_DATA` environment variable, else `../shared/data` relative to the
//! current directory (the layout CI uses: `shared/` beside the checkout).
//! Tests resolve it from the workspace root instead of the current directory
//! so they work from any crate. When it is absent they skip with a message on
//! a developer's machine, but fail under `CI=true`: CI always has the data
//! beside the checkout, so a missing directory there is a broken set-up that
//! must not turn every data-gated test silently green.

use std::path::{Path, PathBuf};

/// Environment variable naming the data root.
pub const DATA_ENV: &str = "BLAPOSE_DATA";

/// The default data root, relative to the current directory.
pub const DEFAULT_DATA_ROOT: &str = "../shared/data";

/// The data root: `flag` if given, else `$BLAPOSE_DATA` if set and
/// non-empty, else `../shared/data`. The path is not checked for existence.
pub fn data_root(flag: Option<PathBuf>) -> PathBuf {
    if let Some(p) = flag {
        return p;
    }
    match std::env::var_os(DATA_ENV) {
        Some(v) if !v.is_empty() => PathBuf::from(v),
        _ => PathBuf::from(DEFAULT_DATA_ROOT),
    }
}

/// The workspace root (two levels above this crate's manifest).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Environment variable that CI sets to `true`.
pub const CI_ENV: &str = "CI";

/// Whether the tests run under CI (`CI=true` or `CI=1`).
pub fn running_in_ci() -> bool {
    std::env::var(CI_ENV).is_ok_and(|v| v.eq_ignore_ascii_case("true") || v == "1")
}

/// For tests: the data root (`$BLAPOSE_DATA`, else `../shared/data` beside
/// the workspace root) if `subpath` exists under it. Otherwise, outside CI,
/// prints `skipping <what>: <path> not found` and returns `None`, so a test
/// can `let Some(root) = test_data_root("h36m", "my test") else { return };`.
///
/// # Panics
/// Under `CI=true` when `subpath` is missing ([`running_in_ci`]).
pub fn test_data_root(subpath: &str, what: &str) -> Option<PathBuf> {
    test_data_root_in(subpath, what, running_in_ci())
}

fn test_data_root_in(subpath: &str, what: &str, in_ci: bool) -> Option<PathBuf> {
    let root = match std::env::var_os(DATA_ENV) {
        Some(v) if !v.is_empty() => PathBuf::from(v),
        _ => workspace_root().join(DEFAULT_DATA_ROOT),
    };
    let wanted = root.join(subpath);
    if wanted.exists() {
        return Some(root);
    }
    assert!(
        !in_ci,
        "{what} needs {} and {CI_ENV}=true: CI must have the data beside the checkout \
         (or set {DATA_ENV} to the data root)",
        wanted.display()
    );
    println!(
        "skipping {what}: {} not found (set {DATA_ENV} to the data root)",
        wanted.display()
    );
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flag_wins() {
        assert_eq!(
            data_root(Some(PathBuf::from("/x/y"))),
            PathBuf::from("/x/y")
        );
    }

    #[test]
    fn missing_subpath_skips_outside_ci() {
        assert!(test_data_root_in("definitely/not/here.npz", "this check", false).is_none());
    }

    #[test]
    #[should_panic(expected = "CI must have the data")]
    fn missing_subpath_fails_in_ci() {
        test_data_root_in("definitely/not/here.npz", "this check", true);
    }
}
