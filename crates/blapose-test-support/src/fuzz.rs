//! What the fuzz tests of blapose-core, blapose-data and blapose-server
//! share: a fixed-seed proptest configuration that `PROPTEST_CASES`
//! lengthens, and byte mutations of valid inputs (files, tokens), so that
//! each test states only its target.

use proptest::prelude::*;
use proptest::test_runner::RngSeed;

/// `cases` cases (or `PROPTEST_CASES`), from a fixed seed (`seed`), with
/// nothing persisted: the same cases on every run, in seconds.
pub fn config(cases: u32, seed: u64) -> ProptestConfig {
    ProptestConfig {
        cases: std::env::var("PROPTEST_CASES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(cases),
        rng_seed: RngSeed::Fixed(seed),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// One edit of a byte string (positions taken modulo its length).
#[derive(Debug, Clone)]
pub enum Mutation {
    /// Overwrite a byte.
    Set(usize, u8),
    /// Cut the rest off.
    Truncate(usize),
    /// Insert bytes.
    Insert(usize, Vec<u8>),
    /// Remove up to n bytes.
    Remove(usize, usize),
}

/// Mutations, overwrites the most likely.
pub fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        6 => (any::<usize>(), any::<u8>()).prop_map(|(i, b)| Mutation::Set(i, b)),
        1 => any::<usize>().prop_map(Mutation::Truncate),
        1 => (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16)).prop_map(|(i, b)| Mutation::Insert(i, b)),
        1 => (any::<usize>(), 1usize..64).prop_map(|(i, n)| Mutation::Remove(i, n)),
    ]
}

/// `bytes` with `mutations` applied after its first `keep` bytes.
pub fn mutate(mut bytes: Vec<u8>, mutations: &[Mutation], keep: usize) -> Vec<u8> {
    for m in mutations {
        let len = bytes.len();
        if len <= keep {
            break;
        }
        let at = |i: &usize| keep + i % (len - keep);
        match m {
            Mutation::Set(i, b) => {
                let i = at(i);
                bytes[i] = *b;
            }
            Mutation::Truncate(i) => bytes.truncate(at(i)),
            Mutation::Insert(i, b) => {
                let i = at(i);
                bytes.splice(i..i, b.iter().copied());
            }
            Mutation::Remove(i, n) => {
                let i = at(i);
                bytes.drain(i..(i + n).min(len));
            }
        }
    }
    bytes
}
