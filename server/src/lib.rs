//! blapose-server (under construction).
