//! Fast CPU inference (under construction).
