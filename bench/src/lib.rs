//! blapose-bench (under construction).
