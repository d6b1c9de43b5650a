//! blapose-model (under construction).
