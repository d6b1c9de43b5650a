//! blapose-proto (under construction).
