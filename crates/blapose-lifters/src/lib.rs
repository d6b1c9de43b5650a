//! blapose-lifters (under construction).
