//! blapose-train (under construction).
