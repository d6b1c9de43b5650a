//! blapose-train's integration tests in one test binary: each links the
//! trainer and candle, so one link instead of nine.

mod ansur_split;
mod eval_fixture;
mod fastnet_matches_candle;
mod lifter;
mod lifter_real;
mod pipeline;
mod shipped_lifters;
mod shipped_weights;
mod train_loop;
