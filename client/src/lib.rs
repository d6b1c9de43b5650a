//! blapose-client (under construction).
