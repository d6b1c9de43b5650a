//! blapose-data (under construction).
