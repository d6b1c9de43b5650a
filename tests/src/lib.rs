//! blapose-tests (under construction).
